"""``evsemmap live --store DIR``: the live map kept as a map store (the batch format, written by
``apps.batch.write_store_from_mapper``) so that nothing is lost when the run ends badly.

Every ``every_s`` seconds, and when the run ends (Ctrl-C included), a copy of the map taken between two scans
is written on a thread of its own into ``DIR.next``, which then replaces ``DIR`` by two renames (``DIR`` ->
``DIR.prev``, ``DIR.next`` -> ``DIR``): a crash loses at most the last interval, and ``DIR`` is always a whole
store (or, killed between the renames, ``DIR.prev`` is, and is taken back on the next start). A store that
exists when ``live`` starts is resumed: its map is the start of the live map, in its frame (its name must be
the robot's fixed frame), with its method and parameters (others are refused)."""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

from ..apps.viewer.live import LatestOnlyWorker, reading_template
from ..config import ConfigError
from ..core import map_store
from ..core.voxel_map import sum_shard_rows


class LiveStore(LatestOnlyWorker):
    """The store at ``path``, rewritten every ``every_s`` seconds from offered copies of the map."""

    def __init__(self, path, *, every_s: float, tile_voxels: int = map_store.DEFAULT_TILE_VOXELS, sources: list[str] = ()):
        self.path, self.every_s, self.tile_voxels, self.sources = Path(path), every_s, tile_voxels, list(sources)
        self.next_path, self.prev_path = self.path.with_name(self.path.name + ".next"), self.path.with_name(self.path.name + ".prev")
        self._due = time.monotonic() + every_s
        self.flushes = 0
        self.last_error: str | None = None
        if not self.path.exists() and self.prev_path.is_dir():  # killed between the two renames: the previous store is whole
            self.prev_path.rename(self.path)
        super().__init__("evsemmap-live-store")

    def resume(self, run):
        """The existing store's map (a Mapper), or None when there is none yet; ConfigError when it was made with
        another method, other parameters or classes."""
        if not (self.path / map_store.INDEX_NAME).is_file():
            if self.path.exists() and any(self.path.iterdir()):
                raise ConfigError(f"--store {self.path}: exists and is not a map store; give a new folder, or the store of an earlier live run")
            return None
        store = map_store.MapStore(self.path)
        mine, theirs = run.mapping.as_dict(), store.config.as_dict()
        differing = sorted(k for k in mine if mine.get(k) != theirs.get(k))
        if differing:
            what = ", ".join(f"{k} {theirs.get(k)!r} there, {mine[k]!r} here" for k in differing[:3])
            raise ConfigError(f"--store {self.path}: made with other mapping parameters ({what}); resume with the same method and "
                              f"presets, or give a new folder")
        return store.to_mapper()

    def offer(self, mapper, *, force: bool = False) -> bool:
        """Between two scans: hand over a copy of the map when a flush is due (``force``: now)."""
        if mapper is None or mapper.origin_index is None or not (force or time.monotonic() >= self._due):
            return False
        self._due = time.monotonic() + self.every_s
        template = reading_template(mapper)
        template.scans_integrated, template.points_integrated = mapper.scans_integrated, mapper.points_integrated
        template.scan_ids = None if mapper.scan_ids is None else set(mapper.scan_ids)
        self.hand_over((template, mapper.shard_rows()))
        return True

    def _draw(self, item) -> None:
        template, shards = item
        local = sum_shard_rows(shards)
        scans, points, scan_ids = template.scans_integrated, template.points_integrated, template.scan_ids
        template.load_voxels(dataclasses.replace(local, index=local.index + template.origin_index), origin_index=template.origin_index)
        template.scans_integrated, template.points_integrated, template.scan_ids = scans, points, scan_ids
        from ..apps.batch import write_store_from_mapper

        shutil.rmtree(self.next_path, ignore_errors=True)
        write_store_from_mapper(template, self.next_path, self.tile_voxels, self.sources)
        shutil.rmtree(self.prev_path, ignore_errors=True)
        if self.path.exists():
            self.path.rename(self.prev_path)
        self.next_path.rename(self.path)
        shutil.rmtree(self.prev_path, ignore_errors=True)
        self.flushes += 1

    def _show_error(self, message: str) -> None:
        from .feed import say

        if message != self.last_error:
            say(f"writing the store {self.path} failed: {message} (mapping goes on; the store holds the last interval written)")
        self.last_error = message
