"""The batch fold's rate with 1, 2, ... fold lanes, and the worker count it keeps up with.

Maps the first ``--frames`` of the long drive once with the local pool (``--workers``), keeping a copy of every
chunk's partials and done record as the driver receives them; then folds copies of those chunks into tiles
again with each width of fold lanes, threads of the driver (``local``, the pool's lanes) and Ray actors on a local
instance (``ray``, processes of their own, as on the nodes of a cluster), timing the fold alone: voxels of partials
folded per second of wall time, the driver's seconds (handing out partials, writing tiles, and of those its waits for
the lanes' answers), and the lanes' seconds. Every width must write the same tiles,
byte for byte (checked). A worker's voxel rate (its chunks' partial voxels over their mapping seconds, from the
mapping run's summary) gives the worker count each width keeps up with: fold rate / one worker's rate.
The results go to a run record (docs/bench/bench_fold-<UTC>.json, tools/bench_record.py); the last line
printed is its path.

    python tools/bench_fold.py --data DIR [--frames 2000] [--widths 1,2] [--lanes local,ray] [--repeats 3]
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from bench_record import write_record

from evsemmap_warp.apps import batch
from evsemmap_warp.apps.batch import BatchOptions, reduction, run_batch
from evsemmap_warp.apps.batch.ray_executor import RayExecutor
from evsemmap_warp.apps.batch.ray_fold import RayFoldLanes
from evsemmap_warp.apps.batch.store import chunk_dir


def map_keeping_partials(data: Path, out: Path, kept: Path, workers: int) -> dict:
    """A batch run whose driver copies every finished chunk's folder to ``kept`` before folding it; its summary."""
    original = reduction.TileFolder.chunk_finished

    def keep(self, number):
        shutil.copytree(chunk_dir(self.out, number), chunk_dir(kept, number))
        original(self, number)

    reduction.TileFolder.chunk_finished = keep
    try:
        return run_batch([str(data)], BatchOptions(method="ebs", out=out, executor="local", workers=workers, progress=False),
                         log=lambda m: None)
    finally:
        reduction.TileFolder.chunk_finished = original


def fold_once(kept: Path, out: Path, planned, lanes_kind: str, width: int, ray) -> dict:
    """Fold the kept chunks into a fresh store folder ``out`` with ``width`` lanes; the timings and the tiles' hash."""
    inputs, sources, config, chunks, identity, origin_index, class_names = planned
    shutil.rmtree(out, ignore_errors=True)
    (out / "tiles").mkdir(parents=True)
    shutil.copytree(kept / "work", out / "work")
    context = batch.Context(out, sources, config, sources[0].num_classes, class_names, origin_index, 256, frame=sources[0].frame)
    lanes = reduction.ThreadFoldLanes(width, context) if lanes_kind == "local" else RayFoldLanes(ray.attach(context, identity), width, context)
    started = time.perf_counter()
    folder = reduction.TileFolder(out, context, chunks, lanes)
    for chunk in chunks:
        folder.chunk_finished(chunk.number)
    handing = folder.seconds
    folder.finish()
    wall = time.perf_counter() - started
    folder.close()
    tiles = hashlib.sha256(b"".join(p.read_bytes() for p in sorted((out / "tiles").iterdir()))).hexdigest()
    shutil.rmtree(out)
    return {"wall_s": round(wall, 3), "voxels_folded": folder.voxels_folded, "driver_handing_s": round(handing, 3),
            "driver_s": round(folder.seconds, 3), "driver_wait_s": round(folder.waited, 3), "lane_s": round(folder.lane_seconds, 3), "tiles_sha256": tiles}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="the long drive (evsemmap synth --world long --no-camera --frames N)")
    parser.add_argument("--frames", type=int, default=2000, help="frames of --data (stated in the record)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--widths", default="1,2")
    parser.add_argument("--lanes", default="local,ray", help="local (threads of the driver), ray (Ray actors on a local instance)")
    parser.add_argument("--repeats", type=int, default=3, help="folds per width (median reported)")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_fold_"))
    results = {"frames": args.frames, "workers": args.workers, "repeats": args.repeats, "lanes": {}}
    try:
        summary = map_keeping_partials(args.data, tmp / "store", tmp / "kept", args.workers)
        worker_s = sum(summary["chunk_stage_seconds_total"].values())
        per_worker = summary["voxels_folded"] / worker_s
        results["mapping"] = {"voxels_folded": summary["voxels_folded"], "worker_s": round(worker_s, 3), "worker_voxels_per_s": round(per_worker),
                              "driver_fold_s": summary["seconds"]["fold"], "fold_lanes": summary["fold_lanes"]}
        options = BatchOptions(method="ebs", out=tmp / "store")
        inputs, sources, config, chunks, identity = batch.plan_batch([str(args.data)], options)
        origin_index, class_names, *_ = batch.probe(sources, config)
        planned = (inputs, sources, config, chunks, identity, origin_index, class_names)
        hashes = set()
        for kind in args.lanes.split(","):
            ray = RayExecutor(max(int(w) for w in args.widths.split(",")), None) if kind == "ray" else None
            try:
                for width in (int(w) for w in args.widths.split(",")):
                    runs = [fold_once(tmp / "kept", tmp / "fold", planned, kind, width, ray) for _ in range(args.repeats)]
                    hashes |= {r.pop("tiles_sha256") for r in runs}
                    wall = statistics.median(r["wall_s"] for r in runs)
                    rate = runs[0]["voxels_folded"] / wall
                    results["lanes"][f"{kind}x{width}"] = {
                        "runs": runs, "wall_s_median": wall, "voxels_per_s": round(rate),
                        "driver_s_per_mvoxel": round(statistics.median(r["driver_handing_s"] for r in runs) / runs[0]["voxels_folded"] * 1e6, 4),
                        "keeps_up_with_workers": math.floor(rate / per_worker)}
                    print(f"{kind} x{width}: {results['lanes'][f'{kind}x{width}']}", flush=True)
            finally:
                if ray is not None:
                    ray.close()
        if len(hashes) != 1:
            raise SystemExit(f"the widths wrote different tiles: {sorted(hashes)}")
        results["same_tiles_every_width"] = True
        print(write_record("bench_fold", results))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
