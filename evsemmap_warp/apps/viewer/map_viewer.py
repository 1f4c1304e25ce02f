"""``MapViewer``: a viser server showing map files, maps in memory and map stores, composed of parts with
one job each (the attributes below), as viser composes its handles. It reads maps only; it launches no kernel."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from ...frames import check_same_frame
from ...terrain.config import load_terrain_config
from .camera import Cameras
from .colors import TRAJECTORY_COLOR, class_palette
from .comparison import Comparison
from .exports import write_html, write_ply
from .inputs import check_address, load_points, load_trajectory
from .lighting import configure_lighting
from .map_layer import MapLayer
from .orientation import Orientation
from .panel import add_class_toggles, add_panel, variance_slider_range
from .picking import Picking
from .store import StoreOverview, StoreTiles
from .tabs import Tabs
from .terrain import TerrainView
from .voxels import VoxelLayers


class MapViewer:
    """A viser server showing one or more maps, with filters, colorings, picking and export.

    All maps must be in one world frame (``frame``; a ``FrameError`` naming both files and both frames
    otherwise). ``trajectory`` and ``scan`` are read as world coordinates of that frame. The scene is
    drawn relative to ``origin`` (float64 world coordinates, marked by a world-axes frame and a label).
    ``terrain``: compute each map's terrain layers at start (``terrain_resolution`` m cells, the cost
    table ``costs``; the GUI's button does it on demand otherwise). The cost table's ``layers.min_evidence``
    is also what the viewer calls known (``min_evidence``, ``terrain.known``): voxels below it are hidden
    until *Show below the evidence threshold* is ticked. ``truth``: a ground truth for the
    comparison of two maps (``comparison.load_truth``).

    ``map_paths`` may hold ``MapLayer`` objects (a map in memory: a live map, a drive's replay), which
    ``replace_layer`` updates. A store (``StoreOverview``, in ``stores``) is read for its first frame up to
    ``store_first_voxels`` of its voxels (and ``FIRST_FRAME_ROWS`` overview rows), nearest its center
    first; a loader thread reads the rest of its overview, and the tiles a browser's camera comes near or
    a click hits, in full.

    Handles: ``server``; ``gui_*``, the panel's shared controls (``panel``); and the parts: ``voxels``
    (``voxels.VoxelLayers``: the voxels drawn and their colors), ``tabs`` (``tabs.Tabs``: each browser tab's
    own coloring, legend, selection and measurement), ``cameras`` (``camera.Cameras``), ``orientation``
    (``orientation.Orientation``: the origin's axes, the ground grid), ``picking`` (``picking.Picking``:
    clicks and measuring), ``terrain`` (``terrain.TerrainView``), ``comparison`` (``comparison.Comparison``:
    the maps shown, side by side or compared) and ``tiles`` (``store.StoreTiles``: stores read in the
    background). ``gui_color_by``, ``gui_legend``, ``gui_selection``, ``gui_measure``,
    ``gui_measure_result``, ``measure_points`` and ``last_point`` are those of the tab that acted last (a
    script's, without a browser)."""

    FIRST_FRAME_ROWS = 100_000  # a store's first frame: about 1.5 MB to send, a fraction of a second to draw

    def __init__(self, map_paths, *, host: str = "127.0.0.1", port: int = 8080, style: str = "points",
                 max_voxels: int = 500_000, trajectory=None, scan=None, export_dir=None, terrain: bool = False,
                 terrain_resolution=None, costs=None, truth=None, store_first_voxels: int = 1_000_000, same_frame: bool = False):
        import viser

        if style not in ("points", "boxes"):
            raise ValueError(f"style must be 'points' or 'boxes', got {style!r}")
        if not map_paths:
            raise ValueError("give at least one map file")
        # "known" is the layers' (terrain.known): the cost table's layers.min_evidence, read before any server starts
        self.min_evidence = load_terrain_config(costs).layers.min_evidence
        truth_path = Path(truth) if truth is not None else None
        if truth_path is not None and not truth_path.is_file():
            raise ValueError(f"{truth_path}: no such ground-truth file")
        self._open_maps(map_paths, max_voxels, store_first_voxels, same_frame)
        self.style, self.max_voxels = style, int(max_voxels)
        self.export_dir = Path(export_dir) if export_dir else self.layers[0].path.parent
        self.map_fade = 0.0  # the voxels' colors drawn this share of the way to white (a drive's scan shown over them)
        # Updates of a layer (replace_layer) and the controls' callbacks (viser's threads) take turns.
        self.lock = threading.RLock()
        self._refresh_held_by: int | None = None  # the thread in replace_layer, whose control changes wait for its refresh
        self.closed = threading.Event()
        lo, hi = self.bounds()
        # A local origin keeps float32 positions fine-grained however far the map is from 0. Maps that start
        # empty (a live map) get theirs from their first voxels (replace_layer); a store's comes from its index.
        self.origin = np.round((lo + hi) / 2.0)
        self._origin_from_data = any(len(layer.centers) for layer in self.layers) or bool(self.stores)

        check_address(host, port)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        configure_lighting(self.server.scene)
        self.comparison = Comparison(self, truth_path)
        self.comparison.side_by_side_step = float(hi[0] - lo[0]) + 2.0
        self.voxels = VoxelLayers(self)
        self.terrain = TerrainView(self, resolution_m=terrain_resolution, costs=costs)
        self.tiles = StoreTiles(self)
        self.cameras = Cameras(self)
        self.cameras.frame(lo, hi)
        self.orientation = Orientation(self)
        add_panel(self)
        self.orientation.add_origin_marker(float(max(np.max(hi - lo), 1.0)))
        self.orientation.add_ground_grid(lo, hi)
        self.tabs = Tabs(self)
        self.picking = Picking(self)
        self._add_drive_marks(trajectory, scan)
        try:
            if terrain:
                self.terrain.compute()
            self.refresh()
        except BaseException:
            self.server.stop()
            raise
        self.tiles.start()  # stores: the rest of the overview, and tiles in full when asked for

    def _open_maps(self, map_paths, max_voxels: int, store_first_voxels: int, same_frame: bool) -> None:
        from ...core.map_store import is_store

        # a MapLayer is shown as given (a live map, a drive's replay); paths are read
        self.stores = {i: StoreOverview(p, max_voxels) for i, p in enumerate(map_paths) if not isinstance(p, MapLayer) and is_store(p)}
        for overview in self.stores.values():  # the tiles of the first frame; the rest fill in after it
            overview.read_first(store_first_voxels, self.FIRST_FRAME_ROWS)
        self.layers = [p if isinstance(p, MapLayer) else self.stores[i].layer() if i in self.stores else MapLayer.from_file(p)
                       for i, p in enumerate(map_paths)]
        self.same_frame = same_frame  # two runs' odom frames shown as one, the user says (frames.check_same_frame)
        for layer in self.layers[1:]:  # switchable or side by side: only maps of one frame share the scene
            check_same_frame("view together", (str(self.layers[0].path), self.layers[0].frame), (str(layer.path), layer.frame),
                             same_frame=same_frame)
        self.frame = self.layers[0].frame
        self.classes = list(dict.fromkeys(c for layer in self.layers for c in layer.classes))
        self.palette = dict(zip(self.classes, class_palette(self.classes)))
        # the classes some map holds (a voxel with evidence carries them): the only ones offered as toggles
        present = {layer.classes[k] for layer in self.layers for k in layer.present_labels() if k < len(layer.classes)}
        self.present_classes = [c for c in self.classes if c in present]

    def _add_drive_marks(self, trajectory, scan) -> None:
        """The trajectory and the scan files: world coordinates of the maps' frame, drawn relative to the local origin."""
        scene = self.server.scene
        self.trajectory_handles: list = []
        if trajectory is not None:
            positions = load_trajectory(trajectory) - self.origin
            if len(positions) >= 2:
                self.trajectory_handles.append(scene.add_spline_catmull_rom(
                    "/trajectory", positions.astype(np.float32), color=TRAJECTORY_COLOR, thickness=3.0, thickness_units="screen"))
            self.trajectory_handles.append(scene.add_point_cloud(
                "/trajectory_poses", positions.astype(np.float32), colors=TRAJECTORY_COLOR, point_size=0.3, precision="float32"))
        if scan is not None:
            points = load_points(scan) - self.origin
            scene.add_point_cloud("/scan", points.astype(np.float32), colors=(200, 200, 200), point_size=0.05, precision="float32")

    @property
    def url(self) -> str:
        """The address the viewer serves on (http://host:port)."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    # What the tab that acted last (a script's, without a browser) has of its own (tabs.ClientView).
    gui_color_by = property(lambda self: self.tabs.acting.color_by)
    gui_legend = property(lambda self: self.tabs.acting.legend)
    gui_selection = property(lambda self: self.tabs.acting.selection)
    gui_measure = property(lambda self: self.tabs.acting.measure)
    gui_measure_result = property(lambda self: self.tabs.acting.measure_result)
    measure_points = property(lambda self: self.tabs.acting.measure_points)
    last_point = property(lambda self: self.tabs.acting.last_point)
    # What the parts hold that scripts read most.
    visible_rows = property(lambda self: self.voxels.visible_rows)
    ground = property(lambda self: self.orientation.ground)
    center_hit = property(lambda self: self.cameras.center_hit)

    @property
    def max_variance(self) -> float:
        """The variance threshold the slider sets (the slider counts in ``variance_unit``)."""
        return float(self.gui_max_variance.value) * self.variance_unit

    def origin_text(self) -> str:
        """The local origin in world coordinates of the frame, e.g. "map: x=500003.000, y=4000003.000, z=100.000 m"."""
        return self.orientation.origin_text()

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The maps' bounding box (world coordinates, m): their voxel centers, and the whole of each store (from
        its index, however much of it is read); zeros while every map is empty."""
        lows = [layer.centers.min(axis=0) for layer in self.layers if len(layer.centers)] + [o.bounds[0] for o in self.stores.values()]
        highs = [layer.centers.max(axis=0) for layer in self.layers if len(layer.centers)] + [o.bounds[1] for o in self.stores.values()]
        return np.min(lows or [np.zeros(3)], axis=0), np.max(highs or [np.zeros(3)], axis=0)

    # ------------------------------------------------------------------ showing
    def on_control(self) -> None:
        """A shared control changed: show the maps anew (unless ``replace_layer``, on this thread, does it next)."""
        # replace_layer sets several controls, then refreshes once; a change made on another thread meanwhile refreshes itself
        if self._refresh_held_by != threading.get_ident():
            self.refresh()

    def refresh(self) -> None:
        """Recompute what is shown from the controls and push it to every browser."""
        with self.lock:
            if not self.comparison.check():  # the comparison turned itself off, which showed the maps anew
                return
            shown = self.comparison.shown_layers()
            hide = self.terrain.voxels_hidden()
            with self.server.atomic():
                drawn, visible, stands_for = self.voxels.draw(shown, hide)
                self.terrain.draw(shown)
                for view in self.tabs.all_views():
                    self.voxels.draw_view(view)
            self.gui_status.content = self.voxels.status_text(shown, drawn, visible, stands_for, hide)
            self.gui_terrain_legend.visible = self.terrain.shown()
            self.gui_frame.content = self.orientation.frame_text()
            self.comparison.show_status(self.voxels.color_ranges.get("comparison"))

    def replace_layer(self, i: int, layer: MapLayer) -> None:
        """Show ``layer`` as map ``i`` from now on (a drive's map as of a scan, a live map's latest copy,
        a store overview with more tiles): the classes it holds join the toggles, and the variance slider,
        the ground grid and (for maps that were empty) the local origin are fitted to it. Safe to call
        from any thread."""
        with self.lock:
            if self.closed.is_set():  # a loader, a replay or a live map still at work after close()
                return
            check_same_frame("view together", (str(self.layers[i].path), self.layers[i].frame), (str(layer.path), layer.frame),
                             same_frame=self.same_frame)
            was_at_top = self.gui_max_variance.value >= self.gui_max_variance.max - 0.5 * self.gui_max_variance.step
            threshold = self.max_variance
            self.voxels.replace(i, layer)
            self.layers[i] = layer
            self._refresh_held_by = threading.get_ident()
            try:
                self._add_new_classes()
                unit, step, top, label = variance_slider_range(self.layers)
                if (unit, step, top) != (self.variance_unit, self.gui_max_variance.step, self.gui_max_variance.max):
                    self.variance_unit = unit
                    self.gui_max_variance.label, self.gui_max_variance.step, self.gui_max_variance.max = label, step, top
                    # the threshold keeps its variance (the slider's unit may change), or stays at the top
                    self.gui_max_variance.value = top if was_at_top else min(round(threshold / unit / step) * step, top)
                self._fit_scene()
            finally:
                self._refresh_held_by = None
            self.refresh()

    def _add_new_classes(self) -> None:
        for layer in self.layers:
            for name in layer.classes:
                if name not in self.palette:
                    self.classes.append(name)
                    self.palette[name] = class_palette(self.classes)[-1]
        present = {layer.classes[k] for layer in self.layers for k in layer.present_labels() if k < len(layer.classes)}
        new = [c for c in self.classes if c in present and c not in self.present_classes]
        if new:
            self.present_classes = [c for c in self.classes if c in present or c in self.present_classes]
            add_class_toggles(self, new)

    def _fit_scene(self) -> None:
        """The local origin from the first voxels of maps that started empty; the ground grid over the maps' extent."""
        lo, hi = self.bounds()
        if not any(len(layer.centers) for layer in self.layers):
            return
        if not self._origin_from_data:
            self.origin = np.round((lo + hi) / 2.0)
            self._origin_from_data = True
            self.orientation.add_origin_marker(float(max(np.max(hi - lo), 1.0)))
            self.gui_frame.content = self.orientation.frame_text()
            self.cameras.frame(lo, hi)
            self.orientation.add_ground_grid(lo, hi)
        elif not self.orientation.covers(lo, hi):
            self.cameras.frame(lo, hi)
            self.orientation.add_ground_grid(lo, hi)
        self.comparison.side_by_side_step = float(hi[0] - lo[0]) + 2.0

    # ------------------------------------------------------------------ exports and serving
    def export_html(self, path) -> Path:
        """A standalone HTML file of the current scene (viewable offline, without viser's GUI panel but
        with the legend, a summary of what is shown and the frame note).

        Its positions are viser's float32 scene positions, relative to the local origin (``origin``), not
        world coordinates; the page states the offset: ``<meta name="evsemmap-frame">`` (the frame's name,
        "none" where not recorded), ``evsemmap-crs`` (an EPSG code or "none"), ``evsemmap-local-origin``
        ("x y z", metres in that frame), an HTML comment and a visible note saying the same, and the scene's
        labelled world axes at the origin. ``<div id="evsemmap-legend">`` (``exports.legend_html``) holds the legend."""
        return write_html(self, path)

    def export_ply(self, path) -> Path:
        """The visible voxels of the shown maps as a binary PLY point cloud: vertex positions are float64
        (``property double x/y/z``) world coordinates of the maps' frame, metres, not shifted side by side;
        color (RGBA) and label, state, variance and observation count as per-vertex properties. The
        header names the frame: ``comment frame NAME`` and ``comment crs EPSG:NNNN`` ("none" where not
        recorded)."""
        return write_ply(self, path)

    def wait_for_stores(self, timeout: float | None = None) -> bool:
        """Wait until every store's overview is read in full and shown (exports then hold all of it); whether it was."""
        return self.tiles.wait(timeout)

    def close(self) -> None:
        """Stop reading stores and serving."""
        with self.lock:  # after a layer update under way, and before any other
            self.closed.set()
        self.tiles.stop()
        self.cameras.stop()
        self.server.stop()

    def serve_forever(self) -> None:
        """Keep serving until Ctrl-C, then stop the server."""
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()
