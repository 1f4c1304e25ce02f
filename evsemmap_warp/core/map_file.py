"""The map file: one ``.npz`` (no pickle), schema defined here and nowhere else.

Arrays (V voxels in ascending index order, K classes):
  centers [V, 3] float64 voxel centers (m)      voxel_index [V, 3] int64 global grid indices
  alpha [V, K] float64 concentrations            label [V] int32 argmax class (lowest on ties)
  evidence [V, K] float64 alpha - prior as accumulated (kept so that a round trip is exact)
  state [V] int8 0 UNKNOWN, 1 FREE, 2 OCCUPIED   variance [V] float64 variance of the label's class
  weight_sum [V] float64 sum of kernel weights   weighted_uncertainty_sum [V] float64 sum of weight * u
  hits [V] int64 number of contributions         touched [V] bool updated at least once
  resolution float64 (m)                         origin [3] float64 map origin (m), on the voxel lattice
  format_version int
  meta: JSON string with the classes, the method and all its parameters, the grid offset, the world
        frame ({"name", "crs"}: the frame centers and origin are in, docs/algorithm.md §6.6), provenance,
        scan_ids (the fingerprints of the scans the map holds, core/mapper.scan_fingerprint; optional:
        a merge refuses maps holding a scan in common) and, in a store's tile, tile (core/map_store.py).
Voxel i's center is (i + 0.5) * resolution + grid offset. A round trip is exact.

Reading validates the content, not only the shapes: every member's declared size against what the
file holds (before anything is allocated), finite non-negative evidence, unique integer indices within
the key range around the origin, the origin on the lattice, resolution and meta agreeing, meta keys
present with the right types. Version 1 files (float32 values, no origin) are read as well.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..config import ConfigError, MappingConfig
from ..frames import FrameError, WorldFrame
from ..voxel_keys import check_index_range

FORMAT_NAME = "evsemmap_warp.map"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
_PER_VOXEL = ("centers", "voxel_index", "alpha", "evidence", "label", "state", "variance", "weight_sum",
              "weighted_uncertainty_sum", "hits", "touched")
_REQUIRED = _PER_VOXEL + ("resolution", "format_version", "meta")
# meta key -> accepted types
_META_TYPES = {"format": (str,), "classes": (list,), "num_classes": (int,), "method": (str,), "mapping": (dict,),
               "grid_offset_m": (int, float), "scans_integrated": (int,), "points_integrated": (int,), "format_version": (int,)}
# How far an origin or a center may sit off the lattice and still count as on it (in voxels).
_LATTICE_TOLERANCE = 1e-6


class MapFileError(ValueError):
    """The map file is missing, corrupt, truncated, inconsistent or of another format version."""


@dataclass
class MapContents:
    """A map file's content, validated. ``index`` holds global voxel indices."""

    meta: dict
    origin: np.ndarray
    index: np.ndarray
    evidence: np.ndarray
    alpha: np.ndarray
    centers: np.ndarray
    summary: object  # DirichletSummary (label, probabilities, variance, state) when writing
    weight_sum: np.ndarray
    weighted_uncertainty_sum: np.ndarray
    hits: np.ndarray
    touched: np.ndarray
    resolution: float
    config: MappingConfig | None = None
    origin_index: np.ndarray | None = None
    frame: WorldFrame | None = None


def write_map_file(path, contents: MapContents) -> Path:
    """Write atomically (files.write_atomically: a temporary name in the same folder, then a rename), so
    that a killed writer never leaves a half-written file under the final name."""
    return files.write_atomically(Path(path), lambda f: write_npz(f, **file_arrays(contents)))


def file_arrays(contents: MapContents) -> dict[str, np.ndarray]:
    """The arrays a map file of ``contents`` holds (``read_map_arrays`` gives them back), in the schema's
    types: for readers that want a map file's arrays of a map that is not one (a store's tile)."""
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
        resolution=np.float64(contents.resolution),
        origin=np.asarray(contents.origin, np.float64),
        format_version=np.int64(FORMAT_VERSION),
        meta=np.array(json.dumps(meta)),
    )


