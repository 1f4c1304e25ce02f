"""Batch-mapping benchmark on this machine: the long synthetic drive (``evsemmap synth --world long
--no-camera``: 5,000 LiDAR frames, 2 km) mapped by ``evsemmap map`` and by ``evsemmap batch`` with the
local process pool and with Ray, at 1 and 2 workers, in one run. Ray is measured twice: the local instance a
run starts and stops itself (``--executor ray``), and a running Ray instance the runs join (``--ray-address``,
as on a cluster: the tool starts one with ``ray start --head --block`` for these rows, runs one unrecorded
warm-up batch in it, and stops it after them). ``ray-2node``: a real two-node Ray cluster on the loopback
(tools/ray_cluster.py: the head, and a second node in a private mount namespace that sees neither the drive nor
the stores, so the driver reads and sends the scans), mapped by 2 workers, one per node; its store is checked
byte for byte against the local pool's (its row says so), and its row has its own ``fold`` (the fold's rates
and the worker count it limits). It needs root (mount namespaces): elsewhere it is skipped, saying why.

Each configuration runs as the command a user types (a fresh process, start-up included), after a
warm-up batch on the first 200 frames (kernel cache, page cache). Reported per configuration: wall
time, frames/s, input points/s, peak memory of a worker and of the driver, the streaming reduction's
cost (the driver's share of folding partials into tiles while the workers map), the store's size (bytes per
voxel) and the peak disk use during the run (sampled), the speed-up over ``evsemmap map``, and where a
worker's time goes (each stage's median over the chunks: open, read, integrate, extract, write_partial; a worker
process's start, the result's size and its way back to the driver). From
the measured per-point mapping cost and per-tile fold cost, the tool projects the wall time of a whole
RELLIS-3D and of a 1,000 km fleet log on a 16-node cluster (the model is printed with the figures). The
fold's rates (voxels of partials folded into tiles per second: the driver's share, one fold lane's, the busier
of the two at the run's lane count) and the worker counts from which the fold limits the long drive are the
record's ``fold`` (from the 1-worker pool run; ``fold_bottleneck``).
The results go to a run record (docs/bench/bench_batch-<UTC>.json, tools/bench_record.py); the last
line printed is its path.

    python tools/bench_batch.py [--frames 2000] [--method ebs] [--data DIR] [--repeats 1] [--executors local,ray,ray-cluster,ray-2node]
    python tools/bench_batch.py --frames 2000 --repeats 3 --executors local   # the pool against `evsemmap map`, and the fold
    python tools/bench_batch.py --frames 2000 --repeats 3 --executors local,ray-2node   # two nodes beside the pool
    python tools/bench_batch.py --markdown docs/bench/bench_batch-<UTC>.json   # a record's table, for the docs
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

from bench_record import write_record

REPO = Path(__file__).resolve().parents[1]
EVSEMMAP = [sys.executable, "-m", "evsemmap_warp.apps.cli"]

# The projection's workloads and cluster (stated, not measured):
# 5 sequences; OS1-64 x 2048 with about 55 % returns; about 2.5 m/s on average, so ~3.4 km of tiles
RELLIS3D = {"frames": 13_556, "points_per_frame": 131_072 * 0.55, "drive_km": 3.4}
FLEET_KM = 1_000.0
FLEET_FRAME_SPACING_M = 0.5  # 10 Hz at 5 m/s
CLUSTER = {"nodes": 16, "cores_per_node": 16}
# the `long` synthetic drive's frames (evsemmap synth --world long), of which --frames renders the first
LONG_DRIVE_FRAMES = int(yaml.safe_load((REPO / "configs" / "synthetic" / "long.yaml").read_text())["trajectory"]["frames"])
RAY_CLUSTER_ENV = {"RAY_AUTH_MODE": "token"}
EXECUTORS = ("local", "ray", "ray-cluster", "ray-2node")
# each two-node cluster node's object store: the scans the driver sends (a chunk of the long drive's is about
# 100 MB, one in flight per worker) and the chunks' results; beyond it Ray spills to disk
TWO_NODE_OBJECT_STORE_BYTES = 1 << 30
# the two-node runs: the fold in one thread of the driver (the default), and in two lanes, one actor on each node
TWO_NODE_RUNS = {"ray-2node": [], "ray-2node-lanes": ["--fold-workers", "2"]}
FOLD_TARGET_WORKERS = 32  # the worker count the fold must keep up with (issue 49)


def folder_size(path: Path) -> int:
    total = 0
    for folder, _, names in os.walk(path):  # os.walk skips what vanishes while it looks, rglob raises
        for name in names:
            try:
                total += os.stat(os.path.join(folder, name)).st_size
            except OSError:  # renamed or deleted while we looked (a temporary file, a folded partial)
                pass
    return total


@contextlib.contextmanager
def running_ray(cores: int, folder: Path):
    """A Ray instance of ``cores`` CPUs started for the rows that join one (``ray start --head --block``,
    in its own temporary folder), its address while the block runs; stopped after, alone (``ray stop`` would
    stop every Ray instance of this user). It authenticates by token (Ray's default), so a run joining it by
    address needs RAY_AUTH_MODE=token (RAY_CLUSTER_ENV), as a user's would."""
    import socket

    with socket.socket() as probe:  # a free port for its GCS
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    ray_cli = Path(sys.executable).with_name("ray")
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / "head.log"
    with open(log, "w") as log_file:
        head = subprocess.Popen([str(ray_cli), "start", "--head", "--block", "--node-ip-address", "127.0.0.1", "--port", str(port),
                                 "--num-cpus", str(cores), "--include-dashboard", "false", "--disable-usage-stats", "--temp-dir", str(folder)],
                                stdout=log_file, stderr=subprocess.STDOUT, cwd=REPO, env=os.environ | RAY_CLUSTER_ENV)
    address = f"127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while "Ray runtime started" not in log.read_text():  # what ray start prints once a driver can join
            if head.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"ray start --head did not come up at {address}:\n{log.read_text()[-2000:]}")
            time.sleep(0.2)
        yield address
    finally:
        head.terminate()  # --block: the head stops its instance's processes on SIGTERM
        try:
            head.wait(30)
        except subprocess.TimeoutExpired:
            head.kill()


