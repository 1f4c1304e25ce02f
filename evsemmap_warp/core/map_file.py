"""The map file, schema defined here and nowhere else. Format version 3 (written now) holds what a map
needs once, compressed as a store's tiles are (core/tile_codec.py's columns in one zstd frame):

  MAGIC (8 bytes), a little-endian uint32 header length, a JSON header, then the payload.
  header: format, format_version, voxels V, columns (K + 5), resolution (m), origin [3] (m, on the voxel
          lattice), index_low [3] and index_extent [3] (the voxels' global indices lie in
          index_low .. index_low + index_extent - 1), payload_bytes, payload_crc32, and meta.
  payload: tile_codec.compress_columns of the indices minus index_low and the [V, K + 5] sums of
          ``VoxelArrays.rows()`` (evidence, weight sum, weighted-uncertainty sum, contribution count,
          weighted height sum, touched), voxels in ascending key order (x, then y, then z index), each once.
  meta: classes, the method and all its parameters, the grid offset, the world frame ({"name", "crs"}:
        the frame centers and origin are in, docs/algorithm.md §6.6), provenance and scan_ids (the
        fingerprints of the scans the map holds, core/mapper.scan_fingerprint; optional: a merge refuses
        maps holding a scan in common).

Centers, concentrations (alpha), labels, states and variance are derived on reading, as a Mapper derives
them (``file_arrays`` gives every array of a map, derived ones included; ``read_map_file`` does not derive
them). Voxel i's center is (i + 0.5) * resolution + grid offset. A round trip is exact.

Reading validates the content, not only the shapes: every declared size against what the file holds
(before anything of that size is allocated), finite non-negative sums, unique integer indices within
the key range around the origin, in key order, the origin on the lattice, resolution and meta agreeing,
meta keys present with the right types. A file of another format version (the ``.npz`` of every array
that versions 1 and 2 were) is refused, naming its version.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..config import ConfigError, MappingConfig
from ..frames import FrameError, WorldFrame
from ..kernels.scatter import COL_HITS, COL_WEIGHT, COL_WEIGHTED_HEIGHT, COL_WEIGHTED_UNCERTAINTY
from ..voxel_keys import check_index_range, pack_voxel_keys
from . import tile_codec
from .voxel_map import EXTRA_COLUMNS, VoxelArrays

FORMAT_NAME = "evsemmap_warp.map"
FORMAT_VERSION = 3
MAGIC = b"EVSMMAP3"
_HEADER_LIMIT = 1 << 26  # a header beyond 64 MB (meta with its scan ids) is not one this writes
# meta key -> accepted types
_META_TYPES = {"format": (str,), "classes": (list,), "num_classes": (int,), "method": (str,), "mapping": (dict,),
               "grid_offset_m": (int, float), "scans_integrated": (int,), "points_integrated": (int,), "format_version": (int,)}
# How far an origin or a center may sit off the lattice and still count as on it (in voxels).
_LATTICE_TOLERANCE = 1e-6


class MapFileError(ValueError):
    """The map file is missing, corrupt, truncated, inconsistent or of another format version."""


@dataclass
class MapContents:
    """A map file's content, validated. ``index`` holds global voxel indices. The read-out (``alpha``,
    ``centers``, ``summary``) is derived, not stored: None where no one asked for it (``core.mapper.with_read_out``)."""

    meta: dict
    origin: np.ndarray
    index: np.ndarray
    evidence: np.ndarray
    weight_sum: np.ndarray
    weighted_uncertainty_sum: np.ndarray
    hits: np.ndarray
    touched: np.ndarray
    weighted_height_sum: np.ndarray
    resolution: float
    config: MappingConfig | None = None
    origin_index: np.ndarray | None = None
    frame: WorldFrame | None = None
    alpha: np.ndarray | None = None
    centers: np.ndarray | None = None
    summary: object = None  # DirichletSummary (label, probabilities, variance, state)

    def voxels(self) -> VoxelArrays:
        """The stored sums as VoxelArrays (global indices)."""
        return VoxelArrays(index=self.index, evidence=self.evidence, weight_sum=self.weight_sum,
                           weighted_uncertainty_sum=self.weighted_uncertainty_sum, hits=self.hits, touched=self.touched,
                           weighted_height_sum=self.weighted_height_sum)


def write_map_file(path, contents: MapContents) -> Path:
    """Write atomically (files.write_atomically: a temporary name in the same folder, then a rename), so
    that a killed writer never leaves a half-written file under the final name."""
    data = encode_map(contents)
    return files.write_atomically(Path(path), lambda f: f.write(data))


def encode_map(contents: MapContents) -> bytes:
    """A version-3 map file's bytes: the header and the compressed sums of ``contents`` (the read-out
    is not stored). The same contents give the same bytes."""
    voxels = contents.voxels()
    index = np.asarray(voxels.index, np.int64).reshape(-1, 3)
    if len(index) > 1 and np.any(np.diff(pack_voxel_keys(index - lattice_index(contents.origin, contents.resolution))) <= 0):
        order = np.lexsort(index.T[::-1])  # key order, as a Mapper's voxels come
        voxels = VoxelArrays.from_rows(index[order], voxels.rows()[order])
        index = voxels.index
    low = index.min(axis=0) if len(index) else np.zeros(3, np.int64)
    extent = index.max(axis=0) - low + 1 if len(index) else np.ones(3, np.int64)
    dtype = np.dtype(tile_codec.index_dtype(int(extent.max())))
    columns = voxels.evidence.shape[1] + EXTRA_COLUMNS
    total = 3 * len(index) * dtype.itemsize + (columns - 1) * len(index) * 8 + (len(index) + 7) // 8
    payload = tile_codec.compress_parts(_payload_parts(voxels, low, dtype), total)
    header = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "voxels": len(index), "columns": columns,
              "resolution": float(contents.resolution), "origin": [float(v) for v in contents.origin],
              "index_low": [int(v) for v in low], "index_extent": [int(v) for v in extent], "payload_bytes": len(payload),
              "payload_crc32": zlib.crc32(payload), "meta": contents.meta | {"format_version": FORMAT_VERSION}}
    return tile_codec.framed(MAGIC, header, payload)


def _payload_parts(voxels: VoxelArrays, low: np.ndarray, dtype: np.dtype):
    """tile_codec.compress_columns's payload of ``voxels`` (indices minus ``low``), one column at a time:
    a map's save holds one column beside the compressed bytes, not copies of the whole map."""
    for axis in range(3):
        yield (voxels.index[:, axis] - low[axis]).astype(dtype)
    for values in (*voxels.evidence.T, voxels.weight_sum, voxels.weighted_uncertainty_sum, voxels.hits, voxels.weighted_height_sum):
        yield np.ascontiguousarray(values, "<f8")
    yield np.packbits(np.asarray(voxels.touched, bool))


