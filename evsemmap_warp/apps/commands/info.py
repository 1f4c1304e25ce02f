"""``evsemmap info``: summarise a map file or a map store."""

from __future__ import annotations

import json
from pathlib import Path


def add_parser(sub) -> None:
    """Add ``info`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("info", help="summarise a map file or a map store")
    p.add_argument("map", type=Path)
    p.set_defaults(func=run)


def run(args) -> int:
    """Print a map file's or a map store's summary as JSON."""
    from ...core.map_file import read_map_file
    from ...core.mapper import reader_mapper
    from ...core.map_store import MapStore, is_store, voxel_bounds

    if is_store(args.map) or (args.map.is_dir() and (args.map / "work").is_dir()):
        print(json.dumps(MapStore(args.map).summary(), indent=1))
        return 0

    contents = read_map_file(args.map)  # the sums; the states are read out below, the rest of the read-out is not needed
    meta, reader = contents.meta, reader_mapper(contents)
    state = reader.summarize(contents.evidence, contents.touched).state
    print(json.dumps({
        "file": str(args.map),
        "method": meta["method"],
        "classes": meta["classes"],
        "format_version": meta["format_version"],
        "resolution_m": contents.resolution,
        "origin_m": contents.origin.tolist(),
        "frame": meta.get("frame"),  # None: a map of no known world frame
        "voxels": int(len(state)),
        "bounds_m": voxel_bounds(reader, contents.index),  # [[x0, y0, z0], [x1, y1, z1]] in the frame, None when empty
        "states": {"UNKNOWN": int((state == 0).sum()), "FREE": int((state == 1).sum()), "OCCUPIED": int((state == 2).sum())},
        "scans_integrated": meta.get("scans_integrated"),
        "mapping": meta["mapping"],
    }, indent=1))
    return 0