def write_npz(file, **arrays: np.ndarray) -> None:
    """np.savez's format (an uncompressed zip of .npy members, readable by np.load) with fixed member
    timestamps, so that the same arrays give the same bytes: np.savez stamps each member with the
    time of writing, and stores and maps are compared byte for byte."""
    with zipfile.ZipFile(file, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            with archive.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def lattice_index(origin: np.ndarray, resolution: float) -> np.ndarray:
    """[3] int64: the voxel-lattice index nearest a map origin (m)."""
    return np.round(np.asarray(origin, np.float64) / resolution).astype(np.int64)


def _check_member_sizes(path: Path) -> None:
    """Refuse a member whose .npy header declares more data than the member holds (a lying or
    corrupt header would otherwise make numpy allocate it), or an object array (pickle)."""
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read_header(member)
                if dtype.hasobject:
                    raise MapFileError(f"{path}: member {info.filename!r} holds Python objects (pickle); map files never do")
                declared = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
                available = info.file_size - member.tell()
                if declared > available:
                    raise MapFileError(f"{path}: member {info.filename!r} declares shape {list(shape)} ({declared:,} bytes) "
                                       f"but holds {available:,} bytes: truncated or corrupt")


def read_map_arrays(path) -> tuple[dict[str, np.ndarray], dict]:
    """Every array of a map file and its parsed meta, validated (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise MapFileError(f"{path}: no such map file")
    try:
        _check_member_sizes(path)
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _REQUIRED if k not in data.files]
            if missing:
                raise MapFileError(f"{path}: not an evsemmap map file (missing {missing})")
            arrays = {k: data[k] for k in data.files}
    except MapFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MapFileError(f"{path}: corrupt or truncated map file ({type(exc).__name__}: {exc})") from None
    meta = _read_meta(path, arrays)
    version = int(meta["format_version"])
    if version == 1:
        arrays["origin"] = np.zeros(3)
    elif "origin" not in arrays:
        raise MapFileError(f"{path}: not an evsemmap map file (missing ['origin'])")
    _validate_arrays(path, arrays, meta)
    mapping_config(path, meta)
    return arrays, meta


def mapping_config(path, meta: dict) -> MappingConfig:
    """The map's MappingConfig from meta.mapping (flat keys of before the mode sections included), or a
    MapFileError naming what is wrong."""
    try:
        return MappingConfig.from_dict(meta["mapping"], "meta.mapping")
    except ConfigError as exc:
        raise MapFileError(f"{path}: field 'meta.mapping' is not a valid mapping config ({exc})") from None


def _read_meta(path: Path, arrays: dict) -> dict:
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as exc:
        raise MapFileError(f"{path}: field 'meta' is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise MapFileError(f"{path}: field 'meta' must be a JSON object, got {type(meta).__name__}")
    for key, types in _META_TYPES.items():
        if key not in meta:
            raise MapFileError(f"{path}: meta lacks the key {key!r}")
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, types):
            raise MapFileError(f"{path}: meta.{key} = {value!r} has the wrong type (expected {' or '.join(t.__name__ for t in types)})")
    if meta["format"] != FORMAT_NAME:
        raise MapFileError(f"{path}: meta.format is {meta['format']!r}, not {FORMAT_NAME!r}")
    file_version = arrays["format_version"]
    if file_version.shape != () or not np.issubdtype(file_version.dtype, np.integer) or int(file_version) != meta["format_version"]:
        raise MapFileError(f"{path}: format_version {file_version!r} disagrees with meta.format_version {meta['format_version']}")
    if meta["format_version"] not in READABLE_VERSIONS:
        raise MapFileError(f"{path}: map format version {meta['format_version']}; this evsemmap_warp reads versions "
                           f"{', '.join(map(str, READABLE_VERSIONS))}")
    if meta["num_classes"] < 2 or len(meta["classes"]) != meta["num_classes"] or not all(isinstance(c, str) for c in meta["classes"]):
        raise MapFileError(f"{path}: meta lists {len(meta['classes'])} class names for {meta['num_classes']} classes "
                           f"(names must be strings, at least 2 classes)")
    if meta["scans_integrated"] < 0 or meta["points_integrated"] < 0:
        raise MapFileError(f"{path}: meta.scans_integrated / points_integrated must be >= 0")
    ids = meta.get("scan_ids")  # optional: files written before maps recorded their scans have none
    if ids is not None and not (isinstance(ids, list) and all(isinstance(i, str) for i in ids) and len(set(ids)) == len(ids)):
        raise MapFileError(f"{path}: meta.scan_ids must be a list of distinct scan ids (strings), got {str(ids)[:80]}")
    try:  # optional: files written before maps recorded their world frame have none
        WorldFrame.from_dict(meta.get("frame"), f"{path}: meta.frame")
    except FrameError as exc:
        raise MapFileError(str(exc)) from None
    return meta


def _validate_arrays(path: Path, arrays: dict, meta: dict) -> None:
    def fail(text: str):
        raise MapFileError(f"{path}: {text}")

    v = len(arrays["voxel_index"]) if arrays["voxel_index"].ndim else -1
    k = meta["num_classes"]
    expected = {"centers": (v, 3), "voxel_index": (v, 3), "alpha": (v, k), "evidence": (v, k), "label": (v,), "state": (v,),
                "variance": (v,), "weight_sum": (v,), "weighted_uncertainty_sum": (v,), "hits": (v,), "touched": (v,),
                "resolution": (), "origin": (3,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            fail(f"field {name!r} has shape {list(arrays[name].shape)}, expected {list(shape)} ({v} voxels, {k} classes)")
    for name in ("voxel_index", "label", "state", "hits"):
        if not np.issubdtype(arrays[name].dtype, np.integer):
            fail(f"field {name!r} must hold integers, got {arrays[name].dtype}")
    for name in ("centers", "alpha", "evidence", "variance", "weight_sum", "weighted_uncertainty_sum", "resolution", "origin"):
        if not np.issubdtype(arrays[name].dtype, np.floating):
            fail(f"field {name!r} must hold floats, got {arrays[name].dtype}")
        bad = ~np.isfinite(arrays[name])
        if bad.any():
            fail(f"field {name!r} holds {int(bad.sum())} NaN/inf values")
    for name in ("evidence", "weight_sum", "hits"):
        if v and arrays[name].min() < 0:
            fail(f"field {name!r} holds negative values (min {arrays[name].min()}); evidence, weights and counts only grow")
    if v and (arrays["label"].min() < 0 or arrays["label"].max() >= k):
        fail(f"field 'label' holds values outside [0, {k - 1}]")
    if v and not np.isin(arrays["state"], (0, 1, 2)).all():
        fail("field 'state' holds values other than 0 (UNKNOWN), 1 (FREE), 2 (OCCUPIED)")
    resolution = float(arrays["resolution"])
    mapping = meta["mapping"]
    if not resolution > 0 or mapping.get("resolution_m") != resolution:
        fail(f"resolution {resolution} disagrees with meta.mapping.resolution_m {mapping.get('resolution_m')!r}")
    origin_index = lattice_index(arrays["origin"], resolution)
    if np.abs(arrays["origin"] / resolution - origin_index).max() > _LATTICE_TOLERANCE:
        fail(f"origin {arrays['origin'].tolist()} is not on the voxel lattice (a whole number of {resolution} m voxels)")
    index = arrays["voxel_index"].astype(np.int64)
    try:
        check_index_range(index - origin_index, "voxel indices")
    except ValueError as exc:
        fail(str(exc))
    if v:
        order = np.lexsort(index.T[::-1])
        sorted_index = index[order]
        repeated = np.all(sorted_index[1:] == sorted_index[:-1], axis=1)
        if repeated.any():
            fail(f"voxel index {sorted_index[1:][repeated][0].tolist()} appears more than once")
        centers = (index + 0.5) * resolution + float(meta["grid_offset_m"])
        if np.abs(centers - arrays["centers"]).max() > _LATTICE_TOLERANCE * resolution + 1e-9 * np.abs(centers).max():
            fail("field 'centers' disagrees with voxel_index, resolution and meta.grid_offset_m")


def read_map_file(path) -> MapContents:
    """A validated map file with its mapping config, ready to become a Mapper."""
    arrays, meta = read_map_arrays(path)
    config = mapping_config(path, meta)
    origin = arrays["origin"].astype(np.float64)
    return MapContents(
        meta=meta, origin=origin, index=arrays["voxel_index"].astype(np.int64), evidence=arrays["evidence"].astype(np.float64),
        alpha=arrays["alpha"], centers=arrays["centers"], summary=None, weight_sum=arrays["weight_sum"].astype(np.float64),
        weighted_uncertainty_sum=arrays["weighted_uncertainty_sum"].astype(np.float64), hits=arrays["hits"].astype(np.int64),
        touched=arrays["touched"].astype(bool), resolution=float(arrays["resolution"]), config=config,
        origin_index=lattice_index(origin, float(arrays["resolution"])), frame=WorldFrame.from_dict(meta.get("frame"), str(path)),
    )
