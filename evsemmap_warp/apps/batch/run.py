"""``run_batch``: a batch run from its inputs to the finished store (plan, map the chunks with an executor,
fold them into tiles, write store.json), and its summary."""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ... import files
from ...config import ConfigError
from ...core import map_store
from ...limits import check_tile_voxels
from .executors import InlineExecutor, LocalExecutor
from .planning import BatchOptions, check_memory, choose_chunk_frames, fold_width, folds_on_nodes, plan_batch, probe
from .ray_executor import RayExecutor
from .ray_fold import RayFoldLanes
from .reduction import ThreadFoldLanes, TileFolder
from .store import check_store, chunk_dir, remove_unfinished_chunks, store_index, store_lock
from .worker import CHUNK_STAGES, Context, FaultPlan, map_chunk, peak_rss_mb


def run_batch(paths: list[str], options: BatchOptions, log=None, *, on_tile=None, fault: FaultPlan | None = None) -> dict:
    """Plan, map chunks, fold them into tiles and write the store; returns the summary. ``on_tile(name,
    voxels)``: called in this process with each tile's voxels (VoxelArrays, global indices) every time a
    chunk is folded into it (a live view of the store filling in). ``fault``: the tests' fault injection
    (a FaultPlan the workers receive in their Context), never used otherwise."""
    # never over a config, nor inside a sequence folder, the alpha files or a checkpoint (the data that dataset
    # configs point at is checked once planned); before the lock, which creates the folder
    files.check_not_inside(options.out, [p for p in (*paths, options.checkpoint, options.alpha) if p is not None], "batch --out")
    check_tile_voxels(options.tile_voxels, "--tile-voxels")  # before the store folder exists: a store its readers refuse is never begun
    with store_lock(Path(options.out)):
        return _run_batch(paths, options, log, on_tile=on_tile, fault=fault)


def _run_batch(paths: list[str], options: BatchOptions, log=None, *, on_tile=None, fault: FaultPlan | None = None) -> dict:
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
        return _map_and_write(options, log, on_tile, fault, times, started, executor, (inputs, sources, config, chunks, identity))
    finally:
        if executor is not None:
            executor.close()  # a run that failed before its chunks (bad input): Ray is stopped all the same


