"""Batch-mapping benchmark on this machine: the long synthetic drive (``evsemmap synth --preset long
--no-camera``: 5,000 LiDAR frames, 2 km) mapped by ``evsemmap map`` and by ``evsemmap batch`` with the
local process pool and with Ray, at 1 and 2 workers, in one run.

Each configuration runs as the command a user types (a fresh process, start-up included), after a
warm-up batch on the first 200 frames (kernel cache, page cache). Reported per configuration: wall
time, frames/s, input points/s, peak memory of a worker and of the driver, the reduction's cost
(summing partials and writing the tiles) and the store's size, and the speed-up over ``evsemmap map``.
From the measured per-frame mapping cost (per input point) and per-tile reduction cost, the tool
projects the wall time of a whole RELLIS-3D and of a 1,000 km fleet log on a 16-node cluster (the
model is printed with the figures). The last line printed is one JSON object.

    python tools/bench_batch.py [--frames 5000] [--method ebs] [--data DIR] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
EVSEMMAP = [sys.executable, "-m", "evsemmap_warp.apps.cli"]

# The projection's workloads and cluster (stated, not measured):
# 5 sequences; OS1-64 x 2048 with about 55 % returns; about 2.5 m/s on average, so ~3.4 km of tiles
RELLIS3D = {"frames": 13_556, "points_per_frame": 131_072 * 0.55, "drive_km": 3.4}
FLEET_KM = 1_000.0
FLEET_FRAME_SPACING_M = 0.5  # 10 Hz at 5 m/s
CLUSTER = {"nodes": 16, "cores_per_node": 16}


def run(args: list[str]) -> tuple[float, dict]:
    started = time.perf_counter()
    done = subprocess.run(EVSEMMAP + args, capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{done.stderr[-3000:]}")
    return seconds, json.loads(done.stdout)


def folder_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--method", default="ebs")
    parser.add_argument("--chunk-frames", type=int, default=100)
    parser.add_argument("--data", type=Path, help="render the long drive here (kept and reused), default a temporary folder")
    parser.add_argument("--repeats", type=int, default=1, help="runs per configuration (median reported)")
    parser.add_argument("--executors", default="local,ray")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    data = args.data or tmp / "long"
    results = {"method": args.method, "frames": args.frames, "chunk_frames": args.chunk_frames, "repeats": args.repeats, "runs": {}}
    try:
        if not (data / "synth.yaml").exists():
            started = time.perf_counter()
            subprocess.run(EVSEMMAP + ["synth", "--preset", "long", "--no-camera", "--frames", str(args.frames), "--out", str(data), "--quiet"],
                           check=True, capture_output=True, cwd=REPO)
            results["render_seconds"] = round(time.perf_counter() - started, 1)
            print(f"rendered {args.frames} frames in {results['render_seconds']} s", flush=True)
        warm = tmp / "warm"
        warm_seq = tmp / "warm_seq"
        shutil.copytree(data, warm_seq, ignore=lambda d, names: [n for n in names if n.endswith((".bin", ".label")) and n[:6].isdigit()
                                                                   and int(n[:6]) >= 200])
        run(["batch", str(warm_seq), "--method", args.method, "--out", str(warm), "--quiet"])

        def repeat(name: str, command: list[str], out: Path | None):
            times, summaries = [], []
            for _ in range(args.repeats):
                if out is not None:
                    shutil.rmtree(out, ignore_errors=True)
                seconds, summary = run(command)
                times.append(seconds)
                summaries.append(summary)
            return statistics.median(times), summaries[-1]

        map_seconds, map_report = repeat("map", ["map", str(data), "--method", args.method, "--out", str(tmp / "map.npz"), "--quiet"], None)
        points = map_report["input_points"]
        results["runs"]["map"] = {"wall_s": round(map_seconds, 2), "frames_per_s": round(args.frames / map_seconds, 1),
                                  "input_points_per_s": round(points / map_seconds), "voxels": map_report["voxels"]}
        print(f"evsemmap map: {map_seconds:.1f} s, {args.frames / map_seconds:.1f} frames/s, {points / map_seconds / 1e3:.0f} k points/s", flush=True)
        for executor in args.executors.split(","):
            for workers in (1, 2):
                out = tmp / f"store_{executor}_{workers}"
                seconds, summary = repeat(f"{executor}{workers}", ["batch", str(data), "--method", args.method, "--out", str(out), "--executor",
                                                                    executor, "--workers", str(workers), "--chunk-frames", str(args.chunk_frames), "--quiet"], out)
                row = {
                    "wall_s": round(seconds, 2), "frames_per_s": round(args.frames / seconds, 1), "input_points_per_s": round(points / seconds),
                    "speedup_vs_map": round(map_seconds / seconds, 2), "map_stage_s": summary["seconds"]["map"],
                    "reduce_s": summary["seconds"]["reduce"], "index_s": summary["seconds"]["index"], "store_mb": round(folder_size(out / "tiles") / 1e6, 1),
                    "partials_mb": round(folder_size(out / "work") / 1e6, 1), "tiles": summary["tiles"], "voxels": summary["voxels"],
                    "worker_peak_mb": summary["peak_rss_mb"]["worker_max"], "driver_peak_mb": summary["peak_rss_mb"]["driver"],
                    "chunk_s_median": summary["chunk_seconds_median"], "tile_s_median": summary["tile_seconds_median"],
                    "memory_budget_per_worker_mb": summary["memory_budget"]["per_worker_mb"],
                }
                results["runs"][f"{executor}x{workers}"] = row
                print(f"batch {executor} x{workers}: {seconds:.1f} s ({row['speedup_vs_map']:.2f}x map), {row['frames_per_s']} frames/s, "
                      f"reduce {row['reduce_s']:.1f} s, store {row['store_mb']} MB in {row['tiles']} tiles, worker peak {row['worker_peak_mb']:.0f} MB, "
                      f"driver {row['driver_peak_mb']:.0f} MB", flush=True)
        # Projection: mapping cost per input point (one worker, median chunk) and reduction cost per tile,
        # spread over every core of the cluster; tiles grow with the distance driven.
        one = results["runs"].get("localx1") or next(iter(v for k, v in results["runs"].items() if k != "map"))
        chunk_points = points / max(1, -(-args.frames // args.chunk_frames))
        per_point = one["chunk_s_median"] / chunk_points
        drive_km = float(yaml.safe_load((data / "synth.yaml").read_text())["summary"]["drive_m"]) / 1000
        tiles_per_km = one["tiles"] / drive_km
        cores = CLUSTER["nodes"] * CLUSTER["cores_per_node"]

        def projected(frames: float, points_per_frame: float, km: float) -> dict:
            mapping = frames * points_per_frame * per_point / cores
            reduction = km * tiles_per_km * one["tile_s_median"] / cores
            return {"frames": int(frames), "mapping_s": round(mapping, 1), "reduction_s": round(reduction, 1), "total_s": round(mapping + reduction, 1)}

        fleet_frames = FLEET_KM * 1000 / FLEET_FRAME_SPACING_M
        results["projection"] = {
            "model": (f"wall = frames x points/frame x {per_point * 1e9:.1f} ns/point (one worker, measured) / {cores} cores "
                      f"+ km x {tiles_per_km:.1f} tiles/km x {one['tile_s_median']:.3f} s/tile / {cores} cores; "
                      f"{CLUSTER['nodes']} nodes x {CLUSTER['cores_per_node']} cores, perfect scaling, storage and network not limiting"),
            "rellis3d": projected(RELLIS3D["frames"], RELLIS3D["points_per_frame"], RELLIS3D["drive_km"]),
            "fleet_1000km": projected(fleet_frames, RELLIS3D["points_per_frame"], FLEET_KM),
        }
        print(f"projection ({results['projection']['model']}): RELLIS-3D {results['projection']['rellis3d']['total_s']} s, "
              f"1,000 km fleet log {results['projection']['fleet_1000km']['total_s']} s")
        print(json.dumps(results))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
