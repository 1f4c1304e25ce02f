"""The S-BKI toy example in the sbki compatibility mode, beside the original C++'s published counts.

Maps the 12 toy scans with S-CSM and S-BKI exactly as ganlumomo/BKISemanticMapping does (VoxelGrid,
free-space rays, block support) and prints the cell states next to those of the original C++
(docs/compatibility.md §1.5).

    python examples/01_sbki_toy_conformance.py [--device cpu]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evsemmap_warp import Mapper, load_config, open_dataset

REPO = Path(__file__).resolve().parents[1]
CPP = {"s-csm": {"UNKNOWN": 41329, "FREE": 15813, "OCCUPIED": 6988}, "s-bki": {"UNKNOWN": 0, "FREE": 163872, "OCCUPIED": 52064}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    for method, golden in CPP.items():
        run = load_config([REPO / "configs/datasets/sbki_toy.yaml"], method=method)
        dataset = open_dataset(run.dataset)
        mapper = Mapper.for_dataset(dataset, run.mapping, device=args.device)  # its classes, in its world frame
        for scan in dataset:
            mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
        counts = mapper.state_counts()
        print(f"{method}: {mapper.voxel_count} cells")
        for state in ("UNKNOWN", "FREE", "OCCUPIED"):
            print(f"  {state:9s} ours {counts[state]:7d}   original C++ {golden[state]:7d}")


if __name__ == "__main__":
    main()
