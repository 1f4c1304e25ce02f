"""A batch run's plan: its options, its chunks (consecutive insertions of the inputs), the origin and classes
``evsemmap map`` would give the map (probe), and the memory check that refuses, before any work, workers that
cannot fit."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import files
from ...config import ConfigError, MappingConfig, flat_items, is_robot_log, load_config, read_yaml_file
from ...core import map_store
from ...core.mapper import Mapper
from ...core.voxel_map import EXTRA_COLUMNS
from ...frames import check_same_frame
from ...limits import CHUNK_TIMEOUT_S, RAY_CONNECT_TIMEOUT_S, available_memory, check_chunk_frames
from ..scan_sources import open_scan_source

WORKER_OVERHEAD_BYTES = 450 * 2**20  # a worker process with numpy, Warp and its kernels loaded (measured: ~0.4 GB)
DRIVER_OVERHEAD_BYTES = 450 * 2**20
# workers one fold lane keeps up with: 6 to 7 (the driver's thread in docs/bench/bench_batch-20261207T183954Z.json, on
# one node and on two), 6 for a lane on a node of its own (docs/bench/bench_fold-20261207T182947Z.json)
WORKERS_PER_FOLD_LANE = 6
FOLD_CACHE_TILES = 12  # tiles the fold lanes keep while the drive passes through them (reduction.TileFolder)
FOLD_TILE_BYTES = 16 * 2**20  # one of them in memory: up to ~15 MB (a 256-voxel tile of a LiDAR map)
# The automatic chunk size (--chunk-frames not given): the inputs' frames cut into at least AUTO_CHUNKS
# chunks (two per worker up to 8 workers, so short inputs use every core), at most MAX_AUTO_CHUNK_FRAMES
# frames each. It depends on the inputs only, never on the worker count: stores stay byte-identical.
AUTO_CHUNKS = 16
MAX_AUTO_CHUNK_FRAMES = 100


@dataclass(frozen=True)
class BatchOptions:
    """What ``evsemmap batch`` was asked for (its flags); ``run_batch`` takes the inputs beside it."""

    method: str
    out: Path
    executor: str = "local"  # local | ray (| inline: in this process, for tests and debugging)
    workers: int | None = None  # default: one per core (local), the cluster's CPUs (ray)
    fold_workers: int | None = None  # --fold-workers: tiles folded at once (with ray: lanes on the nodes); None: fold_width's
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
    if config.convbki.lengths_file:  # the mapping names the learned lengths' file (convbki, ebs-learned): a resume needs the same lengths
        identity["learned_lengths"] = _input_identity([config.convbki.lengths_file])
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


def fold_width(requested: int | None, workers: int = 1) -> int:
    """The fold lanes' width (--fold-workers): as asked; else one lane per WORKERS_PER_FOLD_LANE ``workers``, so one
    (a thread of the driver) for up to that many: a lane on the nodes takes cores from the mapping, and on a
    machine without cores to spare it slowed a 2-worker run (docs/performance.md, "The fold in lanes")."""
    if requested is not None:
        if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ConfigError(f"batch: fold_workers = {requested!r}: give a whole number of fold lanes, at least 1 (or None: the default)")
        return requested
    return max(1, math.ceil(workers / WORKERS_PER_FOLD_LANE))


def folds_on_nodes(options: BatchOptions, workers: int) -> bool:
    """Whether the fold lanes are Ray actors on the nodes (ray_fold.RayFoldLanes), not threads of the driver: with Ray,
    when asked for (--fold-workers) or when ``workers`` need more than one lane."""
    return options.executor == "ray" and (options.fold_workers is not None or fold_width(None, workers) > 1)


def driver_bytes(options: BatchOptions, workers: int) -> int:
    """The driver's memory with its fold: the threads of the driver hold the tiles the drive is passing and as many
    waiting to be written; lanes on the nodes are worker processes (of this machine, with a local Ray instance)."""
    if folds_on_nodes(options, workers):
        return DRIVER_OVERHEAD_BYTES + fold_width(options.fold_workers, workers) * WORKER_OVERHEAD_BYTES
    return DRIVER_OVERHEAD_BYTES + 2 * FOLD_CACHE_TILES * FOLD_TILE_BYTES


def bytes_per_voxel(num_classes: int) -> int:
    """A worker's memory per voxel of its partial map: the hash table and its [K + 5] float64 rows
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
    driver = driver_bytes(options, workers)
    need = driver + workers * per_worker
    have = available_memory()
    budget = {"chunk_voxels_estimate": int(chunk_voxels), "per_worker_mb": round(per_worker / 2**20), "total_mb": round(need / 2**20),
              "available_mb": round(have / 2**20)}
    if (options.executor == "local" or (options.executor == "ray" and not options.ray_address)) and need > have:
        room = (have - driver) / workers - WORKER_OVERHEAD_BYTES
        fitting = max(0, int(np.floor((room / bytes_per_voxel(num_classes) - first) / max(new_per_insertion, 1))) + 1)
        if fitting >= 1:
            advice = f"use --chunk-frames {fitting} or fewer --workers"
        elif workers > 1 and (most := int((have - driver) // (WORKER_OVERHEAD_BYTES + first * bytes_per_voxel(num_classes)))) >= 1:
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