def file_arrays(contents: MapContents) -> dict[str, np.ndarray]:
    """Every array of a map (V voxels, K classes), derived ones included, of ``contents`` with its read-out
    (``core.mapper.with_read_out``): for readers that want them all (``core.mapper.read_map_arrays``).

      centers [V, 3] float64                         voxel_index [V, 3] int64 global grid indices
      alpha [V, K] float64 concentrations            label [V] int32 argmax class (lowest on ties)
      evidence [V, K] float64 alpha - prior          state [V] int8 0 UNKNOWN, 1 FREE, 2 OCCUPIED
      variance [V] float64 of the label's class      weight_sum, weighted_uncertainty_sum [V] float64
      hits [V] int64 number of contributions         touched [V] bool updated at least once
      weighted_height_sum [V] float64 sum of weight * (z - the voxel center's z) (m; 0 in the compat modes)
      resolution float64 (m)                         origin [3] float64 (m)
      format_version int                             meta: JSON string, as the file's
    """
    meta = contents.meta | {"format_version": FORMAT_VERSION}
    return dict(
        centers=contents.centers,
        voxel_index=contents.index.astype(np.int64),
        alpha=contents.alpha.astype(np.float64),
        evidence=contents.evidence.astype(np.float64),
        label=contents.summary.label.astype(np.int32),
        state=contents.summary.state.astype(np.int8),
        variance=contents.summary.variance.astype(np.float64),
        weight_sum=contents.weight_sum.astype(np.float64),
        weighted_uncertainty_sum=contents.weighted_uncertainty_sum.astype(np.float64),
        hits=contents.hits.astype(np.int64),
        touched=contents.touched.astype(bool),
        weighted_height_sum=contents.weighted_height_sum.astype(np.float64),
        resolution=np.float64(contents.resolution),
        origin=np.asarray(contents.origin, np.float64),
        format_version=np.int64(FORMAT_VERSION),
        meta=np.array(json.dumps(meta)),
    )


