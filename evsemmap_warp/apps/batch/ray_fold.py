"""Fold lanes on a Ray cluster (reduction.TileFolder's, on Ray with ``--fold-workers N`` or past one lane's worth of
workers: planning.folds_on_nodes): N actors on the nodes, each holding the tiles dealt to it in memory and folding
their partials in the order the driver sends them.

A tile entering the lanes is dealt to one (the one with the least work waiting) and stays there until it is written
and leaves, so its partials reach one process, in chunk order, and the bits are the serial fold's; different tiles
fold side by side on the lanes. The driver sends each partial once (its bytes, from ``work/``), and fetches a tile
when it leaves the lanes to be written (and, for a live view, after each of its folds): no tile crosses the object
store per fold, as it did when each fold was a task that took its tile's previous fold.

A lane lost with its node loses its tiles' sums, but not their evidence: a tile's partials are deleted only once
a tile file holds them (TileFolder). So the driver keeps, per tile, what it sent since the tile's last written
version (the folds and encodes, ``_Log``), starts a new lane and sends all of it again: the tile ends with the
same bits, and the loss costs that resend, nothing else."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...core import map_store
from ...core.voxel_map import EXTRA_COLUMNS, VoxelArrays
from ...frames import WorldFrame
from ...limits import MAX_FOLD_LANE_RESTARTS
from .executors import stuck_error
from .ray_executor import ClusterError, first_line
from .reduction import decode_tile, fold_partials
from .worker import Context

BATCHES_IN_FLIGHT_PER_LANE = 8  # sent and unanswered: bounds the partials waiting in the object store for a busy lane


def _buffer(path: Path) -> np.ndarray:
    """A file's bytes as an array, which Ray stores without pickling it (bytes are copied into the pickle, then into the
    object store: the driver's largest cost in handing out partials, profiled)."""
    return np.frombuffer(path.read_bytes(), np.uint8)


@dataclass(frozen=True)
class FoldSpec:
    """What a fold lane needs of the store (put once in the object store): its identity and tiling, the partials'
    columns, the driver's store path (named in messages) and what its tiles' headers and entries are made of."""

    out: Path
    identity: str
    tile_voxels: int
    columns: int
    config: object
    class_names: tuple
    origin_index: object
    frame: WorldFrame | None

    @classmethod
    def of(cls, context: Context) -> "FoldSpec":
        """The spec of a run's store, from the workers' context."""
        return cls(context.store, context.identity(), context.tile_voxels, context.num_classes + EXTRA_COLUMNS, context.config,
                   context.class_names, context.origin_index, context.frame)


class FoldLane:
    """One lane's tiles, in the memory of the process that hosts it (a Ray actor): each tile's running
    (index, rows), started and grown by ``apply`` in the order the calls come."""

    def __init__(self, spec: FoldSpec):
        self.spec, self.tiles = spec, {}
        self.template = map_store.template_mapper(spec.config, spec.class_names, spec.origin_index, spec.frame)
        self.failure: Exception | None = None  # a failed batch's error: every later call raises it (_failed)

    def _failed(self) -> None:
        """A batch that failed left its tiles short of a chunk: no later call may encode them as if whole (the driver
        would write such a tile and delete the partial it lacks), so each raises the first failure."""
        if self.failure is not None:
            raise self.failure

    def apply(self, ops: list[tuple], datas: list[np.ndarray]) -> tuple[list[int], float]:
        """``ops`` in order, each ("restore", tile, data index or None, path): the tile starts from a tile file's bytes
        (``datas[i]``, read by the driver from ``path``) or empty; or ("fold", tile, [(chunk number, path, data index)]):
        the tile plus those partials, in chunk order. Returns the voxels each fold folded, and the seconds it took."""
        self._failed()
        try:
            return self._apply(ops, datas)
        except Exception as exc:
            self.failure = exc
            raise

    def _apply(self, ops: list[tuple], datas: list[np.ndarray]) -> tuple[list[int], float]:
        started, folded = time.perf_counter(), []
        for op in ops:
            if op[0] == "restore":
                _, name, index, path = op
                self.tiles[name] = decode_tile(datas[index].tobytes(), Path(path), self.spec.identity, self.spec.out) if index is not None else None
            else:
                _, name, partials = op
                read = (map_store.decode_partial(datas[index].tobytes(), Path(path), self.spec.columns, self.spec.tile_voxels, self.spec.identity,
                                                 number) for number, path, index in partials)
                self.tiles[name], voxels = fold_partials(self.tiles[name], read)
                folded.append(voxels)
        return folded, time.perf_counter() - started

    def encode(self, name: str, folded_through: int) -> tuple[np.ndarray, dict, float]:
        """Tile ``name``'s file bytes (an array: the driver reads them where Ray stores them, without a copy) and index
        entry (it stays here until ``forget``), and the seconds it took."""
        self._failed()
        started = time.perf_counter()
        data, entry = map_store.tile_bytes(name, self.template, VoxelArrays.from_rows(*self.tiles[name]), self.spec.tile_voxels,
                                           folded_through=folded_through)
        return np.frombuffer(data, np.uint8), entry, time.perf_counter() - started

    def state(self, name: str):
        """Tile ``name``'s (index, rows) now (a live view's)."""
        self._failed()
        return self.tiles[name]

    def forget(self, name: str) -> None:
        """Tile ``name`` is written and left the lanes."""
        self.tiles.pop(name, None)


