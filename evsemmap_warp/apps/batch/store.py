"""The store folder as a batch run writes it: the lock that lets one run at a time write it, the work folder's
records (plan.json, each chunk's done.json) checked against the plan, the leftovers of killed workers, and
store.json."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from ...config import ConfigError
from ...core import map_store
from ...core.mapper import Mapper
from ...core.voxel_map import VoxelArrays
from ...limits import check_tile_voxels
from .planning import Chunk


def chunk_dir(store: Path, number: int) -> Path:
    """The work folder of chunk ``number`` in the batch store ``store``, where its partial tiles and done record wait."""
    return store / "work" / f"chunk_{number:06d}"


def _read_work_json(path: Path, what: str, remedy: str):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise map_store.StoreError(f"{path}: not a readable {what} ({type(exc).__name__}: {exc}); {remedy}") from None


def read_done(store: Path, chunk: Chunk, folded: dict[str, int] | None = None) -> dict:
    """A finished chunk's record (done.json), validated against the chunk and, given ``folded`` (tile ->
    the last chunk folded into it), against the partials beside it: each tile's is there, or folded."""
    folder = chunk_dir(store, chunk.number)
    path = folder / "done.json"
    record = _read_work_json(path, "chunk record", f"delete {folder} and rerun to map that chunk again")
    counts = ("number", "frames", "scans", "points", "voxels")
    problem = None
    if not isinstance(record, dict) or not all(isinstance(record.get(k), int) and not isinstance(record[k], bool) and record[k] >= 0
                                               for k in counts):
        problem = f"needs whole counts >= 0 for {', '.join(counts)}"
    elif (record["number"], record["frames"]) != (chunk.number, chunk.frames) or record["scans"] > chunk.frames:
        problem = (f"says chunk {record['number']} of {record['frames']} frames with {record['scans']} scans, the plan has chunk "
                   f"{chunk.number} of {chunk.frames} frames")
    elif not isinstance(record.get("tiles"), list) or not all(isinstance(t, str) for t in record["tiles"]):
        problem = "needs the list of its tiles"
    elif not isinstance(record.get("scan_ids"), list) or not all(isinstance(i, str) for i in record["scan_ids"]):
        problem = "needs the list of its scan ids"
    else:
        for name in record["tiles"]:
            try:
                map_store.parse_tile_name(name)
            except map_store.StoreError as exc:
                problem = str(exc)
                break
            partial = folder / f"{name}{map_store.PARTIAL_SUFFIX}"
            if folded is not None and not partial.is_file() and folded.get(name, -1) < chunk.number:
                problem = f"lists tile {name}, whose partial {partial} is missing (and not folded into the tile)"
                break
    if problem:
        raise map_store.StoreError(f"{path}: {problem}; delete {folder} and rerun to map that chunk again")
    return record


def check_store(out: Path, identity: dict) -> None:
    """Raise one line unless ``out`` may receive this run: empty or absent, or the work of the same inputs and
    settings (``identity``, which the plan records) to resume."""
    plan_path = out / "work" / "plan.json"
    if plan_path.is_file():
        earlier = _read_work_json(plan_path, "batch plan", f"delete {out / 'work'} to start over")
        if not isinstance(earlier, dict):
            raise map_store.StoreError(f"{plan_path}: not a batch plan (a JSON object); delete {out / 'work'} to start over")
        if earlier.get("store_format_version") != identity["store_format_version"]:
            raise ConfigError(f"{out}: a store of format {earlier.get('store_format_version', 1)}, written by an older evsemmap_warp; "
                              f"this version writes and reads format {identity['store_format_version']}: give a new --out to map again")
        if earlier != identity:
            differing = sorted(k for k in set(earlier) | set(identity) if k not in earlier or k not in identity or earlier[k] != identity[k])
            raise ConfigError(f"{out}: holds a batch run of other inputs or settings (differing: {', '.join(differing)}); "
                              f"give a new --out, or delete {out} to start over")
    elif (out / map_store.INDEX_NAME).is_file() and _store_format(out) != map_store.STORE_VERSION:
        raise ConfigError(f"{out}: a store of format {_store_format(out)}, written by an older evsemmap_warp; this version writes "
                          f"and reads format {map_store.STORE_VERSION}: give a new --out to map again")
    elif (out / map_store.INDEX_NAME).is_file():
        raise ConfigError(f"{out}: a finished store whose partial maps were discarded (--discard-partials); delete it to map again, "
                          f"or give a new --out")
    elif out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: exists and is not a batch store; give a new --out")