def lattice_index(origin: np.ndarray, resolution: float) -> np.ndarray:
    """[3] int64: the voxel-lattice index nearest a map origin (m)."""
    return np.round(np.asarray(origin, np.float64) / resolution).astype(np.int64)


def read_map_file(path) -> MapContents:
    """A validated map file with its mapping config, ready to become a Mapper; its read-out is not
    derived (``core.mapper.with_read_out``). A file of another format is refused in one line."""
    path = Path(path)
    if not is_compact(path):
        version = _npz_format_version(path)
        if version is not None:
            raise MapFileError(f"{path}: map format version {version}; this evsemmap_warp reads version {FORMAT_VERSION} only "
                               f"(map the data again with it)")
        raise MapFileError(f"{path}: not an evsemmap map file (a version-{FORMAT_VERSION} map file begins with {MAGIC.decode()})")
    return _read_compact(path)


def _npz_format_version(path: Path) -> int | None:
    """The format version an ``.npz`` map of versions 1 and 2 states in its format_version member, or None
    when ``path`` is no such file (the member is read only when it is a scalar's few bytes)."""
    try:
        with zipfile.ZipFile(path) as archive:
            info = archive.getinfo("format_version.npy")
            if info.file_size > 1024:
                return None
            with archive.open(info) as member:
                value = np.lib.format.read_array(member, allow_pickle=False)
    except (zipfile.BadZipFile, KeyError, OSError, ValueError, EOFError):
        return None
    return int(value) if value.shape == () and np.issubdtype(value.dtype, np.integer) else None


def is_compact(path: Path) -> bool:
    """Whether ``path`` begins with a version-3 map file's signature."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read the map file ({exc.strerror})") from None


def _read_compact(path: Path) -> MapContents:
    """A version-3 file, validated: header, payload size and checksums, sizes before decompressing, then
    the voxels and the meta."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read the map file ({exc.strerror})") from None
    header, start = _compact_header(path, data)
    meta = _check_meta(path, header["meta"], header["format_version"])
    count, columns, low, extent = header["voxels"], header["columns"], header["index_low"], header["index_extent"]
    k = meta["num_classes"]
    if columns == k + EXTRA_COLUMNS - 1:
        raise MapFileError(f"{path}: {columns} columns for {k} classes, without the weighted height sum this evsemmap_warp's maps "
                           f"hold (K + {EXTRA_COLUMNS}): a map written before it; map the data again")
    if columns != k + EXTRA_COLUMNS:
        raise MapFileError(f"{path}: header says {columns} columns, {k} classes need {k + EXTRA_COLUMNS}")
    try:
        payload = data[start:]
        tile_codec.check_payload(payload, header, path)
        local, rows = tile_codec.decompress_columns(payload, count, columns, tile_codec.index_dtype(max(extent)), path)
    except tile_codec.VoxelFileError as exc:
        raise MapFileError(f"corrupt or truncated map file: {exc}") from None
    del data, payload
    if count and np.any(local.max(axis=0) >= extent):
        raise MapFileError(f"{path}: voxel indices beyond the header's index_extent {extent}")
    _check_sums(path, rows)
    voxels = VoxelArrays.from_rows(local + np.asarray(low, np.int64), rows)
    del local, rows
    contents = MapContents(meta=meta, origin=np.asarray(header["origin"], np.float64), index=voxels.index, evidence=voxels.evidence,
                           weight_sum=voxels.weight_sum, weighted_uncertainty_sum=voxels.weighted_uncertainty_sum, hits=voxels.hits,
                           touched=voxels.touched, weighted_height_sum=voxels.weighted_height_sum, resolution=float(header["resolution"]),
                           config=mapping_config(path, meta),
                           frame=WorldFrame.from_dict(meta.get("frame"), str(path)))
    _validate_compact(path, contents)
    return contents


