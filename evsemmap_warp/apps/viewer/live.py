"""Watching maps being made: ``evsemmap map ... --view`` and ``evsemmap batch ... --view``.

``LiveMap``: the mapping thread maps in segments of ``every`` scans (``map_live``; a segment's scans are
the ones ``Mapper.integrate_many`` would map, so the map is the same) and, between segments, hands the
viewer a host copy of each shard's voxel table. Reading the copy out (adding the shards, labels,
variance) and drawing it happens on the viewer's own thread; the mapping thread only copies, and skips
the copy while the viewer is still busy with the previous one, so a slow browser never holds mapping
back. At the end, ``show_final`` shows the map exactly as it is written to the map file.

``LiveTiles``: the ``on_tile(name, voxels)`` receiver of ``run_batch``: each tile's running sum, decimated
to its share of ``max_voxels`` on the driver's thread (an index, no read-out), then read out and drawn
on the viewer's thread as an overview of the tiles so far.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from itertools import islice

import numpy as np

from ...core.map_file import file_arrays
from ...core.voxel_map import VoxelArrays, sum_shard_rows
from .colors import TRAJECTORY_COLOR
from .map_layer import MapLayer


def reading_template(mapper):
    """A Mapper with ``mapper``'s parameters, classes, frame and origin, holding nothing: it reads copies
    of ``mapper``'s voxels out (``contents_of``) on another thread without touching ``mapper``."""
    from ...core.mapper import Mapper

    template = Mapper(mapper.config, mapper.num_classes, class_names=mapper.class_names, device="cpu", workers=1,
                      initial_capacity=1, frame=mapper.frame)
    template.origin_index = None if mapper.origin_index is None else np.array(mapper.origin_index)
    return template


class LatestOnlyWorker:
    """One background thread handling (``_draw``) the newest thing handed to it; older ones not yet handled are
    dropped. The live viewer draws with it, ``evsemmap live`` publishes the map with it."""

    def __init__(self, name: str):
        self._cond = threading.Condition()
        self._pending = None
        self._busy = False
        self._stopped = False
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """Whether something is being handled or waits to be."""
        with self._cond:
            return self._busy or self._pending is not None

    def hand_over(self, item) -> None:
        """Give the thread ``item`` to handle next (replacing one still waiting)."""
        with self._cond:
            self._pending = item
            self._cond.notify_all()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait up to ``timeout`` seconds until nothing is handled or waiting; returns whether it came to that."""
        end = time.time() + timeout
        with self._cond:
            while self._busy or self._pending is not None:
                if not self._cond.wait(timeout=max(end - time.time(), 0.0)) and time.time() >= end:
                    return False
        return True

    def close(self) -> None:
        """Stop the thread (what waits is not handled) and join it, 30 s at most."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._thread.join(timeout=30)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stopped and self._pending is None:
                    self._cond.wait()
                if self._stopped:
                    return
                item, self._pending, self._busy = self._pending, None, True
            try:
                self._draw(item)
            except Exception as exc:  # shown, not raised: mapping goes on
                self.errors.append(f"{type(exc).__name__}: {exc}")
                self._show_error(self.errors[-1])
            finally:
                item = None  # a map's copy is not held while waiting for the next one
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _draw(self, item) -> None:
        raise NotImplementedError

    def _show_error(self, message: str) -> None:
        pass


