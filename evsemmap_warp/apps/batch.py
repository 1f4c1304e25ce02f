"""``evsemmap batch``: map long sequences on every core of a machine, or on a Ray cluster, into a map
store (core/map_store.py).

BKI maps are sums, so partial maps of disjoint scan sets add up exactly. A run:

1. plans: the inputs' insertions (scans, or bins of camera-labelled frames) are cut into chunks of
   consecutive insertions (``--chunk-frames`` frames, by default chosen from the inputs' total frames
   alone, see choose_chunk_frames; rounded to whole bins, so per-insertion rules see what
   ``evsemmap map`` shows them); the map origin is that ``evsemmap map`` picks (the first scan's);
2. maps each chunk in a worker into a partial map, written per spatial tile under ``STORE/work``
   (a chunk is done when its folder is renamed into place, so a killed worker leaves nothing that
   counts);
3. folds, in the driver while the workers map, every finished chunk's partials into the store's
   tiles, in chunk order (so the sums do not depend on which chunk finished first), and deletes them:
   a tile is final as soon as the last chunk touching it is folded, and the disk holds the tiles plus
   the partials of chunks not yet folded. Each tile records the last chunk folded into it, so a
   resumed run folds every chunk into every tile exactly once;
4. writes ``STORE/store.json`` last.

A rerun of the same command skips finished chunks and folds what is left, so an interrupted run
finishes without counting any chunk twice; a worker that dies is replaced and its chunk mapped again.
The same inputs give the same store, byte for byte, whatever the executor, worker count or completion
order.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pickle
import resource
import shutil
import socket
import sys
import threading
import time
from collections import OrderedDict
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, ThreadPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..config import ConfigError, MappingConfig, flat_items, is_robot_log, load_config
from ..core import map_store, tile_codec
from ..core.mapper import Mapper
from ..core.voxel_map import EXTRA_COLUMNS, VoxelArrays
from ..frames import WorldFrame, check_same_frame
from ..limits import available_memory, check_chunk_frames, check_tile_voxels
from .scan_sources import map_scans, open_scan_source

WORKER_OVERHEAD_BYTES = 450 * 2**20  # a worker process with numpy, Warp and its kernels loaded (measured: ~0.4 GB)
DRIVER_OVERHEAD_BYTES = 450 * 2**20
FOLD_CACHE_TILES = 12  # tiles the driver keeps in memory while folding (the drive passes through them; up to ~15 MB each)
# The automatic chunk size (--chunk-frames not given): the inputs' frames cut into at least AUTO_CHUNKS
# chunks (two per worker up to 8 workers, so short inputs use every core), at most MAX_AUTO_CHUNK_FRAMES
# frames each. It depends on the inputs only, never on the worker count: stores stay byte-identical.
AUTO_CHUNKS = 16
MAX_AUTO_CHUNK_FRAMES = 100
# How long --ray-address's host:port may take to accept a connection (--ray-connect-timeout-s): ray.init
# retries an address where nothing answers for many minutes ("Failed to connect to GCS").
RAY_CONNECT_TIMEOUT_S = 30.0
# How long a run waits for some chunk to finish before it stops as stuck (a worker or node that hangs); a chunk of
# the default size maps in seconds, one labelled by a network on the CPU in minutes.
CHUNK_TIMEOUT_S = 3600.0


@dataclass(frozen=True)
class _FaultPlan:
    """Fault injection, a seam for the tests only (run_batch's private ``_fault``): the worker that maps
    chunk ``kill_chunk`` dies halfway through its first attempt, as a killed process would."""

    kill_chunk: int
    hang_chunk: int | None = None  # the worker that maps this chunk sleeps instead, as a stuck one would


@dataclass(frozen=True)
class BatchOptions:
    """What ``evsemmap batch`` was asked for (its flags); ``run_batch`` takes the inputs beside it."""

    method: str
    out: Path
    executor: str = "local"  # local | ray (| inline: in this process, for tests and debugging)
    workers: int | None = None  # default: one per core (local), the cluster's CPUs (ray)
    chunk_frames: int | None = None  # None: automatic (choose_chunk_frames), from the inputs' frames
    ray_address: str | None = None
    ray_connect_timeout_s: float = RAY_CONNECT_TIMEOUT_S
    chunk_timeout_s: float = CHUNK_TIMEOUT_S  # --chunk-timeout-s: the run stops when no chunk finishes for this long
    same_frame: bool = False  # --same-frame: the inputs' run frames (odom) are one run's, a drive cut into several logs
    max_memory: int | None = None  # --max-memory: each worker's voxel table budget (Mapper max_memory); None: the memory available
    checkpoint: Path | None = None
    alpha: Path | None = None
    bin_frames: int | None = None
    batch_size: int = 4
    frame: str | None = None  # --frame: overrides the inputs' dataset.frame (a name, or first-scan)
    crs: str | None = None  # --crs
    tile_voxels: int = map_store.DEFAULT_TILE_VOXELS
    discard_partials: bool = False
    progress: bool = True


@dataclass(frozen=True)
class Chunk:
    """A run's unit of work: insertions ``start..stop-1`` of input ``sequence``, ``frames`` frames."""

    number: int
    sequence: int  # which input
    start: int  # insertions start..stop-1 of that input
    stop: int
    frames: int


@dataclass
class Context:
    """What every task needs; sent once to each worker (a process pool's initializer, a Ray object)."""

    store: Path
    sources: list
    config: MappingConfig
    num_classes: int
    class_names: tuple[str, ...]
    origin_index: np.ndarray
    tile_voxels: int
    frame: WorldFrame | None = None  # the world frame every input is mapped in
    fault: _FaultPlan | None = None  # tests only (run_batch's _fault); None in use

    max_memory: int | None = None  # each worker's voxel table budget (BatchOptions.max_memory)

    def template(self) -> Mapper:
        """An empty Mapper with the store's parameters, classes, origin and frame (map_store.template_mapper)."""
        return map_store.template_mapper(self.config, self.class_names, self.origin_index, self.frame)

    def identity(self) -> str:
        """The store's identity (map_store.store_identity), which its partials and tiles record."""
        return map_store.template_identity(self.template(), self.tile_voxels)


# Planning ------------------------------------------------------------------------------------------
def split_inputs(paths: list[str]) -> tuple[list[str], list[str]]:
    """The inputs (sequence folders, robot logs, config files with a dataset section: one sequence
    each) and the configs shared by all of them (presets by name, files without a dataset)."""
    inputs, shared = [], []
    for text in paths:
        path = Path(text)
        if path.is_dir() or is_robot_log(path):
            inputs.append(text)
        elif path.suffix in (".yaml", ".yml") and path.is_file() and "dataset" in (load_yaml_sections(path)):
            inputs.append(text)
        else:
            shared.append(text)
    if not inputs:
        raise ConfigError(f"batch: none of {paths} is a sequence (a folder, a robot log or a config with a dataset section)")
    return inputs, shared


def load_yaml_sections(path: Path) -> set:
    """The top-level keys of a YAML file (empty when it holds no mapping)."""
    from ..config import read_yaml_file

    data = read_yaml_file(path)
    return set(data) if isinstance(data, dict) else set()


def _input_identity(paths: list, dataset=None) -> list:
    """What a resumed run must find unchanged: the content of every file it reads (files.content_identity,
    where the trade-off against size + mtime is measured): the given paths (a folder, a log, configs;
    a preset by its name) and the data a dataset config points at (its folder, file or logs)."""
    data = []
    if dataset is not None:
        data = list(dataset.resolve_logs()) if dataset.kind == "bag" else [dataset.resolve_path()]
    seen, out = set(), []
    for path in [Path(p) for p in paths] + data:
        key = str(path.resolve()) if path.exists() else str(path)
        if key not in seen:
            seen.add(key)
            out.append(files.content_identity(path))
    return out


def choose_chunk_frames(requested: int | None, total_frames: int) -> tuple[int, str]:
    """Frames per chunk, and the rule that gave them: ``requested`` (--chunk-frames) when given, else
    ceil(total_frames / AUTO_CHUNKS), at most MAX_AUTO_CHUNK_FRAMES and at least 1 (plan_batch then
    rounds to whole bins, at least one). The inputs' frames alone decide, never the worker count."""
    if requested is not None:
        try:
            return check_chunk_frames(requested, "--chunk-frames"), "given: --chunk-frames"
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    chosen = max(1, min(MAX_AUTO_CHUNK_FRAMES, -(-total_frames // AUTO_CHUNKS)))
    return chosen, (f"automatic: ceil({total_frames} frames / {AUTO_CHUNKS}) capped at {MAX_AUTO_CHUNK_FRAMES}, from the inputs' frames "
                    f"only (at least {AUTO_CHUNKS} chunks, two per worker up to {AUTO_CHUNKS // 2} workers, when the frames allow; "
                    f"the same store for any worker count)")


def plan_batch(paths: list[str], options: BatchOptions):
    """The sources, the mapping config, the chunks and the identity of the run (for resuming)."""
    inputs, shared = split_inputs(paths)
    sources, runs = [], []
    for text in inputs:
        run = load_config([text] + shared, method=options.method, frame=options.frame, crs=options.crs)
        if run.dataset is None:
            raise ConfigError(f"{text}: no dataset section")
        runs.append(run)
        sources.append(open_scan_source(run, checkpoint=options.checkpoint, alpha_dir=options.alpha, bin_frames=options.bin_frames,
                                        batch_size=options.batch_size))
    config = runs[0].mapping
    for text, run, source in zip(inputs, runs, sources):
        if run.mapping != config:
            mine, theirs = flat_items(config.as_dict()), flat_items(run.mapping.as_dict())
            raise ConfigError(f"{text}: its mapping parameters differ from {inputs[0]}'s: "
                              + ", ".join(f"{k} {mine[k]!r} vs {theirs[k]!r}" for k in mine if mine[k] != theirs[k]))
        if source.num_classes != sources[0].num_classes:
            raise ConfigError(f"{text}: {source.num_classes} classes, {inputs[0]} has {sources[0].num_classes}")
        # inputs combine only in one frame; a drive cut into several logs is one run's, when the user says so
        check_same_frame("batch", (inputs[0], sources[0].frame), (text, source.frame), same_frame=options.same_frame)
    chunk_frames, _ = choose_chunk_frames(options.chunk_frames, sum(source.frames_in(0, len(source)) for source in sources))
    chunks = []
    for s, source in enumerate(sources):
        per_bin = max(1, getattr(source, "bin_frames", 1))
        insertions = max(1, chunk_frames // per_bin)  # whole bins: a chunk never splits one
        for start in range(0, len(source), insertions):
            stop = min(start + insertions, len(source))
            chunks.append(Chunk(len(chunks), s, start, stop, source.frames_in(start, stop)))
    if not chunks:
        raise ConfigError(f"batch: the inputs {inputs} hold no scans")
    identity = {
        "store_format_version": map_store.STORE_VERSION,
        "inputs": [_input_identity([text] + shared, run.dataset) for text, run in zip(inputs, runs)], "method": options.method,
        "mapping": config.as_dict(),
        "chunk_frames": chunk_frames, "tile_voxels": options.tile_voxels,  # the number used, chosen or given
        "frame": sources[0].frame.as_dict(),
        "payload": {"checkpoint": _input_identity([str(options.checkpoint)]) if options.checkpoint else None,
                    "alpha": _input_identity([str(options.alpha)]) if options.alpha else None, "bin_frames": options.bin_frames},
    }
    held = {}  # the same drive twice (one path given twice, or a copy) would count every scan twice
    for text, run, entry in zip(inputs, runs, identity["inputs"]):
        data = {str(p.resolve()) for p in (run.dataset.resolve_logs() if run.dataset.kind == "bag" else [run.dataset.resolve_path()])}
        key = tuple(sorted(e["sha256"] for e in entry if e.get("path") in data))
        if key in held:
            raise ConfigError(f"batch: inputs {held[key]} and {text} hold the same data (the same files, by content): "
                              f"each drive once, or its scans count twice")
        held[key] = text
    return inputs, sources, config, chunks, identity


def probe(sources, config: MappingConfig, max_memory: int | None = None) -> tuple[np.ndarray, tuple[str, ...], int, int]:
    """The origin and class names ``evsemmap map`` would give the map (the origin of the first
    non-empty scan), and the voxels of the first insertion and of the first two (for the memory
    estimate)."""
    source = sources[0]
    mapper = Mapper.for_dataset(source, config, workers=1, max_memory=max_memory)
    counts = []
    for i in range(len(source)):
        for scan in source.scans(i, i + 1):
            mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
        if mapper.origin_index is not None:
            counts.append(mapper.voxel_count)
        if len(counts) == 2:
            break
    if mapper.origin_index is None:
        raise ConfigError("batch: every scan of the first input is empty")
    return mapper.origin_index.copy(), mapper.class_names, counts[0], counts[-1]


def bytes_per_voxel(num_classes: int) -> int:
    """A worker's memory per voxel of its partial map: the hash table and its [K + 4] float64 rows
    (kept below half full, so ~2-4x the voxels), the host copy, the post-pass and the tile split."""
    row = (num_classes + EXTRA_COLUMNS) * 8
    return 3 * (row + 16) + 3 * row


def check_memory(options: BatchOptions, workers: int, chunk_insertions: int, first: int, first_two: int, num_classes: int,
                 *, automatic: bool = False) -> dict:
    """Refuse, before any work, a configuration whose workers cannot fit in this machine's memory.
    ``options.chunk_frames`` is the number in use; ``automatic``: it was chosen, not given."""
    new_per_insertion = max(first_two - first, first // 4)
    chunk_voxels = first + (chunk_insertions - 1) * new_per_insertion
    per_worker = WORKER_OVERHEAD_BYTES + chunk_voxels * bytes_per_voxel(num_classes)
    need = DRIVER_OVERHEAD_BYTES + workers * per_worker
    have = available_memory()
    budget = {"chunk_voxels_estimate": int(chunk_voxels), "per_worker_mb": round(per_worker / 2**20), "total_mb": round(need / 2**20),
              "available_mb": round(have / 2**20)}
    if (options.executor == "local" or (options.executor == "ray" and not options.ray_address)) and need > have:
        room = (have - DRIVER_OVERHEAD_BYTES) / workers - WORKER_OVERHEAD_BYTES
        fitting = max(0, int(np.floor((room / bytes_per_voxel(num_classes) - first) / max(new_per_insertion, 1))) + 1)
        if fitting >= 1:
            advice = f"use --chunk-frames {fitting} or fewer --workers"
        elif workers > 1 and (most := int((have - DRIVER_OVERHEAD_BYTES) // (WORKER_OVERHEAD_BYTES + first * bytes_per_voxel(num_classes)))) >= 1:
            advice = f"use fewer --workers (at most {most} fit, with --chunk-frames 1; not even chunks of one scan or bin fit {workers})"
        elif workers > 1:
            advice = "use fewer --workers (not even chunks of one scan or bin fit this many)"
        else:
            advice = "this machine lacks the memory for one worker"
        given = f"--chunk-frames {options.chunk_frames}" + (" (chosen automatically)" if automatic else "")
        raise ConfigError(f"batch: {given} with {workers} workers needs about {need / 2**30:.1f} GB "
                          f"({per_worker / 2**30:.2f} GB per worker for ~{chunk_voxels:,} voxels a chunk), but {have / 2**30:.1f} GB "
                          f"are available; {advice}")
    return budget


# Worker tasks ----------------------------------------------------------------------------------------
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


def _handoff(submitted: float):
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


def _as_task(fn, submitted: float, *args):
    """``fn(*args)`` in a pool worker, marked as a task for _worker_interrupt; ``submitted``: when the
    driver submitted it (time.time()), for the hand-off costs (_handoff)."""
    global _IN_TASK
    handoff = _handoff(submitted)
    _IN_TASK = True
    try:
        return handoff(fn(*args))
    finally:
        _IN_TASK = False


def _init_worker(context: Context, threads: int) -> None:
    global _CONTEXT
    _CONTEXT = context
    import signal

    signal.signal(signal.SIGINT, _worker_interrupt)
    try:
        import torch

        torch.set_num_threads(threads)  # workers share the cores: no worker's inference takes them all
    except ImportError:  # pragma: no cover - torch is a dependency
        pass


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _chunk_dir(store: Path, number: int) -> Path:
    return store / "work" / f"chunk_{number:06d}"


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


def map_chunk(chunk: Chunk, context: Context | None = None) -> dict:
    """Map one chunk into its partial map, written per tile; returns its counts and costs: ``seconds``,
    and ``stage_seconds`` (CHUNK_STAGES), which add up to them: "open", the setup (an empty mapper, the
    scan source's iterator); "read", getting each next scan from the source (reading and preparing it:
    files, projection, inference); "integrate", the mapper's work on the scans; "extract", the map's
    voxels out of the mapper, split by tile; "write_partial", the partials and done.json written (encoded,
    written, made durable) and the chunk's folder renamed into place."""
    context = context or _CONTEXT
    started = time.perf_counter()
    done = _chunk_dir(context.store, chunk.number)
    if (done / "done.json").is_file():  # a retried task whose first attempt finished after all
        return _read_done(context.store, chunk) | {"seconds": 0.0, "stage_seconds": {}, "peak_rss_mb": _peak_rss_mb()}
    partial = context.store / "work" / f".chunk_{chunk.number:06d}.{os.getpid()}.tmp"
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
    voxels, _ = mapper.voxels()
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
    return record | {"seconds": now - started, "stage_seconds": clock, "peak_rss_mb": _peak_rss_mb()}


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
        self.tiles_written = 0
        for path in sorted((out / "tiles").glob(f"*{map_store.TILE_SUFFIX[map_store.STORE_VERSION]}")):
            header = self._tile_header(path)
            self.folded[path.stem] = header["folded_through"]
            self.entries[path.stem] = header["entry"]

    def _tile_path(self, name: str) -> Path:
        return self.out / "tiles" / f"{name}{map_store.TILE_SUFFIX[map_store.STORE_VERSION]}"

    def _partial_path(self, number: int, name: str) -> Path:
        return _chunk_dir(self.out, number) / f"{name}{map_store.PARTIAL_SUFFIX}"

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
        record = _read_done(self.out, chunk, self.folded)
        for name in record["tiles"]:
            if self.folded.get(name, -1) >= chunk.number:
                self._partial_path(chunk.number, name).unlink(missing_ok=True)  # folded and written before the last run was killed
                continue
            index, rows = map_store.read_partial(self._partial_path(chunk.number, name), self.columns, self.tile_voxels, self.identity,
                                                 chunk.number)
            running = map_store.fold(self._running_tile(name), index, rows)
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


def _store_index(template: Mapper, tile_voxels: int, entries: dict, inputs: list, chunks: list, totals: dict, scan_ids) -> dict:
    """store.json: everything but the tiles' voxels; nothing that depends on how or when it ran.
    ``identity``: what its tiles record (map_store.store_identity); ``scan_ids``: the scans it holds
    (a merge refuses to count them twice), None when not known."""
    config = template.config
    return {
        "identity": map_store.template_identity(template, tile_voxels), "scan_ids": None if scan_ids is None else sorted(scan_ids),
        "format": map_store.STORE_FORMAT, "format_version": map_store.STORE_VERSION, "resolution_m": config.resolution_m,
        "origin_index": [int(v) for v in template.origin_index], "origin_m": template.origin.tolist(),
        "grid_offset_m": template.grid_offset_m, "frame": None if template.frame is None else template.frame.as_dict(),
        "classes": list(template.class_names), "method": config.method,
        "mapping": config.as_dict(), "tile_voxels": tile_voxels,
        "tiles": {name: entries[name] for name in sorted(entries)},
        "inputs": inputs, "chunks": chunks, "scans": int(totals["scans"]), "points": int(totals["points"]),
    }


def write_store_from_mapper(mapper: Mapper, out, tile_voxels: int, sources: list[str]) -> Path:
    """A whole map (a merge's result) written as a store."""
    out = Path(out)
    check_tile_voxels(tile_voxels, "--tile-voxels")
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: exists and is not empty; a store is written to a new folder")
    voxels, _ = mapper.voxels()
    template = map_store.template_mapper(mapper.config, mapper.class_names,
                                         mapper.origin_index if mapper.origin_index is not None else np.zeros(3, np.int64), mapper.frame)
    totals = {"scans": mapper.scans_integrated, "points": mapper.points_integrated}
    entries = {name: map_store.write_tile(out / "tiles" / f"{name}{map_store.TILE_SUFFIX[map_store.STORE_VERSION]}", template,
                                          VoxelArrays.from_rows(index, rows), tile_voxels)
               for name, (index, rows) in map_store.split_by_tile(voxels.index, voxels.rows(), tile_voxels).items()}
    map_store.write_json(out / map_store.INDEX_NAME, _store_index(template, tile_voxels, entries, [{"source": s} for s in sources], [], totals,
                                                                  mapper.scan_ids))
    return out


# Executors -----------------------------------------------------------------------------------------
class InlineExecutor:
    """The tasks one after another in this process (tests and debugging: the same task functions,
    without the process boundary)."""

    name = "inline"
    workers = 1

    def __init__(self, context: Context):
        self.context = context

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item in order; ``on_done(item, result)`` after each."""
        for item in items:
            on_done(item, fn(*item, context=self.context))

    def close(self) -> None:
        """Nothing to release."""


_MATH_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def stuck_error(timeout_s: float) -> TimeoutError:
    """The run's end when no chunk finished for ``timeout_s`` (a worker or a node stuck): the chunks mapped so far stay."""
    return TimeoutError(f"no chunk finished in {timeout_s:g} s (--chunk-timeout-s): a worker or a node is stuck; "
                        "the chunks mapped so far are kept, and a rerun resumes from them")


class LocalExecutor:
    """A process pool, one worker per core by default; a pool whose worker died is replaced and the
    unfinished tasks are run again (each at most ``retries`` more times)."""

    name = "local"

    def __init__(self, workers: int, context: Context, retries: int = 3, log=None, chunk_timeout_s: float = CHUNK_TIMEOUT_S):
        import multiprocessing

        self.workers, self.context, self.retries, self.log = workers, context, retries, log or (lambda m: None)
        self.chunk_timeout_s = chunk_timeout_s
        self._mp = multiprocessing.get_context("spawn")  # no fork of a process with Warp and threads loaded
        self._threads = max(1, (os.cpu_count() or 1) // workers)
        self._pool = None

    def _submit(self, fn, item):
        """Submit a task; a worker process started by it starts with Ctrl-C ignored (the setting passes
        through exec) until _init_worker installs its handler, so an interrupt while workers start up
        leaves no traceback of theirs, only the driver's "interrupted". It also starts with its math
        libraries' thread pools (OpenBLAS, OpenMP, MKL) at its share of the cores, which they read once
        on loading: at their default, every worker's BLAS used every core (the point transforms), and two
        workers on two cores ran their chunks slower than with one thread each. A user's own setting of
        those variables is kept."""
        import signal

        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if threading.current_thread() is threading.main_thread() else None
        saved = {name: os.environ.get(name) for name in _MATH_THREAD_VARIABLES}
        for name in _MATH_THREAD_VARIABLES:
            os.environ.setdefault(name, str(self._threads))
        try:
            return self._pool.submit(_as_task, fn, time.time(), *item)
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def _new_pool(self):
        return ProcessPoolExecutor(self.workers, mp_context=self._mp, initializer=_init_worker, initargs=(self.context, self._threads))

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item, at most two per worker in flight; ``on_done(item, result)``."""
        pending = list(items)
        attempts = {i: 0 for i in range(len(items))}
        order = {id(item): i for i, item in enumerate(items)}
        while pending:
            self._pool = self._pool or self._new_pool()
            flight = {}
            broken = False
            queue = list(pending)
            try:
                while queue or flight:
                    while queue and len(flight) < 2 * self.workers:
                        item = queue.pop(0)
                        flight[self._submit(fn, item)] = item
                    finished, _ = wait(flight, timeout=self.chunk_timeout_s, return_when=FIRST_COMPLETED)
                    if not finished:
                        self._interrupt_workers()
                        raise stuck_error(self.chunk_timeout_s)
                    for future in finished:
                        item = flight.pop(future)
                        on_done(item, future.result())
                        pending.remove(item)
            except BrokenProcessPool:
                broken = True
            except KeyboardInterrupt:  # Ctrl-C: stop the workers' tasks too (a worker that was still starting missed it)
                self._interrupt_workers()
                raise
            if broken:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                for item in pending:
                    attempts[order[id(item)]] += 1
                    if attempts[order[id(item)]] > self.retries:
                        raise RuntimeError(f"batch: a worker died {self.retries + 1} times running {item[0]}; giving up")
                self.log(f"a worker died; a new pool runs the {len(pending)} unfinished task(s) again")

    def _interrupt_workers(self) -> None:
        """Cancel what has not started and interrupt every worker: one in a task stops it (cleaning up
        its temporary files), an idle one exits (_worker_interrupt)."""
        import signal

        if self._pool is None:
            return
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        for process in processes:
            try:
                os.kill(process.pid, signal.SIGINT)
            except (ProcessLookupError, TypeError):
                pass
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = None
        # a worker that was still starting up (Ctrl-C ignored until _init_worker) would run a whole chunk:
        # a few seconds' grace, then it is stopped (what it leaves is cleared by the next run, _remove_unfinished_chunks)
        deadline = time.monotonic() + 3.0
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.terminate()

    def close(self) -> None:
        """Stop the pool's workers (tasks not started are cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


@contextlib.contextmanager
def _environment(values: dict):
    """``values`` in os.environ while the block runs; what was there before, after."""
    before = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


_RAY_CONTEXTS: dict = {}  # object id -> context, per Ray worker process


def _ray_task(fn, threads: int, context_box: list, submitted: float, *args):
    """A Ray task. The context (put once by the driver) comes boxed in a list, so Ray does not fetch
    and unpickle it for every task: each worker process fetches it once (unboxed, unpickling the
    sources for every task made short tasks several times slower, docs/performance.md). ``submitted``:
    when the driver submitted it (time.time()), for the hand-off costs (_handoff)."""
    import ray

    global _TASKS_STARTED
    key = context_box[0].hex()
    if key not in _RAY_CONTEXTS:
        _TASKS_STARTED = 0  # a cluster's worker that served an earlier run: this run's first task in it
    handoff = _handoff(submitted)  # before fetching the context: a worker's start includes it
    if key not in _RAY_CONTEXTS:
        _RAY_CONTEXTS.clear()
        _RAY_CONTEXTS[key] = ray.get(context_box[0])
        _init_worker(_RAY_CONTEXTS[key], threads)
    return handoff(fn(*args, context=_RAY_CONTEXTS[key]))


class RayExecutor:
    """The same tasks on Ray: a local instance (started and stopped here) or a cluster (``address``:
    "auto" or "ray://host:port"). Ray retries a task whose worker died."""

    name = "ray"
    chunk_timeout_s = CHUNK_TIMEOUT_S  # how long run() waits for some task to finish (__init__ sets the run's)

    def __init__(self, workers: int | None, address: str | None, log=None, connect_timeout_s: float = RAY_CONNECT_TIMEOUT_S,
                 chunk_timeout_s: float = CHUNK_TIMEOUT_S):
        """Start (or join) Ray; ``attach`` gives it the run's context. Apart, so that a run starts Ray while it
        plans (_run_batch). ``connect_timeout_s``: how long ``address`` may take to answer (check_ray_address)."""
        try:
            import ray
        except ImportError:
            raise ConfigError('--executor ray needs Ray: pip install "evsemmap_warp[ray]"') from None
        self.ray, self.log, self.chunk_timeout_s = ray, log or (lambda m: None), chunk_timeout_s
        self.started = not ray.is_initialized()
        self.own_instance = self.started and not address  # a local instance of exactly ``workers`` CPUs
        if self.started:
            env = {k: v for k, v in os.environ.items() if k in ("WARP_CACHE_PATH", "XDG_CACHE_HOME")}
            # Ray workers import numpy before any task runs, so its BLAS pool is sized by the environment
            # the worker starts with: at its share of the cores, as the pool's workers (LocalExecutor._submit;
            # Ray sets OMP_NUM_THREADS alone). A task takes one CPU of a cluster; a local instance splits this
            # machine. A user's own setting is kept.
            share = max(1, (os.cpu_count() or 1) // (workers or os.cpu_count() or 1)) if not address else 1
            env |= {name: os.environ.get(name, str(share)) for name in _MATH_THREAD_VARIABLES}
            options = {"include_dashboard": False, "logging_level": "ERROR", "log_to_driver": False}
            if address:
                check_ray_address(address, connect_timeout_s)
                try:
                    ray.init(address=address, runtime_env={"env_vars": env}, **options)
                except ConnectionError as exc:
                    # Ray authenticates by token by default, and joins by address (not "auto") only with it asked for
                    hint = "" if os.environ.get("RAY_AUTH_MODE") else (
                        "; a Ray instance that authenticates by token (Ray's default) is joined by address with RAY_AUTH_MODE=token "
                        "set here (and its token in ~/.ray/auth_token or RAY_AUTH_TOKEN), or with --ray-address auto on its own machine")
                    raise ConfigError(f"--ray-address {address}: could not join the Ray instance ({exc}){hint}") from None
            else:
                # A local instance's processes, and the workers it starts ahead of the first tasks, inherit this
                # process's environment at ray.init: set for it alone. A runtime_env made Ray start other workers for
                # the first tasks instead of using those (0.5 s more before the first chunk ran).
                with _environment(env):
                    ray.init(num_cpus=workers or os.cpu_count(), **options)
        self.workers = workers or int(ray.cluster_resources().get("CPU", 1))
        self._task = ray.remote(num_cpus=1, max_retries=3)(_ray_task)
        self.context_ref = None

    def attach(self, context: Context) -> "RayExecutor":
        """Put the run's context in Ray's object store, once for all tasks."""
        self.context_ref = self.ray.put(context)
        return self

    def run(self, fn, items: list, on_done) -> None:
        """``fn(*item)`` for every item as Ray tasks; ``on_done(item, result)``. A local instance has as many
        CPUs as workers, so two tasks per worker are in flight (the next one waits in Ray, not in this loop);
        on a running instance or a cluster, which may have more CPUs, one per worker, so that ``workers``
        bounds what the run takes of it (two per worker ran a 1-worker run on both CPUs of a 2-CPU instance).
        A finished task's successor is submitted before ``on_done`` folds its result, so that no worker waits for
        the driver's fold (with one task per worker in flight a worker idled through every fold; docs/performance.md)."""
        queue = list(items)
        flight = {}
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        most_in_flight = (2 if self.own_instance else 1) * self.workers

        def submit():
            while queue and len(flight) < most_in_flight:
                item = queue.pop(0)
                flight[self._task.remote(fn, threads, [self.context_ref], time.time(), *item)] = item

        submit()
        while flight:
            finished, _ = self.ray.wait(list(flight), num_returns=1, timeout=self.chunk_timeout_s)
            if not finished:
                for ref in flight:
                    self.ray.cancel(ref, force=True)
                raise stuck_error(self.chunk_timeout_s)
            results = [(flight.pop(ref), self.ray.get(ref)) for ref in finished]
            submit()
            for item, result in results:
                on_done(item, result)

    def close(self) -> None:
        """Shut down the Ray instance this executor started (a cluster given by address is left running); once.
        Here, not on a thread while the tiles are written: shutting Ray down while the driver may still release
        object references ends the process (tried: stopping it as the last result came in)."""
        if self.started:
            self.started = False
            self.ray.shutdown()


def check_ray_address(address: str, timeout_s: float) -> None:
    """Refuse (ConfigError, the line docs/troubleshooting.md lists) a --ray-address host:port (or ray://host:port)
    that does not accept a connection within ``timeout_s`` seconds, before ray.init, which retries such an
    address for many minutes. "auto" and addresses without a port are left to Ray."""
    target = address.removeprefix("ray://")
    host, _, port = target.rpartition(":")
    if address == "auto" or not host:
        return
    try:
        port_number = int(port)
    except ValueError:
        raise ConfigError(f"--ray-address {address}: the port {port!r} is not a number (auto, host:port or ray://host:port)") from None
    try:
        socket.create_connection((host.strip("[]"), port_number), timeout=timeout_s).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise ConfigError(f"--ray-address {address}: could not join the Ray instance (nothing accepted a connection at "
                          f"{host}:{port_number} within {timeout_s:g} s: {reason}; --ray-connect-timeout-s sets the wait)") from None


# The run ----------------------------------------------------------------------------------------------
def _read_work_json(path: Path, what: str, remedy: str):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise map_store.StoreError(f"{path}: not a readable {what} ({type(exc).__name__}: {exc}); {remedy}") from None


def _read_done(store: Path, chunk: Chunk, folded: dict[str, int] | None = None) -> dict:
    """A finished chunk's record (done.json), validated against the chunk and, given ``folded`` (tile ->
    the last chunk folded into it), against the partials beside it: each tile's is there, or folded."""
    folder = _chunk_dir(store, chunk.number)
    path = folder / "done.json"
    record = _read_work_json(path, "chunk record", f"delete {folder} and rerun to map that chunk again")
    counts = ("number", "frames", "scans", "points", "voxels")
    problem = None
    if not isinstance(record, dict) or not all(isinstance(record.get(k), int) and not isinstance(record[k], bool) and record[k] >= 0
                                               for k in counts):
        problem = f"needs whole counts >= 0 for {', '.join(counts)}"
    elif (record["number"], record["frames"]) != (chunk.number, chunk.frames) or record["scans"] > chunk.frames:
        problem = (f"says chunk {record['number']} of {record['frames']} frames with {record['scans']} scans, the plan has chunk "
                   f"{chunk.number} of {chunk.frames} frames")
    elif not isinstance(record.get("tiles"), list) or not all(isinstance(t, str) for t in record["tiles"]):
        problem = "needs the list of its tiles"
    elif not isinstance(record.get("scan_ids"), list) or not all(isinstance(i, str) for i in record["scan_ids"]):
        problem = "needs the list of its scan ids (a chunk mapped by an older version: rerun it)"
    else:
        for name in record["tiles"]:
            try:
                map_store.parse_tile_name(name)
            except map_store.StoreError as exc:
                problem = str(exc)
                break
            partial = folder / f"{name}{map_store.PARTIAL_SUFFIX}"
            if folded is not None and not partial.is_file() and folded.get(name, -1) < chunk.number:
                problem = f"lists tile {name}, whose partial {partial} is missing (and not folded into the tile)"
                break
    if problem:
        raise map_store.StoreError(f"{path}: {problem}; delete {folder} and rerun to map that chunk again")
    return record


def _check_store(out: Path, identity: dict) -> None:
    plan_path = out / "work" / "plan.json"
    if plan_path.is_file():
        earlier = _read_work_json(plan_path, "batch plan", f"delete {out / 'work'} to start over")
        if not isinstance(earlier, dict):
            raise map_store.StoreError(f"{plan_path}: not a batch plan (a JSON object); delete {out / 'work'} to start over")
        if earlier.get("store_format_version") != identity["store_format_version"]:
            raise ConfigError(f"{out}: a store of format {earlier.get('store_format_version', 1)}, written by an older evsemmap_warp; "
                              f"this version writes format {identity['store_format_version']} (it still reads the old one: info, "
                              f"export, view, layers): give a new --out to map again")
        if earlier != identity:
            differing = sorted(k for k in set(earlier) | set(identity) if earlier.get(k) != identity.get(k))
            raise ConfigError(f"{out}: holds a batch run of other inputs or settings (differing: {', '.join(differing)}); "
                              f"give a new --out, or delete {out} to start over")
    elif (out / map_store.INDEX_NAME).is_file() and _store_format(out) != map_store.STORE_VERSION:
        raise ConfigError(f"{out}: a store of format {_store_format(out)}, written by an older evsemmap_warp; this version writes "
                          f"format {map_store.STORE_VERSION} (it still reads the old one: info, export, view, layers): give a new --out "
                          f"to map again")
    elif (out / map_store.INDEX_NAME).is_file():
        raise ConfigError(f"{out}: a finished store whose partial maps were discarded (--discard-partials); delete it to map again, "
                          f"or give a new --out")
    elif out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: exists and is not a batch store; give a new --out")


def _store_format(out: Path):
    """The format version store.json states (None when it states none or cannot be read)."""
    try:
        return json.loads((out / map_store.INDEX_NAME).read_text()).get("format_version")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        return None


def _remove_unfinished_chunks(out: Path) -> None:
    """What workers killed halfway left (temporary chunk folders, temporary tile files): never counted,
    removed (the store lock says no other run is writing them)."""
    for stale in (out / "work").glob(".chunk_*"):
        shutil.rmtree(stale, ignore_errors=True)
    for stale in (out / "tiles").glob(".*.tmp"):
        stale.unlink(missing_ok=True)


@contextlib.contextmanager
def _store_lock(out: Path):
    """One batch run at a time per store: an exclusive lock on the store folder (created here, and
    removed again when the run leaves it empty). Two runs into one store used to interleave their chunks,
    plans and tiles: a store of one drive's inputs holding another's voxels, both exiting 0."""
    import fcntl

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    handle = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(f"{out}: another batch run is writing this store now; wait for it to finish, or give another --out") from None
        yield
    finally:
        os.close(handle)  # releases the lock
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def run_batch(paths: list[str], options: BatchOptions, log=None, *, on_tile=None, _fault: _FaultPlan | None = None) -> dict:
    """Plan, map chunks, fold them into tiles and write the store; returns the summary. ``on_tile(name,
    voxels)``: called in this process with each tile's voxels (VoxelArrays, global indices) every time a
    chunk is folded into it (a live view of the store filling in). ``_fault``: the tests' fault injection
    (a _FaultPlan the workers receive in their Context), never used otherwise."""
    # never over a config, nor inside a sequence folder, the alpha files or a checkpoint (the data that dataset
    # configs point at is checked once planned); before the lock, which creates the folder
    files.check_not_inside(options.out, [p for p in (*paths, options.checkpoint, options.alpha) if p is not None], "batch --out")
    check_tile_voxels(options.tile_voxels, "--tile-voxels")  # before the store folder exists: a store its readers refuse is never begun
    with _store_lock(Path(options.out)):
        return _run_batch(paths, options, log, on_tile=on_tile, _fault=_fault)


def _run_batch(paths: list[str], options: BatchOptions, log=None, *, on_tile=None, _fault: _FaultPlan | None = None) -> dict:
    log = log or (lambda m: print(m, file=sys.stderr))
    times = {}
    started = time.perf_counter()
    out = Path(options.out)
    if options.executor not in ("local", "ray", "inline"):
        raise ConfigError(f"--executor {options.executor!r}: local or ray")
    if options.executor == "ray":
        # Ray takes seconds to start its processes: the run is planned meanwhile (reading and hashing the inputs)
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="evsemmap-batch-plan") as planner:
            planning = planner.submit(plan_batch, paths, options)
            executor = RayExecutor(options.workers, options.ray_address, log, options.ray_connect_timeout_s, options.chunk_timeout_s)
            try:
                inputs, sources, config, chunks, identity = planning.result()
            except BaseException:
                executor.close()
                raise
    else:
        inputs, sources, config, chunks, identity = plan_batch(paths, options)
        executor = None
    try:
        return _map_and_write(options, log, on_tile, _fault, times, started, executor, (inputs, sources, config, chunks, identity))
    finally:
        if executor is not None:
            executor.close()  # a run that failed before its chunks (bad input): Ray is stopped all the same


def _map_and_write(options: BatchOptions, log, on_tile, _fault, times: dict, started: float, ray_executor, planned) -> dict:
    """The rest of ``_run_batch``, once the run is planned (and Ray started, for the Ray executor); ``times['plan']``
    includes Ray's start, which planning overlaps."""
    out = Path(options.out)
    inputs, sources, config, chunks, identity = planned
    files.check_not_inside(out, [e["path"] for entry in identity["inputs"] for e in entry if "path" in e], "batch --out")
    _check_store(out, identity)
    origin_index, class_names, first, first_two = probe(sources, config, options.max_memory)
    workers = options.workers or (os.cpu_count() or 1)
    insertions = max(c.stop - c.start for c in chunks)
    chunk_frames = identity["chunk_frames"]
    chunk_rule = choose_chunk_frames(options.chunk_frames, sum(c.frames for c in chunks))[1]
    budget = check_memory(dataclasses.replace(options, chunk_frames=chunk_frames), workers, insertions, first, first_two,
                          sources[0].num_classes, automatic=options.chunk_frames is None)
    times["plan"] = time.perf_counter() - started
    (out / "work").mkdir(parents=True, exist_ok=True)
    map_store.write_json(out / "work" / "plan.json", identity)
    _remove_unfinished_chunks(out)
    context = Context(out, sources, config, sources[0].num_classes, class_names, origin_index, options.tile_voxels, frame=sources[0].frame,
                      fault=_fault, max_memory=options.max_memory)
    finished = [c for c in chunks if (_chunk_dir(out, c.number) / "done.json").is_file()]
    todo = [c for c in chunks if c not in finished]
    total_frames = sum(c.frames for c in chunks)
    if finished:
        log(f"resuming: {len(finished)} of {len(chunks)} chunks are mapped already")
    if ray_executor is not None:
        executor = ray_executor.attach(context)
    elif options.executor == "inline":
        executor = InlineExecutor(context)
    else:
        executor = LocalExecutor(workers, context, log=log, chunk_timeout_s=options.chunk_timeout_s)
    folder = TileFolder(out, context, chunks, on_tile)
    try:
        from tqdm import tqdm

        stage = time.perf_counter()
        for chunk in finished:  # a resumed run folds what the killed one mapped but did not fold
            folder.chunk_finished(chunk.number)
        bar = tqdm(total=total_frames, initial=sum(c.frames for c in finished), unit="frame", desc=f"batch {executor.name} x{executor.workers}",
                   disable=not options.progress, dynamic_ncols=True)
        costs = []

        def chunk_done(item, result):
            if "handoff" in result:  # the worker's return to here: pickling, the pipe, and this driver folding an earlier chunk
                result["handoff"]["return_s"] = time.time() - result["handoff"].pop("returned_at")
            costs.append(result)
            folder.chunk_finished(item[0].number)
            bar.update(item[0].frames)

        executor.run(map_chunk, [(c,) for c in todo], chunk_done)
        bar.close()
        _remove_unfinished_chunks(out)
        times["map"] = time.perf_counter() - stage
    finally:
        executor.close()
    if folder.frontier < len(chunks):  # every chunk is mapped once executor.run returns; this names a broken invariant, not a user error
        raise RuntimeError(f"batch: chunk {folder.chunks[folder.frontier].number} was mapped but not folded")
    stage = time.perf_counter()
    folder.finish()
    times["write_tiles"] = time.perf_counter() - stage
    times["fold"] = folder.seconds
    stage = time.perf_counter()
    records, entries = folder.records, folder.entries
    totals = {"scans": sum(r["scans"] for r in records.values()), "points": sum(r["points"] for r in records.values())}
    listed = {name for r in records.values() for name in r["tiles"]}
    for old in (out / "tiles").glob("*"):
        if old.is_file() and old.stem not in listed and not old.name.startswith("."):
            old.unlink()
    entries = {name: entries[name] for name in sorted(listed)}
    inputs_entry = [{"source": str(Path(text).resolve()) if Path(text).exists() else text, "insertions": len(s), "frames": s.frames_in(0, len(s))}
                    for text, s in zip(inputs, sources)]
    chunks_entry = [dataclasses.asdict(c) | {k: records[c.number][k] for k in ("scans", "points", "voxels")} for c in chunks]
    scan_ids = set().union(*(records[c.number]["scan_ids"] for c in chunks))
    index = _store_index(context.template(), options.tile_voxels, entries, inputs_entry, chunks_entry, totals, scan_ids)
    map_store.write_json(out / map_store.INDEX_NAME, index)
    if options.discard_partials:
        shutil.rmtree(out / "work", ignore_errors=True)
    times["index"] = time.perf_counter() - stage
    times["total"] = time.perf_counter() - started
    chunk_seconds = [r["seconds"] for r in costs]
    staged = [r["stage_seconds"] for r in costs if r.get("stage_seconds")]  # not a retried task's (it did nothing)
    handoffs = [r["handoff"] for r in costs if "handoff" in r]  # the local pool's and Ray's tasks, not inline ones

    def median(values):
        return round(float(np.median(values)), 3) if values else None
    return {
        "store": str(out), "executor": executor.name, "workers": executor.workers, "inputs": len(inputs), "frames": total_frames,
        "chunks": len(chunks), "chunks_resumed": len(finished), "chunk_frames": chunk_frames, "chunk_frames_rule": chunk_rule,
        "input_points": totals["points"],
        "voxels": sum(e["voxels"] for e in entries.values()), "tiles": len(entries), "tile_writes": folder.tiles_written,
        "seconds": {k: round(v, 3) for k, v in times.items()},
        "frames_per_second": round(sum(c.frames for c in todo) / times["map"], 2) if todo and times["map"] > 0 else None,
        "chunk_seconds_median": round(float(np.median(chunk_seconds)), 3) if chunk_seconds else None,
        # where a worker's time goes (map_chunk's stages, CHUNK_STAGES): each stage's median over the chunks, and
        # all chunks' together
        "chunk_stage_seconds_median": {k: median([s[k] for s in staged]) for k in CHUNK_STAGES} if staged else None,
        "chunk_stage_seconds_total": {k: round(sum(s[k] for s in staged), 3) for k in CHUNK_STAGES} if staged else None,
        # around it (_handoff): a worker process's start (submission to its first task starting), the result's size
        # and its way back to the driver
        "chunk_handoff": {
            "worker_start_s_median": median([h["wait_s"] for h in handoffs if h["first_in_process"]]),
            "worker_start_s_max": round(max(h["wait_s"] for h in handoffs if h["first_in_process"]), 3)
            if any(h["first_in_process"] for h in handoffs) else None,
            "result_kb_median": median([h["result_bytes"] / 1024 for h in handoffs]),
            "return_s_median": median([h["return_s"] for h in handoffs]),
        } if handoffs else None,
        "peak_rss_mb": {"worker_max": round(max([r["peak_rss_mb"] for r in costs], default=0.0), 1),
                        "driver": round(_peak_rss_mb(), 1)},
        "memory_budget": budget,
    }
