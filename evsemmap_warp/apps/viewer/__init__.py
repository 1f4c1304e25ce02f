"""Browser-based map inspection with viser: ``MapViewer`` and ``evsemmap view``.

The viewer reads map files only (``map_file.read_map_file``); it launches no kernel. Voxels are drawn as
point sprites or instanced boxes, in float32 positions relative to a local origin (viser's default
float16 would quantise a map a few hundred metres from its origin). Everything a control changes
goes through ``MapViewer.refresh()``, so the same code serves the browser and the tests.

Coordinates: a map's voxel centers are float64 world coordinates of its world frame (``frames.WorldFrame``:
a name and an optional EPSG CRS, e.g. UTM metres). The viewer shows that frame, reports a clicked voxel's
center in it (float64, mm digits), and draws a world-axes marker at the local origin labelled with the
origin's world coordinates. Maps are shown together (switchable or side by side) only when their frames
agree (two maps written before frames were recorded agree; an unrecorded and a recorded frame do not).
``--trajectory`` and ``--scan`` files are read as world coordinates of the maps' frame.

One module per part, composed by ``MapViewer`` (``map_viewer``): the maps as held (``map_layer``) and
stores (``store``); the voxels drawn (``voxels``), their colors (``colors``) and the lit meshes'
(``lighting``); the panel (``panel``) and what each browser tab has of its own (``tabs``); cameras
(``camera``), the ground grid and origin (``orientation``), picking and measuring (``picking``); terrain
layers (``terrain``); maps side by side or compared (``comparison``); the HTML and PLY exports
(``exports``); drive playback (``drive``) and maps being made (``live``). viser 1.1 sends clicks and
camera moves, not pointer moves, to the server, so in place of coordinates on hover the panel follows the
point under the screen's center (marked by a crosshair at the orbit center) as the view moves.
"""

from .inputs import check_address, free_port, load_points, load_trajectory
from .map_layer import MapLayer
from .map_viewer import MapViewer
from .store import StoreOverview

__all__ = ["MapLayer", "MapViewer", "StoreOverview", "check_address", "free_port", "load_points", "load_trajectory"]
