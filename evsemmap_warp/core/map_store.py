"""The map store: one map as a folder of spatial tiles, for maps larger than one file or one
process's memory (written by ``evsemmap batch``, read here).

    STORE/store.json        the index: format and version, resolution, float64 origin, grid offset,
                            the world frame (name, CRS), classes, method and every mapping parameter, tile size, per-tile voxel
                            counts and bounds, the inputs and the chunks the map holds
    STORE/tiles/X_Y_Z.npz   one tile's voxels in the map-file schema (core/map_file.py): tile (X, Y, Z)
                            holds the voxels whose global index // tile_voxels is (X, Y, Z)
    STORE/work/             a batch run's partial maps (one folder per chunk), kept so that a rerun
                            resumes instead of starting over

Every file is written under a temporary name and renamed, so a killed writer never leaves a file that
looks whole; files hold no pickle, and the same content gives the same bytes. Opening a store reads
the index only; a query loads the tiles its points fall in, nothing else.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .. import files
from ..config import MappingConfig, dataclass_from_dict
from ..frames import FrameError, WorldFrame, describe_frame
from ..voxel_keys import voxel_index_of
from . import map_file
from .mapper import Mapper, QueryResult, UNKNOWN_LABEL, VoxelState
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
    keys = tile_keys(index, tile_voxels)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(unique) + 1))
    parts = {}
    for t, key in enumerate(unique):
        rows_of_tile = order[bounds[t]:bounds[t + 1]]
        parts[tile_name(key)] = (index[rows_of_tile], rows[rows_of_tile])
    return dict(sorted(parts.items()))


# ``write(file)`` into a temporary name beside ``path``, then renamed into place (the package's one writer).
write_atomically = files.write_atomically


def write_json(path: Path, data) -> Path:
    """The store's JSON files (store.json, plan.json, done.json): indented, keys sorted, a final newline."""
    return files.write_json_atomically(path, data, indent=1, sort_keys=True)


def write_partial(path: Path, index: np.ndarray, rows: np.ndarray) -> Path:
    """A partial map's voxels (global indices and [V, K + 4] rows), for reduction."""
    return write_atomically(path, lambda f: map_file.write_npz(f, index=np.asarray(index, np.int64), rows=np.asarray(rows, np.float64)))


def read_partial(path: Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            index, rows = data["index"], data["rows"]
    except (OSError, ValueError, KeyError) as exc:
        raise StoreError(f"{path}: not a readable partial map ({type(exc).__name__}: {exc})") from None
    if index.ndim != 2 or index.shape[1] != 3 or rows.shape != (len(index), columns) or not np.isfinite(rows).all():
        raise StoreError(f"{path}: a partial map needs index [V, 3] and finite rows [V, {columns}], got {index.shape} and {rows.shape}")
    return index, rows


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


def write_tile(path: Path, template: Mapper, voxels: VoxelArrays, totals: dict) -> Path:
    """One tile in the map-file schema; ``template`` (an empty Mapper with the store's config and
    origin) gives the read-out, ``totals`` the whole map's scan and point counts."""
    summary = template.summarize(voxels.evidence, voxels.touched)
    meta = template.metadata() | {"scans_integrated": int(totals["scans"]), "points_integrated": int(totals["points"])}
    contents = map_file.MapContents(
        meta=meta, origin=template.origin, index=voxels.index, evidence=voxels.evidence, alpha=template.concentrations(voxels.evidence),
        centers=template.voxel_centers(voxels.index), summary=summary, weight_sum=voxels.weight_sum,
        weighted_uncertainty_sum=voxels.weighted_uncertainty_sum, hits=voxels.hits, touched=voxels.touched,
        resolution=template.config.resolution_m)
    return map_file.write_map_file(path, contents)


class MapStore:
    """An opened store: its index, and tiles loaded on demand (the ``cache_tiles`` most recently used
    are kept)."""

    def __init__(self, path, *, cache_tiles: int = 16):
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
        self.template = template_mapper(self.config, self.class_names, self.index["origin_index"], self.frame)
        self._cache: OrderedDict[str, Mapper] = OrderedDict()
        self.cache_tiles = cache_tiles
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
            if not isinstance(index.get(key), kind):
                raise StoreError(f"{where}: key {key!r} missing or not a {kind.__name__}")
        if index["tile_voxels"] < 1:
            raise StoreError(f"{where}: tile_voxels {index['tile_voxels']} must be >= 1")
        for name, info in index["tiles"].items():
            parse_tile_name(name)
            if not isinstance(info, dict) or not isinstance(info.get("voxels"), int):
                raise StoreError(f"{where}: tile {name} has no voxel count")

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
        if name not in self.tiles:
            raise StoreError(f"{self.path}: no tile {name}")
        try:
            mapper = Mapper.load(self.tile_path(name))
        except (map_file.MapFileError, OSError, ValueError) as exc:
            raise StoreError(f"{self.tile_path(name)}: {exc}") from None
        if mapper.frame != self.frame:
            raise StoreError(f"{self.tile_path(name)}: the tile is in {describe_frame(mapper.frame)}, its store in {describe_frame(self.frame)}")
        expected = self.tiles[name]["voxels"]
        if mapper.voxel_count != expected:
            raise StoreError(f"{self.tile_path(name)}: {mapper.voxel_count} voxels, the index says {expected}")
        self.tiles_loaded += 1
        self._cache[name] = mapper
        while len(self._cache) > self.cache_tiles:
            self._cache.popitem(last=False)
        return mapper

    def voxel_index_of(self, points: np.ndarray) -> np.ndarray:
        """The global voxel index of each point, as the mapper that wrote the store computed it."""
        return voxel_index_of(points, self.config.resolution_m, self.template.grid_offset_m, self.template.origin_index)

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state at each point [M, 3], as ``Mapper.query``;
        only the tiles the points fall in are read."""
        from .mapper import _validate_points

        points = _validate_points(points, "query points")
        m = len(points)
        label = np.full(m, UNKNOWN_LABEL, np.int32)
        probabilities = np.zeros((m, self.num_classes))
        variance = np.zeros(m)
        state = np.full(m, int(VoxelState.UNKNOWN), np.int8)
        voxel_index = self.voxel_index_of(points)
        # one name per tile met, not per point: queries may hold millions of points
        keys, inverse = np.unique(tile_keys(voxel_index, self.tile_voxels), axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        met = {tile_name(key): t for t, key in enumerate(keys)}
        for name in sorted(set(met) & set(self.tiles)):
            rows = np.flatnonzero(inverse == met[name])
            result = self.tile(name).query(points[rows])
            label[rows], probabilities[rows], variance[rows], state[rows] = result.label, result.probabilities, result.variance, result.state
        return QueryResult(label, probabilities, variance, state, voxel_index)

    def tiles_in(self, bounds: np.ndarray | None) -> list[str]:
        """Tiles whose voxel bounds meet the box [[x0, y0, z0], [x1, y1, z1]] (m); all without one."""
        if bounds is None:
            return sorted(self.tiles)
        low, high = np.asarray(bounds, np.float64)
        return sorted(name for name, info in self.tiles.items()
                      if np.all(np.asarray(info["bounds_m"][1]) >= low) and np.all(np.asarray(info["bounds_m"][0]) <= high))

    def to_mapper(self, bounds=None) -> Mapper:
        """The store (or the voxels whose centres lie in ``bounds``) as one Mapper."""
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