def _map_and_write(options: BatchOptions, log, on_tile, fault, times: dict, started: float, ray_executor, planned) -> dict:
    """The rest of ``_run_batch``, once the run is planned (and Ray started, for the Ray executor); ``times['plan']``
    includes Ray's start, which planning overlaps."""
    out = Path(options.out)
    inputs, sources, config, chunks, identity = planned
    context, budget, workers = _prepare_store(options, fault, identity, sources, config, chunks)
    times["plan"] = time.perf_counter() - started
    finished = [c for c in chunks if (chunk_dir(out, c.number) / "done.json").is_file()]
    todo = [c for c in chunks if c not in finished]
    if finished:
        log(f"resuming: {len(finished)} of {len(chunks)} chunks are mapped already")
    if ray_executor is not None:
        executor = ray_executor.attach(context, identity)
    elif options.executor == "inline":
        executor = InlineExecutor(context)
    else:
        executor = LocalExecutor(workers, context, log=log, chunk_timeout_s=options.chunk_timeout_s)
    width = fold_width(options.fold_workers, executor.workers)
    on_nodes = ray_executor is not None and folds_on_nodes(options, executor.workers)
    lanes = RayFoldLanes(ray_executor, width, context) if on_nodes else ThreadFoldLanes(width, context)
    folder = TileFolder(out, context, chunks, lanes, on_tile)
    try:
        stage = time.perf_counter()
        costs = _map_chunks(executor, folder, finished, todo, options.progress, close=ray_executor is None)
        times["map"] = time.perf_counter() - stage
        stage = time.perf_counter()
        folder.finish()
        times["write_tiles"] = time.perf_counter() - stage
    finally:
        folder.close()
    times["fold"] = folder.seconds
    stage = time.perf_counter()
    entries, totals = _write_index(out, options, folder, context, inputs, sources)
    times["index"] = time.perf_counter() - stage
    times["total"] = time.perf_counter() - started
    return {
        "store": str(out), "executor": executor.name, "workers": executor.workers, "inputs": len(inputs), "frames": sum(c.frames for c in chunks),
        "chunks": len(chunks), "chunks_resumed": len(finished), "chunk_frames": identity["chunk_frames"],
        "chunk_frames_rule": choose_chunk_frames(options.chunk_frames, sum(c.frames for c in chunks))[1],
        "input_points": totals["points"],
        "voxels": sum(e["voxels"] for e in entries.values()), "tiles": len(entries), "tile_writes": folder.tiles_written,
        "voxels_folded": folder.voxels_folded,  # the driver's own time per folded voxel: seconds.fold / voxels_folded
        # the lanes that fold (reduction.py): how many, and their time folding and encoding tiles, all lanes together (their
        # rate per lane: voxels_folded / lane_seconds)
        # how often one was started again, lost with its node (ray_fold.RayFoldLanes), and how long the driver waited for
        # their answers, of seconds.fold (the driver's own share of the folding is the rest)
        "fold_lanes": {"width": width, "lane_seconds": round(folder.lane_seconds, 3), "restarts": lanes.restarts,
                       "driver_wait_s": round(folder.waited, 3)},
        "seconds": {k: round(v, 3) for k, v in times.items()},
        "frames_per_second": round(sum(c.frames for c in todo) / times["map"], 2) if todo and times["map"] > 0 else None,
        **_chunk_costs(costs),
        "memory_budget": budget,
    } | ({"cluster": ray_executor.summary()} if ray_executor is not None else {})  # its nodes, and how the inputs reached them


def _prepare_store(options: BatchOptions, fault, identity: dict, sources: list, config, chunks: list) -> tuple[Context, dict, int]:
    """Check the store folder against the plan, probe the inputs, refuse what cannot fit in memory, and write
    ``work/plan.json``; returns the workers' context, the memory budget and the worker count."""
    out = Path(options.out)
    files.check_not_inside(out, [e["path"] for entry in identity["inputs"] for e in entry if "path" in e], "batch --out")
    check_store(out, identity)
    origin_index, class_names, first, first_two = probe(sources, config, options.max_memory)
    workers = options.workers or (os.cpu_count() or 1)
    insertions = max(c.stop - c.start for c in chunks)
    budget = check_memory(dataclasses.replace(options, chunk_frames=identity["chunk_frames"]), workers, insertions, first, first_two,
                          sources[0].num_classes, automatic=options.chunk_frames is None)
    (out / "work").mkdir(parents=True, exist_ok=True)
    map_store.write_json(out / "work" / "plan.json", identity)
    remove_unfinished_chunks(out)
    context = Context(out, sources, config, sources[0].num_classes, class_names, origin_index, options.tile_voxels, frame=sources[0].frame,
                      fault=fault, max_memory=options.max_memory)
    return context, budget, workers


def _map_chunks(executor, folder: TileFolder, finished: list, todo: list, progress: bool, close: bool) -> list[dict]:
    """Fold what a killed run mapped but did not fold, then map the chunks ``todo`` with ``executor``, folding
    each as it finishes; returns the tasks' records (their costs). ``close``: the executor is closed after (not
    Ray, whose lanes may fold the tiles until the end: _run_batch stops it)."""
    from tqdm import tqdm

    try:
        for chunk in finished:
            folder.chunk_finished(chunk.number)
        bar = tqdm(total=sum(c.frames for c in folder.chunks), initial=sum(c.frames for c in finished), unit="frame",
                   desc=f"batch {executor.name} x{executor.workers}", disable=not progress, dynamic_ncols=True)
        costs = []

        def chunk_done(item, result):
            if "handoff" in result:  # the worker's return to here: pickling, the pipe, and this driver folding an earlier chunk
                result["handoff"]["return_s"] = time.time() - result["handoff"].pop("returned_at")
            costs.append(result)
            folder.chunk_finished(item[0].number)
            bar.update(item[0].frames)

        executor.run(map_chunk, [(c,) for c in todo], chunk_done)
        bar.close()
        remove_unfinished_chunks(folder.out)
    finally:
        if close:
            executor.close()
    if folder.frontier < len(folder.chunks):  # every chunk is mapped once executor.run returns; this names a broken invariant
        raise RuntimeError(f"batch: chunk {folder.chunks[folder.frontier].number} was mapped but not folded")
    return costs


