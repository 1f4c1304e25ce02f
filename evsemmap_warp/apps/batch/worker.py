"""A worker's side of a batch run: the context every task receives, the task (map_chunk: one chunk into its
partial map, written per tile under ``STORE/work``), the worker process's set-up and Ctrl-C handling, the
hand-off costs a task records, and the tests' fault injection (FaultPlan)."""

from __future__ import annotations

import os
import pickle
import resource
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import files
from ...config import MappingConfig
from ...core import map_store
from ...core.mapper import Mapper
from ...core.voxel_map import VoxelArrays, sum_shard_rows
from ...frames import WorldFrame
from ..scan_sources import CheckpointScans, map_scans
from .planning import Chunk
from .store import chunk_dir, read_done


@dataclass(frozen=True)
class FaultPlan:
    """Fault injection, a seam for the tests only (run_batch's ``fault``): the worker that maps
    chunk ``kill_chunk`` dies halfway through its first attempt, as a killed process would."""

    kill_chunk: int
    hang_chunk: int | None = None  # the worker that maps this chunk sleeps instead, as a stuck one would


@dataclass
class Context:
    """What every task needs; sent once to each worker (a file a process pool's workers read as they start, a Ray object)."""

    store: Path
    sources: list
    config: MappingConfig
    num_classes: int
    class_names: tuple[str, ...]
    origin_index: np.ndarray
    tile_voxels: int
    frame: WorldFrame | None = None  # the world frame every input is mapped in
    fault: FaultPlan | None = None  # tests only (run_batch's fault); None in use

    max_memory: int | None = None  # each worker's voxel table budget (BatchOptions.max_memory)

    def template(self) -> Mapper:
        """An empty Mapper with the store's parameters, classes, origin and frame (map_store.template_mapper)."""
        return map_store.template_mapper(self.config, self.class_names, self.origin_index, self.frame)

    def identity(self) -> str:
        """The store's identity (map_store.store_identity), which its partials and tiles record."""
        return map_store.template_identity(self.template(), self.tile_voxels)


_CONTEXT: Context | None = None


_IN_TASK = False  # a worker process is running a task (map_chunk) now
_TASKS_STARTED = 0  # tasks this worker process has started (its first one also paid for the process's start)


def _worker_interrupt(signum, frame) -> None:
    """Ctrl-C reaches every process of the terminal's group: a worker in a task stops it as an
    interruption (its writes clean up after themselves: no temporary file stays), an idle one leaves
    without a traceback; the driver says "interrupted" once."""
    if _IN_TASK:
        raise KeyboardInterrupt
    os._exit(130)


def reset_tasks_started() -> None:
    """This process's next task is its first of a run (a Ray worker that served an earlier run)."""
    global _TASKS_STARTED
    _TASKS_STARTED = 0


def handoff_recorder(submitted: float):
    """The start of a task submitted at wall-clock time ``submitted`` (time.time(), the driver's): a
    function that adds the task's hand-off costs to a result that is a dict (a chunk record), as
    ``handoff``: ``wait_s``, submission to start (for a worker process's first task, ``first_in_process``,
    that is its start: spawning, imports, the context; for a later one, the queue behind its previous
    task); ``result_bytes``, the pickled result; ``returned_at``, the wall-clock time it was returned
    (the driver takes the time to receiving it, ``return_s``). Wall clocks: meaningful on one machine."""
    global _TASKS_STARTED
    began, first = time.time(), _TASKS_STARTED == 0
    _TASKS_STARTED += 1

    def add(result):
        if not isinstance(result, dict):
            return result
        handoff = {"wait_s": began - submitted, "first_in_process": first, "result_bytes": len(pickle.dumps(result))}
        return result | {"handoff": handoff | {"returned_at": time.time()}}

    return add


def as_task(fn, submitted: float, *args):
    """``fn(*args)`` in a pool worker, marked as a task for _worker_interrupt; ``submitted``: when the
    driver submitted it (time.time()), for the hand-off costs (handoff_recorder)."""
    global _IN_TASK
    handoff = handoff_recorder(submitted)
    _IN_TASK = True
    try:
        return handoff(fn(*args))
    finally:
        _IN_TASK = False


def init_worker(context: Context, threads: int) -> None:
    """A worker process's set-up, before its first task: the run's context, Ctrl-C handling, torch's threads."""
    global _CONTEXT
    _CONTEXT = context
    import signal

    signal.signal(signal.SIGINT, _worker_interrupt)
    # Only a worker that runs a network imports torch: the import costs each worker process about 1.5 s of
    # CPU and doubles the objects Python's collector walks, paid out of the mapping's time where the
    # workers share the cores (docs/performance.md, "Batch mapping").
    if any(isinstance(source, CheckpointScans) for source in context.sources):
        import torch

        torch.set_num_threads(threads)  # workers share the cores: no worker's inference takes them all


