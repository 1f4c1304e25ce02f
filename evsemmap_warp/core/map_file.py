"""The map file: one ``.npz`` (no pickle), schema defined here and nowhere else.

Arrays (V voxels in ascending index order, K classes):
  centers [V, 3] float64 voxel centres (m)      voxel_index [V, 3] int32 grid indices
  alpha [V, K] float32 concentrations            label [V] int32 argmax class (lowest on ties)
  evidence [V, K] float32 alpha - prior as accumulated (kept so that a round trip is exact)
  state [V] int8 0 UNKNOWN, 1 FREE, 2 OCCUPIED   variance [V] float32 variance of the label's class
  weight_sum [V] float32 sum of kernel weights   weighted_uncertainty_sum [V] float32 sum of weight * u
  hits [V] int32 number of contributions         touched [V] bool updated at least once
  resolution float64 (m)                         format_version int
  meta: JSON string with the classes, the method and all its parameters, the grid offset, provenance.
A round trip through ``save_map`` / ``load_map`` is exact.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from ..config import ConfigError, MappingConfig
from .voxel_map import VoxelArrays

FORMAT_NAME = "evsemmap_warp.map"
FORMAT_VERSION = 1
_REQUIRED = ("centers", "voxel_index", "alpha", "evidence", "label", "state", "variance", "weight_sum",
             "weighted_uncertainty_sum", "hits", "touched", "resolution", "format_version", "meta")


class MapFileError(ValueError):
    """The map file is missing, corrupt, truncated or of another format version."""


def save_map(path, mapper) -> Path:
    path = Path(path)
    arrays, summary = mapper.voxels()
    meta = mapper.metadata() | {"format_version": FORMAT_VERSION}
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:  # a file object keeps numpy from appending ".npz" to other names
        np.savez(
            f,
            centers=mapper.voxel_centers(arrays.index),
            voxel_index=arrays.index.astype(np.int32),
            alpha=mapper.concentrations(arrays.evidence),
            evidence=arrays.evidence,
            label=summary.label,
            state=summary.state,
            variance=summary.variance,
            weight_sum=arrays.weight_sum,
            weighted_uncertainty_sum=arrays.weighted_uncertainty_sum,
            hits=arrays.hits,
            touched=arrays.touched,
            resolution=np.float64(mapper.config.resolution_m),
            format_version=np.int64(FORMAT_VERSION),
            meta=np.array(json.dumps(meta)),
        )
    return path


def read_map_arrays(path) -> tuple[dict[str, np.ndarray], dict]:
    """Every array of a map file and its parsed meta, validated against the schema."""
    path = Path(path)
    if not path.exists():
        raise MapFileError(f"{path}: no such map file")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _REQUIRED if k not in data.files]
            if missing:
                raise MapFileError(f"{path}: not an evsemmap map file (missing {missing})")
            arrays = {k: data[k] for k in data.files}
    except MapFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise MapFileError(f"{path}: corrupt or truncated map file ({type(exc).__name__}: {exc})") from None
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as exc:
        raise MapFileError(f"{path}: field 'meta' is not valid JSON ({exc})") from None
    version = int(arrays["format_version"])
    if meta.get("format") != FORMAT_NAME or version != FORMAT_VERSION or meta.get("format_version") != FORMAT_VERSION:
        raise MapFileError(f"{path}: map format version {version} ({meta.get('format')!r}); this evsemmap_warp reads version {FORMAT_VERSION}")
    v = len(arrays["voxel_index"])
    k = int(meta["num_classes"])
    expected = {"centers": (v, 3), "voxel_index": (v, 3), "alpha": (v, k), "evidence": (v, k), "label": (v,), "state": (v,),
                "variance": (v,), "weight_sum": (v,), "weighted_uncertainty_sum": (v,), "hits": (v,), "touched": (v,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise MapFileError(f"{path}: field {name!r} has shape {list(arrays[name].shape)}, expected {list(shape)} ({v} voxels, {k} classes)")
    if len(meta["classes"]) != k:
        raise MapFileError(f"{path}: meta lists {len(meta['classes'])} class names for {k} classes")
    return arrays, meta


def load_map(path, *, device: str | None = "cpu"):
    from .mapper import Mapper

    arrays, meta = read_map_arrays(path)
    try:
        config = MappingConfig(**{k: v for k, v in _config_fields(meta["mapping"]).items()})
    except (ConfigError, TypeError) as exc:
        raise MapFileError(f"{path}: field 'meta.mapping' is not a valid mapping config ({exc})") from None
    mapper = Mapper(config, int(meta["num_classes"]), class_names=meta["classes"], device=device)
    mapper.load_voxels(
        VoxelArrays(
            index=arrays["voxel_index"].astype(np.int64),
            evidence=arrays["evidence"].astype(np.float32),
            weight_sum=arrays["weight_sum"].astype(np.float32),
            weighted_uncertainty_sum=arrays["weighted_uncertainty_sum"].astype(np.float32),
            hits=arrays["hits"].astype(np.int32),
            touched=arrays["touched"].astype(bool),
        )
    )
    mapper.scans_integrated = int(meta.get("scans_integrated", 0))
    mapper.points_integrated = int(meta.get("points_integrated", 0))
    return mapper


def _config_fields(mapping: dict) -> dict:
    from dataclasses import fields

    from ..config import Compat, Fusion, Kernel, Media

    enums = {"kernel": Kernel, "media": Media, "compat": Compat, "fusion": Fusion}
    known = {f.name for f in fields(MappingConfig)}
    unknown = set(mapping) - known
    if unknown:
        raise TypeError(f"unknown parameters {sorted(unknown)}")
    return {k: (enums[k](v) if k in enums else v) for k, v in mapping.items()}