def _write_index(out: Path, options: BatchOptions, folder: TileFolder, context: Context, inputs: list, sources: list) -> tuple[dict, dict]:
    """store.json, once every tile is written (and tiles no chunk lists removed); returns its tile entries and totals."""
    records, chunks = folder.records, folder.chunks
    totals = {"scans": sum(r["scans"] for r in records.values()), "points": sum(r["points"] for r in records.values())}
    listed = {name for r in records.values() for name in r["tiles"]}
    for old in (out / "tiles").glob("*"):
        if old.is_file() and old.stem not in listed and not old.name.startswith("."):
            old.unlink()
    entries = {name: folder.entries[name] for name in sorted(listed)}
    inputs_entry = [{"source": str(Path(text).resolve()) if Path(text).exists() else text, "insertions": len(s), "frames": s.frames_in(0, len(s))}
                    for text, s in zip(inputs, sources)]
    chunks_entry = [dataclasses.asdict(c) | {k: records[c.number][k] for k in ("scans", "points", "voxels")} for c in chunks]
    scan_ids = set().union(*(records[c.number]["scan_ids"] for c in chunks))
    index = store_index(context.template(), options.tile_voxels, entries, inputs_entry, chunks_entry, totals, scan_ids)
    map_store.write_json(out / map_store.INDEX_NAME, index)
    if options.discard_partials:
        shutil.rmtree(out / "work", ignore_errors=True)
    return entries, totals


def _chunk_costs(costs: list[dict]) -> dict:
    """The summary's account of the tasks' costs (their records, as map_chunk and the executors return them)."""
    chunk_seconds = [r["seconds"] for r in costs]
    staged = [r["stage_seconds"] for r in costs if r.get("stage_seconds")]  # not a retried task's (it did nothing)
    handoffs = [r["handoff"] for r in costs if "handoff" in r]  # the local pool's and Ray's tasks, not inline ones

    def median(values):
        return round(float(np.median(values)), 3) if values else None
    return {
        "chunk_seconds_median": round(float(np.median(chunk_seconds)), 3) if chunk_seconds else None,
        # where a worker's time goes (map_chunk's stages, CHUNK_STAGES): each stage's median over the chunks, and
        # all chunks' together
        "chunk_stage_seconds_median": {k: median([s[k] for s in staged]) for k in CHUNK_STAGES} if staged else None,
        "chunk_stage_seconds_total": {k: round(sum(s[k] for s in staged), 3) for k in CHUNK_STAGES} if staged else None,
        # around it (handoff_recorder): a worker process's start (submission to its first task starting), the result's size
        # and its way back to the driver
        "chunk_handoff": {
            "worker_start_s_median": median([h["wait_s"] for h in handoffs if h["first_in_process"]]),
            "worker_start_s_max": round(max(h["wait_s"] for h in handoffs if h["first_in_process"]), 3)
            if any(h["first_in_process"] for h in handoffs) else None,
            "result_kb_median": median([h["result_bytes"] / 1024 for h in handoffs]),
            "return_s_median": median([h["return_s"] for h in handoffs]),
        } if handoffs else None,
        "peak_rss_mb": {"worker_max": round(max([r["peak_rss_mb"] for r in costs], default=0.0), 1),
                        "driver": round(peak_rss_mb(), 1)},
    }