def process_tag() -> str:
    """This process as a chunk's temporary folder names it: its machine's boot, its PID namespace and its PID
    (``BOOT_NAMESPACE-PID``). Nodes in containers, or on other machines, may share a temporary folder while each has
    PIDs of its own: a PID alone would name another node's live task as a dead one of this node
    (ray_executor.remove_dead_tasks_leftovers). Namespace numbers repeat across machines; boot ids do not."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()[:8]
        namespace = os.stat("/proc/self/ns/pid").st_ino
    except OSError:  # no /proc (not Linux): one machine's one namespace, as far as this can tell
        boot, namespace = "0", 0
    return f"{boot}_{namespace}-{os.getpid()}"


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MB (Linux's ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _inject_fault(context: Context, chunk: Chunk, partial_dir: Path) -> None:
    if context.fault is not None and context.fault.hang_chunk == chunk.number:
        time.sleep(3600)
    if context.fault is not None and context.fault.kill_chunk == chunk.number:
        marker = context.store / "work" / f".fault-{chunk.number}"
        if not marker.exists():
            marker.write_text("killed once\n")
            partial_dir.mkdir(parents=True, exist_ok=True)
            (partial_dir / f"0_0_0{map_store.PARTIAL_SUFFIX}").write_bytes(b"half a file")
            os._exit(137)


CHUNK_STAGES = ("open", "read", "integrate", "extract", "write_partial")  # map_chunk's stage_seconds, in the order they run


def _timed(scans, clock: dict):
    """The items of ``scans``; the time spent getting each (reading and preparing it) added to clock["read"]."""
    iterator = iter(scans)
    while True:
        started = time.perf_counter()
        try:
            scan = next(iterator)
        except StopIteration:
            return
        finally:
            clock["read"] += time.perf_counter() - started
        yield scan


def chunk_voxels(mapper: Mapper) -> VoxelArrays:
    """The mapper's voxels with global indices, the arrays ``mapper.voxels()`` gives without its read-out
    (the Dirichlet summary a partial does not store): that read-out was half of a chunk's extract stage."""
    voxels = sum_shard_rows(mapper.shard_rows())
    if mapper.origin_index is not None:
        voxels.index = voxels.index + mapper.origin_index
    return voxels


def map_chunk(chunk: Chunk, context: Context | None = None) -> dict:
    """Map one chunk into its partial map, written per tile; returns its counts and costs: ``seconds``,
    and ``stage_seconds`` (CHUNK_STAGES), which add up to them: "open", the setup (an empty mapper, the
    scan source's iterator); "read", getting each next scan from the source (reading and preparing it:
    files, projection, inference); "integrate", the mapper's work on the scans; "extract", the map's
    voxels out of the mapper, split by tile; "write_partial", the partials and done.json written (encoded,
    written, made durable) and the chunk's folder renamed into place."""
    context = context or _CONTEXT
    started = time.perf_counter()
    done = chunk_dir(context.store, chunk.number)
    if (done / "done.json").is_file():  # a retried task whose first attempt finished after all
        return read_done(context.store, chunk) | {"seconds": 0.0, "stage_seconds": {}, "peak_rss_mb": peak_rss_mb()}
    partial = context.store / "work" / f".chunk_{chunk.number:06d}.{process_tag()}.tmp"
    shutil.rmtree(partial, ignore_errors=True)
    _inject_fault(context, chunk, partial)
    source = context.sources[chunk.sequence]
    mapper = Mapper.for_dataset(source, context.config, workers=1, origin=context.origin_index * context.config.resolution_m,
                                max_memory=context.max_memory)
    scans_in = source.scans(chunk.start, chunk.stop)
    clock = dict.fromkeys(CHUNK_STAGES, 0.0)
    mark = time.perf_counter()
    clock["open"] = mark - started
    stats = map_scans(mapper, _timed(scans_in, clock))  # one worker thread: reading and integrating take turns
    clock["integrate"] = max(0.0, time.perf_counter() - mark - clock["read"])
    mark = time.perf_counter()
    points, scans = sum(s.input_points for s in stats), len(stats)
    voxels = chunk_voxels(mapper)
    parts = map_store.split_by_tile(voxels.index, voxels.rows(), context.tile_voxels)
    identity = context.identity()
    now = time.perf_counter()
    clock["extract"], mark = now - mark, now
    try:
        partial.mkdir(parents=True, exist_ok=True)
        for name, (index, rows) in parts.items():
            map_store.write_partial(partial / f"{name}{map_store.PARTIAL_SUFFIX}", index, rows, context.tile_voxels, identity, chunk.number)
    except OSError as exc:  # a full disk: nothing of the chunk stays, the error names the store, not the temporary folder
        shutil.rmtree(partial, ignore_errors=True)
        raise files.error_naming(exc, context.store, f"writing chunk {chunk.number}'s partial maps; the mapped chunks are kept, "
                                                    f"rerun to resume") from None
    record = {"number": chunk.number, "frames": chunk.frames, "scans": scans, "points": points, "voxels": int(len(voxels.index)),
              "tiles": list(parts), "scan_ids": sorted(mapper.scan_ids)}
    map_store.write_json(partial / "done.json", record)
    try:
        os.rename(partial, done)  # the chunk counts from here on, all of it or nothing
    except OSError:  # another attempt of this chunk got there first: same content
        shutil.rmtree(partial, ignore_errors=True)
    now = time.perf_counter()
    clock["write_partial"] = now - mark
    return record | {"seconds": now - started, "stage_seconds": clock, "peak_rss_mb": peak_rss_mb()}
