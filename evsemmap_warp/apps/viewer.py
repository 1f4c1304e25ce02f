"""Browser-based map inspection with viser: ``MapViewer`` and ``evsemmap view``.

The viewer reads map files only (``map_file.read_map_file``); it launches no kernel. Voxels are drawn as
point sprites or instanced boxes, in float32 positions relative to a local origin (viser's default
float16 would quantise a map a few hundred metres from its origin). Everything a control changes
goes through ``refresh()``, so the same code serves the browser and the tests.

Coordinates: a map's voxel centers are float64 world coordinates of its world frame (``frames.WorldFrame``:
a name and an optional EPSG CRS, e.g. UTM metres). The viewer shows that frame, reports a clicked voxel's
center in it (float64, mm digits), and draws a world-axes marker at the local origin labelled with the
origin's world coordinates. Maps are shown together (switchable or side by side) only when their frames
agree (two maps written before frames were recorded agree; an unrecorded and a recorded frame do not).
``--trajectory`` and ``--scan`` files are read as world coordinates of the maps' frame. Exports: the PLY
holds float64 world coordinates (header comments ``frame`` and ``crs``); the HTML holds viser's float32
positions relative to the local origin, and states that origin and the frame in a ``<meta>`` element, a
comment and a visible note, beside the legend and a summary of what is shown.

Beside the voxels (``viewer_layers``): a terrain layer as a colored height surface (``terrain=True`` or
the GUI's button computes ``terrain.compute_layers`` of each map or store), two maps' differences
(labels that differ, colored by which map agrees with a ground truth when ``truth`` gives one, and the
variance difference), a ground grid labelled in metres of the world frame, a scale bar that follows the
camera, and a measuring tool. A click reports the world coordinates of the point it hits (a voxel, a
terrain cell, or the ground grid's plane). viser 1.1 sends clicks and camera moves, not pointer moves,
to the server, so in place of coordinates on hover the panel follows the point under the screen's
center (marked by a crosshair at the orbit center) as the view moves. Lit meshes (boxes, the surface)
are drawn under the viewer's own lights with compensated colors so that they show the palette's colors.
"""

from __future__ import annotations

import collections
import html
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..classes import named_colors
from ..core.map_file import file_arrays, lattice_index, read_map_file
from ..core.mapper import reader_mapper
from ..data.point_files import read_npy, read_point_file
from ..frames import WorldFrame, check_same_frame, describe_frame
from ..voxel_keys import voxel_index_of
from . import viewer_layers as vl

STATE_NAMES = ("UNKNOWN", "FREE", "OCCUPIED")
COLOR_MODES = ("semantic", "variance", "mean uncertainty", "observations")
# Class colors come from configs/classes (docs/algorithm.md §5.1 for the mapping classes); other names get tab10.
CLASS_COLORS = named_colors()
_FALLBACK = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                      (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)
# viridis at 9 stops; np.interp between them is indistinguishable at voxel-color precision.
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)
_NO_DATA = np.array([128, 128, 128], np.uint8)
TRAJECTORY_COLOR = (255, 140, 0)  # orange (README: "the drive in orange")
SELECTION_COLOR = (255, 0, 0)  # the clicked voxel's wireframe box: a color no class and no other marker has
VIEW_BUTTONS = ("top-down", "reset view")