class LiveMap(LatestOnlyWorker):
    """``mapper``'s map, shown as map ``map_index`` of ``viewer`` while it is made (named ``name``, to be
    written to ``path``), with the last scan of each update and the sensor's path so far. ``offer`` on
    the mapping thread; the rest happens on this object's thread."""

    def __init__(self, viewer, mapper, *, name: str, path, scan_total: int | None = None, map_index: int = 0):
        self.viewer, self.mapper, self.name, self.path, self.map_index = viewer, mapper, name, path, map_index
        self.scan_total = scan_total
        self.template = reading_template(mapper)
        self.updates = 0  # maps drawn
        self.offers_skipped = 0  # offers made while the previous copy was still being drawn
        self.copy_seconds = 0.0  # the mapping thread's time spent copying
        self.sensor_path: list[np.ndarray] = []
        self.final = False
        folder = viewer.gui_drive_folder
        folder.label, folder.visible = "Mapping", True
        with folder:
            self.gui_status = viewer.server.gui.add_markdown("waiting for the first scans")
        super().__init__("evsemmap-live-map")

    def offer(self, scans_done: int, last_scan=None) -> bool:
        """Between two segments (no scan in flight): hand the viewer a copy of the map, unless it is
        still drawing the previous one. Returns whether a copy was handed over."""
        if last_scan is not None:
            self.sensor_path.append(np.asarray(last_scan.sensor_origin, np.float64))
        if self.busy:
            self.offers_skipped += 1
            return False
        started = time.perf_counter()
        shards = self.mapper.shard_rows()
        origin_index = None if self.mapper.origin_index is None else np.array(self.mapper.origin_index)
        self.copy_seconds += time.perf_counter() - started
        points = None if last_scan is None else np.array(last_scan.points, np.float64)
        self.hand_over(["copy", shards, origin_index, scans_done, points, list(self.sensor_path)])
        return True

    def show_final(self) -> MapLayer:
        """Show the map as ``save_map`` writes it (same read-out of the same voxels), after any update in
        flight; returns the layer shown."""
        self.wait_idle()
        layer = MapLayer.from_mapper(self.name, self.path, self.mapper)
        self.final = True
        self._show(layer, self.mapper.scans_integrated if self.scan_total is None else self.scan_total, None, self.sensor_path)
        return layer

    def _draw(self, item) -> None:
        _, shards, origin_index, scans_done, points, sensor_path = item
        if origin_index is None:  # nothing mapped yet
            return
        self.template.origin_index = origin_index
        item[1] = None  # the copy's rows, once summed, are not held while the layer is made
        voxels = sum_shard_rows(shards)
        del shards
        voxels = dataclasses.replace(voxels, index=voxels.index + origin_index)
        self._show(MapLayer.from_mapper(self.name, self.path, self.template, voxels), scans_done, points, sensor_path)

    def _show(self, layer: MapLayer, scans_done: int, points, sensor_path) -> None:
        viewer = self.viewer
        viewer.replace_layer(self.map_index, layer)
        scene = viewer.server.scene
        if points is not None and len(points):
            scene.add_point_cloud("/live/scan", (points - viewer.origin).astype(np.float32), colors=(90, 90, 90),
                                  point_size=0.5 * layer.resolution, point_shape="circle", precision="float32")
        if len(sensor_path) >= 2:
            scene.add_spline_catmull_rom("/live/path", (np.array(sensor_path) - viewer.origin).astype(np.float32), color=TRAJECTORY_COLOR,
                                         thickness=3.0, thickness_units="screen")
        self.updates += 1
        of = f" of {self.scan_total}" if self.scan_total is not None else ""
        state = "**done**: the map as written to" if self.final else "mapping into"
        self.gui_status.content = (f"{state} `{self.path}`\n\n{scans_done}{of} scans, {len(layer.state):,} voxels "
                                   f"(update {self.updates}; the last scan in grey, the sensor's path in orange)")

    def _show_error(self, message: str) -> None:
        self.gui_status.content = f"**Cannot show the map:** {message} (mapping goes on)"


def map_live(mapper, scans, live: LiveMap, *, every: int, progress=None) -> list:
    """``scan_sources.map_scans`` in segments of ``every`` scans, offering ``live`` the map after each
    (the same map: integrate_many maps scans in order, whatever the segments); returns the per-scan stats."""
    from ..scan_sources import map_scans

    if every < 1:
        raise ValueError(f"every must be at least 1, got {every}")
    iterator = iter(scans)
    stats: list = []
    last = []

    def remembered(segment):
        for scan in segment:
            last[:] = [scan]
            yield scan

    while True:
        done = map_scans(mapper, remembered(islice(iterator, every)), progress)
        if not done:
            return stats
        stats += done
        live.offer(len(stats), last[0] if last else None)