def _compact_header(path: Path, data: bytes) -> tuple[dict, int]:
    """A version-3 file's header (its keys present, of the right types) and where its payload starts."""
    def fail(text):
        raise MapFileError(f"{path}: corrupt or truncated map file: {text}")

    header, start = tile_codec.split_framed(data, MAGIC, _HEADER_LIMIT, fail)
    for key in ("format_version", "voxels", "columns", "payload_bytes", "payload_crc32"):
        value = header.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise MapFileError(f"{path}: header key {key!r} = {value!r} must be a whole number >= 0")
    for key, kind in (("index_low", int), ("index_extent", int), ("origin", (int, float))):
        value = header.get(key)
        if not (isinstance(value, list) and len(value) == 3 and all(isinstance(v, kind) and not isinstance(v, bool) for v in value)):
            raise MapFileError(f"{path}: header key {key!r} = {str(value)[:80]} must be three numbers")
    if min(header["index_extent"]) < 1:
        raise MapFileError(f"{path}: header key 'index_extent' = {header['index_extent']} must be at least 1 per axis")
    resolution = header.get("resolution")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, float)):
        raise MapFileError(f"{path}: header key 'resolution' = {resolution!r} must be a number")
    if header.get("format") != FORMAT_NAME:
        raise MapFileError(f"{path}: header format is {header.get('format')!r}, not {FORMAT_NAME!r}")
    if not isinstance(header.get("meta"), dict):
        raise MapFileError(f"{path}: field 'meta' must be a JSON object, got {type(header.get('meta')).__name__}")
    return header, start


def _check_sums(path: Path, rows: np.ndarray) -> None:
    """Refuse NaN/inf sums ([V, K + 5] as ``VoxelArrays.rows()``), negative ones (all but the signed
    weighted height sum), or counts that are not whole."""
    k = rows.shape[1] - EXTRA_COLUMNS
    fields = {"evidence": rows[:, :k], "weight_sum": rows[:, k + COL_WEIGHT], "weighted_uncertainty_sum": rows[:, k + COL_WEIGHTED_UNCERTAINTY],
              "hits": rows[:, k + COL_HITS], "weighted_height_sum": rows[:, k + COL_WEIGHTED_HEIGHT]}
    for name, values in fields.items():
        bad = ~np.isfinite(values)
        if bad.any():
            raise MapFileError(f"{path}: field {name!r} holds {int(bad.sum())} NaN/inf values")
        if name != "weighted_height_sum" and values.size and values.min() < 0:
            raise MapFileError(f"{path}: field {name!r} holds negative values (min {values.min()}); evidence, weights and counts only grow")
    if np.any(fields["hits"] != np.floor(fields["hits"])):
        raise MapFileError(f"{path}: field 'hits' holds values that are not whole numbers")