def class_palette(classes: list[str]) -> np.ndarray:
    """[K, 3] uint8: the class set's color for known class names, a tab10 color otherwise."""
    return np.array([CLASS_COLORS.get(name.lower(), tuple(_FALLBACK[i % len(_FALLBACK)])) for i, name in enumerate(classes)], np.uint8)


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """viridis colors for values in [lo, hi]; NaN -> grey."""
    finite = np.isfinite(values)
    t = np.clip((np.where(finite, values, lo) - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    stops = np.linspace(0, 1, len(_VIRIDIS))
    out = np.stack([np.interp(t, stops, _VIRIDIS[:, c]) for c in range(3)], axis=1).astype(np.uint8)
    out[~finite] = _NO_DATA
    return out


def held_classes(label: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Class indices that some OCCUPIED voxel carries: the classes a map holds, and the only ones its class
    toggles offer (a FREE voxel's label is the free-space evidence's, "void", which no object has)."""
    return np.unique(label[state == STATE_NAMES.index("OCCUPIED")]).astype(np.int64)


def faded(colors: np.ndarray, share: float) -> np.ndarray:
    """sRGB colors ``share`` (0..1) of the way to white."""
    colors = np.asarray(colors, np.float64)
    return np.round(colors + share * (255.0 - colors)).astype(np.uint8)


def frame_of(meta: dict, where) -> WorldFrame | None:
    """The world frame a map file's meta records (None: written before maps recorded their frame)."""
    frame = (meta or {}).get("frame")
    return frame if isinstance(frame, WorldFrame) else WorldFrame.from_dict(frame, f"{where}: meta.frame")


def frame_label(frame: WorldFrame | None) -> str:
    """"map (EPSG:32617)", "map", or "not recorded": the frame as the GUI names it."""
    if frame is None:
        return "not recorded"
    return frame.name + (f" ({frame.crs})" if frame.crs else "")


@dataclass
class MapLayer:
    """One map file, as the viewer needs it: float64 centers in world coordinates of ``frame`` (metres)."""

    name: str
    path: Path
    classes: list[str]
    resolution: float
    grid_offset: float
    centers: np.ndarray
    voxel_index: np.ndarray
    alpha: np.ndarray
    label: np.ndarray
    state: np.ndarray
    variance: np.ndarray
    hits: np.ndarray
    mean_uncertainty: np.ndarray
    method: str
    frame: WorldFrame | None = None
    origin_index: np.ndarray = field(default_factory=lambda: np.zeros(3, np.int64))  # the map origin's voxel index
    # a store overview's rows stand for several voxels each (its tiles are decimated): how many; None: one each
    weight: np.ndarray | None = None
    # class indices that label at least one OCCUPIED voxel (held_classes); None: from the voxels held
    present: np.ndarray | None = None

    def present_labels(self) -> np.ndarray:
        """Class indices that some OCCUPIED voxel carries (the classes the map holds)."""
        if self.present is not None:
            return self.present
        return held_classes(self.label, self.state)

    @classmethod
    def from_file(cls, path) -> "MapLayer":
        """A map file as a layer (read and validated by map_file.read_map_file), read out as ``from_voxels``."""
        contents = read_map_file(path)
        return cls.from_voxels(Path(path).stem, Path(path), reader_mapper(contents), contents.voxels())

    @classmethod
    def from_voxels(cls, name: str, path, reader, voxels, summary=None) -> "MapLayer":
        """A layer of ``voxels`` (VoxelArrays, global indices in key order) read out with ``reader``'s (a
        Mapper's) parameters, classes, origin and frame; ``summary``: their read-out when at hand. The
        layer holds what is drawn or reported, not the sums (evidence, weights) it was read out of."""
        summary = summary if summary is not None else reader.summarize(voxels.evidence, voxels.touched)
        label, state, variance = summary.label.astype(np.int32, copy=False), summary.state.astype(np.int8, copy=False), summary.variance
        del summary  # its class probabilities [V, K] are not drawn: gone before the concentrations are made
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_unc = np.where(voxels.weight_sum > 0, voxels.weighted_uncertainty_sum / voxels.weight_sum, np.nan)
        resolution = reader.config.resolution_m
        return cls(name, Path(path), list(reader.class_names), resolution, reader.grid_offset_m, reader.voxel_centers(voxels.index),
                   np.asarray(voxels.index, np.int64), reader.concentrations(voxels.evidence), label, state, variance, voxels.hits,
                   mean_unc, reader.config.method, reader.frame, lattice_index(reader.origin, resolution))

    @classmethod
    def from_arrays(cls, name: str, path: Path, arrays: dict, meta: dict) -> "MapLayer":
        """A layer from a map file's arrays and meta (map_file.file_arrays gives them for maps that are not files)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_unc = np.where(arrays["weight_sum"] > 0, arrays["weighted_uncertainty_sum"] / arrays["weight_sum"], np.nan)
        return cls(name, path, list(meta["classes"]), float(arrays["resolution"]), float(meta.get("grid_offset_m", 0.0)),
                   np.asarray(arrays["centers"], np.float64), arrays["voxel_index"].astype(np.int64), arrays["alpha"],
                   arrays["label"], arrays["state"], arrays["variance"], arrays["hits"], mean_unc, meta["method"],
                   frame_of(meta, path), lattice_index(np.asarray(arrays["origin"], np.float64), float(arrays["resolution"])))

    @classmethod
    def from_mapper(cls, name: str, path, mapper, voxels=None) -> "MapLayer":
        """A map in memory, as its map file would show it: ``mapper``'s voxels, or ``voxels`` (a copy of
        them, global indices) read out with ``mapper``'s parameters, origin and frame."""
        arrays, summary = mapper.voxels() if voxels is None else (voxels, None)
        return cls.from_voxels(name, path, mapper, arrays, summary)

    def voxel_at(self, points_world: np.ndarray) -> np.ndarray:
        """Row of the voxel containing each point, -1 where none is stored (map files are sorted by key)."""
        if len(self.voxel_index) == 0:
            return np.full(len(points_world), -1)
        # Global indices can exceed the table's 21-bit key range (far maps), so pack relative to the
        # map's own bounding box; the order stays x, then y, then z, as the file is sorted.
        index = voxel_index_of(points_world, self.resolution, self.grid_offset, self.origin_index)
        lo, hi = self.voxel_index.min(axis=0), self.voxel_index.max(axis=0)
        inside = np.all((index >= lo) & (index <= hi), axis=1)
        span = hi - lo + 1

        def pack(rows):
            rows = np.asarray(rows, np.int64) - lo
            return (rows[:, 0] * span[1] + rows[:, 1]) * span[2] + rows[:, 2]

        stored = pack(self.voxel_index)
        keys = pack(np.where(inside[:, None], index, lo).astype(np.int64))
        rows = np.clip(np.searchsorted(stored, keys), 0, len(stored) - 1)
        return np.where(inside & (stored[rows] == keys), rows, -1)


_LAYER_ARRAYS = ("centers", "voxel_index", "alpha", "label", "state", "variance", "hits", "weight_sum", "weighted_uncertainty_sum")


class StoreOverview:
    """A map store in the viewer, at two levels of detail: an overview in which every tile holds an evenly
    spaced share of ``max_voxels`` (its share of the store's voxels, from store.json's counts), and up to
    ``max_detail_tiles`` tiles in full (asked for by the GUI, a pick, or a camera coming near). What is
    held is the overview and those tiles, never the store: tiles are read one at a time and dropped.

    The overview fills in tile by tile (``read_next``, nearest the store's center first), so a viewer can
    draw a first frame before the store is read; the store's extent comes from store.json. Thread-safe:
    the viewer's loader thread reads while GUI callbacks ask for detail."""

    def __init__(self, path, max_voxels: int, *, max_detail_tiles: int = 6):
        from ..core.map_store import MapStore

        self.store = MapStore(path, cache_tiles=0)
        self.path = Path(path)
        if not self.store.tiles:
            raise ValueError(f"{self.path}: the store has no tiles")
        self.max_voxels, self.max_detail_tiles = int(max_voxels), int(max_detail_tiles)
        self.total_voxels = self.store.voxel_count  # in the store's tiles (the overview holds a share of them)
        boxes = {name: np.asarray(info["bounds_m"], np.float64) for name, info in self.store.tiles.items()}
        self.boxes = boxes  # tile -> the box its voxels fill, [[x0, y0, z0], [x1, y1, z1]] (m, world)
        self.bounds = (np.min([b[0] for b in boxes.values()], axis=0), np.max([b[1] for b in boxes.values()], axis=0))
        center = (self.bounds[0] + self.bounds[1]) / 2
        self.along = along_the_strip(boxes)  # tile -> metres along the store's long axis
        # the tiles nearest the middle of the first view first
        self.unread = sorted(boxes, key=lambda name: (float(np.linalg.norm(boxes[name].mean(axis=0)[:2] - center[:2])), name))
        self.parts: dict[str, dict] = {}  # tile -> its overview rows
        self.details: dict[str, dict] = {}  # tile -> all its rows, most recently asked for last
        self.meta = self.store.template.metadata()
        self._present: set[int] = set()
        self._lock = threading.RLock()
        # store.json's frame (MapStore.frame); a store from before stores recorded it: its tiles' meta
        self.frame = self.store.frame if hasattr(self.store, "frame") else frame_of(self.meta, self.path)

    @property
    def complete(self) -> bool:
        """Every tile is in the overview (the background reading is done)."""
        return not self.unread

    @property
    def detail(self) -> tuple[str, ...]:
        """The tiles held in full detail now."""
        return tuple(self.details)

    @property
    def present(self) -> np.ndarray:
        """Class indices that some voxel of the tiles read so far carries."""
        return np.array(sorted(self._present), np.int64)

    @property
    def held_rows(self) -> int:
        """Voxel rows held: the overview's and the detail tiles' (what bounds the viewer's memory)."""
        with self._lock:
            return sum(len(p["state"]) for p in self.parts.values()) + sum(len(p["state"]) for p in self.details.values())

    def _read(self, name: str, keep: int | None) -> dict:
        arrays = file_arrays(self.store.tile_contents(name))
        n = len(arrays["state"])
        self._present.update(held_classes(arrays["label"], arrays["state"]).tolist())
        rows = np.arange(n) if keep is None or keep >= n else np.linspace(0, n - 1, keep).astype(np.int64)
        return {k: arrays[k][rows] for k in _LAYER_ARRAYS} | {"resolution": arrays["resolution"], "origin": arrays["origin"],
                                                             "weight": np.full(len(rows), n / max(len(rows), 1), np.float64)}

    def read_next(self) -> str | None:
        """Read the next tile into the overview; its name, None when every tile is read."""
        with self._lock:
            if not self.unread:
                return None
            name = self.unread.pop(0)
            self.parts[name] = self._read(name, self._share(self.store.tiles[name]["voxels"]))
            return name

    def _share(self, n: int) -> int:
        """Overview rows of a tile of ``n`` voxels: its share of ``max_voxels``, at least one, at most all."""
        return min(n, max(1, int(self.max_voxels * n / max(self.total_voxels, 1))))

    def read_first(self, voxels: int, rows: int | None = None) -> None:
        """Read tiles into the overview, nearest the center first, until it is complete or the next tile would take
        the voxels read beyond ``voxels`` (the cost of reading) or the overview beyond ``rows`` (the cost of
        sending and drawing); at least one tile."""
        read, held = 0, 0
        while self.unread:
            n = self.store.tiles[self.unread[0]]["voxels"]
            share = self._share(n)
            if read and (read + n > voxels or (rows is not None and held + share > rows)):
                return
            read, held = read + n, held + share
            self.read_next()

    def set_detail(self, names) -> bool:
        """Hold these tiles (the latest ``max_detail_tiles`` of them) in full, and no others; whether that changed anything."""
        names = [n for n in dict.fromkeys(names) if n in self.store.tiles][-self.max_detail_tiles:]
        with self._lock:
            if list(self.details) == names:
                return False
            self.details = {name: self.details.get(name) or self._read(name, None) for name in names}
            return True

    def add_detail(self, names) -> bool:
        """Hold these tiles in full as well, dropping those asked for longest ago beyond ``max_detail_tiles``."""
        with self._lock:
            return self.set_detail([n for n in self.details if n not in names] + list(names))

    def tiles_at(self, points_world: np.ndarray, *, column: bool = True) -> list[str]:
        """The store's tiles holding these world points (with ``column``: every tile above and below them too)."""
        from ..core.map_store import tile_keys

        keys = {tuple(k) for k in tile_keys(self.store.voxel_index_of(np.asarray(points_world, np.float64).reshape(-1, 3)),
                                            self.store.tile_voxels).tolist()}
        names = []
        for name in sorted(self.store.tiles):
            key = tuple(int(v) for v in name.split("_"))
            if key in keys or (column and key[:2] in {k[:2] for k in keys}):
                names.append(name)
        return names

    def tiles_along(self) -> list[str]:
        """The store's tiles in order along its long axis (a drive's strip from one end to the other), lowest first."""
        from ..core.map_store import parse_tile_name

        return sorted(self.store.tiles, key=lambda name: (self.along[name], parse_tile_name(name)[::-1]))

    def tile_label(self, name: str) -> str:
        """A tile as a user finds it: "tile (3, -1, 0) at E512 m N-140 m, 830 m along" (its box's middle, world frame)."""
        from ..core.map_store import parse_tile_name

        east, north, _ = self.boxes[name].mean(axis=0)
        return f"tile {parse_tile_name(name)} at E{east:.0f} m N{north:.0f} m, {self.along[name]:.0f} m along"

    def decimated(self, name: str) -> bool:
        """Whether the overview holds only a share of this tile's voxels (showing it in full would add some)."""
        n = self.store.tiles[name]["voxels"]
        return self._share(n) < n

    def tiles_near(self, point_world, reach_m: float, *, around=None) -> list[str]:
        """The tiles whose voxel box lies within ``reach_m`` of ``point_world`` (a camera), nearest ``around`` (what
        the camera looks at; the camera itself without it) first: by the horizontal gap to it, then the vertical."""
        names = list(self.boxes)
        low, high = np.array([self.boxes[n][0] for n in names]), np.array([self.boxes[n][1] for n in names])

        def gaps(point):
            point = np.asarray(point, np.float64).reshape(3)
            return np.maximum(low - point, 0.0) + np.maximum(point - high, 0.0)

        near = np.linalg.norm(gaps(point_world), axis=1) < reach_m
        order = gaps(point_world if around is None else around)
        ranked = sorted(np.flatnonzero(near), key=lambda k: (float(np.linalg.norm(order[k, :2])), float(order[k, 2]), names[k]))
        return [names[k] for k in ranked]

    def layer(self) -> MapLayer:
        """The overview read so far, with the detail tiles in full."""
        with self._lock:
            parts = dict(self.parts) | dict(self.details)  # a tile in full replaces its overview rows
            if not parts:  # nothing read yet: an empty map of the store's classes
                from ..core.voxel_map import VoxelArrays

                empty = VoxelArrays.from_rows(np.zeros((0, 3), np.int64), np.zeros((0, self.store.num_classes + 4)))
                layer = MapLayer.from_arrays(self.path.name, self.path, file_arrays(self.store.template.contents_of(empty)), self.meta)
                layer.frame, layer.weight, layer.present = self.frame, np.zeros(0), self.present
                return layer
            present = self.present
        joined = {k: np.concatenate([p[k] for p in parts.values()]) for k in _LAYER_ARRAYS + ("weight",)}
        joined["resolution"] = next(iter(parts.values()))["resolution"]
        joined["origin"] = next(iter(parts.values()))["origin"]  # a store's tiles share its origin
        order = np.lexsort(joined["voxel_index"].T[::-1])  # key order (x, then y, then z), as a map file's: voxel_at needs it
        joined.update({k: joined[k][order] for k in _LAYER_ARRAYS + ("weight",)})
        layer = MapLayer.from_arrays(self.path.name, self.path, joined, self.meta)
        layer.frame = self.frame
        layer.weight = joined["weight"]
        layer.present = present
        return layer


def along_the_strip(boxes: dict[str, np.ndarray]) -> dict[str, float]:
    """Each tile's place along the tiles' long horizontal axis (m from the first; the principal axis of their
    columns' middles, so that the tiles of a column share it): a drive's strip, end to end. The axis points
    east, or north where it runs north-south."""
    from ..core.map_store import parse_tile_name

    names = list(boxes)
    columns: dict[tuple, list] = {}
    for name in names:
        columns.setdefault(parse_tile_name(name)[:2], []).append(boxes[name].mean(axis=0)[:2])
    middles = np.array([np.mean(columns[parse_tile_name(n)[:2]], axis=0) for n in names]).reshape(-1, 2)
    centered = middles - middles.mean(axis=0)
    axis = np.linalg.svd(centered, full_matrices=False)[2][0] if len(names) > 1 else np.array([1.0, 0.0])
    axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis
    along = centered @ axis
    return {name: float(a - along.min()) for name, a in zip(names, along)}


def load_trajectory(path) -> np.ndarray:
    """Positions [N, 3] from a KITTI/RELLIS poses.txt (12 numbers per line), or N x 3 .txt/.npy."""
    path = Path(path)
    if path.suffix == ".npy":
        data = read_npy(path)
    else:
        try:
            data = np.loadtxt(path, ndmin=2)
        except ValueError as exc:  # UnicodeDecodeError included: binary junk
            raise ValueError(f"{path}: not a table of numbers ({exc})") from None
    if data.ndim == 2 and data.shape[1] == 12:
        return data[:, [3, 7, 11]]
    if data.ndim == 2 and data.shape[1] == 3:
        return data
    raise ValueError(f"{path}: a trajectory needs 3 (x y z) or 12 (3x4 pose) numbers per row, got shape {list(data.shape)}")


def load_points(path) -> np.ndarray:
    """Points [N, 3] from any plain point file (.pcd, .ply, .npy, KITTI .bin)."""
    return read_point_file(path).points


def check_address(host: str, port: int) -> None:
    """Refuse a host this machine cannot serve on (viser would wait forever on it) or a port out of range."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} is outside 1..65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind((address[0], 0))  # any free port: only whether the address is ours is in question
    except (OSError, UnicodeError) as exc:
        raise ValueError(f"cannot serve on host {host!r}: {exc}") from None


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for tests and examples that serve on their own port)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


SELECTION_PROMPT = "Click a voxel, the terrain surface or the ground."


class LocalControl:
    """A control of a view without a browser (a script's, a test's clicks): a viser handle's ``value`` and
    ``content``, whose ``on_update`` callbacks run when ``value`` is set."""

    def __init__(self, value=None, content: str = ""):
        self._value, self.content, self._callbacks = value, content, []

    @property
    def value(self):
        """The control's value; setting it runs the ``on_update`` callbacks, as a browser's change would."""
        return self._value

    @value.setter
    def value(self, value) -> None:
        """Set the value and run the callbacks."""
        self._value = value
        for callback in self._callbacks:
            callback(None)

    def on_update(self, callback):
        """Run ``callback(None)`` whenever ``value`` is set (a viser handle's decorator); returns it."""
        self._callbacks.append(callback)
        return callback


@dataclass
class ClientView:
    """What one browser tab has of its own, from the defaults when it connects: the selection and its
    highlight, the measuring tool and its points. ``scene``: where its marks are drawn (the client's scene,
    seen by that tab only); ``selection``, ``measure``, ``measure_result``: its controls in the panel."""

    scene: object
    selection: object
    measure: object
    measure_result: object
    measure_points: list = field(default_factory=list)
    last_point: np.ndarray | None = None  # world coordinates of the last clicked point
    measure_handles: list = field(default_factory=list)
    selection_handles: list = field(default_factory=list)


class MapViewer:
    """A viser server showing one or more map files, with filters, colorings, picking and export.

    All maps must be in one world frame (``frame``; a ``FrameError`` naming both files and both frames
    otherwise). ``trajectory`` and ``scan`` are read as world coordinates of that frame. The scene is
    drawn relative to ``origin`` (float64 world coordinates, marked by a world-axes frame and a label).
    ``terrain``: compute each map's terrain layers at start (``terrain_resolution`` m cells, the cost
    table ``costs``; the GUI's button does it on demand otherwise). ``truth``: a ground truth for the
    comparison of two maps (``viewer_layers.load_truth``). Handles are attributes: ``server``, ``gui_*``
    for the controls, ``voxel_handles`` per layer, ``terrain_handles``, ``grid_handle``,
    ``origin_axes`` and ``origin_label``.

    ``map_paths`` may hold ``MapLayer`` objects (a map in memory: a live map, a drive's replay), which
    ``replace_layer`` updates. A store (``StoreOverview``) is read for its first frame up to
    ``store_first_voxels`` of its voxels (and ``FIRST_FRAME_ROWS`` overview rows), nearest its center
    first; a loader thread reads the rest of its overview, and the tiles a browser's camera comes near or
    a click hits, in full."""

    FIRST_FRAME_ROWS = 100_000  # a store's first frame: about 1.5 MB to send, a fraction of a second to draw

    def __init__(self, map_paths, *, host: str = "127.0.0.1", port: int = 8080, style: str = "points",
                 max_voxels: int = 500_000, trajectory=None, scan=None, export_dir=None, terrain: bool = False,
                 terrain_resolution=None, costs=None, truth=None, store_first_voxels: int = 1_000_000, same_frame: bool = False):
        import viser

        if style not in ("points", "boxes"):
            raise ValueError(f"style must be 'points' or 'boxes', got {style!r}")
        if not map_paths:
            raise ValueError("give at least one map file")
        from ..core.map_store import is_store

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
        self.style = style
        self.max_voxels = int(max_voxels)
        self.export_dir = Path(export_dir) if export_dir else self.layers[0].path.parent
        self.classes = list(dict.fromkeys(c for layer in self.layers for c in layer.classes))
        self.palette = dict(zip(self.classes, class_palette(self.classes)))
        # the classes some map holds (a voxel with evidence carries them): the only ones offered as toggles
        present = {layer.classes[k] for layer in self.layers for k in layer.present_labels() if k < len(layer.classes)}
        self.present_classes = [c for c in self.classes if c in present]
        self.terrain_resolution, self.costs = terrain_resolution, costs
        self.truth_path = Path(truth) if truth is not None else None
        if self.truth_path is not None and not self.truth_path.is_file():
            raise ValueError(f"{self.truth_path}: no such ground-truth file")
        self.terrain: dict[int, vl.TerrainSurface] = {}
        self._truth: dict[int, np.ndarray] = {}
        self._diff_cache: dict = {}
        self.map_fade = 0.0  # the voxels' colors drawn this share of the way to white (a drive's scan shown over them)
        self.scale_bar: tuple[float, float, float] | None = None  # (metres, pixels, metres per pixel)
        self.center_hit: dict | None = None  # what lies under the screen's center (pick_point), for the last camera
        self._center_camera = None  # (position, look_at) a browser last reported, waiting for _follow_view_center
        self._center_wake = threading.Condition()
        # Updates of a layer (replace_layer) and the controls' callbacks (viser's threads) take turns.
        self._lock = threading.RLock()
        self._refresh_held_by: int | None = None  # the thread in replace_layer, whose control changes wait for its refresh
        self._closed = threading.Event()
        self._detail_wanted: dict[int, list[str]] = {}  # store -> tiles to show in full, for the loader thread
        self._cameras_placed: set[int] = set()  # browsers whose camera has been where the viewer put it
        self._store_wake = threading.Condition()
        self._overviews_shown = threading.Event()  # every store's overview read in full and drawn
        lo, hi = self._bounds()
        # A local origin keeps float32 positions fine-grained however far the map is from 0. Maps that start
        # empty (a live map) get theirs from their first voxels (replace_layer); a store's comes from its index.
        self.origin = np.round((lo + hi) / 2.0)
        self._origin_from_data = any(len(layer.centers) for layer in self.layers) or bool(self.stores)
        self.side_by_side_step = float(hi[0] - lo[0]) + 2.0
        # A fixed random order per layer: decimation keeps the same voxels as filters change.
        self._lod_order = [np.random.default_rng(0).permutation(len(layer.centers)) for layer in self.layers]
        self.visible_rows: list[np.ndarray] = [np.zeros(0, np.int64) for _ in self.layers]

        check_address(host, port)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        vl.configure_lighting(self.server.scene)
        extent = float(max(np.max(hi - lo), 1.0))
        self._auto_camera = None  # (position, look_at) the viewer last set: browsers still there follow the maps as they grow
        # every position the viewer has put cameras at: a browser's report can lag a move or two behind (it was
        # sent before the move arrived), and a camera at any of them has not been moved by its user
        self._auto_positions: collections.deque = collections.deque(maxlen=64)
        self._frame_camera(lo, hi)
        self._build_gui()
        self._add_origin_marker(extent)
        self._add_ground_grid(lo, hi)
        # the orbit center's crosshair, sized in screen pixels on each camera move (_update_scale_bar)
        self.crosshair_handle = self.server.scene.add_line_segments(
            "/view_center", np.array([[[-1, 0, 0], [1, 0, 0]], [[0, -1, 0], [0, 1, 0]], [[0, 0, -1], [0, 0, 1]]], np.float32),
            colors=(30, 30, 30), thickness=2.0, thickness_units="screen", visible=False)
        threading.Thread(target=self._follow_view_center, name="evsemmap-view-center", daemon=True).start()
        self.voxel_handles: list = [None] * len(self.layers)
        self.terrain_handles: dict[int, object] = {}
        self._terrain_drawn: dict[int, tuple] = {}  # what each surface was last drawn as (layer, mode, shift)
        # trajectory and scan: world coordinates of the maps' frame, drawn relative to the local origin
        self.trajectory_handles: list = []
        if trajectory is not None:
            positions = load_trajectory(trajectory) - self.origin
            if len(positions) >= 2:
                self.trajectory_handles.append(self.server.scene.add_spline_catmull_rom(
                    "/trajectory", positions.astype(np.float32), color=TRAJECTORY_COLOR, thickness=3.0, thickness_units="screen"))
            self.trajectory_handles.append(self.server.scene.add_point_cloud(
                "/trajectory_poses", positions.astype(np.float32), colors=TRAJECTORY_COLOR, point_size=0.3, precision="float32"))
        if scan is not None:
            points = load_points(scan) - self.origin
            self.server.scene.add_point_cloud("/scan", points.astype(np.float32), colors=(200, 200, 200),
                                              point_size=0.05, precision="float32")
        self.server.scene.on_click()(self._on_click)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        try:
            if terrain:
                self.compute_terrain()
            self.refresh()
        except BaseException:
            self.server.stop()
            raise
        # stores: the rest of the overview, and tiles in full when asked for (a pick, the camera coming near)
        if all(o.complete for o in self.stores.values()):
            self._overviews_shown.set()
        if self.stores:
            self._store_loader = threading.Thread(target=self._load_stores, name="evsemmap-store-tiles", daemon=True)
            self._store_loader.start()

    @property
    def url(self) -> str:
        """The address the viewer serves on (http://host:port)."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        # The panel's first screen holds what a user reads all the time: the map, its coloring, the
        # counter, the legend and the scale; filters, classes and tools follow.
        with gui.add_folder("Map"):
            names = tuple(f"{i}: {layer.name} ({layer.method})" for i, layer in enumerate(self.layers))
            self.gui_map = gui.add_dropdown("Map", options=names, initial_value=names[0])
            self.gui_side_by_side = gui.add_checkbox("Side by side", initial_value=False, disabled=len(self.layers) == 1)
            self.gui_color_by = gui.add_dropdown("Color by", options=COLOR_MODES, initial_value="semantic")
            # here, not in the terrain folder: with terrain layers, what is drawn is the first thing a user switches
            self.gui_terrain_mode = gui.add_dropdown("Draw", options=vl.TERRAIN_MODES, initial_value=vl.TERRAIN_MODES[1], visible=False)
            self.gui_status = gui.add_markdown("")
        with gui.add_folder("Legend"):
            self.gui_legend = gui.add_image(vl.swatch_image([("", (255, 255, 255))]), label=None)
            # the terrain surface's color bar or class legend, once layers are computed
            self.gui_terrain_legend = gui.add_image(vl.swatch_image([("", (255, 255, 255))]), label=None, visible=False)
            self.gui_scale_bar = gui.add_html('<div id="evsemmap-scale-bar" style="font:12px sans-serif">scale: waiting for the camera</div>')
            self.gui_view_center = gui.add_markdown("under the screen's center: waiting for the camera")
        # filled by a drive's playback (viewer_drive.DrivePlayback) or a live map (viewer_live): kept next to the legend
        self.gui_drive_folder = gui.add_folder("Drive", visible=False)
        # the selection and the measuring tool are each browser tab's own (ClientView), made as it connects
        self.gui_selected_folder = gui.add_folder("Selected")
        with gui.add_folder("Filters"):
            self.variance_unit, step, top, label = self._variance_slider_range()
            self.gui_max_variance = gui.add_slider(label, min=0.0, max=top, step=step, initial_value=top)
            self.gui_show_free = gui.add_checkbox("Show FREE", initial_value=False)
            self.gui_show_unknown = gui.add_checkbox("Show UNKNOWN", initial_value=False)
            self.gui_full_map = gui.add_checkbox("Full map (no decimation)", initial_value=False)
            self.gui_tile = None
            if self.stores:  # a store: its overview, and a tile in full detail, flown to
                tiles = ("(overview only)",) + tuple(self.tile_choices)
                self.gui_tile = gui.add_dropdown("Store tile in full", options=tiles, initial_value=tiles[0])
                self.gui_tile.on_update(lambda _event: self.show_tile(self.gui_tile.value))
        self.gui_classes_folder = gui.add_folder("Classes")
        with self.gui_classes_folder:
            self.gui_classes = {name: gui.add_checkbox(name, initial_value=True) for name in self.present_classes}
        self.gui_orientation_folder = gui.add_folder("Orientation and measuring")
        with self.gui_orientation_folder:
            self.gui_view = gui.add_button_group("View", VIEW_BUTTONS)
            self.gui_grid = gui.add_checkbox("Ground grid", initial_value=True)
        with gui.add_folder("Terrain layers"):
            self.gui_terrain_compute = gui.add_button("Compute terrain layers")
            self.gui_terrain_show = gui.add_checkbox("Show surface", initial_value=True)
            self.gui_terrain_band = gui.add_dropdown("Layer", options=("traversability_cost",), initial_value="traversability_cost")
            self.gui_terrain_status = gui.add_markdown("Not computed: the button computes the layers of each map (docs/terrain.md).")
        self.gui_diff = self.gui_diff_against = self.gui_diff_status = None
        if len(self.layers) > 1:
            with gui.add_folder("Compare maps"):
                self.gui_diff = gui.add_dropdown("Show", options=vl.DIFF_MODES, initial_value="off")
                self.gui_diff_against = gui.add_dropdown("Second map", options=names, initial_value=names[1])
                truth = f"truth: `{self.truth_path.name}`" if self.truth_path else "no ground truth given (`--truth`)"
                self.gui_diff_status = gui.add_markdown(f"The first map is the one chosen above; {truth}.")
        with gui.add_folder("Frame"):
            self.gui_frame = gui.add_markdown(self._frame_text())
        with gui.add_folder("Export"):
            self.gui_export_html = gui.add_button("Standalone HTML")
            self.gui_export_ply = gui.add_button("PLY point cloud")
            self.gui_export_status = gui.add_markdown("")
        controls = [self.gui_map, self.gui_side_by_side, self.gui_color_by, self.gui_max_variance, self.gui_show_free, self.gui_show_unknown,
                    self.gui_full_map, *self.gui_classes.values(), self.gui_terrain_show, self.gui_terrain_band, self.gui_terrain_mode]
        if self.gui_diff is not None:
            controls += [self.gui_diff, self.gui_diff_against]
        for handle in controls:
            handle.on_update(lambda _event: self._on_control())
        self.gui_grid.on_update(lambda _event: self._show_grid(self.gui_grid.value))
        self.gui_view.on_click(lambda event: self.set_view(event.target.value, event.client))
        self.gui_side_by_side.on_update(lambda event: self.frame_shown(event.client))
        # a view for clicks that come from no browser (scripts, tests)
        self._local_view = self._new_view(self.server.scene, LocalControl(content=SELECTION_PROMPT),
                                          LocalControl(False), LocalControl(content=""))
        self._views: dict[int, ClientView] = {}
        self._acting_view = self._local_view
        self.gui_terrain_compute.on_click(lambda _event: self._compute_terrain_from_gui())
        self.gui_export_html.on_click(lambda _event: self._export_from_gui("html"))
        self.gui_export_ply.on_click(lambda _event: self._export_from_gui("ply"))

    def _on_control(self) -> None:
        # replace_layer sets several controls, then refreshes once; a change made on another thread meanwhile refreshes itself
        if self._refresh_held_by != threading.get_ident():
            self.refresh()

    def _variance_slider_range(self) -> tuple[float, float, float, str]:
        """(unit, step, top, label) of the variance slider for the maps' largest variance."""
        max_var = max([float(layer.variance.max()) for layer in self.layers if len(layer.variance)] or [1.0])
        # The slider counts in units of 10^e so that its number box shows the whole value ("1.71", not "0.01710").
        unit = 10.0 ** math.floor(math.log10(max_var)) if max_var > 0 else 1.0
        step = 10.0 ** math.floor(math.log10(max(max_var / unit, 1e-12) / 200))
        top = math.ceil(max_var / unit / step - 1e-9) * step if max_var > 0 else 1.0
        exponent = int(round(math.log10(unit)))
        return unit, step, top, "Max variance" + (f" ×1e{exponent}" if exponent else "")

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The maps' bounding box (world coordinates, m): their voxel centers, and the whole of each store (from
        its index, however much of it is read); zeros while every map is empty."""
        lows = [layer.centers.min(axis=0) for layer in self.layers if len(layer.centers)] + [o.bounds[0] for o in self.stores.values()]
        highs = [layer.centers.max(axis=0) for layer in self.layers if len(layer.centers)] + [o.bounds[1] for o in self.stores.values()]
        return np.min(lows or [np.zeros(3)], axis=0), np.max(highs or [np.zeros(3)], axis=0)

    def replace_layer(self, i: int, layer: "MapLayer") -> None:
        """Show ``layer`` as map ``i`` from now on (a drive's map as of a scan, a live map's latest copy,
        a store overview with more tiles): the classes it holds join the toggles, and the variance slider,
        the ground grid and (for maps that were empty) the local origin are fitted to it. Safe to call
        from any thread."""
        with self._lock:
            if self._closed.is_set():  # a loader, a replay or a live map still at work after close()
                return
            check_same_frame("view together", (str(self.layers[i].path), self.layers[i].frame), (str(layer.path), layer.frame),
                             same_frame=self.same_frame)
            was_at_top = self.gui_max_variance.value >= self.gui_max_variance.max - 0.5 * self.gui_max_variance.step
            threshold = self.max_variance
            if self.voxel_handles[i] is not None and layer.name != self.layers[i].name:
                self.voxel_handles[i].remove()  # its scene node is named after the map: another name, another node
                self.voxel_handles[i] = None
            self.layers[i] = layer
            self._lod_order[i] = np.random.default_rng(0).permutation(len(layer.centers))
            self._refresh_held_by = threading.get_ident()
            try:
                self._add_new_classes()
                unit, step, top, label = self._variance_slider_range()
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
        if not new:
            return
        self.present_classes = [c for c in self.classes if c in present or c in self.present_classes]
        with self.gui_classes_folder:
            for name in new:
                self.gui_classes[name] = self.server.gui.add_checkbox(name, initial_value=True)
                self.gui_classes[name].on_update(lambda _event: self._on_control())

    def _fit_scene(self) -> None:
        """The local origin from the first voxels of maps that started empty; the ground grid over the maps' extent."""
        lo, hi = self._bounds()
        if not any(len(layer.centers) for layer in self.layers):
            return
        extent = float(max(np.max(hi - lo), 1.0))
        if not self._origin_from_data:
            self.origin = np.round((lo + hi) / 2.0)
            self._origin_from_data = True
            self._add_origin_marker(extent)
            self.gui_frame.content = self._frame_text()
            self._frame_camera(lo, hi)
            self._add_ground_grid(lo, hi)
        elif np.any(lo[:2] < (self.ground.x0, self.ground.y0)) or np.any(hi[:2] > (self.ground.x1, self.ground.y1)):
            self._frame_camera(lo, hi)
            self._add_ground_grid(lo, hi)
        self.side_by_side_step = float(hi[0] - lo[0]) + 2.0

    def _frame_camera(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Point the initial camera, and the cameras of browsers whose users have not moved theirs, at the maps' extent."""
        extent = float(max(np.max(hi - lo), 1.0))
        position, look_at = self._framing(lo, hi)
        previous, self._auto_camera = self._auto_camera, (position, look_at)
        self.server.initial_camera.position, self.server.initial_camera.look_at = tuple(position), tuple(look_at)
        # viser clips at 1 km by default: a long store framed whole (its camera a few km away) drew nothing
        far = self.far_plane_m(extent)
        self.server.initial_camera.far = far
        for client in self.server.get_clients().values():
            client.camera.far = far  # (its setter sends nothing when unchanged)
            if previous is not None and self._camera_left_alone(client.camera):
                client.camera.position, client.camera.look_at = tuple(position), tuple(look_at)
        self._auto_positions.append((position, 1e-3 * max(float(np.linalg.norm(position - look_at)), 1.0)))

    def _framing(self, lo: np.ndarray, hi: np.ndarray, *, panel_margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(position, look_at) in display coordinates of a camera that sees the box ``lo``..``hi`` (world
        coordinates) whole from the south, above. ``panel_margin``: the box's share of its width moved left
        of the screen's center, out from under the GUI panel on the right, with the camera that much further away."""
        extent = float(max(np.max(hi - lo), 1.0))
        look_at = np.round((lo + hi) / 2.0) - self.origin + np.array([panel_margin * float(hi[0] - lo[0]), 0.0, 0.0])
        reach = extent * (1.0 + panel_margin)
        return look_at + np.array([0.0, -0.9 * reach, 0.7 * reach]), look_at

    def _place_cameras(self, client, position: np.ndarray, look_at: np.ndarray) -> None:
        """Move one browser's camera (``client``; every browser's for None) to ``position``, looking at ``look_at``."""
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for each in clients:
            each.camera.position, each.camera.look_at = tuple(position), tuple(look_at)  # position moves look_at along: it goes first

    def set_view(self, which: str, client=None) -> None:
        """The View buttons: "top-down" looks straight down at what a browser's camera looks at, from as far;
        "reset view" puts it where the viewer first put it (the maps whole, from the south)."""
        if which == VIEW_BUTTONS[1]:
            self._place_cameras(client, *self._auto_camera)
            return
        for each in [client] if client is not None else list(self.server.get_clients().values()):
            look_at = np.asarray(each.camera.look_at, np.float64)
            distance = float(np.linalg.norm(np.asarray(each.camera.position, np.float64) - look_at))
            # a little south of straight above: orbit controls have no heading when looking exactly along the up axis
            self._place_cameras(each, look_at + np.array([0.0, -1e-3 * distance, distance]), look_at)

    def frame_shown(self, client=None) -> None:
        """Point a browser's camera (every browser's for None) at the maps shown, all of them side by side, clear
        of the GUI panel."""
        shown = [i for i in self._shown_layers() if len(self.layers[i].centers)]
        if not shown:
            return
        lo = np.min([self.layers[i].centers.min(axis=0) + self._shift(i) for i in shown], axis=0)
        hi = np.max([self.layers[i].centers.max(axis=0) + self._shift(i) for i in shown], axis=0)
        self._place_cameras(client, *self._framing(lo, hi, panel_margin=0.15 if len(shown) > 1 else 0.0))

    @staticmethod
    def far_plane_m(extent_m: float) -> float:
        """The cameras' far clipping plane for maps ``extent_m`` across: the whole of them from the initial
        camera (about 1.14 extents away) and from a camera pulled back a few times further; never nearer
        than viser's 1 km."""
        return max(1000.0, 8.0 * extent_m)

    def _camera_left_alone(self, camera) -> bool:
        """Whether a browser's camera is still where the viewer put it, at this or an earlier move (the position
        alone: a report sent between a move's position and its look-at holds the one and not the other)."""
        try:
            reported = np.asarray(camera.position, dtype=np.float64)
        except AssertionError:  # viser: this browser has not reported its camera yet; the initial camera will place it
            return False
        return any(np.linalg.norm(reported - placed) < tolerance for placed, tolerance in self._auto_positions)

    @property
    def max_variance(self) -> float:
        """The variance threshold the slider sets (the slider counts in ``variance_unit``)."""
        return float(self.gui_max_variance.value) * self.variance_unit

    # ------------------------------------------------------------------ world frame
    def origin_text(self) -> str:
        """The local origin in world coordinates of the frame, e.g. "map: x=500003.000, y=4000003.000, z=100.000 m"."""
        name = self.frame.name if self.frame is not None else "world (frame not recorded)"
        return f"{name}: " + ", ".join(f"{axis}={value:.3f}" for axis, value in zip("xyz", self.origin)) + " m"

    def _frame_text(self) -> str:
        count = len(self.layers)
        lines = [f"frame: **{frame_label(self.frame)}**" + (f" (all {count} maps)" if count > 1 else ""),
                 f"axes at the local origin, {self.origin_text()}"]
        if count > 1 and self.gui_side_by_side.value:
            lines.append(f"side by side: map *i* is drawn shifted by *i* x {self.side_by_side_step:.1f} m along x "
                         "(display only; a clicked voxel reports world coordinates)")
        return "\n\n".join(lines)

    def _add_origin_marker(self, extent: float) -> None:
        """World axes at the local origin (the scene's 0), labelled with its world coordinates in the frame."""
        length = float(np.clip(0.1 * extent, 1.0, 50.0))
        self.origin_axes = self.server.scene.add_frame("/world_origin", axes_length=length, axes_radius=length / 40)
        self.origin_label = self.server.scene.add_label("/world_origin/label", self.origin_text(), anchor="top-right")
        for k, axis in enumerate("xyz"):
            tip = np.zeros(3)
            tip[k] = 1.1 * length
            self.server.scene.add_label(f"/world_origin/{axis}", f"+{axis}", position=tuple(tip), anchor="center-center")

    # ------------------------------------------------------------------ orientation
    def _add_ground_grid(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """A grid under the maps, its lines on round world coordinates, labelled in metres of the frame."""
        occupied = [layer.centers[layer.state == STATE_NAMES.index("OCCUPIED"), 2] for layer in self.layers]
        occupied = np.concatenate(occupied) if occupied else np.zeros(0)
        resolution = min(layer.resolution for layer in self.layers)
        ground = float(np.percentile(occupied, 1.0)) if len(occupied) else float(lo[2])
        grid = self.ground = vl.ground_grid(lo, hi, ground - 0.5 * resolution)
        for handle in getattr(self, "grid_label_handles", []):  # a grid redrawn for maps that grew
            handle.remove()
        center = np.array([(grid.x0 + grid.x1) / 2, (grid.y0 + grid.y1) / 2, grid.z]) - self.origin
        size = max(grid.x1 - grid.x0, grid.y1 - grid.y0)
        self.grid_handle = self.server.scene.add_grid(
            "/ground_grid", width=grid.x1 - grid.x0, height=grid.y1 - grid.y0, plane="xy", cell_size=grid.cell, section_size=grid.section,
            cell_color=(215, 215, 215), section_color=(150, 150, 150), section_thickness=1.5, fade_distance=4.0 * size,
            shadow_opacity=0.0, position=tuple(center), visible=self.gui_grid.value)
        self.grid_label_handles = [
            self.server.scene.add_label(f"/ground_grid_labels/{k}", text, position=tuple(position - self.origin), anchor="center-center",
                                        font_screen_scale=0.8, visible=self.gui_grid.value)
            for k, (text, position) in enumerate(grid.labels)]

    def _show_grid(self, visible: bool) -> None:
        for handle in [self.grid_handle, *self.grid_label_handles]:
            handle.visible = bool(visible)

    def _new_view(self, scene, selection, measure, measure_result) -> ClientView:
        view = ClientView(scene, selection, measure, measure_result)
        measure.on_update(lambda _event: self._reset_measure(view, acting=True))
        return view

    def _on_connect(self, client) -> None:
        with self.gui_selected_folder:
            selection = client.gui.add_markdown(SELECTION_PROMPT)
        with self.gui_orientation_folder:
            measure = client.gui.add_checkbox("Measure (click 2 points)", initial_value=False)
            result = client.gui.add_markdown("")
        self._views[client.client_id] = self._new_view(client.scene, selection, measure, result)
        client.camera.on_update(lambda camera: self._on_camera(client.client_id, camera))
        self._update_scale_bar(client.camera)

    def _on_disconnect(self, client) -> None:
        view = self._views.pop(client.client_id, None)
        if view is self._acting_view:
            self._acting_view = self._local_view

    def view_of(self, client) -> ClientView:
        """A browser tab's own view (``client``: a viser client; None: the view of clicks from no browser)."""
        if client is None:
            return self._local_view
        return self._views.get(client.client_id) or self._local_view

    # The view whose controls a click or a tick changed last: what these names read (scripts and tests).
    gui_selection = property(lambda self: self._acting_view.selection)
    gui_measure = property(lambda self: self._acting_view.measure)
    gui_measure_result = property(lambda self: self._acting_view.measure_result)
    measure_points = property(lambda self: self._acting_view.measure_points)
    last_point = property(lambda self: self._acting_view.last_point)

    def _on_camera(self, client_id: int, camera) -> None:
        self._update_scale_bar(camera)
        if not self.stores:
            return
        # A browser first reports viser's default camera (3 m from the origin), then the initial one: only a
        # camera that has been where the viewer put it has come near anything.
        if client_id not in self._cameras_placed:
            position, look_at = self._auto_camera
            if np.linalg.norm(np.asarray(camera.position) - position) > 1e-3 * max(float(np.linalg.norm(position - look_at)), 1.0):
                return
            self._cameras_placed.add(client_id)
        self._approach(camera)

    def _update_scale_bar(self, camera) -> None:
        """The scale bar for a browser's camera: a round length and its screen pixels at the orbit center."""
        try:
            height = float(camera.image_height)
            m_per_px = vl.metres_per_pixel(camera.position, camera.look_at, camera.fov, height)
        except (AttributeError, TypeError, ValueError):
            return
        if not height > 0 or not np.isfinite(m_per_px) or m_per_px <= 0:
            return
        html_text, metres, pixels = vl.scale_bar_html(m_per_px)
        self.scale_bar = (metres, pixels, m_per_px)
        self.gui_scale_bar.content = html_text
        self._fit_point_sizes()
        look_at = np.asarray(camera.look_at, np.float64)
        self.crosshair_handle.position = tuple(look_at)
        self.crosshair_handle.scale = 8.0 * m_per_px
        if not self.crosshair_handle.visible:  # once: each assignment is a message to every browser
            self.crosshair_handle.visible = True
        with self._center_wake:
            self._center_camera = (np.asarray(camera.position, np.float64), look_at)
            self._center_wake.notify_all()

    def _follow_view_center(self) -> None:
        """The panel's line on what lies under the screen's center, for the camera reported last: picking walks the
        visible voxels, so it runs here, off viser's callbacks, and skips the cameras a drag passed through."""
        while not self._closed.is_set():
            with self._center_wake:
                while self._center_camera is None and not self._closed.is_set():
                    self._center_wake.wait(1.0)
                camera, self._center_camera = self._center_camera, None
            if camera is None:
                continue
            position, look_at = camera
            try:
                with self._lock:
                    hit = self.pick_point(position, look_at - position) if np.linalg.norm(look_at - position) > 0 else None
                    self.center_hit = hit
                    self.gui_view_center.content = self._center_text(hit)
            except Exception:  # noqa: BLE001 - a layer replaced under the pick, or the server stopping: the next camera tries again
                if self._closed.is_set():
                    return

    def _center_text(self, hit: dict | None) -> str:
        if hit is None:
            return "under the screen's center: nothing (no voxel, surface or ground there)"
        where = ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", hit["point"]))
        if hit["kind"] == "voxel":
            layer = self.layers[hit["layer"]]
            what = f"a voxel of {layer.name}, {layer.classes[layer.label[hit['row']]]}"
        elif hit["kind"] == "cell":
            what = f"the terrain surface of {self.layers[hit['layer']].name}"
        else:
            what = "the ground grid's plane"
        return f"under the screen's center ({what}): {where} m in {describe_frame(self.frame)}"

    MIN_POINT_PX = 2.0  # a voxel drawn as a point is never smaller than this on screen, at the orbit center

    def _point_size(self, i: int) -> float:
        """Layer ``i``'s point size (m): its voxel edge, or, when that would be under ``MIN_POINT_PX`` pixels at the
        last camera's orbit center, that many pixels' worth. viser sizes points in world units (shrinking with
        distance, with no screen minimum), so a long store seen whole, 0.2 m voxels over kilometres, drew
        nothing at all."""
        floor = self.MIN_POINT_PX * self.scale_bar[2] if self.scale_bar is not None else 0.0
        return max(float(self.layers[i].resolution), floor)

    def _fit_point_sizes(self) -> None:
        """Resize the drawn point layers to the camera (a size change only: the points are not sent again). The
        size is the scene's, shared by every browser: the camera that moved last sets it."""
        if self.style != "points":
            return
        # under the layers' lock: a store loader or a live map may be replacing these handles right now (viser
        # refuses writes to a removed one), and a layer drawn anew takes its size from _point_size anyway
        with self._lock:
            for i, handle in enumerate(self.voxel_handles):
                if handle is not None:
                    size = self._point_size(i)
                    if abs(handle.point_size - size) > 0.05 * size:  # not for every small camera move
                        handle.point_size = size

    # ------------------------------------------------------------------ layers shown
    @property
    def tile_choices(self) -> dict[str, tuple[int, str]]:
        """The *Store tile in full* list: each store's tiles in order along it, labelled by where they are
        (``StoreOverview.tile_label``, after "i: " where there are several maps) -> (map, tile)."""
        prefix = len(self.layers) > 1
        return {(f"{i}: " if prefix else "") + overview.tile_label(name): (i, name)
                for i, overview in self.stores.items() for name in overview.tiles_along()}

    def show_tile(self, choice: str) -> None:
        """Show a store's tile (a ``tile_choices`` label, or "i: X_Y_Z") in full detail over its overview and fly
        every browser's camera to it; "(overview only)": no tile of any store in full."""
        chosen = None if choice.startswith("(") else self.tile_choices.get(choice) or (int(choice.split(":")[0]), choice.split(": ")[1])
        if chosen is not None:  # first: the camera moves at once, while the tile is read and sent
            self.fly_to_tile(*chosen)
        for i, overview in self.stores.items():
            if chosen is None:
                changed = overview.set_detail([])
            elif chosen[0] == i:  # added to the tiles the camera's new place brings in (_approach), not in place of them
                changed = overview.add_detail([chosen[1]])
            else:
                continue
            if changed:
                self.replace_layer(i, overview.layer())

    def fly_to_tile(self, i: int, name: str) -> None:
        """Move every browser's camera to store ``i``'s tile ``name``: looking at its middle from the south, above,
        near enough that the tile fills most of the view (and so nearer than ``APPROACH_TILES``: its neighbours
        come in full as well)."""
        box = self.stores[i].boxes[name]
        look_at = box.mean(axis=0) - self.origin + self._shift(i)
        distance = max(float(np.max(box[1, :2] - box[0, :2])), 4.0 * self.layers[i].resolution)
        self._place_cameras(None, look_at + distance * np.array([0.0, -0.6, 0.8]), look_at)

    # ------------------------------------------------------------------ store tiles in the background
    # A browser's camera nearer a store's tile than this many tile edges brings tiles in full: from a long drive's
    # store (tiles 51 m across, an overview of 1 voxel in 50), 4 edges is where its points stand apart on screen.
    APPROACH_TILES = 4.0
    # ... and nearer than this share of the store's length: a camera that frames a small store whole is not near it
    APPROACH_EXTENT = 0.25

    def request_detail(self, i: int, names: list[str]) -> None:
        """Have store ``i``'s tiles ``names`` shown in full (read on the loader thread)."""
        if names and not set(names) <= set(self.stores[i].detail):
            with self._store_wake:
                self._detail_wanted[i] = list(names)
                self._store_wake.notify_all()

    def _approach(self, camera) -> None:
        """Tiles in full where a browser's camera has come near a store: of the tiles within ``APPROACH_TILES``
        tile edges (and ``APPROACH_EXTENT`` of the store's length) of the camera, those nearest its orbit center
        (its column first), up to the store's ``max_detail_tiles``. Only tiles the overview decimates: the
        others are there in full already."""
        try:
            position, look_at = np.asarray(camera.position, np.float64), np.asarray(camera.look_at, np.float64)
        except (AttributeError, TypeError, ValueError):
            return
        for i, overview in self.stores.items():
            if i not in self._shown_layers():
                continue
            length = float(np.max(overview.bounds[1][:2] - overview.bounds[0][:2]))
            reach = min(self.APPROACH_TILES * overview.store.tile_voxels * self.layers[i].resolution, self.APPROACH_EXTENT * length)
            to_world = self.origin - self._shift(i)
            near = [name for name in overview.tiles_near(position + to_world, reach, around=look_at + to_world) if overview.decimated(name)]
            self.request_detail(i, near[: overview.max_detail_tiles][::-1])  # the nearest asked for last: kept longest

    def _load_stores(self) -> None:
        sent = {i: len(self.layers[i].state) for i in self.stores}  # rows each store's overview had when last sent
        while not self._closed.is_set():
            with self._store_wake:
                while not self._closed.is_set() and not self._detail_wanted and all(o.complete for o in self.stores.values()):
                    self._store_wake.wait(timeout=1.0)
                wanted, self._detail_wanted = self._detail_wanted, {}
            try:
                for i, names in wanted.items():
                    # the tile asked for last (nearest what the camera looks at) shown first, then the rest with it
                    for batch in (names[-1:], names):
                        if self.stores[i].add_detail(batch):
                            self.replace_layer(i, self.stores[i].layer())
                for i, overview in self.stores.items():
                    if overview.complete or wanted:
                        continue  # detail first: what the user is looking at
                    overview.read_next()
                    # Each push sends the whole overview again: pushed as it grows by half, the browser receives about
                    # twice the final overview in all, however many tiles the store has.
                    if overview.complete or overview.held_rows >= 1.5 * sent[i]:
                        self.replace_layer(i, overview.layer())
                        sent[i] = len(self.layers[i].state)
                    if all(o.complete for o in self.stores.values()):
                        self._overviews_shown.set()
                    break
            except Exception as exc:  # shown, not raised: the viewer keeps serving what it has
                self.gui_status.content = f"**Cannot read the store:** {type(exc).__name__}: {exc}"
                self._closed.wait(5.0)

    def wait_for_stores(self, timeout: float | None = None) -> bool:
        """Wait until every store's overview is read in full and shown (exports then hold all of it); whether it was."""
        return self._overviews_shown.wait(timeout)

    def close(self) -> None:
        """Stop reading stores and serving."""
        with self._lock:  # after a layer update under way, and before any other
            self._closed.set()
        for wake in (self._store_wake, self._center_wake):
            with wake:
                wake.notify_all()
        self.server.stop()

    def _diff_pair(self) -> tuple[int, int] | None:
        """(first, second) map indices while a comparison is shown."""
        if self.gui_diff is None or self.gui_diff.value == "off":
            return None
        first, second = int(self.gui_map.value.split(":")[0]), int(self.gui_diff_against.value.split(":")[0])
        return (first, second) if first != second else None

    def _shown_layers(self) -> list[int]:
        if self._diff_pair() is not None:
            return [self._diff_pair()[0]]
        if self.gui_side_by_side.value:
            return list(range(len(self.layers)))
        return [int(self.gui_map.value.split(":")[0])]

    def _shift(self, i: int) -> np.ndarray:
        side_by_side = self.gui_side_by_side.value and self._diff_pair() is None
        return np.array([self.side_by_side_step * i if side_by_side else 0.0, 0.0, 0.0])

    def _voxels_hidden(self) -> bool:
        """The terrain surface is drawn instead of the voxels."""
        return bool(self.terrain) and self.gui_terrain_show.value and self.gui_terrain_mode.value == vl.TERRAIN_MODES[1]

    def visible_mask(self, i: int) -> np.ndarray:
        """[V] bool: the voxels of layer ``i`` the panel's filters (states, classes, maximum variance, the diff) leave visible."""
        layer = self.layers[i]
        keep = np.ones(len(layer.state), bool)
        if not self.gui_show_free.value:
            keep &= layer.state != STATE_NAMES.index("FREE")
        if not self.gui_show_unknown.value:
            keep &= layer.state != STATE_NAMES.index("UNKNOWN")
        keep &= layer.variance <= self.max_variance + 1e-12
        hidden = [k for k, name in enumerate(layer.classes) if name in self.gui_classes and not self.gui_classes[name].value]
        if hidden:
            keep &= ~np.isin(layer.label, hidden)
        pair = self._diff_pair()
        if pair is not None and i == pair[0]:
            diff = self.diff()
            compared = np.zeros(len(layer.state), bool)
            rows = diff.a_rows[diff.differ] if self.gui_diff.value == "labels differ" else diff.a_rows
            compared[rows] = True
            keep &= compared
        return keep

    # ------------------------------------------------------------------ comparing two maps
    def truth_labels(self, i: int) -> np.ndarray | None:
        """The ground truth's label of every voxel of map ``i`` (-1: none), None without ``truth``."""
        if self.truth_path is None:
            return None
        key = (i, id(self.layers[i]))
        if key not in self._truth:
            self._truth = {key: vl.load_truth(self.truth_path, self.layers[i], self.frame)}
        return self._truth[key]

    def diff(self) -> vl.MapDiff:
        """The comparison of the first and second maps chosen in the GUI (cached)."""
        first, second = self._diff_pair()
        key = (first, second, id(self.layers[first]), id(self.layers[second]))
        if key not in self._diff_cache:
            self._diff_cache = {key: vl.compare_maps(self.layers[first], self.layers[second], self.truth_labels(first))}
        return self._diff_cache[key]

    def colors(self, i: int, rows: np.ndarray) -> np.ndarray:
        """[len(rows), 3] uint8 sRGB colors of layer ``i``'s voxels ``rows`` in the chosen coloring (class, variance, uncertainty, or the diff's)."""
        layer = self.layers[i]
        pair = self._diff_pair()
        if pair is not None and i == pair[0]:
            diff = self.diff()
            where = np.full(len(layer.state), -1, np.int64)
            where[diff.a_rows] = np.arange(len(diff.a_rows))
            at = where[rows]
            if self.gui_diff.value == "labels differ":
                table = np.array(list(vl.DIFF_COLORS.values()), np.uint8)
                return table[np.clip(diff.category()[at], 0, len(table) - 1)]
            values = diff.variance_difference[at]
            limit = float(np.abs(values).max()) if len(values) else 0.0
            limit = limit if limit > 0 else 1.0
            self._color_range = (-limit, limit)
            return vl.diverging(values, limit)
        mode = self.gui_color_by.value
        if mode == "semantic":
            table = np.array([self.palette[name] for name in layer.classes], np.uint8)
            return table[layer.label[rows]]
        values = {"variance": layer.variance, "mean uncertainty": layer.mean_uncertainty,
                  "observations": np.log10(1.0 + layer.hits.astype(np.float64))}[mode][rows]
        finite = values[np.isfinite(values)]
        lo, hi = (float(finite.min()), float(finite.max())) if len(finite) else (0.0, 1.0)
        self._color_range = (lo, hi)
        return colormap(values, lo, hi)

    def refresh(self) -> None:
        """Recompute what is shown from the controls and push it to every browser."""
        with self._lock:
            self._refresh()

    def _refresh(self) -> None:
        try:
            pair = self._diff_pair()
            if pair is not None:
                self.diff()
        except ValueError as exc:  # maps that cannot be compared voxel by voxel: say why, show them as they are
            self.gui_diff_status.content = f"**Cannot compare:** {exc}"
            self.gui_diff.value = "off"
            return  # setting the value refreshes
        shown = self._shown_layers()
        hide_voxels = self._voxels_hidden()
        total_visible = total_drawn = 0
        stands_for = 0.0  # voxels of the maps (a store's, not only its overview's) that the filters let through
        self._color_range = None
        with self.server.atomic():
            for i, layer in enumerate(self.layers):
                if i not in shown or hide_voxels:
                    if self.voxel_handles[i] is not None:
                        self.voxel_handles[i].visible = False
                    self.visible_rows[i] = np.zeros(0, np.int64)
                    continue
                keep = self.visible_mask(i)
                total_visible += int(keep.sum())
                stands_for += float(layer.weight[keep].sum()) if layer.weight is not None else float(keep.sum())
                order = self._lod_order[i]
                rows = order[keep[order]]
                # a store's layer is decimated already (its overview), except the tile asked for in full
                if not self.gui_full_map.value and len(rows) > self.max_voxels and i not in self.stores:
                    rows = rows[: self.max_voxels]
                rows = np.sort(rows)
                self.visible_rows[i] = rows
                total_drawn += len(rows)
                self._draw_layer(i, rows)
            self._draw_terrain(shown)
        self.gui_status.content = self._status_text(shown, total_drawn, total_visible, stands_for, hide_voxels)
        self.gui_legend.image = self._legend_image()
        self.gui_legend.visible = not hide_voxels
        self.gui_terrain_legend.visible = bool(self.terrain) and self.gui_terrain_show.value
        self.gui_frame.content = self._frame_text()
        pair = self._diff_pair()
        if pair is not None:
            keep = self.visible_mask(pair[0])[self.diff().a_rows] if self.gui_diff.value == "variance difference" else None
            text = self.diff().describe(keep)
            if self.gui_diff.value == "variance difference" and self._color_range:
                text += (f"\n\ncolor: variance of the first minus the second, ±{self._color_range[1]:.3g} "
                         "(blue: the first map is surer, red: the second)")
            self.gui_diff_status.content = text

    def _status_text(self, shown, drawn: int, visible: int, stands_for: float, hide_voxels: bool) -> str:
        """The counter: drawn against visible voxels, a store's overview against the store it stands for."""
        if hide_voxels:
            return "voxels hidden: the terrain surface is drawn instead"
        if any(i in self.stores for i in shown):
            total = sum(self.stores[i].total_voxels for i in shown if i in self.stores) + sum(
                len(self.layers[i].state) for i in shown if i not in self.stores)
            held = sum(len(self.layers[i].state) for i in shown)
            unread = sum(len(self.stores[i].unread) for i in shown if i in self.stores)
            reading = f"; reading its tiles: {unread:,} to go" if unread else ""
            full = sum(len(self.stores[i].detail) for i in shown if i in self.stores)
            detail = f"; {full} tile(s) in full" if full else ""
            if held < total:
                return (f"{drawn:,} voxels drawn of about {round(stands_for):,} visible in the store (decimated: a store overview holds "
                        f"{held:,} of its {total:,} voxels{detail}{reading}; come near a tile, click it or choose it for full detail)")
        elif any(self.layers[i].weight is not None for i in shown):  # an overview of tiles as they are written
            total = round(sum(float(self.layers[i].weight.sum()) if self.layers[i].weight is not None else len(self.layers[i].state)
                              for i in shown))
            held = sum(len(self.layers[i].state) for i in shown)
            if held < total:
                return (f"{drawn:,} voxels drawn of about {round(stands_for):,} visible (decimated: the overview holds {held:,} of the "
                        f"tiles' {total:,} voxels)")
        return f"{drawn:,} of {visible:,} visible voxels drawn" + ("" if drawn == visible else " (decimated; tick *Full map* for all)")

    def _draw_layer(self, i: int, rows: np.ndarray) -> None:
        layer = self.layers[i]
        positions = (layer.centers[rows] - self.origin + self._shift(i)).astype(np.float32)
        colors = self.colors(i, rows)
        if self.map_fade > 0:
            colors = faded(colors, self.map_fade)
        name = f"/maps/{i}_{layer.name}"
        if len(rows) == 0:  # viser wants at least one point; hide an empty layer instead
            positions, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        if self.style == "points":
            self.voxel_handles[i] = self.server.scene.add_point_cloud(
                name, positions, colors, point_size=self._point_size(i), point_shape="square", precision="float32", visible=len(rows) > 0)
        else:
            import trimesh

            box = trimesh.creation.box(extents=[layer.resolution * 0.95] * 3)
            self.voxel_handles[i] = self.server.scene.add_batched_meshes_simple(
                name, box.vertices.astype(np.float32), box.faces.astype(np.uint32),
                batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(positions), 1)),
                batched_positions=positions, batched_colors=vl.mesh_colors(colors), cast_shadow=False, receive_shadow=False,
                visible=len(rows) > 0)

    def _legend_image(self) -> np.ndarray:
        pair = self._diff_pair()
        if pair is not None:
            if self.gui_diff.value == "labels differ":
                return vl.swatch_image(list(vl.DIFF_COLORS.items()))
            lo, hi = self._color_range or (-1.0, 1.0)
            return vl.color_bar_image(lo, hi, "variance: first - second map", vl._DIVERGING)
        if self.gui_color_by.value == "semantic":
            return vl.swatch_image([(name, self.palette[name]) for name in self.present_classes] or [("no classes", (128, 128, 128))])
        lo, hi = getattr(self, "_color_range", None) or (0.0, 1.0)
        label = self.gui_color_by.value + (" (log10 1+n)" if self.gui_color_by.value == "observations" else "")
        return vl.color_bar_image(lo, hi, label)

    # ------------------------------------------------------------------ terrain layers
    def compute_terrain(self) -> None:
        """Compute the terrain layers of every map (a store's: the mosaic of its tiles) and show them."""
        started = time.perf_counter()
        self.gui_terrain_status.content = "computing terrain layers ..."
        try:
            for i, layer in enumerate(self.layers):
                layers, voxel_m = vl.compute_terrain(layer.path, resolution_m=self.terrain_resolution, costs=self.costs)
                self.terrain[i] = vl.TerrainSurface(layers, voxel_m=voxel_m, max_cells=self.max_voxels)
        except (ValueError, OSError) as exc:  # ConfigError included: a cost table that does not fit the map's classes
            self.gui_terrain_status.content = f"**Cannot compute terrain layers:** {exc}"
            raise
        bands = self.terrain[0].band_names
        self.gui_terrain_band.options = tuple(bands)
        if self.gui_terrain_band.value not in bands:
            self.gui_terrain_band.value = bands[0]
        self.gui_terrain_compute.visible = False
        self.gui_terrain_mode.visible = True
        grid = self.terrain[0].grid
        self.gui_terrain_status.content = (
            f"{len(self.terrain)} map(s): cells of {grid.cell_m:g} m, {time.perf_counter() - started:.1f} s; click the surface for a "
            "cell's values" + ("" if self.terrain[0].stride == 1 else f" (drawn every {self.terrain[0].stride} cells)"))
        self.refresh()

    def _compute_terrain_from_gui(self) -> None:
        try:
            self.compute_terrain()
        except (ValueError, OSError):
            pass  # the GUI's status line names the problem

    def _draw_terrain(self, shown: list[int]) -> None:
        band, mode = self.gui_terrain_band.value, self.gui_terrain_mode.value
        for i, surface in self.terrain.items():
            visible = self.gui_terrain_show.value and i in shown and len(surface.rows) > 0
            if not visible:
                if i in self.terrain_handles:
                    self.terrain_handles[i].visible = False
                continue
            key = (band, mode, float(self._shift(i)[0]), id(surface))
            if self._terrain_drawn.get(i) == key and i in self.terrain_handles:
                self.terrain_handles[i].visible = True  # drawn as asked already: only shown again
                continue
            self._terrain_drawn[i] = key
            layer = self.layers[i]
            palette = np.array([self.palette[name] for name in layer.classes], np.uint8)
            tile = surface.grid.cell_m * surface.stride
            thickness = 0.25 * surface.voxel_m
            positions = np.c_[surface.centers[:, :2], surface.tile_tops(mode) - thickness / 2] - self.origin + self._shift(i)
            import trimesh

            box = trimesh.creation.box(extents=[tile * 0.98, tile * 0.98, thickness])
            self.terrain_handles[i] = self.server.scene.add_batched_meshes_simple(
                f"/terrain/{i}", box.vertices.astype(np.float32), box.faces.astype(np.uint32),
                batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(positions), 1)),
                batched_positions=positions.astype(np.float32), batched_colors=vl.mesh_colors(surface.colors(band, palette)),
                cast_shadow=False, receive_shadow=False)
        if self.terrain:
            first = next((i for i in shown if i in self.terrain), next(iter(self.terrain)))
            palette = np.array([self.palette[name] for name in self.layers[first].classes], np.uint8)
            self.gui_terrain_legend.image = self.terrain[first].legend(band, self.layers[first].classes, palette)

    # ------------------------------------------------------------------ picking
    def _pick_voxel(self, ray_origin, ray_direction) -> tuple[float, int, int] | None:
        d = np.asarray(ray_direction, np.float64)
        d = d / np.linalg.norm(d)
        best = None
        for i in self._shown_layers():
            rows = self.visible_rows[i]
            if len(rows) == 0:
                continue
            layer = self.layers[i]
            o = np.asarray(ray_origin, np.float64) + self.origin - self._shift(i)  # world frame
            if layer.weight is not None:  # a decimated overview: a ray passes between its points, a click beside one picks it
                point = self._pick_overview_point(i, o, d)
                if point is not None and (best is None or point[0] < best[0]):
                    best = (point[0], i, point[1])
            lo = layer.centers[rows].min(axis=0) - layer.resolution
            hi = layer.centers[rows].max(axis=0) + layer.resolution
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (lo - o) / d, (hi - o) / d
            t_near = np.nanmax(np.minimum(t1, t2))
            t_far = np.nanmin(np.maximum(t1, t2))
            if t_far < max(t_near, 0.0):
                continue
            ts = np.arange(max(t_near, 0.0), t_far, layer.resolution / 4.0)[:400_000]
            hit_rows = layer.voxel_at(o + ts[:, None] * d)
            visible = np.zeros(len(layer.state), bool)
            visible[rows] = True
            good = np.flatnonzero((hit_rows >= 0) & visible[np.maximum(hit_rows, 0)])
            if len(good) and (best is None or ts[good[0]] < best[0]):
                row = int(hit_rows[good[0]])
                # where the ray enters that voxel's box
                half = layer.resolution / 2.0
                with np.errstate(divide="ignore", invalid="ignore"):
                    a, b = (layer.centers[row] - half - o) / d, (layer.centers[row] + half - o) / d
                entry = float(np.nanmax(np.minimum(a, b)))
                best = (max(entry, 0.0) if np.isfinite(entry) else float(ts[good[0]]), i, row)
        return best

    CLICK_RADIUS_PX = 6.0  # a click this many pixels (at the orbit center's scale) from an overview's point picks it

    def _pick_overview_point(self, i: int, ray_origin_world: np.ndarray, direction: np.ndarray) -> tuple[float, int] | None:
        """(distance along the ray, row) of the nearest visible decimated point of layer ``i`` (one standing for several
        voxels; a tile in full is picked voxel by voxel) that the ray (world frame, unit direction) passes within
        its drawn size or ``CLICK_RADIUS_PX`` of."""
        layer, rows = self.layers[i], self.visible_rows[i]
        rows = rows[layer.weight[rows] > 1.0]
        offsets = layer.centers[rows] - ray_origin_world
        along = offsets @ direction
        # squared distances from the ray, without an [N, 3] temporary: this runs on every camera move (the center line)
        beside2 = np.einsum("ij,ij->i", offsets, offsets) - along * along
        radius = max(self._point_size(i), self.CLICK_RADIUS_PX * self.scale_bar[2] if self.scale_bar is not None else 0.0)
        near = np.flatnonzero((along > 0) & (beside2 <= radius * radius))
        if len(near) == 0:
            return None
        k = near[np.argmin(along[near])]
        return max(float(along[k]) - layer.resolution / 2, 0.0), int(rows[k])

    def pick(self, ray_origin, ray_direction) -> tuple[int, int] | None:
        """(layer, row) of the first visible voxel along a ray given in display coordinates."""
        hit = self._pick_voxel(ray_origin, ray_direction)
        return None if hit is None else (hit[1], hit[2])

    def pick_point(self, ray_origin, ray_direction) -> dict | None:
        """What a click hits first: a visible voxel, a cell of the terrain surface, or the ground grid's
        plane; a dict with ``kind`` ("voxel", "cell", "ground"), ``point`` (world coordinates, m) and
        ``layer`` / ``row`` / ``column``."""
        o = np.asarray(ray_origin, np.float64)
        d = np.asarray(ray_direction, np.float64)
        d = d / np.linalg.norm(d)
        hits = []
        voxel = self._pick_voxel(o, d)
        if voxel is not None:
            t, i, row = voxel
            hits.append((t, {"kind": "voxel", "layer": i, "row": row, "point": o + t * d + self.origin - self._shift(i)}))
        if self.gui_terrain_show.value:
            for i, surface in self.terrain.items():
                if i not in self._shown_layers():
                    continue
                world = o + self.origin - self._shift(i)
                cell = surface.pick(world, d, self.gui_terrain_mode.value)
                if cell is not None:
                    t, row, column = cell
                    hits.append((t, {"kind": "cell", "layer": i, "row": row, "column": column, "point": world + t * d}))
        if self.gui_grid.value and d[2] < 0:
            t = (self.ground.z - self.origin[2] - o[2]) / d[2]
            if t > 0:
                hits.append((t, {"kind": "ground", "point": o + t * d + self.origin}))
        return min(hits, key=lambda h: h[0])[1] if hits else None

    def describe(self, i: int, row: int) -> str:
        """Markdown for a voxel: its center in world coordinates of the map's frame (float64, mm), label, evidence."""
        layer = self.layers[i]
        alpha = layer.alpha[row]
        probs = alpha / alpha.sum()
        center = np.asarray(layer.centers[row], np.float64)
        lines = [f"**{layer.name}** voxel {tuple(int(v) for v in layer.voxel_index[row])}",
                 f"center in {describe_frame(layer.frame)}: " + ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", center)) + " m",
                 f"label: **{layer.classes[layer.label[row]]}** ({layer.label[row]}), state {STATE_NAMES[layer.state[row]]}",
                 f"variance: {layer.variance[row]:.3g}, observations: {int(layer.hits[row])}",
                 "", "| class | alpha | p |", "|---|---|---|"]
        lines += [f"| {name} | {a:.4g} | {p:.3f} |" for name, a, p in zip(layer.classes, alpha, probs)]
        pair = self._diff_pair()
        if pair is not None and i == pair[0]:
            diff = self.diff()
            at = np.flatnonzero(diff.a_rows == row)
            if len(at):
                k = int(at[0])
                truth = diff.truth[k]
                lines.insert(4, f"second map ({diff.b_name}): **{layer.classes[diff.b_label[k]]}**, variance "
                                f"{self.layers[pair[1]].variance[diff.b_rows[k]]:.3g}; truth: "
                                + (layer.classes[truth] if truth >= 0 else "none here"))
        return "\n".join(lines)

    def _on_click(self, event) -> None:
        view = self._acting_view = self.view_of(getattr(event, "client", None))
        hit = self.pick_point(event.ray_origin, event.ray_direction)
        self._highlight(view, hit)
        if hit is None:
            view.selection.content = "Nothing under the cursor."
            return
        point = np.asarray(hit["point"], np.float64)
        view.last_point = point
        where = (f"clicked point in {describe_frame(self.frame)}: " + ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", point)) + " m")
        if hit["kind"] == "voxel":
            text = self.describe(hit["layer"], hit["row"])
            if hit["layer"] in self.stores:  # a store's voxel: its tile column in full
                self.request_detail(hit["layer"], self.stores[hit["layer"]].tiles_at(point))
        elif hit["kind"] == "cell":
            layer = self.layers[hit["layer"]]
            text = self.terrain[hit["layer"]].describe(hit["row"], hit["column"], layer.classes, describe_frame(self.frame))
        else:
            text = "on the ground grid's plane"
        view.selection.content = where + "\n\n" + text
        if view.measure.value:
            self._add_measure_point(view, point)

    SELECTION_STEM_VOXELS = 6.0  # the stem above the selected voxel, in voxel edges

    def _highlight(self, view: ClientView, hit: dict | None) -> None:
        """The clicked voxel marked: a wireframe box around it (a little larger, so that its own faces do not
        hide it) and, since its neighbours hide most of the box, a stem rising from it to a label, which show
        above the map; removed when a click hits something else."""
        for handle in view.selection_handles:
            handle.remove()
        view.selection_handles = []
        if hit is None or hit["kind"] != "voxel":
            return
        layer = self.layers[hit["layer"]]
        center = np.asarray(layer.centers[hit["row"]], np.float64) - self.origin + self._shift(hit["layer"])
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(corners[a] - corners[b]).sum() == 2]
        half = 0.6 * layer.resolution
        segments = [[corners[a] * half + center, corners[b] * half + center] for a, b in edges]
        top = center + [0.0, 0.0, half + self.SELECTION_STEM_VOXELS * layer.resolution]
        segments.append([center + [0.0, 0.0, half], top])
        scene = view.scene
        view.selection_handles = [
            scene.add_line_segments("/selection/box", np.array(segments, np.float32), colors=SELECTION_COLOR, thickness=4.0,
                                    thickness_units="screen"),
            scene.add_label("/selection/label", "selected", position=tuple(top), anchor="bottom-center")]

    # ------------------------------------------------------------------ measuring
    def _reset_measure(self, view: ClientView, *, acting: bool = False) -> None:
        if acting:
            self._acting_view = view
        view.measure_points.clear()
        for handle in view.measure_handles:
            handle.remove()
        view.measure_handles.clear()
        view.measure_result.content = "Click the first point." if view.measure.value else ""

    def _add_measure_point(self, view: ClientView, point: np.ndarray) -> None:
        """Two clicks: the distance and height difference between them (a third click starts again)."""
        if len(view.measure_points) >= 2:
            self._reset_measure(view)
        view.measure_points.append(np.asarray(point, np.float64))
        local = [p - self.origin for p in view.measure_points]
        scene = view.scene
        view.measure_handles.append(scene.add_point_cloud(f"/measure/point{len(local)}", local[-1][None].astype(np.float32),
                                                           colors=(230, 0, 230), point_size=0.25, point_shape="circle", precision="float32"))
        if len(view.measure_points) == 1:
            view.measure_result.content = "first point set; click the second."
            return
        a, b = view.measure_points
        view.measure_handles.append(scene.add_line_segments("/measure/line", np.array([local], np.float32), colors=(230, 0, 230),
                                                             thickness=3.0, thickness_units="screen"))
        view.measure_handles.append(scene.add_label("/measure/label", f"{np.linalg.norm(b - a):.2f} m, dz {b[2] - a[2]:+.2f} m",
                                                     position=tuple((local[0] + local[1]) / 2), anchor="bottom-center"))
        view.measure_result.content = vl.measurement_text(a, b, describe_frame(self.frame))

    # ------------------------------------------------------------------ export
    def offset_note(self) -> str:
        """What an HTML export's positions are: relative to the local origin, given in world coordinates."""
        x, y, z = self.origin
        note = (f"positions are relative to the local origin at x={x:.3f} y={y:.3f} z={z:.3f} m in "
                f"{describe_frame(self.frame)}; add it for world coordinates")
        if len(self._shown_layers()) > 1:
            note += f"; side by side, map i is drawn shifted by a further i x {self.side_by_side_step:.3f} m along x"
        return note

    def legend_html(self) -> str:
        """The legend and a summary of the view as an HTML panel (``id="evsemmap-legend"``) for the HTML
        export: class swatches with names (or the color bar as an image), the terrain layer's bar when the
        surface is shown, the counter and the maps' frame."""
        import base64
        from io import BytesIO

        from PIL import Image

        def image(array, alt):
            buffer = BytesIO()
            Image.fromarray(np.asarray(array, np.uint8)).save(buffer, format="PNG")
            data = base64.b64encode(buffer.getvalue()).decode("ascii")
            return f'<img alt="{html.escape(alt, quote=True)}" src="data:image/png;base64,{data}" style="display:block;width:220px" />'

        shown = [self.layers[i] for i in self._shown_layers()]
        pair = self._diff_pair()
        if pair is not None:
            title = f"{self.gui_diff.value}: {self.layers[pair[0]].name} against {self.layers[pair[1]].name}"
        else:
            title = f"color by {self.gui_color_by.value}"
        parts = [f'<div style="font-weight:bold">{html.escape(", ".join(layer.name for layer in shown))}</div>',
                 f"<div>{html.escape(title)}</div>"]
        if pair is not None and self.gui_diff.value == "labels differ":
            entries = list(vl.DIFF_COLORS.items())
        elif pair is None and self.gui_color_by.value == "semantic":
            entries = [(name, self.palette[name]) for name in self.present_classes]
        else:
            entries = None
        if entries is not None:
            for name, color in entries:
                rgb = ",".join(str(int(c)) for c in color)
                parts.append(f'<div class="evsemmap-legend-entry"><span style="display:inline-block;width:14px;height:14px;'
                             f'margin-right:6px;vertical-align:middle;border:1px solid #5a5a5a;background:rgb({rgb})"></span>'
                             f"{html.escape(name)}</div>")
        else:
            lo, hi = self._color_range or (0.0, 1.0)
            parts.append(image(self._legend_image(), f"color bar {lo:.3g} to {hi:.3g}"))
        if self.terrain and self.gui_terrain_show.value:
            parts.append(f"<div>terrain surface: {html.escape(self.gui_terrain_band.value)}</div>")
            parts.append(image(self.gui_terrain_legend.image, f"terrain {self.gui_terrain_band.value}"))
        status = self.gui_status.content.replace("*", "")
        parts.append(f'<div style="color:#444">{html.escape(status)}</div>')
        parts.append(f'<div style="color:#444">frame: {html.escape(frame_label(self.frame))}; grid lines every '
                     f"{self.ground.section:g} m</div>")
        return ('<div id="evsemmap-legend" style="position:fixed;left:8px;top:8px;z-index:1000;max-width:260px;max-height:80vh;'
                'overflow:auto;font:12px sans-serif;background:rgba(255,255,255,0.92);padding:6px 8px;border-radius:4px;'
                'border:1px solid #ccc">' + "".join(parts) + "</div>")

    def export_html(self, path) -> Path:
        """A standalone HTML file of the current scene (viewable offline, without viser's GUI panel but
        with the legend, a summary of what is shown and the frame note).

        Its positions are viser's float32 scene positions, relative to the local origin (``origin``), not
        world coordinates; the page states the offset: ``<meta name="evsemmap-frame">`` (the frame's name,
        "none" where not recorded), ``evsemmap-crs`` (an EPSG code or "none"), ``evsemmap-local-origin``
        ("x y z", metres in that frame), an HTML comment and a visible note saying the same, and the scene's
        labelled world axes at the origin. ``<div id="evsemmap-legend">`` (``legend_html``) holds the legend."""
        x, y, z = self.origin
        note = self.offset_note()
        metas = {"evsemmap-frame": self.frame.name if self.frame is not None else "none",
                 "evsemmap-crs": (self.frame.crs if self.frame is not None else None) or "none",
                 "evsemmap-local-origin": f"{x:.3f} {y:.3f} {z:.3f}",
                 "evsemmap-coordinates": note}
        head = "".join(f'<meta name="{key}" content="{html.escape(value, quote=True)}" />' for key, value in metas.items())
        head += "<!-- evsemmap_warp map viewer export: " + note.replace("--", "- -") + " -->"
        visible = ('<div id="evsemmap-frame-note" style="position:fixed;left:8px;bottom:8px;z-index:1000;'
                   'pointer-events:none;font:12px sans-serif;background:rgba(255,255,255,0.8);padding:2px 6px;'
                   f'border-radius:4px">{html.escape(note, quote=False)}</div>') + self.legend_html()
        page = self.server.get_scene_serializer().as_html()
        at = page.find("<head>")
        page = page[: at + 6] + head + page[at + 6:] if at >= 0 else head + page
        at = page.rfind("</body>")
        page = page[:at] + visible + page[at:] if at >= 0 else page + visible
        from ..files import write_text_atomically

        return write_text_atomically(Path(path), page)  # whole or not at all, errors naming the path

    def export_ply(self, path) -> Path:
        """The visible voxels of the shown maps as a binary PLY point cloud: vertex positions are float64
        (``property double x/y/z``) world coordinates of the maps' frame, metres, not shifted side by side;
        color (RGBA) and label, state, variance and observation count as per-vertex properties. The
        header names the frame: ``comment frame NAME`` and ``comment crs EPSG:NNNN`` ("none" where not
        recorded)."""
        parts = [(i, self.visible_rows[i]) for i in self._shown_layers()]
        colors = np.concatenate([self.colors(i, r) for i, r in parts])
        fields = {"label": "label", "state": "state", "variance": "variance", "observations": "hits"}
        vertex = np.zeros(len(colors), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                                        ("blue", "u1"), ("alpha", "u1")] + [(name, "<f4") for name in fields])
        centers = np.concatenate([np.asarray(self.layers[i].centers[r], np.float64) for i, r in parts])
        for k, axis in enumerate("xyz"):
            vertex[axis] = centers[:, k]
        for k, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = colors[:, k]
        vertex["alpha"] = 255
        for name, attribute in fields.items():
            vertex[name] = np.concatenate([getattr(self.layers[i], attribute)[r] for i, r in parts])

        def one_line(text: str) -> str:
            return " ".join(str(text).splitlines())

        types = {"<f8": "double", "|u1": "uchar", "<f4": "float"}
        header = ["ply", "format binary_little_endian 1.0",
                  "comment evsemmap_warp map viewer export: voxel centers, float64 world coordinates (m) of the frame below",
                  f"comment frame {one_line(self.frame.name) if self.frame is not None else 'none'}",
                  f"comment crs {(self.frame.crs if self.frame is not None else None) or 'none'}",
                  f"element vertex {len(vertex)}"]
        header += [f"property {types[vertex.dtype[name].str]} {name}" for name in vertex.dtype.names]
        header.append("end_header")
        from ..files import write_bytes_atomically

        return write_bytes_atomically(Path(path), ("\n".join(header) + "\n").encode("utf-8") + vertex.tobytes())

    def _export_from_gui(self, kind: str) -> None:
        stem = self.export_dir / f"{self.layers[self._shown_layers()[0]].name}_view"
        path = self.export_html(stem.with_suffix(".html")) if kind == "html" else self.export_ply(stem.with_suffix(".ply"))
        self.gui_export_status.content = f"written: `{path}`"

    def serve_forever(self) -> None:
        """Keep serving until Ctrl-C, then stop the server."""
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()