def run(args: list[str], watch: Path | None = None, env: dict | None = None) -> tuple[float, dict, int]:
    """Wall time, the JSON summary and, with ``watch``, the largest size the folder reached (sampled
    every 0.25 s in a thread of this process: it costs the run a little CPU, the same for every run)."""
    peak = [0]
    stop = threading.Event()

    def sample():
        while not stop.wait(0.25):
            if watch is not None and watch.exists():
                peak[0] = max(peak[0], folder_size(watch))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    started = time.perf_counter()
    done = subprocess.run(EVSEMMAP + args, capture_output=True, text=True, cwd=REPO, env=os.environ | (env or {}))
    seconds = time.perf_counter() - started
    stop.set()
    sampler.join()
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{done.stderr[-3000:]}")
    if watch is not None:
        peak[0] = max(peak[0], folder_size(watch))
    return seconds, json.loads(done.stdout), peak[0]


def markdown(record_path: Path) -> str:
    """The docs' table of a run record (docs/performance.md shows it as printed here)."""
    record = json.loads(Path(record_path).read_text())
    results = record["results"]
    runs = results["runs"]
    names = {"map": "`evsemmap map` (2 threads)", "localx1": "`batch`, local, 1 worker", "localx2": "`batch`, local, 2 workers",
             "rayx1": "`batch`, Ray, 1 worker", "rayx2": "`batch`, Ray, 2 workers",
             "ray-clusterx1": "`batch`, running Ray, 1 worker", "ray-clusterx2": "`batch`, running Ray, 2 workers",
             "ray-2nodex2": "`batch`, Ray, two nodes, 1 worker each (scans sent by the driver)",
             "ray-2node-lanesx2": "the same, folding in 2 lanes, one on each node (`--fold-workers 2`)"}
    lines = [f"<!-- record: docs/bench/{Path(record_path).name} -->",
             "| run | wall | frames/s | input points/s | vs `evsemmap map` | behind local | driver's folding | store | peak disk | worker peak "
             "| driver peak |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, name in names.items():
        if key not in runs:
            continue
        r = runs[key]
        local = runs.get(f"localx{key[-1]}")
        behind = f"{100 * (r['wall_s'] / local['wall_s'] - 1):+.1f} %" if local and not key.startswith(("local", "map")) else "-"
        if key == "map":
            lines.append(f"| {name} | {r['wall_s']} s | {r['frames_per_s']} | {r['input_points_per_s'] / 1e3:.0f} k | (itself) | - | - | - | - | - | - |")
            continue
        lines.append(f"| {name} | {r['wall_s']} s | {r['frames_per_s']} | {r['input_points_per_s'] / 1e3:.0f} k | {r['speedup_vs_map']}x | {behind} | "
                     f"{r['fold_s']} s | {r['store_mb']} MB ({r['store_bytes_per_voxel']} B/voxel) | {r['peak_disk_mb']} MB | "
                     f"{r['worker_peak_mb']:.0f} MB | {r['driver_peak_mb']:.0f} MB |")
    staged = {key: runs[key] for key in names if key != "map" and runs.get(key, {}).get("chunk_stage_s_median")}
    if staged:  # records before the stages were timed have none
        stages = list(next(iter(staged.values()))["chunk_stage_s_median"])
        lines += ["", "Where a worker's time goes (each stage's median over the chunks, s; worker start: a worker process's first task, "
                  "submission to start):", "",
                  "| run | chunk | " + " | ".join(stages) + " | worker start | result | return to driver |",
                  "|---|---|" + "---|" * len(stages) + "---|---|---|"]
        for key, r in staged.items():
            handoff = r.get("chunk_handoff") or {}
            cells = [f"{r['chunk_stage_s_median'].get(stage)}" for stage in stages]
            lines.append(f"| {names[key]} | {r['chunk_s_median']} | " + " | ".join(cells)
                         + f" | {handoff.get('worker_start_s_median', '-')} | {handoff.get('result_kb_median', '-')} kB | "
                         f"{handoff.get('return_s_median', '-')} |")
    folds = {key: runs[key]["fold"] for key in names if "fold" in runs.get(key, {})}
    if folds:  # the two-node runs' fold (fold_bottleneck, fold_lanes_needed)
        lines += ["", f"The fold on two nodes (voxels of partials per second; workers kept up with; at {FOLD_TARGET_WORKERS} workers):", "",
                  "| run | lanes | driver's share | one lane | one worker | bottleneck at this width | one lane keeps up with "
                  f"| the driver limits from | {FOLD_TARGET_WORKERS} workers |", "|---|---|---|---|---|---|---|---|---|"]
        for key, f in folds.items():
            target = f.get("at_target", {}).get("verdict", "-")
            lines.append(f"| {names[key]} | {f['lanes']['width']} | {f['driver_voxels_per_s']:,} | {f['lane_voxels_per_s']:,} | "
                         f"{f['worker_voxels_per_s']:,} | {f['bottleneck_workers']} workers | {f['workers_per_lane']} | "
                         f"{f['driver_limit_workers']} | {target} |")
    return "\n".join(lines)


def breakdown(row: dict) -> str:
    """A batch run's worker time in one line: the median chunk time, each stage's median and the hand-off costs."""
    stages = row.get("chunk_stage_s_median") or {}
    handoff = row.get("chunk_handoff") or {}
    return (f"  median chunk {row['chunk_s_median']} s: " + ", ".join(f"{k} {v} s" for k, v in stages.items())
            + f"; worker start {handoff.get('worker_start_s_median')} s, result {handoff.get('result_kb_median')} kB, "
              f"return to driver {handoff.get('return_s_median')} s")


def describe(row: dict) -> str:
    """A batch row in one line: its wall time against `evsemmap map` and the pool's, the fold, the store, the memory."""
    return (f"{row['wall_s']:.1f} s ({row['speedup_vs_map']:.2f}x map"
            + (f", {row['behind_local_pct']} % behind local" if "behind_local_pct" in row else "")
            + f"), {row['frames_per_s']} frames/s, fold {row['fold_s']:.1f} s, store {row['store_mb']} MB "
            f"({row['store_bytes_per_voxel']} B/voxel) in {row['tiles']} tiles, peak disk {row['peak_disk_mb']} MB, "
            f"worker peak {row['worker_peak_mb']:.0f} MB, driver {row['driver_peak_mb']:.0f} MB")


def models(results: dict) -> str:
    """The record's fold rate and bottleneck, projection and scaling model, as printed."""
    fold, projection, scaling = results["fold"], results["projection"], results["scaling_model"]
    return (f"fold: {fold['voxels_per_s']:,} voxels/s over {fold['lanes']['width']} lane(s), the driver's share "
            f"{fold['driver_voxels_per_s']:,}; it limits the long drive ({LONG_DRIVE_FRAMES} frames) from {fold['bottleneck_workers']} "
            f"workers on, one lane keeps up with {fold['workers_per_lane']} ({fold['model']})\n"
            f"projection ({projection['model']}): RELLIS-3D {projection['rellis3d']['total_s']} s, 1,000 km fleet log "
            f"{projection['fleet_1000km']['total_s']} s ({projection['fleet_1000km']['limited_by']})\n"
            f"scaling model ({scaling['model']}): {scaling['predicted_wall_s']}")


def batch_row(summary: dict, seconds: float, peak_disk: int, out: Path, points: int, frames: int, map_seconds: float, all_walls: list) -> dict:
    """A batch configuration's row of the record: its wall time (the median over the repeats), the run's own
    stages and costs from its summary (the last repeat's), the store's size and the peak disk use."""
    store_bytes = folder_size(out / "tiles")
    return {
        "wall_s": round(seconds, 2), "all_wall_s": all_walls, "frames_per_s": round(frames / seconds, 1),
        "input_points_per_s": round(points / seconds), "speedup_vs_map": round(map_seconds / seconds, 2),
        # the run's own stages (the last repeat's): planning (Ray's start overlaps it), mapping, writing the tiles
        "plan_s": summary["seconds"]["plan"], "map_stage_s": summary["seconds"]["map"],
        "write_tiles_s": summary["seconds"]["write_tiles"], "run_total_s": summary["seconds"]["total"],
        "fold_s": summary["seconds"]["fold"], "index_s": summary["seconds"]["index"], "store_mb": round(store_bytes / 1e6, 1),
        "store_bytes_per_voxel": round(store_bytes / max(summary["voxels"], 1), 1), "peak_disk_mb": round(peak_disk / 1e6, 1),
        "work_mb_after": round(folder_size(out / "work") / 1e6, 2), "tiles": summary["tiles"], "voxels": summary["voxels"],
        "chunks": summary["chunks"], "chunk_frames": summary["chunk_frames"], "voxels_folded": summary.get("voxels_folded"),
        "fold_lanes": summary.get("fold_lanes"),
        "worker_peak_mb": summary["peak_rss_mb"]["worker_max"], "driver_peak_mb": summary["peak_rss_mb"]["driver"],
        "chunk_s_median": summary["chunk_seconds_median"],
        "chunk_stage_s_median": summary.get("chunk_stage_seconds_median"),
        "chunk_stage_s_total": summary.get("chunk_stage_seconds_total"),
        "chunk_handoff": summary.get("chunk_handoff"),
        "memory_budget_per_worker_mb": summary["memory_budget"]["per_worker_mb"],
    }


def projections(one: dict, points: int, drive_km: float) -> tuple[dict, dict]:
    """From one batch row (the 1-worker pool's): the projection of a whole RELLIS-3D and a 1,000 km fleet log
    on a cluster, and the model of more workers on one machine."""
    # Projection: mapping cost per input point (one worker, median chunk) and fold cost per tile,
    # spread over every core of the cluster; tiles grow with the distance driven.
    chunk_points = points / max(1, one["chunks"])
    fold_per_tile = one["fold_s"] / max(1, one["tiles"])
    per_point = one["chunk_s_median"] / chunk_points
    tiles_per_km = one["tiles"] / drive_km
    cores = CLUSTER["nodes"] * CLUSTER["cores_per_node"]

    # The fold runs in the driver, one tile after another, beside the workers: it does not spread
    # over the cluster's cores, so the model takes the larger of the two (they overlap).
    def projected(frames: float, points_per_frame: float, km: float) -> dict:
        mapping = frames * points_per_frame * per_point / cores
        folding = km * tiles_per_km * fold_per_tile
        return {"frames": int(frames), "mapping_s": round(mapping, 1), "folding_s": round(folding, 1),
                "total_s": round(max(mapping, folding), 1), "limited_by": "mapping" if mapping >= folding else "the driver's fold"}

    fleet_frames = FLEET_KM * 1000 / FLEET_FRAME_SPACING_M
    projection = {
        "model": (f"wall = max(frames x points/frame x {per_point * 1e9:.1f} ns/point (one worker, measured) / {cores} cores, "
                  f"km x {tiles_per_km:.1f} tiles/km x {fold_per_tile:.3f} s of folding/tile in the one driver); "
                  f"{CLUSTER['nodes']} nodes x {CLUSTER['cores_per_node']} cores, perfect scaling of the workers, start-up, "
                  f"storage and network not counted"),
        "rellis3d": projected(RELLIS3D["frames"], RELLIS3D["points_per_frame"], RELLIS3D["drive_km"]),
        "fleet_1000km": projected(fleet_frames, RELLIS3D["points_per_frame"], FLEET_KM),
    }
    # Workers on one machine beyond this one's cores: predicted from the measured 1-worker chunk time,
    # not measured (this machine has os.cpu_count() cores).
    start_s = max(0.0, one["wall_s"] - one["chunks"] * one["chunk_s_median"])
    scaling = {
        "measured_up_to_workers": os.cpu_count(),
        "model": f"wall(w) = {start_s:.1f} s (start-up and tail, measured at 1 worker) + max({one['chunks']} chunks x "
                 f"{one['chunk_s_median']:.2f} s / w, {one['fold_s']:.1f} s of folding)",
        "predicted_wall_s": {w: round(start_s + max(one["chunks"] * one["chunk_s_median"] / w, one["fold_s"]), 1) for w in (1, 2, 4, 8, 16)},
    }
    return projection, scaling


def fold_bottleneck(row: dict, frames: int) -> dict:
    """The fold's rates (voxels of partials folded into tiles per second, from a batch row's summary) and the
    worker count from which it limits the long drive. The driver hands partials to the fold lanes and writes
    the tiles they encode (its own share: ``fold_s`` less its waits for the lanes); the lanes fold (``lane_seconds`` over ``width`` lanes
    side by side). Each worker hands over the voxels of its chunks at its own rate (voxels folded / the
    chunks' mapping seconds, all stages), so the fold keeps up while workers x that rate stays under the rate
    of the busier of the driver's share and one lane's share of the folding. Both rates are per voxel, so the
    count holds for any length of the drive; the long drive's figures are the run's scaled to its frames."""
    worker_s = sum((row.get("chunk_stage_s_total") or {}).values())
    folded = row.get("voxels_folded") or 0
    lanes = row.get("fold_lanes") or {"width": 1, "lane_seconds": 0.0}
    # the driver's own share: its fold time less its waits for the lanes' answers (recorded since the lanes are actors)
    driver_s = row["fold_s"] - lanes.get("driver_wait_s", 0.0)
    busiest_s = max(driver_s, lanes["lane_seconds"] / lanes["width"])

    def rate(seconds: float):
        return round(folded / seconds) if seconds else None

    scale = LONG_DRIVE_FRAMES / frames
    return {
        "voxels_folded": folded, "fold_s": row["fold_s"], "driver_s": round(driver_s, 3), "lanes": lanes, "driver_voxels_per_s": rate(driver_s),
        "lane_voxels_per_s": rate(lanes["lane_seconds"]), "voxels_per_s": rate(busiest_s), "worker_voxels_per_s": rate(worker_s),
        "bottleneck_workers": math.floor(worker_s / busiest_s) if busiest_s else None,  # = fold rate / one worker's rate
        "workers_per_lane": math.floor(worker_s / lanes["lane_seconds"]) if lanes["lane_seconds"] else None,
        "driver_limit_workers": math.floor(worker_s / driver_s) if driver_s > 0 else None,
        "long_drive": {"frames": LONG_DRIVE_FRAMES, "fold_s": round(busiest_s * scale, 1), "worker_s": round(worker_s * scale, 1)},
        "model": ("bottleneck workers = floor(the chunks' mapping seconds / max(the driver's own fold seconds, lane seconds / lanes)) "
                  "at this width; workers per lane = floor(mapping seconds / lane seconds), how many workers one more lane "
                  "keeps up with; driver limit = floor(mapping seconds / the driver's own fold seconds (less its waits for the lanes)), the "
                  "count no width lifts"),
    }


def store_differences(a: Path, b: Path) -> list[str]:
    """The files (relative paths) in which stores ``a`` and ``b`` differ: in one only, or other bytes."""
    def read(store):
        return {str(p.relative_to(store)): p for p in sorted(store.rglob("*")) if p.is_file()}

    files_a, files_b = read(a), read(b)
    both = sorted(set(files_a) & set(files_b))
    return sorted(set(files_a) ^ set(files_b)) + [name for name in both if files_a[name].read_bytes() != files_b[name].read_bytes()]


def two_node_rows(results: dict, data: Path, tmp: Path, warm_seq: Path, batch_args: list[str], repeat, walls: dict, local_out: Path) -> None:
    """The two-node cluster's row (``ray-2nodex2``) into ``results``: a TwoNodeCluster whose second node sees neither
    ``data`` nor ``tmp`` (the stores), one unrecorded warm-up batch, then the drive by 2 workers; its store checked
    against the local pool's at ``local_out`` (mapped here, unrecorded, when the run has no local rows). Skipped with
    the reason where this machine allows no mount namespace."""
    from ray_cluster import TwoNodeCluster, mount_namespaces_refused

    refused = mount_namespaces_refused(tmp)
    if refused:
        results.setdefault("skipped", {})["ray-2node"] = refused
        print(f"batch ray-2node: skipped: {refused}", flush=True)
        return
    if not (local_out / "store.json").is_file():
        run(["batch", str(data), *batch_args, "--out", str(local_out), "--executor", "local", "--workers", "2", "--quiet"])
    hidden = [tmp] + ([] if data.resolve().is_relative_to(tmp.resolve()) else [data])
    cluster = TwoNodeCluster(hidden, object_store_bytes=TWO_NODE_OBJECT_STORE_BYTES)
    try:
        joining = ["--executor", "ray", "--ray-address", cluster.address]
        warm = run(["batch", str(warm_seq), *batch_args, "--out", str(tmp / "warm_2node"), *joining, "--quiet"], None, cluster.env)[0]
        results["ray_2node_warmup_wall_s"] = round(warm, 3)
        for name, lanes in TWO_NODE_RUNS.items():
            out = tmp / f"store_{name}"
            seconds, summary, peak_disk = repeat(name, ["batch", str(data), *batch_args, "--out", str(out), *joining, "--workers", "2",
                                                        *lanes, "--quiet"], out, cluster.env)
            two_node_row(results, name, local_out, out, summary, seconds, peak_disk, walls)
    finally:
        cluster.close()


def two_node_row(results: dict, name: str, local_out: Path, out: Path, summary: dict, seconds: float, peak_disk: int, walls: dict) -> None:
    """One two-node run's row (``name``x2) into ``results``, its store checked against the local pool's, with its
    ``fold``: the rates, and how many lanes keep up with FOLD_TARGET_WORKERS workers (fold_lanes_needed)."""
    differing = store_differences(local_out, out)
    if differing:
        raise SystemExit(f"the two-node store {out} differs from the local pool's {local_out}: {', '.join(differing[:5])}")
    row = batch_row(summary, seconds, peak_disk, out, results["input_points"], results["frames"], results["runs"]["map"]["wall_s"],
                    walls[name])
    fold = fold_bottleneck(row, results["frames"])
    row |= {"cluster": summary["cluster"], "same_store_as_local": True, "fold": fold | fold_lanes_needed(fold)}
    local = results["runs"].get("localx2")
    if local:
        row["behind_local_pct"] = round(100 * (seconds / local["wall_s"] - 1), 1)
    results["runs"][f"{name}x2"] = row
    fold = row["fold"]
    print(f"batch {name} x2: {describe(row)}\n{breakdown(row)}\n  inputs {summary['cluster']['inputs']}, chunks per node "
          f"{list(summary['cluster']['chunks_per_node'].values())}, the store the local pool's byte for byte; fold "
          f"{fold['voxels_per_s']:,} voxels/s over {fold['lanes']['width']} lane(s) (the driver's share {fold['driver_voxels_per_s']:,}), "
          f"one worker {fold['worker_voxels_per_s']:,}: the fold limits from {fold['bottleneck_workers']} workers on; "
          f"{FOLD_TARGET_WORKERS} workers: {fold['at_target']['verdict']}", flush=True)


def fold_lanes_needed(fold: dict, workers: int = FOLD_TARGET_WORKERS) -> dict:
    """How many lanes of this run's rate keep up with ``workers`` workers, and whether the driver's own share then
    limits (it does not spread over lanes): lanes are processes of their own (Ray actors on the nodes), so each
    more lane adds one lane's rate, as long as the nodes have a core for it."""
    per_lane, driver = fold["workers_per_lane"], fold["driver_limit_workers"]
    if not per_lane:  # a lane slower than one worker, or no lane time recorded
        return {"at_target": {"workers": workers, "lanes": None, "driver_limits": None, "verdict": "no lane rate to count from"}}
    lanes = math.ceil(workers / per_lane)
    if driver is not None and driver < workers:
        verdict = f"the driver's own share limits from {driver} workers, whatever the lanes"
    else:
        verdict = f"{lanes} lane(s) keep up (one lane: {per_lane} workers), and the driver's own share only from {driver}"
    return {"at_target": {"workers": workers, "lanes": lanes, "driver_limits": driver is not None and driver < workers, "verdict": verdict}}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", type=Path, metavar="RECORD", help="print the docs' table of a run record and exit")
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--method", default="ebs")
    parser.add_argument("--chunk-frames", type=int, help="default: batch's automatic choice")
    parser.add_argument("--data", type=Path, help="render the long drive here (kept and reused), default a temporary folder")
    parser.add_argument("--repeats", type=int, default=1, help="runs per configuration (median reported)")
    parser.add_argument("--executors", default="local,ray,ray-cluster",
                        help="local (the process pool), ray (a local Ray instance per run), ray-cluster (runs joining a running Ray "
                             "instance), ray-2node (a two-node cluster on the loopback whose second node sees no files; needs root)")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    if args.markdown:
        print(markdown(args.markdown))
        return
    executors = args.executors.split(",")
    for executor in executors:
        if executor not in EXECUTORS:
            raise SystemExit(f"--executors: {executor!r} is not one of {', '.join(EXECUTORS)}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    data = args.data or tmp / "long"
    results = {"method": args.method, "frames": args.frames, "chunk_frames": args.chunk_frames, "repeats": args.repeats, "runs": {}}
    try:
        if not (data / "synth.yaml").exists():
            started = time.perf_counter()
            subprocess.run(EVSEMMAP + ["synth", "--world", "long", "--no-camera", "--frames", str(args.frames), "--out", str(data), "--quiet"],
                           check=True, capture_output=True, cwd=REPO)
            results["render_seconds"] = round(time.perf_counter() - started, 1)
            print(f"rendered {args.frames} frames in {results['render_seconds']} s", flush=True)
        warm = tmp / "warm"
        warm_seq = tmp / "warm_seq"
        shutil.copytree(data, warm_seq, ignore=lambda d, names: [n for n in names if n.endswith((".bin", ".label")) and n[:6].isdigit()
                                                                   and int(n[:6]) >= 200])
        run(["batch", str(warm_seq), "--method", args.method, "--out", str(warm), "--quiet"])

        def repeat(name: str, command: list[str], out: Path | None, env: dict | None = None):
            times, summaries, peaks = [], [], []
            for _ in range(args.repeats):
                if out is not None:
                    shutil.rmtree(out, ignore_errors=True)
                seconds, summary, peak = run(command, out, env)
                times.append(seconds)
                summaries.append(summary)
                peaks.append(peak)
            walls[name] = [round(t, 3) for t in times]  # every repeat's wall time, for the record
            return statistics.median(times), summaries[-1], max(peaks)

        walls = {}
        map_seconds, map_report, _ = repeat("map", ["map", str(data), "--method", args.method, "--out", str(tmp / "map.npz"), "--quiet"], None)
        points = results["input_points"] = map_report["input_points"]
        results["runs"]["map"] = {"wall_s": round(map_seconds, 2), "all_wall_s": walls["map"], "frames_per_s": round(args.frames / map_seconds, 1),
                                  "input_points_per_s": round(points / map_seconds), "voxels": map_report["voxels"]}
        print(f"evsemmap map: {map_seconds:.1f} s, {args.frames / map_seconds:.1f} frames/s, {points / map_seconds / 1e3:.0f} k points/s", flush=True)
        chunking = ["--chunk-frames", str(args.chunk_frames)] if args.chunk_frames else []
        with contextlib.ExitStack() as cluster:
            for executor in executors:
                if executor == "ray-2node":
                    two_node_rows(results, data, tmp, warm_seq, ["--method", args.method, *chunking], repeat, walls,
                                  tmp / "store_local_2")
                    continue
                joining, env = [], None
                if executor == "ray-cluster":
                    address = cluster.enter_context(running_ray(os.cpu_count() or 1, tmp / "ray"))
                    joining, env = ["--ray-address", address], RAY_CLUSTER_ENV
                    # the instance's first job sets up its runtime_env agent (seconds): a warm-up, as a cluster's user has
                    warm_seconds = run(["batch", str(warm_seq), "--method", args.method, "--out", str(tmp / "warm_cluster"),
                                        "--executor", "ray", *joining, "--quiet"], None, env)[0]
                    results["ray_cluster_warmup_wall_s"] = round(warm_seconds, 3)
                for workers in (1, 2):
                    out = tmp / f"store_{executor}_{workers}"
                    seconds, summary, peak_disk = repeat(f"{executor}{workers}", [
                        "batch", str(data), "--method", args.method, "--out", str(out), "--executor", "local" if executor == "local" else "ray",
                        *joining, "--workers", str(workers), *chunking, "--quiet"], out, env)
                    row = batch_row(summary, seconds, peak_disk, out, points, args.frames, map_seconds, walls[f"{executor}{workers}"])
                    local = results["runs"].get(f"localx{workers}")
                    if executor != "local" and local:
                        row["behind_local_pct"] = round(100 * (seconds / local["wall_s"] - 1), 1)
                    results["runs"][f"{executor}x{workers}"] = row
                    print(f"batch {executor} x{workers}: {describe(row)}\n{breakdown(row)}", flush=True)
        one = results["runs"].get("localx1") or next(iter(v for k, v in results["runs"].items() if k != "map"))
        drive_km = float(yaml.safe_load((data / "synth.yaml").read_text())["summary"]["drive_m"]) / 1000
        results["projection"], results["scaling_model"] = projections(one, points, drive_km)
        results["fold"] = fold_bottleneck(one, args.frames)
        print(models(results))
        print(write_record("bench_batch", results))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
