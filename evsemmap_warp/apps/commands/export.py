"""``evsemmap export``: a map store (or the part of it inside --bounds) as one map file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def add_parser(sub) -> None:
    """Add ``export`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("export", help="a map store (or the part of it inside --bounds) as one map file")
    p.add_argument("store", type=Path)
    p.add_argument("--bounds", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help="keep voxels whose centers lie in this box (m)")
    p.add_argument("--out", type=Path, required=True, help="map file to write (.npz)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Write a map store, or the part of it inside ``--bounds``, as one map file."""
    from ...core.map_store import MapStore
    from ...core.mapper import save_map

    from ...core.map_store import check_bounds
    from ...files import check_not_inside

    check_not_inside(args.out, [args.store], "export --out")  # never over the store's own files
    store = MapStore(args.store)
    bounds = None
    if args.bounds is not None:
        bounds = np.stack(check_bounds(args.bounds, "--bounds"))
    mapper = store.to_mapper(bounds)
    save_map(args.out, mapper)
    print(json.dumps({"store": str(args.store), "out": str(args.out), "voxels": mapper.voxel_count, "tiles_read": store.tiles_loaded}, indent=1))
    return 0