def _validate_compact(path: Path, contents: MapContents) -> None:
    """What a version-3 file's sums, indices, origin and resolution must satisfy (its sizes and order of
    reading are checked before)."""
    def fail(text: str):
        raise MapFileError(f"{path}: {text}")

    _check_lattice(path, contents.meta, contents.resolution, contents.origin)
    contents.origin_index = lattice_index(contents.origin, contents.resolution)
    local = contents.index - contents.origin_index
    try:
        check_index_range(local, "voxel indices")
    except ValueError as exc:
        fail(str(exc))
    if len(local) > 1:
        steps = np.diff(pack_voxel_keys(local))
        if np.any(steps <= 0):
            at = int(np.flatnonzero(steps <= 0)[0]) + 1
            what = "appears more than once" if steps[at - 1] == 0 else "is out of key order (x, then y, then z)"
            fail(f"voxel index {contents.index[at].tolist()} {what}")


def _check_lattice(path: Path, meta: dict, resolution: float, origin: np.ndarray) -> None:
    """Refuse a resolution other than meta.mapping's, or an origin off the voxel lattice."""
    mapping = meta["mapping"]
    if not resolution > 0 or mapping.get("resolution_m") != resolution:
        raise MapFileError(f"{path}: resolution {resolution} disagrees with meta.mapping.resolution_m {mapping.get('resolution_m')!r}")
    if not np.isfinite(origin).all():
        raise MapFileError(f"{path}: field 'origin' holds NaN/inf values")
    origin_index = lattice_index(origin, resolution)
    if np.abs(origin / resolution - origin_index).max() > _LATTICE_TOLERANCE:
        raise MapFileError(f"{path}: origin {origin.tolist()} is not on the voxel lattice (a whole number of {resolution} m voxels)")


def mapping_config(path, meta: dict) -> MappingConfig:
    """The map's MappingConfig from meta.mapping, or a MapFileError naming what is wrong."""
    try:
        return MappingConfig.from_dict(meta["mapping"], "meta.mapping")
    except ConfigError as exc:
        raise MapFileError(f"{path}: field 'meta.mapping' is not a valid mapping config ({exc})") from None


def _check_meta(path: Path, meta: dict, file_version: int) -> dict:
    """``meta`` checked: every key of the right type, the format and this version agreeing with the
    file's own ``file_version``, classes, counts, scan ids and frame."""
    for key, types in _META_TYPES.items():
        if key not in meta:
            raise MapFileError(f"{path}: meta lacks the key {key!r}")
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, types):
            raise MapFileError(f"{path}: meta.{key} = {value!r} has the wrong type (expected {' or '.join(t.__name__ for t in types)})")
    if meta["format"] != FORMAT_NAME:
        raise MapFileError(f"{path}: meta.format is {meta['format']!r}, not {FORMAT_NAME!r}")
    if file_version != meta["format_version"]:
        raise MapFileError(f"{path}: format_version {file_version!r} disagrees with meta.format_version {meta['format_version']}")
    if meta["format_version"] != FORMAT_VERSION:
        raise MapFileError(f"{path}: map format version {meta['format_version']}; this evsemmap_warp reads version {FORMAT_VERSION} "
                           f"only (map the data again with it)")
    if meta["num_classes"] < 2 or len(meta["classes"]) != meta["num_classes"] or not all(isinstance(c, str) for c in meta["classes"]):
        raise MapFileError(f"{path}: meta lists {len(meta['classes'])} class names for {meta['num_classes']} classes "
                           f"(names must be strings, at least 2 classes)")
    if meta["scans_integrated"] < 0 or meta["points_integrated"] < 0:
        raise MapFileError(f"{path}: meta.scans_integrated / points_integrated must be >= 0")
    ids = meta.get("scan_ids")  # null or absent: a map that does not know its scans
    if ids is not None and not (isinstance(ids, list) and all(isinstance(i, str) for i in ids) and len(set(ids)) == len(ids)):
        raise MapFileError(f"{path}: meta.scan_ids must be a list of distinct scan ids (strings), got {str(ids)[:80]}")
    try:  # null: a map of no known world frame
        WorldFrame.from_dict(meta.get("frame"), f"{path}: meta.frame")
    except FrameError as exc:
        raise MapFileError(str(exc)) from None
    return meta
