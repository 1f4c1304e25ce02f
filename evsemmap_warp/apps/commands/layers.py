"""``evsemmap layers``: 2.5-D terrain layers (elevation, slope, step, class, uncertainty, cost) of a map or store as a GeoTIFF, an npz, PNG previews and a ROS bag (grid_map, OccupancyGrid)."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def add_parser(sub) -> None:
    """Add ``layers`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("layers", help="2.5-D terrain layers (elevation, slope, step, class, uncertainty, cost) of a map or store as a "
                                      "GeoTIFF, an npz, PNG previews and a ROS bag (grid_map, OccupancyGrid)")
    p.add_argument("map", type=Path, help="a map file (.npz) or a map store (a folder)")
    p.add_argument("--out", type=Path, required=True, help="folder to write layers.tif, layers.npz (a store: tiles/X_Y.npz), "
                                                           "layers.bag, previews/ and layers.json into")
    p.add_argument("--resolution-m", type=float, default=None, help="cell edge (m; default: the map's voxel size; a store's must divide its tiles)")
    p.add_argument("--bounds", type=float, nargs="+", metavar="M", help="the region: X0 Y0 X1 Y1, or X0 Y0 Z0 X1 Y1 Z1 to count only "
                                                                        "voxels whose centers lie between Z0 and Z1 (m, the map's world frame)")
    p.add_argument("--costs", type=Path, default=None, help="surface classes and cost table YAML (default: configs/terrain/costs_v3.yaml, "
                                                           "for the remap-v3 / RELLIS-3D classes)")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.add_argument("--no-bag", action="store_true", help="skip the ROS bag")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)


def run(args) -> int:
    """2.5-D terrain layers of a map file or store: GeoTIFF, npz, PNG previews, a ROS bag (docs/terrain.md)."""
    from ...terrain.pipeline import write_layers

    log = None if args.quiet else (lambda m: print(m, file=sys.stderr))
    summary = write_layers(args.map, args.out, resolution_m=args.resolution_m, bounds=args.bounds, costs=args.costs, device=args.device,
                           previews=not args.no_previews, bag=not args.no_bag, log=log)
    summary.pop("files", None)
    print(json.dumps(summary, indent=1))
    return 0