def _store_format(out: Path):
    """The format version store.json states (None when it states none or cannot be read)."""
    try:
        return json.loads((out / map_store.INDEX_NAME).read_text()).get("format_version")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        return None


def remove_unfinished_chunks(out: Path) -> None:
    """What workers killed halfway left (temporary chunk folders, temporary tile files): never counted,
    removed (the store lock says no other run is writing them)."""
    for stale in (out / "work").glob(".chunk_*"):
        shutil.rmtree(stale, ignore_errors=True)
    for stale in (out / "tiles").glob(".*.tmp"):
        stale.unlink(missing_ok=True)


@contextlib.contextmanager
def store_lock(out: Path):
    """One batch run at a time per store: an exclusive lock on the store folder (created here, and
    removed again when the run leaves it empty). Two runs into one store would interleave their chunks,
    plans and tiles: a store of one drive's inputs holding another's voxels, both exiting 0."""
    import fcntl

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    handle = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(f"{out}: another batch run is writing this store now; wait for it to finish, or give another --out") from None
        yield
    finally:
        os.close(handle)  # releases the lock
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def store_index(template: Mapper, tile_voxels: int, entries: dict, inputs: list, chunks: list, totals: dict, scan_ids) -> dict:
    """store.json: everything but the tiles' voxels; nothing that depends on how or when it ran; its identity is
    what its tiles record (map_store.template_identity). ``scan_ids``: the scans it holds
    (a merge refuses to count them twice), None when not known."""
    config = template.config
    return {
        "identity": map_store.template_identity(template, tile_voxels), "scan_ids": None if scan_ids is None else sorted(scan_ids),
        "format": map_store.STORE_FORMAT, "format_version": map_store.STORE_VERSION, "resolution_m": config.resolution_m,
        "origin_index": [int(v) for v in template.origin_index], "origin_m": template.origin.tolist(),
        "grid_offset_m": template.grid_offset_m, "frame": None if template.frame is None else template.frame.as_dict(),
        "classes": list(template.class_names), "method": config.method,
        "mapping": config.as_dict(), "tile_voxels": tile_voxels,
        "tiles": {name: entries[name] for name in sorted(entries)},
        "inputs": inputs, "chunks": chunks, "scans": int(totals["scans"]), "points": int(totals["points"]),
    }


def write_store_from_mapper(mapper: Mapper, out, tile_voxels: int, sources: list[str]) -> Path:
    """A whole map (a merge's result) written as a store."""
    out = Path(out)
    check_tile_voxels(tile_voxels, "--tile-voxels")
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: exists and is not empty; a store is written to a new folder")
    voxels, _ = mapper.voxels()
    template = map_store.template_mapper(mapper.config, mapper.class_names,
                                         mapper.origin_index if mapper.origin_index is not None else np.zeros(3, np.int64), mapper.frame)
    totals = {"scans": mapper.scans_integrated, "points": mapper.points_integrated}
    entries = {name: map_store.write_tile(out / "tiles" / f"{name}{map_store.TILE_SUFFIX}", template,
                                          VoxelArrays.from_rows(index, rows), tile_voxels)
               for name, (index, rows) in map_store.split_by_tile(voxels.index, voxels.rows(), tile_voxels).items()}
    map_store.write_json(out / map_store.INDEX_NAME, store_index(template, tile_voxels, entries, [{"source": s} for s in sources], [], totals,
                                                                  mapper.scan_ids))
    return out
