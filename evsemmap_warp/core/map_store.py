"""The map store: one map as a folder of spatial tiles, for maps larger than one file or one
process's memory (written by ``evsemmap batch``, read here).

    STORE/store.json        the index: format and version, resolution, float64 origin, grid offset,
                            the world frame (name, CRS), classes, method and every mapping parameter, tile size, per-tile voxel
                            counts and bounds, the inputs and the chunks the map holds, its ``identity``
                            (store_identity) and the ids of the scans it holds (a merge never counts one twice)
    STORE/tiles/X_Y_Z.vox   one tile's voxels (core/tile_codec.py: the accumulated float64 sums and
                            nothing derivable, zstd-compressed, ~11 B a voxel): tile (X, Y, Z) holds the
                            voxels whose global index // tile_voxels is (X, Y, Z); its header names its
                            store's identity and parameters, its tile, its index entry and the last chunk
                            folded into it, so a tile that does not belong (another store's, another
                            place's, damaged) is refused
    STORE/work/             a batch run's plan and chunk records, and the partial maps (chunk_N/X_Y_Z.vox,
                            same codec) of chunks not yet folded into the tiles, so that a rerun resumes

A store of another format version is refused, naming its version. Every file is written under a
temporary name and renamed, so a killed writer never leaves a file that looks whole; files hold no
pickle, and the same content gives the same bytes. Opening a store reads the index only; a query loads
the tiles its points fall in, nothing else; the read-out (centers, concentrations, labels, states,
variance) is derived from the sums on reading, as a Mapper derives it.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .. import files
from ..config import MappingConfig, flat_items
from ..frames import FrameError, WorldFrame
from ..limits import check_tile_voxels
from ..voxel_keys import pack_voxel_keys, voxel_index_of
from . import map_file, tile_codec
from .mapper import MAX_COORDINATE_M, Mapper, QueryResult, UNKNOWN_LABEL, VoxelState
from .voxel_map import EXTRA_COLUMNS, VoxelArrays

STORE_FORMAT = "evsemmap_warp.store"
STORE_VERSION = 3  # 3: the rows' weighted height sum (K + 5 columns)
TILE_SUFFIX = ".vox"  # a tile file's name: its tile name, then this
PARTIAL_SUFFIX = ".vox"
INDEX_NAME = "store.json"
DEFAULT_TILE_VOXELS = 256  # 51.2 m at 0.2 m: a few MB per tile of a LiDAR map


class StoreError(ValueError):
    """A store is missing, incomplete, inconsistent or of another format; the message names the file."""


def is_store(path) -> bool:
    """Whether ``path`` is a store folder (holds a store.json); its content is checked on opening."""
    return (Path(path) / INDEX_NAME).is_file()


def tile_keys(index: np.ndarray, tile_voxels: int) -> np.ndarray:
    """[V, 3] int64: the tile of each global voxel index."""
    return np.floor_divide(np.asarray(index, np.int64), tile_voxels)


def tile_name(key) -> str:
    """A tile's name, "X_Y_Z", from its key (X, Y, Z)."""
    return "_".join(str(int(k)) for k in key)


def parse_tile_name(name: str) -> tuple[int, int, int]:
    """A tile's key (X, Y, Z) from its name "X_Y_Z"; raises StoreError for anything else."""
    parts = name.split("_")
    if len(parts) != 3:
        raise StoreError(f"{name!r} is not a tile name (X_Y_Z)")
    try:
        return tuple(int(p) for p in parts)
    except ValueError:
        raise StoreError(f"{name!r} is not a tile name (X_Y_Z)") from None


