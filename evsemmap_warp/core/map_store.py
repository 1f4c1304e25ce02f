"""The map store: one map as a folder of spatial tiles, for maps larger than one file or one
process's memory (written by ``evsemmap batch``, read here).

    STORE/store.json        the index: format and version, resolution, float64 origin, grid offset,
                            the world frame (name, CRS), classes, method and every mapping parameter, tile size, per-tile voxel
                            counts and bounds, the inputs and the chunks the map holds, its ``identity``
                            (store_identity) and the ids of the scans it holds (a merge never counts one twice)
    STORE/tiles/X_Y_Z.npz   one tile's voxels in the map-file schema (core/map_file.py): tile (X, Y, Z)
                            holds the voxels whose global index // tile_voxels is (X, Y, Z); its meta.tile
                            names its store's identity, its own name and a checksum of its voxels, so a
                            tile that does not belong (another store's, another place's, edited) is refused
    STORE/work/             a batch run's partial maps (one folder per chunk), kept so that a rerun
                            resumes instead of starting over

Every file is written under a temporary name and renamed, so a killed writer never leaves a file that
looks whole; files hold no pickle, and the same content gives the same bytes. Opening a store reads
the index only; a query loads the tiles its points fall in, nothing else.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .. import files
from ..config import MappingConfig, dataclass_from_dict
from ..frames import FrameError, WorldFrame, describe_frame
from ..voxel_keys import voxel_index_of
from . import map_file
from .mapper import MAX_COORDINATE_M, Mapper, QueryResult, UNKNOWN_LABEL, VoxelState
from .voxel_map import EXTRA_COLUMNS, VoxelArrays, add_duplicate_voxels

STORE_FORMAT = "evsemmap_warp.store"
STORE_VERSION = 1
INDEX_NAME = "store.json"
DEFAULT_TILE_VOXELS = 256  # 51.2 m at 0.2 m: a few MB per tile of a LiDAR map


class StoreError(ValueError):
    """A store is missing, incomplete, inconsistent or of another format; the message names the file."""


def is_store(path) -> bool:
    return (Path(path) / INDEX_NAME).is_file()


def tile_keys(index: np.ndarray, tile_voxels: int) -> np.ndarray:
    """[V, 3] int64: the tile of each global voxel index."""
    return np.floor_divide(np.asarray(index, np.int64), tile_voxels)


def tile_name(key) -> str:
    return "_".join(str(int(k)) for k in key)


def parse_tile_name(name: str) -> tuple[int, int, int]:
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
    group's bounds in it: group t is order[bounds[t]:bounds[t + 1]]. One sort of packed int64 keys:
    np.unique(axis=0) sorted rows of three and took 15 % of a batch worker's time (3.9 of 29.7 s)."""
    low = keys.min(axis=0)
    span = keys.max(axis=0) - low + 1
    packed = ((keys[:, 0] - low[0]) * span[1] + (keys[:, 1] - low[1])) * span[2] + (keys[:, 2] - low[2])
    order = np.argsort(packed, kind="stable")
    ordered = packed[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    return keys[order[starts]], order, np.r_[starts, len(order)]


# ``write(file)`` into a temporary name beside ``path``, then renamed into place (the package's one writer).
write_atomically = files.write_atomically


def write_json(path: Path, data) -> Path:
    """The store's JSON files (store.json, plan.json, done.json): indented, keys sorted, a final newline."""
    return files.write_json_atomically(path, data, indent=1, sort_keys=True)


def write_partial(path: Path, index: np.ndarray, rows: np.ndarray) -> Path:
    """A partial map's voxels (global indices and [V, K + 4] rows), for reduction."""
    return write_atomically(path, lambda f: map_file.write_npz(f, index=np.asarray(index, np.int64), rows=np.asarray(rows, np.float64)))


def read_partial(path: Path, columns: int, tile_voxels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A partial map (write_partial), validated: integer indices [V, 3], unique, in the tile its name
    says (with ``tile_voxels``), finite non-negative rows [V, columns]."""
    try:
        with np.load(path, allow_pickle=False) as data:
            index, rows = data["index"], data["rows"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise StoreError(f"{path}: not a readable partial map ({type(exc).__name__}: {exc}); delete its chunk folder "
                         f"{Path(path).parent} and rerun to map that chunk again") from None
    if (index.ndim != 2 or index.shape[1:] != (3,) or not np.issubdtype(index.dtype, np.integer) or rows.shape != (len(index), columns)
            or not np.issubdtype(rows.dtype, np.floating) or not np.isfinite(rows).all() or (rows.size and rows.min() < 0)):
        raise StoreError(f"{path}: a partial map needs integer index [V, 3] and finite non-negative float rows [V, {columns}], "
                         f"got {index.dtype} {list(index.shape)} and {rows.dtype} {list(rows.shape)}")
    if tile_voxels is not None and len(index):
        if (tile_keys(index, tile_voxels) != parse_tile_name(Path(path).stem)).any():
            raise StoreError(f"{path}: holds voxels outside tile {Path(path).stem}")
        if len(np.unique(index, axis=0)) != len(index):
            raise StoreError(f"{path}: a voxel appears more than once")
    return index.astype(np.int64), rows


def reduce_partials(template: Mapper, parts: list[tuple[np.ndarray, np.ndarray]]) -> VoxelArrays:
    """The sum of partial maps (global indices), one row per voxel in key order; the parts are added
    in the order given, so the result does not depend on which finished first."""
    index = np.concatenate([p[0] for p in parts])
    rows = np.concatenate([p[1] for p in parts])
    summed = add_duplicate_voxels(index - template.origin_index, rows)
    summed.index = summed.index + template.origin_index
    return summed


def template_mapper(config: MappingConfig, class_names, origin_index, frame: WorldFrame | None) -> Mapper:
    """An empty Mapper with a store's parameters, origin and world frame: the read-out (labels,
    states, concentrations, centres) of tiles and partials, without a table of its own to speak of."""
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
    return store_identity(template.config.as_dict(), template.class_names, None if template.frame is None else template.frame.as_dict(),
                          template.origin_index, tile_voxels, template.grid_offset_m)


def voxel_checksum(voxels: VoxelArrays) -> str:
    """SHA-256 of a tile's voxels (indices and every accumulated column, as the map file stores them)."""
    digest = hashlib.sha256()
    for array, dtype in ((voxels.index, np.int64), (voxels.evidence, np.float64), (voxels.weight_sum, np.float64),
                         (voxels.weighted_uncertainty_sum, np.float64), (voxels.hits, np.int64), (voxels.touched, bool)):
        array = np.ascontiguousarray(array, dtype)
        digest.update(str(array.shape).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def write_tile(path: Path, template: Mapper, voxels: VoxelArrays, totals: dict, tile_voxels: int | None = None) -> Path:
    """One tile in the map-file schema; ``template`` (an empty Mapper with the store's config and
    origin) gives the read-out, ``totals`` the whole map's scan and point counts. Its meta names the
    store it belongs to (store_identity), its tile and a checksum of its voxels, checked on reading."""
    summary = template.summarize(voxels.evidence, voxels.touched)
    meta = template.metadata() | {"scans_integrated": int(totals["scans"]), "points_integrated": int(totals["points"]), "scan_ids": None}
    if tile_voxels is not None:
        meta["tile"] = {"store": template_identity(template, tile_voxels), "name": Path(path).stem, "checksum": voxel_checksum(voxels)}
    contents = map_file.MapContents(
        meta=meta, origin=template.origin, index=voxels.index, evidence=voxels.evidence, alpha=template.concentrations(voxels.evidence),
        centers=template.voxel_centers(voxels.index), summary=summary, weight_sum=voxels.weight_sum,
        weighted_uncertainty_sum=voxels.weighted_uncertainty_sum, hits=voxels.hits, touched=voxels.touched,
        resolution=template.config.resolution_m)
    return map_file.write_map_file(path, contents)


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
            hint = " (a batch run that has not finished: run the same command again to complete it)" if (self.path / "work").is_dir() else ""
            raise StoreError(f"{self.path}: not a map store, no {INDEX_NAME}{hint}")
        try:
            self.index = json.loads(index_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise StoreError(f"{index_path}: not a readable store index ({exc})") from None
        self._validate()
        self.config = dataclass_from_dict(MappingConfig, self.index["mapping"], f"{index_path}: mapping")
        self.class_names = tuple(self.index["classes"])
        self.num_classes = len(self.class_names)
        self.tile_voxels = int(self.index["tile_voxels"])
        self.tiles = {name: info for name, info in self.index["tiles"].items()}
        try:  # stores written before maps recorded their world frame have none
            self.frame = WorldFrame.from_dict(self.index.get("frame"), f"{index_path}: frame")
        except FrameError as exc:
            raise StoreError(str(exc)) from None
        if self.index.get("resolution_m", self.config.resolution_m) != self.config.resolution_m:
            raise StoreError(f"{index_path}: resolution_m {self.index['resolution_m']!r} disagrees with mapping.resolution_m {self.config.resolution_m}")
        self.template = template_mapper(self.config, self.class_names, self.index["origin_index"], self.frame)
        self.identity = store_identity(self.index["mapping"], self.class_names, self.index.get("frame"), self.index["origin_index"],
                                       self.tile_voxels, self.index.get("grid_offset_m", self.template.grid_offset_m))
        if "identity" in self.index and self.index["identity"] != self.identity:
            raise StoreError(f"{index_path}: its method, parameters, classes, frame, origin or tiling were changed after it was written "
                             f"(identity {str(self.index['identity'])[:16]}... vs {self.identity[:16]}... of its content)")
        self.scan_ids = None if self.index.get("scan_ids") is None else set(self.index["scan_ids"])
        self._cache: OrderedDict[str, Mapper] = OrderedDict()
        self.cache_tiles = int(cache_tiles)
        self.tiles_loaded = 0  # how many tile files were read (tests hold queries to the tiles they need)

    def _validate(self) -> None:
        where = self.path / INDEX_NAME
        index = self.index
        if not isinstance(index, dict) or index.get("format") != STORE_FORMAT:
            raise StoreError(f"{where}: not an {STORE_FORMAT} index")
        if index.get("format_version") != STORE_VERSION:
            raise StoreError(f"{where}: store format version {index.get('format_version')!r}; this version reads {STORE_VERSION}")
        for key, kind in (("mapping", dict), ("classes", list), ("tiles", dict), ("origin_index", list), ("tile_voxels", int),
                          ("scans", int), ("points", int)):
            if not isinstance(index.get(key), kind) or isinstance(index.get(key), bool):
                raise StoreError(f"{where}: key {key!r} missing or not a {kind.__name__}")
        for key in ("tile_voxels",):
            if not 1 <= index[key] <= 2**20:
                raise StoreError(f"{where}: {key} {index[key]} must lie in 1..{2**20}")
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
        return sum(info["voxels"] for info in self.tiles.values())

    def tile_path(self, name: str) -> Path:
        return self.path / "tiles" / f"{name}.npz"

    def tile(self, name: str) -> Mapper:
        """Tile ``name`` as a Mapper (validated on reading; its origin is the store's)."""
        if name in self._cache:
            self._cache.move_to_end(name)
            return self._cache[name]
        path = self.tile_path(name)
        contents = self._read_tile(name)
        try:
            mapper = Mapper.from_contents(contents, path)
        except (map_file.MapFileError, ValueError) as exc:
            raise StoreError(f"{path}: {exc}") from None
        mapper.read_only = (f"tile {name} of the store {self.path} (shared by its later queries); use MapStore.to_mapper() "
                            f"or Mapper.load({str(path)!r}) for a map to change")
        self.tiles_loaded += 1
        self._cache[name] = mapper
        while len(self._cache) > self.cache_tiles:
            self._cache.popitem(last=False)
        return mapper

    def _read_tile(self, name: str) -> "map_file.MapContents":
        """Tile ``name``'s file, read and checked (the one reader of ``tile`` and ``tile_arrays``)."""
        if name not in self.tiles:
            raise StoreError(f"{self.path}: no tile {name}")
        path = self.tile_path(name)
        try:
            contents = map_file.read_map_file(path)
        except (map_file.MapFileError, OSError, ValueError) as exc:
            raise StoreError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
        self._check_tile(name, path, contents)
        return contents

    def tile_arrays(self, name: str) -> VoxelArrays:
        """Tile ``name``'s voxels (global indices, key order), read and checked as ``tile`` reads them,
        without building a Mapper's table: for readers that scan a tile's arrays once (the terrain layers'
        sweep over 1,000 frames of the ``long`` drive: 4.4 s against 7.9 s through ``tile``). Cached tiles
        are not read again."""
        if name in self._cache:
            return self._cache[name].voxels()[0]
        contents = self._read_tile(name)
        self.tiles_loaded += 1
        return VoxelArrays(index=contents.index, evidence=contents.evidence, weight_sum=contents.weight_sum,
                           weighted_uncertainty_sum=contents.weighted_uncertainty_sum, hits=contents.hits, touched=contents.touched)

    def _check_tile(self, name: str, path: Path, contents: "map_file.MapContents") -> None:
        """Refuse a tile that does not belong to this store, naming what differs: another store's (its
        recorded identity, or its method, parameters, classes or frame), another tile's place, voxels
        changed since writing (the checksum), or a voxel count other than the index's."""
        def refuse(text: str):
            raise StoreError(f"{path}: {text}; this tile does not belong to the store {self.path}")

        record = contents.meta.get("tile")
        if record is not None and not (isinstance(record, dict) and all(isinstance(record.get(k), str) for k in ("store", "name", "checksum"))):
            refuse(f"meta.tile must name its store, tile and checksum, got {str(record)[:80]}")
        if contents.config != self.config or tuple(contents.meta["classes"]) != self.class_names:
            mine, theirs = self.config.as_dict(), contents.config.as_dict()
            differing = [f"{k} {theirs[k]!r} vs {mine[k]!r}" for k in mine if mine[k] != theirs[k]]
            refuse("its " + (", ".join(differing) if differing else f"classes {contents.meta['classes']} vs {list(self.class_names)}"))
        if contents.frame != self.frame:
            refuse(f"the tile is in {describe_frame(contents.frame)}, its store in {describe_frame(self.frame)}")
        if record is None and "identity" in self.index:
            refuse("it records no store (a tile of a store written before tiles recorded theirs, or a map file)")
        if record is not None:
            if record["store"] != self.identity:
                refuse(f"it was written for another store (identity {record['store'][:16]}..., this store's {self.identity[:16]}...: "
                       f"another origin, tiling or parameters)")
            if record["name"] != name:
                refuse(f"it is tile {record['name']}, not {name}")
        if len(contents.index) and (tile_keys(contents.index, self.tile_voxels) != parse_tile_name(name)).any():
            refuse(f"it holds voxels outside tile {name} (tile_voxels {self.tile_voxels})")
        voxels = VoxelArrays(index=contents.index, evidence=contents.evidence, weight_sum=contents.weight_sum,
                             weighted_uncertainty_sum=contents.weighted_uncertainty_sum, hits=contents.hits, touched=contents.touched)
        if record is not None and voxel_checksum(voxels) != record["checksum"]:
            refuse("its voxels do not match the checksum written with them (changed or damaged since)")
        expected = self.tiles[name]["voxels"]
        if len(contents.index) != expected:
            raise StoreError(f"{path}: {len(contents.index)} voxels, the index says {expected}")

    def voxel_index_of(self, points: np.ndarray) -> np.ndarray:
        """The global voxel index of each point, as the mapper that wrote the store computed it."""
        return voxel_index_of(points, self.config.resolution_m, self.template.grid_offset_m, self.template.origin_index)

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state at each point [M, 3], as ``Mapper.query``;
        only the tiles the points fall in are read."""
        from .mapper import _validate_points

        points = _validate_points(points, "query points", far_ok=True)
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
        """The store (or the voxels whose centres lie in ``bounds``) as one Mapper."""
        if bounds is not None:
            bounds = np.stack(check_bounds(bounds, "bounds"))
        parts = []
        for name in self.tiles_in(bounds):
            voxels = self.tile(name).voxels()[0]
            if bounds is not None:
                centres = self.template.voxel_centers(voxels.index)
                inside = np.all((centres >= bounds[0]) & (centres <= bounds[1]), axis=1)
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
            "voxels": self.voxel_count, "states": states, "scans_integrated": index["scans"], "points_integrated": index["points"],
            "inputs": index.get("inputs", []), "chunks": len(index.get("chunks", [])), "mapping": index["mapping"],
        }
