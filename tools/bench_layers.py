"""Terrain-layer benchmark on this machine: ``evsemmap layers`` on the ``long`` drive's store and on the
bench map, against the time mapping them took (docs/terrain.md, "Speed and memory").

* the store: the ``long`` synthetic drive (``evsemmap synth --world long --no-camera``: 5,000 frames,
  2 km) mapped by ``evsemmap batch`` (local pool, 2 workers, EBS) into a store of 51.2 m tiles, both
  made here in every run (the rendered drive is kept in ``--data`` for reruns, the mapping is timed
  anew: the share below sets two figures of one run side by side); then ``evsemmap layers STORE`` as a
  user types it (a fresh process, start-up included) with every output, and without the previews and
  the bag (the layers and the GeoTIFF and npz tiles), each the median of --repeats;
* the bench map: ../shared/data/bench/rellis_like_30scans.npz (30 scans, 1.8 M points) mapped with
  EBS in this process, then ``compute_layers`` on it (median of --repeats, after a warm-up that
  compiles the kernels) and ``evsemmap layers`` on its map file.

Reported per row: wall time, input points per second (the points that made the map, over the layers'
time: comparable with mapping's rate), voxels and cells per second, the child's peak memory, and the
layers' time as a share of the mapping time. The results go to a run record
(docs/bench/bench_layers-<UTC>.json, tools/bench_record.py); the last line printed is its path.

    python tools/bench_layers.py [--data DIR] [--frames 5000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_record import write_record

REPO = Path(__file__).resolve().parents[1]
# Runs the CLI in a child and prints its peak resident memory (MB) as the last stderr line.
CHILD = ("import resource, sys; from evsemmap_warp.apps.cli import main; code = main(sys.argv[1:]); "
         "print('peak_mb', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, file=sys.stderr); sys.exit(code)")


def run_cli(args: list[str]) -> tuple[float, dict, float]:
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"evsemmap {' '.join(args)} failed:\n{done.stderr[-3000:]}")
    peak = float(done.stderr.strip().splitlines()[-1].split()[-1])
    return seconds, json.loads(done.stdout), peak


def store_rows(data: Path, frames: int, repeats: int) -> tuple[list[dict], dict]:
    """The store rows, all from this run: the drive rendered once (kept in ``data`` for reruns), mapped by
    ``evsemmap batch`` now (into a fresh store: a mapping time of another run would be another machine's
    state), then each layers command ``repeats`` times, its median wall time against that mapping time."""
    import shutil

    drive, store = data / "long", data / "long_store"
    made = {}
    if not (drive / "poses.txt").exists():
        seconds, _, _ = run_cli(["synth", "--world", "long", "--no-camera", "--frames", str(frames), "--out", str(drive), "--quiet"])
        made["render_s"] = round(seconds, 1)
    shutil.rmtree(store, ignore_errors=True)
    batch_s, _, batch_peak = run_cli(["batch", str(drive), "--method", "ebs", "--out", str(store), "--workers", "2", "--quiet"])
    index = json.loads((store / "store.json").read_text())
    points, voxels, tiles = index["points"], sum(t["voxels"] for t in index["tiles"].values()), len(index["tiles"])
    rows = []
    for name, extra in (("store, all outputs", []), ("store, GeoTIFF + npz tiles", ["--no-previews", "--no-bag"])):
        walls, peaks = [], []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory(dir=data) as out:
                seconds, summary, peak = run_cli(["layers", str(store), "--out", str(Path(out) / "layers"), "--quiet", *extra])
            walls.append(round(seconds, 3))
            peaks.append(peak)
        wall = statistics.median(walls)
        rows.append({"row": name, "wall_s": round(wall, 2), "all_wall_s": walls, "layer_s": summary["layer_seconds"], "input_points": points,
                     "voxels": voxels, "tiles": tiles, "cells": summary["cells"], "known_cells": summary["known_cells"],
                     "input_points_per_s": round(points / wall), "voxels_per_s": round(voxels / wall), "cells_per_s": round(summary["cells"] / wall),
                     "peak_mb": round(max(peaks)), "mapping_s": round(batch_s, 1), "share_of_mapping": round(wall / batch_s, 4)})
    return rows, made | {"batch_s": round(batch_s, 1), "batch_peak_mb": round(batch_peak)}


def bench_map_rows(data: Path, repeats: int) -> list[dict]:
    from evsemmap_warp.classes import class_set
    from evsemmap_warp.config import load_config
    from evsemmap_warp.core.mapper import Mapper
    from evsemmap_warp.terrain import compute_layers

    from evsemmap_warp.data.datasets import open_dataset

    workload = REPO.parent / "shared" / "data" / "bench" / "rellis_like_30scans.npz"
    if not workload.exists():
        print(f"bench_layers: {workload} is absent; the bench-map rows are skipped", file=sys.stderr)
        return []
    # the workload as tools/bench_integrate.py reads it: the RELLIS-3D preset, EBS, the scans in memory
    run = load_config([REPO / "configs/presets/rellis3d.yaml", REPO / "configs/datasets/bench_rellis_like.yaml"], method="ebs")
    dataset = open_dataset(run.dataset)
    scans = list(dataset)
    names = dataset.class_names or class_set().names
    warm = Mapper(run.mapping, dataset.num_classes, class_names=names)  # kernel compile outside the timing
    warm.integrate(scans[0].points, scans[0].payload, payload_type=scans[0].payload_type, sensor_origin=scans[0].sensor_origin)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=names)
    started = time.perf_counter()
    mapper.integrate_many(scans)
    mapping_s = time.perf_counter() - started
    points = sum(len(s.points) for s in scans)
    compute_layers(mapper)  # warm-up: kernel compile, the map's read-out cached
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        layers = compute_layers(mapper)
        times.append(time.perf_counter() - started)
    seconds = statistics.median(times)
    cells = layers.grid.width * layers.grid.height
    rows = [{"row": "bench map, compute_layers", "wall_s": round(seconds, 3), "input_points": points, "voxels": mapper.voxel_count, "cells": cells,
             "input_points_per_s": round(points / seconds), "voxels_per_s": round(mapper.voxel_count / seconds), "cells_per_s": round(cells / seconds),
             "mapping_s": round(mapping_s, 2), "share_of_mapping": round(seconds / mapping_s, 4)}]
    with tempfile.TemporaryDirectory(dir=data) as folder:
        path = Path(folder) / "bench_map.npz"
        mapper.save(path)
        wall, summary, peak = run_cli(["layers", str(path), "--out", str(Path(folder) / "layers"), "--quiet"])
    rows.append({"row": "bench map, evsemmap layers (all outputs)", "wall_s": round(wall, 2), "layer_s": summary["layer_seconds"], "input_points": points,
                 "voxels": mapper.voxel_count, "cells": cells, "input_points_per_s": round(points / wall), "voxels_per_s": round(mapper.voxel_count / wall),
                 "cells_per_s": round(cells / wall), "peak_mb": round(peak), "mapping_s": round(mapping_s, 2), "share_of_mapping": round(wall / mapping_s, 4)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "evsemmap_bench_layers",
                        help="the long drive is rendered here once and reused; its store is made anew in each run")
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--skip-store", action="store_true", help="the bench map only")
    args = parser.parse_args()
    args.data.mkdir(parents=True, exist_ok=True)
    rows = bench_map_rows(args.data, args.repeats)
    made = {}
    if not args.skip_store:
        store, made = store_rows(args.data, args.frames, args.repeats)
        rows += store
    print("| row | wall | input points/s | voxels/s | cells/s | peak | mapping | share of mapping |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        peak = f"{r['peak_mb']} MB" if "peak_mb" in r else "-"
        print(f"| {r['row']} | {r['wall_s']} s | {r['input_points_per_s']:,} | {r['voxels_per_s']:,} | {r['cells_per_s']:,} | {peak} | "
              f"{r['mapping_s']} s | {r['share_of_mapping'] * 100:.1f} % |")
    print(write_record("bench_layers", {"rows": rows, **made}))


if __name__ == "__main__":
    main()
