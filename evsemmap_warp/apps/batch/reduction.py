"""The driver's side of the streaming reduction: finished chunks' partials folded into the store's tiles while the
workers map; each tile's partials in chunk order, different tiles in parallel (fold lanes)."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ... import files
from ...core import map_store, tile_codec
from ...core.voxel_map import EXTRA_COLUMNS, VoxelArrays
from .planning import FOLD_CACHE_TILES, Chunk
from .store import chunk_dir, read_done
from .worker import Context

def decode_tile(data: bytes, path: Path, identity: str, out: Path) -> tuple[np.ndarray, np.ndarray]:
    """A tile file's bytes as a fold starts from them (a tile written before it left memory, or by a killed run)."""
    try:
        _, index, rows = tile_codec.check_expected(tile_codec.decode_voxels(data, path), path, {"kind": "tile", "store": identity})
    except tile_codec.VoxelFileError as exc:
        raise map_store.StoreError(f"{exc}; delete {out} and map again (the tile holds chunks whose partials are gone)") from None
    return index, rows


def fold_partials(running: tuple[np.ndarray, np.ndarray] | None, partials) -> tuple[tuple[np.ndarray, np.ndarray], int]:
    """``running`` plus ``partials`` ((index, rows) of one tile, in chunk order), and the voxels they held: the
    one function every lane folds with, so that every lane gives the same bits (map_store.fold)."""
    voxels = 0
    for index, rows in partials:
        running = map_store.fold(running, index, rows)
        voxels += len(index)
    return running, voxels


class ThreadFoldLanes:
    """Fold lanes on ``width`` threads of the driver (one by default: fold_width). Each fold is a future; one
    tile's next fold waits for its previous one (it was queued earlier, so it runs or has run: the FIFO queue
    cannot deadlock), other tiles' folds run beside it."""

    def __init__(self, width: int, context: Context):
        self.width, self.out = width, context.store
        self.template, self.identity = context.template(), context.identity()
        self.tile_voxels, self.columns = context.tile_voxels, context.num_classes + EXTRA_COLUMNS
        self._pool = ThreadPoolExecutor(width, thread_name_prefix="evsemmap-fold")
        self._lock = threading.Lock()
        self.voxels, self.seconds = 0, 0.0  # what the lanes folded, and their time folding and encoding (all lanes')
        self.restarts = 0  # a thread is not lost alone (RayFoldLanes.restarts)
        self.waited = 0.0  # the driver's seconds waiting for the lanes' answers (its fold time, less its own work)
        self._failures: list[BaseException] = []  # the lanes' failures, as they happen (check raises the first)

    def fold(self, previous, name: str, partials: list[tuple[int, Path]]) -> Future:
        """Tile ``name`` (``previous``: a fold's future, its file, or None for a new tile) plus ``partials``
        (chunk number, file), in chunk order; a future of (index, rows)."""
        return self._watched(self._pool.submit(self._fold, previous, partials))

    def _watched(self, future: Future) -> Future:
        future.add_done_callback(self._note_failure)
        return future

    def _note_failure(self, future: Future) -> None:
        if not future.cancelled() and future.exception() is not None:
            with self._lock:
                self._failures.append(future.exception())

    def check(self) -> None:
        """A lane's first failure, raised at the driver's next hand-out: a tile the drive keeps passing is written
        only at the end, and its failed fold would otherwise surface there, hours later."""
        with self._lock:
            failure = self._failures[0] if self._failures else None
        if failure is not None:
            raise failure

    def _fold(self, previous, partials):
        started = time.perf_counter()
        if isinstance(previous, Future):
            running = previous.result()
            started = time.perf_counter()  # the wait for the previous fold is not this one's work
        elif previous is not None:
            running = decode_tile(previous.read_bytes(), previous, self.identity, self.out)
        else:
            running = None
        read = (map_store.read_partial(path, self.columns, self.tile_voxels, self.identity, number) for number, path in partials)
        running, voxels = fold_partials(running, read)
        self._count(voxels, time.perf_counter() - started)
        return running

    def encode(self, state: Future, name: str, folded_through: int) -> Future:
        """A future of tile ``name``'s file bytes and its index entry, from a fold's future ``state``."""
        def encode():
            index, rows = state.result()
            started = time.perf_counter()
            encoded = map_store.tile_bytes(name, self.template, VoxelArrays.from_rows(index, rows), self.tile_voxels,
                                           folded_through=folded_through)
            self._count(0, time.perf_counter() - started)
            return encoded
        return self._watched(self._pool.submit(encode))

    def _count(self, voxels: int, seconds: float) -> None:
        with self._lock:
            self.voxels += voxels
            self.seconds += seconds

    @staticmethod
    def done(handle: Future) -> bool:
        """Whether a fold's or an encode's future has its answer."""
        return handle.done()

    def result(self, handle: Future):
        """A fold's (index, rows) or an encode's (bytes, entry); a lane's failure raised here."""
        started = time.perf_counter()
        try:
            return handle.result()
        finally:
            self.waited += time.perf_counter() - started

    @staticmethod
    def flush() -> None:
        """The chunk's folds are handed out (RayFoldLanes sends them then; a thread has them already)."""

    @staticmethod
    def written(name: str, encoded: Future, left: bool) -> None:
        """Tile ``name``'s file holds ``encoded`` now (RayFoldLanes keeps what rebuilds a tile until then; the threads
        keep each tile's state in its fold's future, and nothing else)."""

    def stats(self) -> tuple[int, float]:
        """Voxels folded and the lanes' seconds folding and encoding, all lanes together."""
        return self.voxels, self.seconds

    def close(self) -> None:
        """Cancel what has not started and wait for what has (no lane writes after the run ends)."""
        self._pool.shutdown(wait=True, cancel_futures=True)


