"""Synthetic-world benchmark on this CPU.

1. Time to generate a preset's whole sequence (default: ``default``, 90 frames, 64 x 1024 LiDAR,
   640 x 400 camera) into a temporary folder, split into world building and per-frame work.
2. Ray-casting throughput of the Warp kernel (LiDAR scans of that world, rays per second), against
   the brute-force numpy twin on a sample of the same rays in the same run (the ratio is the point;
   the twin is not meant to be fast).

The figures go to a run record (docs/bench/bench_synth-<UTC>.json, tools/bench_record.py); the last line
printed is its path, the line before it the figures as one JSON object.

    python tools/bench_synth.py [--world default] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_record import write_record  # noqa: E402

from evsemmap_warp.reference.raycast import cast_rays as numpy_cast_rays  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.scene import generate_world, road_trajectory  # noqa: E402
from evsemmap_warp.synthetic.sensors import RayCaster, lidar_directions  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="default")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    preset = load_preset(args.world)

    with tempfile.TemporaryDirectory() as tmp:
        generate_sequence(load_preset("tiny", trajectory__frames=1), Path(tmp) / "warmup", progress=False, device=args.device)
        start = time.perf_counter()
        summary = generate_sequence(preset, Path(tmp) / "seq", device=args.device)
        total = time.perf_counter() - start
        size_mb = sum(f.stat().st_size for f in (Path(tmp) / "seq").rglob("*") if f.is_file()) / 1e6

    world = generate_world(preset.world, preset.seed)
    poses = road_trajectory(world, preset.trajectory)
    caster = RayCaster(world.vertices, world.faces, device=args.device)
    local = lidar_directions(preset.lidar)
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        for pose in poses[:10]:
            caster.cast(pose[:3, 3], local @ pose[:3, :3].T, preset.lidar.max_range_m)
        times.append(time.perf_counter() - start)
    warp_rate = 10 * len(local) / float(np.median(times))
    sample = np.random.default_rng(0).choice(len(local), 200, replace=False)
    start = time.perf_counter()
    numpy_cast_rays(world.vertices, world.faces, np.broadcast_to(poses[0][:3, 3], (200, 3)), local[sample] @ poses[0][:3, :3].T, preset.lidar.max_range_m)
    numpy_rate = 200 / (time.perf_counter() - start)
    result = {
        "preset": preset.name, "frames": summary["frames"], "triangles": summary["triangles"],
        "generate_seconds": round(total, 2), "world_seconds": summary["world_seconds"],
        "seconds_per_frame": round((total - summary["world_seconds"]) / summary["frames"], 3), "output_mb": round(size_mb, 1),
        "lidar_rays_per_second_warp": round(warp_rate), "lidar_rays_per_second_numpy_twin": round(numpy_rate),
        "speedup_vs_numpy_twin": round(warp_rate / numpy_rate, 1), "device": caster.device,
    }
    print(json.dumps(result))
    print(write_record("bench_synth", result | {"repeats": args.repeats, "world": args.world}))


if __name__ == "__main__":
    main()
