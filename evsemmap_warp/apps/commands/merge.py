"""``evsemmap merge``: add up maps or stores of disjoint scan sets (several drives over one area) into one."""

from __future__ import annotations

import json
from pathlib import Path

from ... import limits
from .args import TILE_VOXELS


def add_parser(sub) -> None:
    """Add ``merge`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("merge", help="add up maps or stores of disjoint scan sets (several drives over one area) into one")
    p.add_argument("inputs", nargs="+", type=Path, help="map files (.npz) and map stores, at least two")
    p.add_argument("--out", type=Path, required=True, help="a map file (.npz) or a map store (a folder)")
    p.add_argument("--tile-voxels", type=TILE_VOXELS, default=256, help=f"tile edge in voxels when writing a store, 1..{limits.MAX_TILE_VOXELS}")
    p.add_argument("--same-frame", action="store_true", help="the inputs' frames of one run (e.g. odom) are one frame: runs that differ or "
                                                             "are unknown are merged (docs/formats.md, the frame's run)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Maps and stores of disjoint scan sets (several drives or robots over one area) into one."""
    from ...core.mapper import save_map

    if len(args.inputs) < 2:
        raise ValueError(f"merge: give at least two maps or stores, got {len(args.inputs)}")
    from ...files import check_not_inside
    from ...frames import check_same_frame

    resolved = [p.resolve() for p in args.inputs]
    for i, path in enumerate(resolved):
        if path in resolved[:i]:  # its evidence would count twice
            raise ValueError(f"merge: {args.inputs[i]} is given twice; merge each map or store once")
    check_not_inside(args.out, args.inputs, "merge --out")

    merged = None
    for path in args.inputs:
        part = _load_map_or_store(path)
        if merged is not None:  # refused before anything is added, naming both inputs and both frames
            check_same_frame("merge", (str(args.inputs[0]), merged.frame), (str(path), part.frame), same_frame=args.same_frame)
        try:
            merged = part if merged is None else merged.merge(part, same_frame=args.same_frame)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    if args.out.suffix == ".npz":
        save_map(args.out, merged)
    else:
        from ..batch import write_store_from_mapper

        write_store_from_mapper(merged, args.out, args.tile_voxels, [str(p) for p in args.inputs])
    print(json.dumps({"inputs": [str(p) for p in args.inputs], "out": str(args.out), "voxels": merged.voxel_count}, indent=1))
    return 0


def _load_map_or_store(path: Path):
    """A map file as a Mapper, or a store (whole) as one."""
    from ...core.map_store import MapStore, is_store
    from ...core.mapper import load_map

    # a folder is a store, or one not written yet (MapStore names why it is not one)
    return MapStore(path).to_mapper() if is_store(path) or Path(path).is_dir() else load_map(path)