class TileFolder:
    """The driver's side of the streaming reduction: finished chunks' partials folded into the store's tiles,
    each tile's in chunk order, on ``lanes`` (ThreadFoldLanes, or ray_fold.RayFoldLanes), different tiles
    in parallel. The tiles the drive is passing stay in the lanes (the ``FOLD_CACHE_TILES`` most recently
    folded); a tile leaving them, and every tile at the end, is encoded by a lane and written here, in the order
    they left, durably with the last chunk it holds (``folded_through``), and only then are the partials it
    absorbed deleted. A killed run therefore loses nothing: what is not in a tile file is still in a partial,
    and the rerun folds exactly the chunks each tile lacks. ``on_tile(name, voxels)`` sees every tile as it
    grows (a live view: the driver waits for each chunk's folds then)."""

    def __init__(self, out: Path, context: Context, chunks: list[Chunk], lanes, on_tile=None):
        self.out, self.chunks, self.lanes, self.on_tile = out, chunks, lanes, on_tile
        self.identity = context.identity()
        self.frontier = 0  # chunks[:frontier] are folded (handed to the lanes)
        self.finished: set[int] = set()
        self.records: dict[int, dict] = {}
        self.entries: dict[str, dict] = {}  # store.json entries of the tiles as written
        self.folded: dict[str, int] = {}  # tile -> the last chunk folded into it (in a lane or on disk)
        self._running: OrderedDict[str, object] = OrderedDict()  # tile -> its last fold's handle, in the lanes
        self._absorbed: dict[str, list[int]] = {}  # tile -> chunks folded into it in the lanes only: their partials wait for its write
        self._writes: deque = deque()  # (tile, encode handle, fold handle, folded_through, absorbed chunks), in the order the tiles left
        self._leaving: dict[str, object] = {}  # tile -> the fold handle of its last write still to be done (a fold goes on from it)
        self.seconds = 0.0  # the driver's time folding: handing partials to the lanes, writing tiles (and waiting: lanes.waited)
        self.voxels_folded, self.lane_seconds = 0, 0.0  # finish's: partial rows folded into tiles, the lanes' time (lanes.stats)
        self.waited = 0.0  # finish's: of ``seconds``, the driver's wait for the lanes' answers
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
        self.lanes.check()
        while self.frontier < len(self.chunks) and self.chunks[self.frontier].number in self.finished:
            self._fold(self.chunks[self.frontier])
            self.frontier += 1
        self.lanes.flush()
        self._collect(most_waiting=FOLD_CACHE_TILES)
        self.seconds += time.perf_counter() - started

    def finish(self) -> None:
        """Write every tile still in the lanes (the run's last step before store.json)."""
        started = time.perf_counter()
        while self._running:
            self._leave(next(iter(self._running)))
        self._collect(most_waiting=0)
        self.voxels_folded, self.lane_seconds = self.lanes.stats()
        self.waited = self.lanes.waited
        self.seconds += time.perf_counter() - started

    def close(self) -> None:
        """Stop the lanes and drop their handles (after finish, or when the run failed: what was not written stays in
        the partials); Ray's references are gone before Ray stops (RayExecutor.close)."""
        self._running.clear()
        self._leaving.clear()
        self._writes.clear()
        self.lanes.close()

    def _fold(self, chunk: Chunk) -> None:
        record = read_done(self.out, chunk, self.folded)
        grown = []
        for name in record["tiles"]:
            if self.folded.get(name, -1) >= chunk.number:
                self._partial_path(chunk.number, name).unlink(missing_ok=True)  # folded and written before the last run was killed
                continue
            previous = self._running.pop(name, None)  # the tile in the lanes, else waiting for its write, else on disk
            if previous is None:
                previous = self._leaving.get(name)
            if previous is None and name in self.folded:
                previous = self._tile_path(name)
            self._running[name] = self.lanes.fold(previous, name, [(chunk.number, self._partial_path(chunk.number, name))])
            self.folded[name] = chunk.number
            self._absorbed.setdefault(name, []).append(chunk.number)
            grown.append(name)
        self.records[chunk.number] = record
        if self.on_tile is not None:
            for name in grown:
                self.on_tile(name, VoxelArrays.from_rows(*self.lanes.result(self._running[name])))
        while len(self._running) > FOLD_CACHE_TILES:
            self._leave(next(iter(self._running)))

    def _leave(self, name: str) -> None:
        """Tile ``name`` leaves the lanes: a lane encodes it, and _collect writes it."""
        state = self._running.pop(name)
        self._writes.append((name, self.lanes.encode(state, name, self.folded[name]), state, self.folded[name], self._absorbed.pop(name, [])))
        self._leaving[name] = state

    def _collect(self, most_waiting: int) -> None:
        """Write the encoded tiles, in the order they left, those ready, and more until at most ``most_waiting``
        wait (the tiles waiting to be written are in memory too)."""
        while self._writes and (len(self._writes) > most_waiting or self.lanes.done(self._writes[0][1])):
            name, encoded, state, through, absorbed = self._writes.popleft()
            data, entry = self.lanes.result(encoded)
            try:  # durable: the partials are deleted next, and the tile is then the only copy of their evidence
                files.write_atomically(self._tile_path(name), lambda f: f.write(data), durable=True)
            except OSError as exc:  # a full disk: the tile keeps its last whole version and the partials stay
                raise files.error_naming(exc, self.out, f"writing tile {name}, which holds chunks up to {through}; nothing "
                                                        f"is lost, rerun to resume once there is room") from None
            self.entries[name] = entry
            self.tiles_written += 1
            for number in absorbed:
                self._partial_path(number, name).unlink(missing_ok=True)
            left = name not in self._running and self._leaving.get(name) is state  # no fold since it left
            self.lanes.written(name, encoded, left)
            if self._leaving.get(name) is state:
                del self._leaving[name]