def split_by_tile(index: np.ndarray, rows: np.ndarray, tile_voxels: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Global voxel indices and their rows grouped by tile, tiles in name order."""
    if len(index) == 0:
        return {}
    unique, order, bounds = group_by_tile(tile_keys(index, tile_voxels))
    parts = {}
    for t, key in enumerate(unique):
        rows_of_tile = order[bounds[t]:bounds[t + 1]]
        parts[tile_name(key)] = (index[rows_of_tile], rows[rows_of_tile])
    return dict(sorted(parts.items()))


def group_by_tile(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct tile keys of [N, 3] ``keys``, a stable order grouping rows by tile and each
    group's bounds in it: group t is order[bounds[t]:bounds[t + 1]]. One sort of packed int64 keys,
    not np.unique(axis=0), which sorts rows of three (docs/performance.md: a batch worker's time)."""
    low = keys.min(axis=0)
    span = keys.max(axis=0) - low + 1
    packed = ((keys[:, 0] - low[0]) * span[1] + (keys[:, 1] - low[1])) * span[2] + (keys[:, 2] - low[2])
    order = np.argsort(packed, kind="stable")
    ordered = packed[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    return keys[order[starts]], order, np.r_[starts, len(order)]


def write_json(path: Path, data) -> Path:
    """The store's JSON files (store.json, plan.json, done.json): indented, keys sorted, a final newline."""
    return files.write_json_atomically(path, data, indent=1, sort_keys=True)


def write_partial(path: Path, index: np.ndarray, rows: np.ndarray, tile_voxels: int, identity: str, chunk: int) -> Path:
    """Chunk ``chunk``'s voxels in tile ``path.stem`` (global indices in key order, [V, K + 5] rows) for
    the store of ``identity``."""
    return tile_codec.write_voxel_file(path, index, rows, parse_tile_name(Path(path).stem), tile_voxels,
                                       {"kind": "partial", "store": identity, "chunk": int(chunk)})


def read_partial(path: Path, columns: int, tile_voxels: int, identity: str, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """A partial map (write_partial) read from ``path`` and checked (decode_partial)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise StoreError(f"{path}: cannot read ({exc.strerror}); delete its chunk folder {Path(path).parent} and rerun to map that "
                         f"chunk again") from None
    return decode_partial(data, path, columns, tile_voxels, identity, chunk)


def decode_partial(data: bytes, path: Path, columns: int, tile_voxels: int, identity: str, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """A partial map's bytes (the file ``path``, read there or sent), validated: of this store and chunk, in the
    tile its name says, [V, columns] finite sums (non-negative but the weighted height sum), voxels unique and in key
    order."""
    folder = Path(path).parent
    expect = {"kind": "partial", "store": identity, "chunk": int(chunk), "tile": list(parse_tile_name(Path(path).stem)),
              "tile_voxels": tile_voxels}
    try:
        _, index, rows = tile_codec.check_expected(tile_codec.decode_voxels(data, path), path, expect)
    except (tile_codec.VoxelFileError, StoreError) as exc:
        raise StoreError(f"{exc}; delete its chunk folder {folder} and rerun to map that chunk again") from None
    if rows.shape[1] != columns:
        raise StoreError(f"{path}: {rows.shape[1]} columns, this store's maps have {columns}; delete its chunk folder {folder} "
                         f"and rerun to map that chunk again")
    return index, rows


def fold(running: tuple[np.ndarray, np.ndarray] | None, index: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``running`` (a tile's sum so far: global indices [V, 3] in key order and [V, K + 5] rows) plus a
    partial's voxels (the same, each voxel once): the voxels of both in key order, rows of one voxel
    added, touched or-ed. Folding partials one by one in chunk order gives the bits that summing all of
    them at once gives (add_duplicate_voxels, the twin the tests hold it to): each voxel's rows are added
    left to right starting from zero, and 0 + x is x. A merge of two sorted key lists (searchsorted and
    insert, linear in the tile), not np.unique and np.add.at over both (docs/performance.md: batch)."""
    index = np.asarray(index, np.int64).reshape(-1, 3)
    if running is None or not len(running[0]):
        summed = np.zeros_like(rows, dtype=np.float64)
        summed += rows
        summed[:, -1] = np.minimum(summed[:, -1], 1.0)
        return index, summed
    if not len(index):
        return running
    running_index, running_rows = running
    base = np.minimum(running_index.min(axis=0), index.min(axis=0))
    running_keys, keys = pack_voxel_keys(running_index - base), pack_voxel_keys(index - base)
    at = np.searchsorted(running_keys, keys)
    present = running_keys[np.minimum(at, len(running_keys) - 1)] == keys
    summed = running_rows.copy()
    summed[at[present]] += rows[present]
    summed[at[present], -1] = np.minimum(summed[at[present], -1], 1.0)  # touched is or-ed, not added
    new = ~present  # inserted before the running voxel that follows them; np.insert keeps their (key) order
    summed = np.insert(summed, at[new], rows[new], axis=0)
    return np.insert(running_index, at[new], index[new], axis=0), summed


def template_mapper(config: MappingConfig, class_names, origin_index, frame: WorldFrame | None) -> Mapper:
    """An empty Mapper with a store's parameters, origin and world frame: the read-out (labels,
    states, concentrations, centers) of tiles and partials, without a table of its own to speak of."""
    mapper = Mapper(config, len(class_names), class_names=tuple(class_names), workers=1, initial_capacity=16, frame=frame)
    mapper.origin_index = np.asarray(origin_index, np.int64).reshape(3)
    return mapper


def store_identity(mapping: dict, classes, frame: dict | None, origin_index, tile_voxels: int, grid_offset_m: float) -> str:
    """What a tile must share with its store (method and every parameter, classes, frame, origin,
    tiling), as one SHA-256: computed from store.json's fields when reading, from the writer's when writing."""
    fields = {"format": STORE_FORMAT, "mapping": mapping, "classes": list(classes), "frame": frame,
              "origin_index": [int(v) for v in origin_index], "tile_voxels": int(tile_voxels), "grid_offset_m": float(grid_offset_m)}
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()


def template_identity(template: Mapper, tile_voxels: int) -> str:
    """store_identity of the store ``template`` (template_mapper) describes, tiled by ``tile_voxels``."""
    return store_identity(template.config.as_dict(), template.class_names, None if template.frame is None else template.frame.as_dict(),
                          template.origin_index, tile_voxels, template.grid_offset_m)


def tile_entry(template: Mapper, voxels: VoxelArrays) -> dict:
    """A tile's entry in store.json: its voxel count, the box its voxels fill (m) and its voxels per state."""
    summary = template.summarize(voxels.evidence, voxels.touched)
    return {"voxels": int(len(voxels.index)), "bounds_m": voxel_bounds(template, voxels.index),
            "states": {s.name: int(np.count_nonzero(summary.state == s)) for s in VoxelState}}


def voxel_bounds(template: Mapper, index: np.ndarray) -> list[list[float]] | None:
    """The box the voxels of global ``index`` [V, 3] fill, in metres of the map's world frame:
    [[x0, y0, z0], [x1, y1, z1]] (voxel faces, not centers); None for no voxels."""
    if not len(index):
        return None
    low, high = index.min(axis=0), index.max(axis=0)
    half = template.config.resolution_m / 2
    return [(template.voxel_centers(low) - half).tolist(), (template.voxel_centers(high) + half).tolist()]


def write_tile(path: Path, template: Mapper, voxels: VoxelArrays, tile_voxels: int, *, folded_through: int | None = None,
               durable: bool = False) -> dict:
    """One tile (tile_bytes) written atomically (``durable``: on disk when this returns); returns its index entry."""
    data, entry = tile_bytes(Path(path).stem, template, voxels, tile_voxels, folded_through=folded_through)
    files.write_atomically(path, lambda f: f.write(data), durable=durable)
    return entry


def tile_bytes(name: str, template: Mapper, voxels: VoxelArrays, tile_voxels: int, *, folded_through: int | None = None) -> tuple[bytes, dict]:
    """Tile ``name``'s file (``voxels``: global indices in key order) of the store ``template`` (an empty Mapper with
    its parameters, classes, frame and origin) describes, and its index entry. Its header names the store
    (identity, method and parameters, classes, frame), the entry and ``folded_through``, the last chunk whose
    partial it holds (a resumed run folds only later ones)."""
    entry = tile_entry(template, voxels)
    header = {"kind": "tile", "store": template_identity(template, tile_voxels), "mapping": template.config.as_dict(),
              "classes": list(template.class_names), "frame": None if template.frame is None else template.frame.as_dict(),
              "entry": entry, "folded_through": folded_through}
    return tile_codec.encode_voxels(voxels.index, voxels.rows(), parse_tile_name(name), tile_voxels, header), entry


def check_bounds(bounds, what: str = "bounds") -> tuple[np.ndarray, np.ndarray]:
    """A box [[x0, y0, z0], [x1, y1, z1]] (or its 6 numbers) as (low, high): no NaN, each minimum <= its
    maximum; +-inf leaves a side open."""
    try:
        box = np.asarray(bounds, np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not 6 numbers x0 y0 z0 x1 y1 z1 ({exc})") from None
    if box.size != 6 or box.shape not in ((6,), (2, 3)):
        raise ValueError(f"{what}: expected [[x0, y0, z0], [x1, y1, z1]] (6 numbers), got shape {list(box.shape)}")
    box = box.reshape(2, 3)
    if np.isnan(box).any():
        raise ValueError(f"{what} {box.reshape(-1).tolist()}: NaN is no coordinate (use -inf / inf for an open side)")
    if np.any(box[0] > box[1]):
        raise ValueError(f"{what} {box.reshape(-1).tolist()}: each minimum must be <= its maximum (x0 y0 z0 x1 y1 z1)")
    return box[0], box[1]


class MapStore:
    """An opened store: its index, and tiles loaded on demand (the ``cache_tiles`` most recently used
    are kept)."""

    def __init__(self, path, *, cache_tiles: int = 16):
        if isinstance(cache_tiles, bool) or not isinstance(cache_tiles, (int, np.integer)) or cache_tiles < 0:
            raise ValueError(f"cache_tiles = {cache_tiles!r}: must be a whole number >= 0 (tiles kept in memory)")
        self.path = Path(path)
        index_path = self.path / INDEX_NAME
        if not index_path.is_file():
            hint = (" (a batch run still writing it, or stopped before the end: wait for it to finish, or run the same command "
                    "again to complete it)") if (self.path / "work").is_dir() else ""
            raise StoreError(f"{self.path}: not a map store, no {INDEX_NAME}{hint}")
        try:
            self.index = json.loads(index_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise StoreError(f"{index_path}: not a readable store index ({exc})") from None
        self._validate()
        self.config = MappingConfig.from_dict(self.index["mapping"], f"{index_path}: mapping")
        self.class_names = tuple(self.index["classes"])
        self.num_classes = len(self.class_names)
        self.tile_voxels = int(self.index["tile_voxels"])
        self.tiles = {name: info for name, info in self.index["tiles"].items()}
        try:  # null: a store of no known world frame
            self.frame = WorldFrame.from_dict(self.index.get("frame"), f"{index_path}: frame")
        except FrameError as exc:
            raise StoreError(str(exc)) from None
        if self.index.get("resolution_m", self.config.resolution_m) != self.config.resolution_m:
            raise StoreError(f"{index_path}: resolution_m {self.index['resolution_m']!r} disagrees with mapping.resolution_m {self.config.resolution_m}")
        self.template = template_mapper(self.config, self.class_names, self.index["origin_index"], self.frame)
        self.identity = store_identity(self.index["mapping"], self.class_names, self.index.get("frame"), self.index["origin_index"],
                                       self.tile_voxels, self.index.get("grid_offset_m", self.template.grid_offset_m))
        if self.index["identity"] != self.identity:
            raise StoreError(f"{index_path}: its method, parameters, classes, frame, origin or tiling were changed after it was written "
                             f"(identity {str(self.index['identity'])[:16]}... vs {self.identity[:16]}... of its content)")
        self.scan_ids = None if self.index.get("scan_ids") is None else set(self.index["scan_ids"])
        self._refuse_unlisted_tiles(index_path)
        self._cache: OrderedDict[str, Mapper] = OrderedDict()
        self.cache_tiles = int(cache_tiles)
        self.tiles_loaded = 0  # how many tile files were read (tests hold queries to the tiles they need)

    def _refuse_unlisted_tiles(self, index_path: Path) -> None:
        """A tile file the index does not list: the index was edited or belongs to other tiles, and
        every read-out would silently lack its voxels (a listed tile missing on disk is refused on reading)."""
        unlisted = sorted(p.name for p in (self.path / "tiles").glob(f"*{TILE_SUFFIX}")
                          if not p.name.startswith(".") and p.stem not in self.tiles)
        if unlisted:
            raise StoreError(f"{self.path / 'tiles' / unlisted[0]}: a tile file that {index_path} does not list ({len(unlisted)} such: "
                             f"{', '.join(unlisted[:4])}{', ...' if len(unlisted) > 4 else ''}); the index was edited or is not the one "
                             f"these tiles were written with, and its read-outs would lack their voxels: write the store again "
                             f"(batch, merge) or remove the files that do not belong")

    def _validate(self) -> None:
        where = self.path / INDEX_NAME
        index = self.index
        if not isinstance(index, dict) or index.get("format") != STORE_FORMAT:
            raise StoreError(f"{where}: not an {STORE_FORMAT} index")
        if index.get("format_version") != STORE_VERSION or isinstance(index.get("format_version"), bool):
            raise StoreError(f"{where}: store format version {index.get('format_version')!r}; this evsemmap_warp reads version "
                             f"{STORE_VERSION} only (map the data again with it)")
        if not isinstance(index.get("identity"), str):
            raise StoreError(f"{where}: key 'identity' missing or not a string (every format-{STORE_VERSION} store records it)")
        for key, kind in (("mapping", dict), ("classes", list), ("tiles", dict), ("origin_index", list), ("tile_voxels", int),
                          ("scans", int), ("points", int)):
            if not isinstance(index.get(key), kind) or isinstance(index.get(key), bool):
                raise StoreError(f"{where}: key {key!r} missing or not a {kind.__name__}")
        try:
            check_tile_voxels(index["tile_voxels"])
        except ValueError as exc:
            raise StoreError(f"{where}: {exc}") from None
        for key in ("scans", "points"):
            if index[key] < 0:
                raise StoreError(f"{where}: {key} = {index[key]} is negative")
        classes = index["classes"]
        if len(classes) < 2 or not all(isinstance(c, str) and c for c in classes) or len(set(classes)) != len(classes):
            raise StoreError(f"{where}: classes must be at least 2 distinct non-empty names, got {str(classes)[:120]}")
        origin = index["origin_index"]
        resolution = index["mapping"].get("resolution_m")
        if not isinstance(resolution, (int, float)) or isinstance(resolution, bool) or not math.isfinite(resolution) or resolution <= 0:
            raise StoreError(f"{where}: mapping.resolution_m = {resolution!r} must be a finite number > 0")
        if (len(origin) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) for v in origin)
                or max(abs(v) for v in origin) * resolution > MAX_COORDINATE_M):
            raise StoreError(f"{where}: origin_index must be 3 whole numbers within {MAX_COORDINATE_M:g} m of (0, 0, 0), "
                             f"got {str(origin)[:80]}")
        for name, info in index["tiles"].items():
            try:
                parse_tile_name(name)
            except StoreError as exc:
                raise StoreError(f"{where}: {exc}") from None
            if not isinstance(info, dict) or not isinstance(info.get("voxels"), int) or isinstance(info["voxels"], bool) or info["voxels"] < 1:
                raise StoreError(f"{where}: tile {name} needs a voxel count >= 1, got {str(info)[:80]}")
            states = info.get("states", {})
            if (not isinstance(states, dict) or not all(k in VoxelState.__members__ and isinstance(v, int) and not isinstance(v, bool)
                                                        and v >= 0 for k, v in states.items())
                    or (states and sum(states.values()) != info["voxels"])):
                raise StoreError(f"{where}: tile {name}: states must map {', '.join(VoxelState.__members__)} to counts adding up to "
                                 f"its {info['voxels']} voxels, got {str(states)[:80]}")
            bounds = info.get("bounds_m")
            try:
                box = np.asarray(bounds, np.float64)
                ok = box.shape == (2, 3) and np.isfinite(box).all() and (box[0] <= box[1]).all()
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise StoreError(f"{where}: tile {name}: bounds_m must be [[x0, y0, z0], [x1, y1, z1]], finite, min <= max, got {str(bounds)[:80]}")
        chunks = index.get("chunks", [])
        if not isinstance(chunks, list) or not all(isinstance(c, dict) and all(isinstance(c.get(k), int) and c[k] >= 0 for k in ("scans", "points"))
                                                   for c in chunks):
            raise StoreError(f"{where}: chunks must be a list of records with scan and point counts >= 0")
        if chunks and (sum(c["scans"] for c in chunks), sum(c["points"] for c in chunks)) != (index["scans"], index["points"]):
            raise StoreError(f"{where}: the chunks hold {sum(c['scans'] for c in chunks)} scans and {sum(c['points'] for c in chunks)} "
                             f"points, the index says {index['scans']} and {index['points']}")
        ids = index.get("scan_ids")
        if ids is not None and not (isinstance(ids, list) and all(isinstance(i, str) for i in ids) and len(set(ids)) == len(ids)
                                    and len(ids) <= index["scans"]):
            raise StoreError(f"{where}: scan_ids must be a list of at most {index['scans']} distinct scan ids (strings)")

    # Reading -----------------------------------------------------------------------------------------
    @property
    def voxel_count(self) -> int:
        """Voxels in all tiles, as the index counts them."""
        return sum(info["voxels"] for info in self.tiles.values())

    @property
    def format_version(self) -> int:
        """The store's format version (the one this evsemmap_warp writes: others are refused on opening)."""
        return int(self.index["format_version"])

    def tile_path(self, name: str) -> Path:
        """Where tile ``name``'s file is."""
        return self.path / "tiles" / f"{name}{TILE_SUFFIX}"

    def tile(self, name: str) -> Mapper:
        """Tile ``name`` as a read-only Mapper (validated on reading; its origin, frame and scan counts
        are the store's)."""
        if name in self._cache:
            self._cache.move_to_end(name)
            return self._cache[name]
        voxels = self._read_tile(name)
        mapper = Mapper(self.config, self.num_classes, class_names=self.class_names, workers=1, initial_capacity=max(16, len(voxels.index)),
                        frame=self.frame)
        mapper.load_voxels(voxels, origin_index=self.template.origin_index)
        mapper.scans_integrated, mapper.points_integrated = int(self.index["scans"]), int(self.index["points"])
        mapper.scan_ids = None if self.scan_ids is None else set(self.scan_ids)
        mapper.read_only = (f"tile {name} of the store {self.path} (shared by its later queries); use MapStore.to_mapper() "
                            f"for a map to change")
        self.tiles_loaded += 1
        self._cache[name] = mapper
        while len(self._cache) > self.cache_tiles:
            self._cache.popitem(last=False)
        return mapper

    def tile_arrays(self, name: str) -> VoxelArrays:
        """Tile ``name``'s voxels (global indices, key order), read and checked as ``tile`` reads them,
        without building a Mapper's table: for readers that scan a tile's arrays once (the terrain
        layers). Cached tiles are not read again."""
        if name in self._cache:
            return self._cache[name].voxels()[0]
        voxels = self._read_tile(name)
        self.tiles_loaded += 1
        return voxels

    def tile_contents(self, name: str) -> "map_file.MapContents":
        """Tile ``name`` as a map file's contents (the read-out derived from its sums): for readers of
        map-file arrays (the viewer, map_file.file_arrays)."""
        return self.template.contents_of(self.tile_arrays(name), scans_integrated=int(self.index["scans"]),
                                         points_integrated=int(self.index["points"]), scan_ids=None)

    def _read_tile(self, name: str) -> VoxelArrays:
        """Tile ``name``'s file, read and checked (the one reader of ``tile`` and ``tile_arrays``)."""
        if name not in self.tiles:
            raise StoreError(f"{self.path}: no tile {name}")
        path = self.tile_path(name)
        try:
            header, index, rows = tile_codec.read_voxel_file(path)
        except tile_codec.VoxelFileError as exc:
            raise StoreError(f"{exc}; the store {self.path} cannot be read until the tile is restored (rerun the batch command "
                             f"that wrote it)") from None
        self._check_tile_header(name, path, header, len(index), rows.shape[1])
        return VoxelArrays.from_rows(index, rows)

    def _check_tile_header(self, name: str, path: Path, header: dict, voxels: int, columns: int) -> None:
        """Refuse a tile that does not belong to this store, naming what differs."""
        def refuse(text: str):
            raise StoreError(f"{path}: {text}; this tile does not belong to the store {self.path}")

        if header.get("kind") != "tile":
            refuse(f"it is a {header.get('kind')!r} file, not a tile")
        if header.get("store") != self.identity:
            mine = flat_items(self.index["mapping"])
            theirs = flat_items(header["mapping"]) if isinstance(header.get("mapping"), dict) else {}
            differing = [f"{k} {theirs.get(k)!r} vs {mine[k]!r}" for k in mine if theirs.get(k) != mine[k]]
            if header.get("classes") != list(self.class_names):
                differing.append(f"classes {header.get('classes')} vs {list(self.class_names)}")
            if header.get("frame") != self.index.get("frame"):
                differing.append(f"frame {header.get('frame')} vs {self.index.get('frame')}")
            refuse("its " + ", ".join(differing) if differing else
                   f"it was written for another store (identity {str(header.get('store'))[:16]}..., this store's {self.identity[:16]}...: "
                   f"another origin, tiling or parameters)")
        if header["tile"] != list(parse_tile_name(name)) or header["tile_voxels"] != self.tile_voxels:
            refuse(f"it is tile {tile_name(header['tile'])}, not {name}")
        if columns != self.num_classes + EXTRA_COLUMNS:
            refuse(f"{columns} columns, this store's maps have {self.num_classes + EXTRA_COLUMNS}"
                   + (" (the weighted height sum is missing: a store written before it; map the data again)"
                      if columns == self.num_classes + EXTRA_COLUMNS - 1 else ""))
        expected = self.tiles[name]["voxels"]
        if voxels != expected:
            raise StoreError(f"{path}: {voxels} voxels, the index says {expected}")

    def voxel_index_of(self, points: np.ndarray) -> np.ndarray:
        """The global voxel index of each point, as the mapper that wrote the store computed it."""
        return voxel_index_of(points, self.config.resolution_m, self.template.grid_offset_m, self.template.origin_index)

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state at each point [M, 3], as ``Mapper.query``;
        only the tiles the points fall in are read."""
        from .mapper import validate_points

        points = validate_points(points, "query points", far_ok=True)
        m = len(points)
        label = np.full(m, UNKNOWN_LABEL, np.int32)
        # outside the tiles, what a map file answers outside its voxels: the prior's read-out (UNKNOWN)
        prior = self.template.summarize(np.zeros((1, self.num_classes)), np.zeros(1, bool))
        probabilities = np.repeat(prior.probabilities, m, axis=0)
        variance = np.repeat(prior.variance, m)
        state = np.full(m, int(VoxelState.UNKNOWN), np.int8)
        voxel_index = self.voxel_index_of(points)
        # one name per tile met, not per point: queries may hold millions of points
        keys, order, bounds = group_by_tile(tile_keys(voxel_index, self.tile_voxels)) if m else (np.zeros((0, 3), np.int64), None, None)
        met = {tile_name(key): t for t, key in enumerate(keys)}
        for name in sorted(set(met) & set(self.tiles)):
            rows = np.sort(order[bounds[met[name]]:bounds[met[name] + 1]])
            result = self.tile(name).query(points[rows])
            label[rows], probabilities[rows], variance[rows], state[rows] = result.label, result.probabilities, result.variance, result.state
        return QueryResult(label, probabilities, variance, state, voxel_index)

    def tiles_in(self, bounds: np.ndarray | None) -> list[str]:
        """Tiles whose voxel bounds meet the box [[x0, y0, z0], [x1, y1, z1]] (m); all without one."""
        if bounds is None:
            return sorted(self.tiles)
        low, high = check_bounds(bounds, "bounds")
        return sorted(name for name, info in self.tiles.items()
                      if np.all(np.asarray(info["bounds_m"][1]) >= low) and np.all(np.asarray(info["bounds_m"][0]) <= high))

    def to_mapper(self, bounds=None) -> Mapper:
        """The store (or the voxels whose centers lie in ``bounds``) as one Mapper."""
        if bounds is not None:
            bounds = np.stack(check_bounds(bounds, "bounds"))
        parts = []
        for name in self.tiles_in(bounds):
            voxels = self.tile_arrays(name)
            if bounds is not None:
                centers = self.template.voxel_centers(voxels.index)
                inside = np.all((centers >= bounds[0]) & (centers <= bounds[1]), axis=1)
                voxels = VoxelArrays.from_rows(voxels.index[inside], voxels.rows()[inside])
            parts.append(voxels)
        out = Mapper(self.config, self.num_classes, class_names=self.class_names, workers=1, frame=self.frame)
        out.origin_index = self.template.origin_index.copy()
        if parts:
            index = np.concatenate([p.index for p in parts])
            rows = np.concatenate([p.rows() for p in parts]) if index.size else np.zeros((0, self.num_classes + EXTRA_COLUMNS))
            out.load_voxels(VoxelArrays.from_rows(index, rows), origin_index=out.origin_index)
        out.scans_integrated = int(self.index["scans"])
        out.points_integrated = int(self.index["points"])
        # a part of the store holds some of its scans, which ones is not known per voxel: the store's ids
        # make a merge with the rest of it refused too (its scans would count twice)
        out.scan_ids = None if self.scan_ids is None else set(self.scan_ids)
        return out

    def bounds_m(self) -> list[list[float]] | None:
        """The box the store's voxels fill (m, its world frame), from its index: [[x0, y0, z0], [x1, y1, z1]];
        None without tiles."""
        boxes = [np.asarray(info["bounds_m"], np.float64) for info in self.tiles.values()]
        if not boxes:
            return None
        return [np.min([b[0] for b in boxes], axis=0).tolist(), np.max([b[1] for b in boxes], axis=0).tolist()]

    def summary(self) -> dict:
        """What ``evsemmap info STORE`` prints."""
        index = self.index
        states = {s.name: 0 for s in VoxelState}
        for info in self.tiles.values():
            for name, count in info.get("states", {}).items():
                states[name] = states.get(name, 0) + count
        return {
            "store": str(self.path), "format_version": index["format_version"], "method": index["mapping"].get("method"),
            "classes": list(self.class_names), "resolution_m": self.config.resolution_m, "origin_m": self.template.origin.tolist(),
            "frame": None if self.frame is None else self.frame.as_dict(),
            "tile_voxels": self.tile_voxels, "tile_size_m": self.tile_voxels * self.config.resolution_m, "tiles": len(self.tiles),
            "voxels": self.voxel_count, "bounds_m": self.bounds_m(), "states": states,
            "scans_integrated": index["scans"], "points_integrated": index["points"],
            "inputs": index.get("inputs", []), "chunks": len(index.get("chunks", [])), "mapping": index["mapping"],
        }
