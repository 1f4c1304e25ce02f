"""The driver's side of the streaming reduction: finished chunks' partials folded into the store's tiles, in
chunk order, while the workers map."""

from __future__ import annotations

import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ... import files
from ...core import map_store, tile_codec
from ...core.voxel_map import EXTRA_COLUMNS, VoxelArrays
from .planning import Chunk
from .store import chunk_dir, read_done
from .worker import Context

FOLD_CACHE_TILES = 12  # tiles the driver keeps in memory while folding (the drive passes through them; up to ~15 MB each)


class TileFolder:
    """The driver's side of the streaming reduction: finished chunks' partials folded into the store's
    tiles in chunk order (map_store.fold). The tiles the drive is passing stay in memory (the
    ``FOLD_CACHE_TILES`` most recently folded); a tile leaving them, and every tile at the end, is
    written durably with the last chunk it holds (``folded_through``), and only then are the partials
    it absorbed deleted. A killed run therefore loses nothing: what is not in a tile file is still in a
    partial, and the rerun folds exactly the chunks each tile lacks. ``on_tile(name, voxels)`` sees
    every tile as it grows (a live view)."""

    def __init__(self, out: Path, context: Context, chunks: list[Chunk], on_tile=None):
        self.out, self.chunks, self.on_tile = out, chunks, on_tile
        self.template = context.template()
        self.identity = context.identity()
        self.tile_voxels = context.tile_voxels
        self.columns = context.num_classes + EXTRA_COLUMNS
        self.frontier = 0  # chunks[:frontier] are folded
        self.finished: set[int] = set()
        self.records: dict[int, dict] = {}
        self.entries: dict[str, dict] = {}  # store.json entries of the tiles as written
        self.folded: dict[str, int] = {}  # tile -> the last chunk folded into it (in memory or on disk)
        self._running: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()  # tile -> (index, rows), in memory
        self._absorbed: dict[str, list[int]] = {}  # tile -> chunks folded into it in memory only: their partials wait for its write
        self.seconds = 0.0
        self.voxels_folded = 0  # partial rows folded into tiles (the fold's work: its rate is voxels_folded / seconds)
        self.tiles_written = 0
        for path in sorted((out / "tiles").glob(f"*{map_store.TILE_SUFFIX}")):
            header = self._tile_header(path)
            self.folded[path.stem] = header["folded_through"]
            self.entries[path.stem] = header["entry"]

    def _tile_path(self, name: str) -> Path:
        return self.out / "tiles" / f"{name}{map_store.TILE_SUFFIX}"

    def _partial_path(self, number: int, name: str) -> Path:
        return chunk_dir(self.out, number) / f"{name}{map_store.PARTIAL_SUFFIX}"

    def _tile_header(self, path: Path) -> dict:
        try:
            header = tile_codec.read_voxel_header(path)
        except tile_codec.VoxelFileError as exc:
            raise map_store.StoreError(f"{exc}; delete {self.out} and map again (its tiles hold chunks whose partials are gone)") from None
        folded = header.get("folded_through")
        if (header.get("kind") != "tile" or header.get("store") != self.identity or isinstance(folded, bool) or not isinstance(folded, int)
                or not isinstance(header.get("entry"), dict)):
            raise map_store.StoreError(f"{path}: not a tile of this batch run (another store's, or one written by a merge); "
                                       f"delete {self.out} and map again, or give a new --out")
        return header

    def chunk_finished(self, number: int) -> None:
        """Chunk ``number`` is mapped: fold it, and every finished chunk after it up to the first that is not."""
        self.finished.add(number)
        started = time.perf_counter()
        while self.frontier < len(self.chunks) and self.chunks[self.frontier].number in self.finished:
            self._fold(self.chunks[self.frontier])
            self.frontier += 1
        self.seconds += time.perf_counter() - started

    def finish(self) -> None:
        """Write every tile still in memory (the run's last step before store.json)."""
        started = time.perf_counter()
        while self._running:
            self._write(next(iter(self._running)))
        self.seconds += time.perf_counter() - started

    def _fold(self, chunk: Chunk) -> None:
        record = read_done(self.out, chunk, self.folded)
        for name in record["tiles"]:
            if self.folded.get(name, -1) >= chunk.number:
                self._partial_path(chunk.number, name).unlink(missing_ok=True)  # folded and written before the last run was killed
                continue
            index, rows = map_store.read_partial(self._partial_path(chunk.number, name), self.columns, self.tile_voxels, self.identity,
                                                 chunk.number)
            running = map_store.fold(self._running_tile(name), index, rows)
            self.voxels_folded += len(index)
            self._running[name] = running
            self._running.move_to_end(name)
            self.folded[name] = chunk.number
            self._absorbed.setdefault(name, []).append(chunk.number)
            if self.on_tile is not None:
                self.on_tile(name, VoxelArrays.from_rows(*running))
        self.records[chunk.number] = record
        while len(self._running) > FOLD_CACHE_TILES:
            self._write(next(iter(self._running)))

    def _write(self, name: str) -> None:
        """Write tile ``name`` from memory, then delete the partials it absorbed."""
        index, rows = self._running.pop(name)
        try:  # durable: the partials are deleted next, and the tile is then the only copy of their evidence
            self.entries[name] = map_store.write_tile(self._tile_path(name), self.template, VoxelArrays.from_rows(index, rows),
                                                      self.tile_voxels, folded_through=self.folded[name], durable=True)
        except OSError as exc:  # a full disk: the tile keeps its last whole version and the partials stay
            raise files.error_naming(exc, self.out, f"writing tile {name}, which holds chunks up to {self.folded[name]}; nothing is "
                                                    f"lost, rerun to resume once there is room") from None
        self.tiles_written += 1
        for number in self._absorbed.pop(name, []):
            self._partial_path(number, name).unlink(missing_ok=True)

    def _running_tile(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        if name in self._running:
            return self._running[name]
        if name not in self.folded:
            return None
        try:
            _, index, rows = tile_codec.read_voxel_file(self._tile_path(name), {"kind": "tile", "store": self.identity})
        except tile_codec.VoxelFileError as exc:
            raise map_store.StoreError(f"{exc}; delete {self.out} and map again (the tile holds chunks whose partials are gone)") from None
        return index, rows