class LiveTiles(LatestOnlyWorker):
    """Tiles of a store being written (``run_batch``'s ``on_tile(name, voxels)``: a tile's running sum,
    global indices) or read, shown as map ``map_index`` of ``viewer``: an overview in which each tile
    holds its share of ``max_voxels``, filled in as tiles arrive. ``template``: a Mapper with the store's
    parameters, classes, frame and origin (it reads the voxels out)."""

    def __init__(self, viewer, template, *, name: str, path, max_voxels: int, map_index: int = 0, tile_total: int | None = None):
        self.viewer, self.template, self.name, self.path, self.map_index = viewer, template, name, path, map_index
        self.max_voxels = int(max_voxels)
        self.tile_total = tile_total
        self.voxel_counts: dict[str, int] = {}  # tile -> its voxels in the last sum received
        self._parts: dict[str, VoxelArrays] = {}  # tile -> its decimated rows (the driver's thread writes, under the lock)
        self._lock = threading.Lock()
        self.updates = 0
        folder = viewer.gui_drive_folder
        folder.label, folder.visible = "Tiles", True
        with folder:
            self.gui_status = viewer.server.gui.add_markdown("waiting for the first tile")
        super().__init__("evsemmap-live-tiles")

    def __call__(self, name: str, voxels: VoxelArrays) -> None:
        """A tile's voxels (its running sum so far): keep an evenly spaced share, and have it drawn."""
        n = len(voxels.index)
        with self._lock:
            self.voxel_counts[name] = n
            total = sum(self.voxel_counts.values())
            self._parts[name] = _decimated(voxels, self._share(n, total))
            if sum(len(p.index) for p in self._parts.values()) > 1.5 * self.max_voxels:  # earlier tiles hold more than their share now
                for tile, part in self._parts.items():
                    self._parts[tile] = _decimated(part, self._share(self.voxel_counts[tile], total))
            snapshot = dict(self._parts), dict(self.voxel_counts)
        self.hand_over(snapshot)

    def _share(self, n: int, total: int) -> int:
        return min(n, max(1, int(self.max_voxels * n / max(total, 1)))) if n else 0

    def _draw(self, snapshot) -> None:
        parts, counts = snapshot
        arrays = []
        for tile in sorted(parts):
            part = parts[tile]
            if not len(part.index):
                continue
            contents = self.template.contents_of(part)
            tile_arrays = file_arrays(contents)
            tile_arrays["weight"] = np.full(len(part.index), counts[tile] / len(part.index))
            arrays.append(tile_arrays)
        if not arrays:
            return
        keys = ("centers", "voxel_index", "alpha", "evidence", "label", "state", "variance", "hits", "weight_sum", "weighted_uncertainty_sum",
                "weight")
        joined = {k: np.concatenate([a[k] for a in arrays]) for k in keys}
        order = np.lexsort(joined["voxel_index"].T[::-1])  # key order, as a map file's (voxel_at needs it)
        joined = {k: v[order] for k, v in joined.items()}
        joined["resolution"], joined["origin"] = arrays[0]["resolution"], arrays[0]["origin"]
        layer = MapLayer.from_arrays(self.name, self.path, joined, contents.meta)
        layer.weight = joined["weight"]
        self.viewer.replace_layer(self.map_index, layer)
        self.updates += 1
        of = f" of {self.tile_total}" if self.tile_total is not None else ""
        held, total = len(layer.state), sum(counts.values())
        self.gui_status.content = (f"{len(counts)}{of} tiles so far, {total:,} voxels; the overview holds {held:,} of them "
                                   f"(update {self.updates})")

    def _show_error(self, message: str) -> None:
        self.gui_status.content = f"**Cannot show the tiles:** {message}"


def _decimated(voxels: VoxelArrays, keep: int) -> VoxelArrays:
    n = len(voxels.index)
    if keep >= n:
        return voxels
    rows = np.linspace(0, n - 1, keep).astype(np.int64) if keep else np.zeros(0, np.int64)
    return VoxelArrays(**{field.name: getattr(voxels, field.name)[rows] for field in dataclasses.fields(voxels)})
