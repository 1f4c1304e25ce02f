"""A map store in the viewer: ``StoreOverview`` holds an overview of its tiles and a few tiles in full, never
the store; ``StoreTiles`` is the part of ``MapViewer`` that reads them in the background (the overview
after the first frame, tiles in full where a camera comes near, a click lands or a tile is chosen)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from ...core.map_file import file_arrays
from ...terrain.known import evidence_sums
from .map_layer import MapLayer, held_classes

# a voxel's evidence is kept summed (what terrain.known compares), not per class: the overview's memory is the viewer's
_LAYER_ARRAYS = ("centers", "voxel_index", "alpha", "evidence_sum", "label", "state", "variance", "hits", "weight_sum",
                 "weighted_uncertainty_sum")


class StoreOverview:
    """A map store in the viewer, at two levels of detail: an overview in which every tile holds an evenly
    spaced share of ``max_voxels`` (its share of the store's voxels, from store.json's counts), and up to
    ``max_detail_tiles`` tiles in full (asked for by the GUI, a pick, or a camera coming near). What is
    held is the overview and those tiles, never the store: tiles are read one at a time and dropped.

    The overview fills in tile by tile (``read_next``, nearest the store's center first), so a viewer can
    draw a first frame before the store is read; the store's extent comes from store.json. Thread-safe:
    the viewer's loader thread reads while GUI callbacks ask for detail."""

    def __init__(self, path, max_voxels: int, *, max_detail_tiles: int = 6):
        from ...core.map_store import MapStore

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
        self.unreadable: dict[str, Exception] = {}  # tile -> why it could not be read into the overview (passed over)
        self.details: dict[str, dict] = {}  # tile -> all its rows, most recently asked for last
        self.meta = self.store.template.metadata()
        self._present: set[int] = set()
        self._lock = threading.RLock()
        self.frame = self.store.frame  # store.json's

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
        arrays["evidence_sum"] = evidence_sums(arrays.pop("evidence"))
        n = len(arrays["state"])
        self._present.update(held_classes(arrays["label"], arrays["state"]).tolist())
        rows = np.arange(n) if keep is None or keep >= n else np.linspace(0, n - 1, keep).astype(np.int64)
        return {k: arrays[k][rows] for k in _LAYER_ARRAYS} | {"resolution": arrays["resolution"], "origin": arrays["origin"],
                                                             "weight": np.full(len(rows), n / max(len(rows), 1), np.float64)}

    def read_next(self) -> str | None:
        """Read the next tile into the overview; its name, None when every tile is read. A tile that cannot be
        read raises, and is passed over (``unreadable``): the overview completes without it."""
        with self._lock:
            if not self.unread:
                return None
            name = self.unread.pop(0)
            try:
                self.parts[name] = self._read(name, self._share(self.store.tiles[name]["voxels"]))
            except Exception as exc:
                self.unreadable[name] = exc
                raise
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
        from ...core.map_store import tile_keys

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
        from ...core.map_store import parse_tile_name

        return sorted(self.store.tiles, key=lambda name: (self.along[name], parse_tile_name(name)[::-1]))

    def tile_label(self, name: str) -> str:
        """A tile as a user finds it: "tile (3, -1, 0) at E512 m N-140 m, 830 m along" (its box's middle, world frame)."""
        from ...core.map_store import parse_tile_name

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
                from ...core.voxel_map import EXTRA_COLUMNS, VoxelArrays

                empty = VoxelArrays.from_rows(np.zeros((0, 3), np.int64), np.zeros((0, self.store.num_classes + EXTRA_COLUMNS)))
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
    from ...core.map_store import parse_tile_name

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


class StoreTiles:
    """The part of a ``MapViewer`` that reads its stores (``viewer.stores``: map index -> ``StoreOverview``) on a
    loader thread: the rest of each overview after the first frame, and tiles in full where a browser's camera
    comes near (``approach``), a click lands (``request``) or a tile is chosen (``show``)."""

    # A browser's camera nearer a store's tile than this many tile edges brings tiles in full: from a long drive's
    # store (tiles 51 m across, an overview of 1 voxel in 50), 4 edges is where its points stand apart on screen.
    APPROACH_TILES = 4.0
    # ... and nearer than this share of the store's length: a camera that frames a small store whole is not near it
    APPROACH_EXTENT = 0.25

    def __init__(self, viewer):
        self.viewer = viewer
        self._wanted: dict[int, list[str]] = {}  # store -> tiles to show in full, for the loader thread
        self._wake = threading.Condition()
        self._overviews_shown = threading.Event()  # every store's overview read in full and drawn

    def start(self) -> None:
        """Start reading the rest of every store's overview (and tiles in full when asked for)."""
        stores = self.viewer.stores
        if all(o.complete for o in stores.values()):
            self._overviews_shown.set()
        if stores:
            threading.Thread(target=self._load, name="evsemmap-store-tiles", daemon=True).start()

    def stop(self) -> None:
        """Wake the loader thread so that it sees the viewer closed."""
        with self._wake:
            self._wake.notify_all()

    @property
    def choices(self) -> dict[str, tuple[int, str]]:
        """The *Store tile in full* list: each store's tiles in order along it, labelled by where they are
        (``StoreOverview.tile_label``, after "i: " where there are several maps) -> (map, tile)."""
        prefix = len(self.viewer.layers) > 1
        return {(f"{i}: " if prefix else "") + overview.tile_label(name): (i, name)
                for i, overview in self.viewer.stores.items() for name in overview.tiles_along()}

    def show(self, choice: str) -> None:
        """Show a store's tile (a ``choices`` label, or "i: X_Y_Z") in full detail over its overview and fly
        every browser's camera to it; "(overview only)": no tile of any store in full."""
        chosen = None if choice.startswith("(") else self.choices.get(choice) or (int(choice.split(":")[0]), choice.split(": ")[1])
        if chosen is not None:  # first: the camera moves at once, while the tile is read and sent
            self.fly_to(*chosen)
        for i, overview in self.viewer.stores.items():
            if chosen is None:
                changed = overview.set_detail([])
            elif chosen[0] == i:  # added to the tiles the camera's new place brings in (approach), not in place of them
                changed = overview.add_detail([chosen[1]])
            else:
                continue
            if changed:
                self.viewer.replace_layer(i, overview.layer())

    def fly_to(self, i: int, name: str) -> None:
        """Move every browser's camera to store ``i``'s tile ``name``: looking at its middle from the south, above,
        near enough that the tile fills most of the view (and so nearer than ``APPROACH_TILES``: its neighbours
        come in full as well)."""
        viewer = self.viewer
        box = viewer.stores[i].boxes[name]
        look_at = box.mean(axis=0) - viewer.origin + viewer.comparison.shift(i)
        distance = max(float(np.max(box[1, :2] - box[0, :2])), 4.0 * viewer.layers[i].resolution)
        viewer.cameras.place(None, look_at + distance * np.array([0.0, -0.6, 0.8]), look_at)

    def request(self, i: int, names: list[str]) -> None:
        """Have store ``i``'s tiles ``names`` shown in full (read on the loader thread)."""
        if names and not set(names) <= set(self.viewer.stores[i].detail):
            with self._wake:
                self._wanted[i] = list(names)
                self._wake.notify_all()

    def approach(self, camera) -> None:
        """Tiles in full where a camera (``position`` and ``look_at``, display coordinates) has come near a store:
        of the tiles within ``APPROACH_TILES`` tile edges (and ``APPROACH_EXTENT`` of the store's length) of the
        camera, those nearest its orbit center (its column first), up to the store's ``max_detail_tiles``. Only
        tiles the overview decimates: the others are there in full already."""
        viewer = self.viewer
        try:
            position, look_at = np.asarray(camera.position, np.float64), np.asarray(camera.look_at, np.float64)
        except (AttributeError, TypeError, ValueError):
            return
        shown = viewer.comparison.shown_layers()
        for i, overview in viewer.stores.items():
            if i not in shown:
                continue
            length = float(np.max(overview.bounds[1][:2] - overview.bounds[0][:2]))
            reach = min(self.APPROACH_TILES * overview.store.tile_voxels * viewer.layers[i].resolution, self.APPROACH_EXTENT * length)
            to_world = viewer.origin - viewer.comparison.shift(i)
            near = [name for name in overview.tiles_near(position + to_world, reach, around=look_at + to_world) if overview.decimated(name)]
            self.request(i, near[: overview.max_detail_tiles][::-1])  # the nearest asked for last: kept longest

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until every store's overview is read in full and shown; whether it was."""
        return self._overviews_shown.wait(timeout)

    def _load(self) -> None:
        viewer = self.viewer
        sent = {i: len(viewer.layers[i].state) for i in viewer.stores}  # rows each store's overview had when last sent
        while not viewer.closed.is_set():
            with self._wake:
                while not viewer.closed.is_set() and not self._wanted and all(o.complete for o in viewer.stores.values()):
                    self._wake.wait(timeout=1.0)
                wanted, self._wanted = self._wanted, {}
            try:
                self._show_detail(wanted)
                if not wanted:  # detail first: what the user is looking at
                    self._read_overview(sent)
            except Exception as exc:  # shown, not raised: the viewer keeps serving what it has
                viewer.gui_status.content = f"**Cannot read the store:** {type(exc).__name__}: {exc}"
                viewer.closed.wait(5.0)

    def _show_detail(self, wanted: dict[int, list[str]]) -> None:
        for i, names in wanted.items():
            # the tile asked for last (nearest what the camera looks at) shown first, then the rest with it
            for batch in (names[-1:], names):
                if self.viewer.stores[i].add_detail(batch):
                    self.viewer.replace_layer(i, self.viewer.stores[i].layer())

    def _read_overview(self, sent: dict[int, int]) -> None:
        """One more tile into the first incomplete overview, which is drawn again once it has grown by half."""
        viewer = self.viewer
        for i, overview in viewer.stores.items():
            if overview.complete:
                continue
            try:
                overview.read_next()
            finally:  # also past an unreadable tile: were it the last, the overview would never count as shown
                # Each push sends the whole overview again: pushed as it grows by half, the browser receives about
                # twice the final overview in all, however many tiles the store has.
                if overview.complete or overview.held_rows >= 1.5 * sent[i]:
                    viewer.replace_layer(i, overview.layer())
                    sent[i] = len(viewer.layers[i].state)
                if all(o.complete for o in viewer.stores.values()):
                    self._overviews_shown.set()
            return
