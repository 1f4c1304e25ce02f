"""``evsemmap info``: summarise a map file or a map store."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def add_parser(sub) -> None:
    """Add ``info`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("info", help="summarise a map file or a map store")
    p.add_argument("map", type=Path)
    p.add_argument("--costs", type=Path, default=None,
                   help="cost table whose layers.min_evidence sets the evidence threshold of the known counts "
                        "(default configs/terrain/costs_v3.yaml)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Print a map file's or a map store's summary as JSON."""
    from ...core.map_file import read_map_file
    from ...core.mapper import reader_mapper
    from ...core.map_store import MapStore, is_store, voxel_bounds
    from ...terrain.config import load_terrain_config

    min_evidence = load_terrain_config(args.costs).layers.min_evidence
    if is_store(args.map) or (args.map.is_dir() and (args.map / "work").is_dir()):
        store = MapStore(args.map)
        print(json.dumps(store.summary() | {"evidence_threshold": store_known_counts(store, min_evidence)}, indent=1))
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
        "evidence_threshold": known_counts(contents.evidence, state, min_evidence),
        "scans_integrated": meta.get("scans_integrated"),
        "mapping": meta["mapping"],
    }, indent=1))
    return 0


def store_known_counts(store, min_evidence: float) -> dict:
    """``known_counts`` of a store: every tile read, one at a time."""
    counts = np.zeros((2, 3), np.int64)
    for name in store.tiles:
        contents = store.tile_contents(name)
        counts += _counts(contents.evidence, contents.summary.state, min_evidence)
    return _report(counts, min_evidence)


def known_counts(evidence, state, min_evidence: float) -> dict:
    """The voxels at or above the evidence threshold (known, ``terrain.known``) and below it, in all and per state."""
    return _report(_counts(evidence, state, min_evidence), min_evidence)


def _counts(evidence, state, min_evidence: float) -> np.ndarray:
    """[2, 3]: voxels known (row 0) and below the threshold (row 1), per state (UNKNOWN, FREE, OCCUPIED)."""
    from ...terrain.known import evidence_sums, is_known

    above = is_known(evidence_sums(evidence), min_evidence)
    return np.stack([np.bincount(state[above], minlength=3), np.bincount(state[~above], minlength=3)])


def _report(counts: np.ndarray, min_evidence: float) -> dict:
    names = ("UNKNOWN", "FREE", "OCCUPIED")
    return {"min_evidence": min_evidence, "known": int(counts[0].sum()), "below": int(counts[1].sum()),
            "known_by_state": dict(zip(names, counts[0].tolist())), "below_by_state": dict(zip(names, counts[1].tolist()))}