@dataclass(eq=False)
class _Call:
    """A call sent to a lane (a handle TileFolder holds): what it was, and where it went last (a resend after a lost
    lane replaces ``lane_actor`` and ``ref``; a fold's ``ref`` is its batch's)."""

    kind: str  # "fold", "encode", "state" or "forget"
    args: tuple
    lane: int
    lane_actor: object = None
    ref: object = None
    counted: bool = False  # a fold's voxels, counted once however often it was sent


@dataclass(eq=False)
class _Batch:
    """One ``apply`` call: a lane's restores and folds sent together (one hand-off, one object, for all the partials
    of a chunk that go to the lane)."""

    lane: int
    lane_actor: object
    ref: object
    folds: list
    size: int  # the partials' and tiles' bytes it carries: the lane's work waiting (RayFoldLanes._least_loaded)


@dataclass
class _Log:
    """What the driver sent for one tile since its last written version (``written``: a tile file holds it; else
    the tile started empty): enough to rebuild the tile on a new lane."""

    lane: int
    written: bool = False
    calls: list = field(default_factory=list)


class RayFoldLanes:
    """``width`` FoldLane actors, dealt out to the nodes in turn, that take no CPU of Ray's count (the mapping tasks
    hold every CPU, and a lane that waited for one would hold up the driver's next hand-out); placed softly, so that
    Ray starts a lost lane's successor on another node. The handles TileFolder holds are ``_Call``s. A chunk's
    folds wait here, per lane, until ``flush`` (or a lane's next other call) sends them as one batch: a call and an
    object per partial cost the driver 3.5 ms each (profiled), more than the thread lane's whole share."""

    def __init__(self, executor, width: int, context: Context):
        self.executor, self.ray, self.width, self.out = executor, executor.ray, width, context.store
        self.spec = executor.put(FoldSpec.of(context))
        self._actor = self.ray.remote(num_cpus=0, max_restarts=0, max_task_retries=0)(FoldLane)
        self._placement = self._alive_nodes() or ["DEFAULT"]
        self.actors = [self._start(lane) for lane in range(width)]
        self._logs: dict[str, _Log] = {}  # tile -> its lane and what was sent for it since its last write
        self._waiting: list[list] = [[] for _ in range(width)]  # per lane: ("restore", tile) and fold calls, to send as a batch
        self._flight: list[_Batch] = []  # batches sent and not answered yet
        self.voxels, self.seconds, self.restarts = 0, 0.0, 0
        self.waited = 0.0  # the driver's seconds waiting for the lanes' answers (ThreadFoldLanes.waited)

    def _alive_nodes(self) -> list:
        """A soft placement on each node alive with CPUs, in a fixed order (Ray places a lane elsewhere if its node goes)."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        nodes = sorted(n["NodeID"] for n in self.ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) > 0)
        return [NodeAffinitySchedulingStrategy(node, soft=True) for node in nodes]

    def _start(self, lane: int):
        return self._actor.options(scheduling_strategy=self._placement[lane % len(self._placement)]).remote(self.spec)

    def flush(self) -> None:
        """Send every lane's waiting folds (TileFolder, after each chunk's hand-out)."""
        for lane in range(self.width):
            self._flush(lane)

    def _flush(self, lane: int) -> None:
        if not self._waiting[lane]:
            return
        ops, datas, folds = [], [], []
        for entry in self._waiting[lane]:
            if isinstance(entry, _Call):
                name, partials = entry.args
                ops.append(("fold", name, [(number, str(path), len(datas) + i) for i, (number, path) in enumerate(partials)]))
                datas += [_buffer(path) for _, path in partials]
                folds.append(entry)
            else:
                name = entry[1]
                path = self.out / "tiles" / f"{name}{map_store.TILE_SUFFIX}"
                ops.append(("restore", name, len(datas) if self._logs[name].written else None, str(path)))
                datas += [_buffer(path)] if self._logs[name].written else []
        self._waiting[lane] = []
        batch = _Batch(lane, self.actors[lane], self.actors[lane].apply.remote(ops, self.executor.put(datas)), folds,
                       sum(data.nbytes for data in datas))
        for call in folds:
            call.lane_actor, call.ref = batch.lane_actor, batch.ref
        self._flight.append(batch)

    def _send(self, call: _Call) -> _Call:
        """``call`` to its lane: a fold waits for the lane's next batch; another call goes now, after it."""
        if call.kind == "fold":
            self._waiting[call.lane].append(call)
            return call
        self._flush(call.lane)
        call.lane_actor = self.actors[call.lane]
        call.ref = getattr(call.lane_actor, call.kind).remote(*call.args)
        return call

    def fold(self, previous, name: str, partials: list[tuple[int, Path]]) -> _Call:
        """As ThreadFoldLanes.fold: ``previous`` a handle of this class (the tile is in its lane), a tile file, or None."""
        if not isinstance(previous, _Call):  # the tile enters the lanes (again): the lane with the least work waiting
            self._logs[name] = _Log(self._least_loaded(), written=previous is not None)
            self._waiting[self._logs[name].lane].append(("restore", name))
        log = self._logs[name]
        self._room(log.lane)
        log.calls.append(self._send(_Call("fold", (name, partials), log.lane)))
        return log.calls[-1]

    def _least_loaded(self) -> int:
        """The lane with the fewest bytes sent and not yet answered. Dealt in turn, tiles left one lane with most of the
        work where the drive's tiles differ in size, and the driver waited on it while the other idled; which lane
        folds a tile does not change its bits."""
        waiting = [0] * self.width
        for batch in self._flight:
            waiting[batch.lane] += batch.size
        return min(range(self.width), key=lambda lane: (waiting[lane], len(self._waiting[lane]), lane))

    def encode(self, state: _Call, name: str, folded_through: int) -> _Call:
        """As ThreadFoldLanes.encode (``state``, the tile's last fold, went to the same lane before)."""
        log = self._logs[name]
        log.calls.append(self._send(_Call("encode", (name, folded_through), log.lane)))
        return log.calls[-1]

    def written(self, name: str, encoded: _Call, left: bool) -> None:
        """Tile ``name``'s file now holds ``encoded``: what was sent for it before is no longer needed to rebuild it;
        ``left``: no fold followed, and the tile leaves its lane's memory."""
        log = self._logs[name]
        del log.calls[:next(i for i, call in enumerate(log.calls) if call is encoded) + 1]
        log.written = True
        if left:  # its next fold restores it from the file, in the lane with the least work then
            self._send(_Call("forget", (name,), log.lane))
            del self._logs[name]

    def _room(self, lane: int) -> None:
        """Wait while ``lane`` has more than BATCHES_IN_FLIGHT_PER_LANE batches unanswered (the other lanes go on)."""
        while len(mine := [batch for batch in self._flight if batch.lane == lane]) > BATCHES_IN_FLIGHT_PER_LANE:
            self._answer(mine[0])

    def check(self) -> None:
        """As ThreadFoldLanes.check: the batches answered since, counted; a lost lane restarted, a failure raised."""
        if self._flight:
            ready = self.ray.wait([batch.ref for batch in self._flight], num_returns=len(self._flight), timeout=0)[0]
            for batch in [batch for batch in self._flight if any(batch.ref is ref for ref in ready)]:
                if batch in self._flight:  # not dropped by a restart meanwhile
                    self._answer(batch)

    def _answer(self, call: _Call | _Batch):
        """``call``'s answer, waited for as the mapping tasks are (RayExecutor.wait); a lost lane is restarted (its
        tiles' calls sent again, and this one), then the answer of the call sent anew (a batch's calls go in new
        batches: it has none). A batch's voxels and every call's seconds are counted."""
        while True:
            started = time.perf_counter()
            if not self.executor.wait([call.ref]):
                raise stuck_error(self.executor.chunk_timeout_s, "fold of the tiles")
            self.waited += time.perf_counter() - started
            try:
                answer = self.ray.get(call.ref)
            except (self.ray.exceptions.RayActorError, self.ray.exceptions.ObjectLostError) as exc:
                # the lane is gone, or its node with the answer (an encoded tile waits in the node's object store)
                if call.lane_actor is self.actors[call.lane]:
                    self._restart(call.lane, exc)
                if isinstance(call, _Batch):
                    return None
                if call.lane_actor is not self.actors[call.lane]:  # a call no tile's log holds (a live view's "state")
                    self._send(call)
                continue
            except self.ray.exceptions.RayError:
                return self.executor.fetch(call.ref)  # a lane's failure (a bad partial): one line, as a task's
            if isinstance(call, _Batch):
                self._flight.remove(call)
                folded, seconds = answer
                for fold, voxels in zip(call.folds, folded):
                    self.voxels += 0 if fold.counted else voxels
                    fold.counted = True
            elif call.kind == "encode":
                *answer, seconds = answer
            else:
                seconds = 0.0
            self.seconds += seconds
            return answer

    def _restart(self, lane: int, cause: Exception) -> None:
        """A new actor for ``lane`` (lost with its node), on a node alive now, and every call its tiles need sent
        again, in order."""
        self.restarts += 1
        if self.restarts > MAX_FOLD_LANE_RESTARTS:
            raise ClusterError(f"fold lanes were lost {self.restarts} times, the last: {first_line(cause)}; the chunks mapped so far "
                               f"are kept, and a rerun resumes from them") from None
        self._placement = self._alive_nodes() or self._placement
        self._flight = [batch for batch in self._flight if batch.lane != lane]
        self._waiting[lane] = []
        with contextlib.suppress(Exception):
            self.ray.kill(self.actors[lane])  # gone already, or about to be
        self.actors[lane] = self._start(lane)
        for name, log in self._logs.items():
            if log.lane == lane:
                self._waiting[lane].append(("restore", name))
                for call in log.calls:
                    self._send(call)
        self._flush(lane)

    def done(self, handle: _Call) -> bool:
        """Whether a call has its answer (a lost lane's call counts: ``result`` then sends it again)."""
        self._flush(handle.lane)
        return bool(self.ray.wait([handle.ref], num_returns=1, timeout=0)[0])

    def result(self, handle: _Call):
        """An encode's (bytes, entry); for a fold, the tile's (index, rows) after it (a live view's)."""
        if handle.kind == "fold":
            handle = self._send(_Call("state", (handle.args[0],), handle.lane))
        return self._answer(handle)

    def stats(self) -> tuple[int, float]:
        """Voxels folded and the lanes' seconds folding and encoding (once every batch is answered)."""
        self.flush()
        while self._flight:
            self._answer(self._flight[0])
        return self.voxels, self.seconds

    def close(self) -> None:
        """Stop the lanes and release the references (before Ray stops: RayExecutor.close)."""
        self._flight, self._logs, self._waiting = [], {}, [[] for _ in range(self.width)]
        for actor in self.actors:
            with contextlib.suppress(Exception):
                self.ray.kill(actor)
        self.actors = []
