"""Plain point files: PCD (our reader), PLY (trimesh), npy and KITTI-style .bin, through one call.

``read_point_file`` returns the points and every per-point field the file carries (PCD fields, PLY
vertex properties, npy columns beyond xyz as ``values``, .bin intensity)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .pcd import read_pcd

POINT_SUFFIXES = (".pcd", ".ply", ".npy", ".bin")


@dataclass
class PointFile:
    """A point file's content: points [N, 3] float64 (m, the file's own frame), per-point extra fields ([N]
    or [N, C]) and the path."""

    points: np.ndarray  # [N, 3] float64
    fields: dict[str, np.ndarray]  # per-point extras, [N] or [N, C]
    path: Path


def _check_points(points: np.ndarray, path: Path) -> np.ndarray:
    if len(points) == 0:
        raise ValueError(f"{path}: holds no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {len(points)} points have NaN or inf coordinates, first at row {int(np.flatnonzero(bad)[0])}")
    return points


def read_kitti_bin(path) -> np.ndarray:
    """KITTI-style .bin scan -> [N, 4] float32 (x, y, z, intensity), zero returns included."""
    size = Path(path).stat().st_size
    if size % 16:
        raise ValueError(f"{path}: {size} bytes is not a whole number of 16-byte (x, y, z, intensity) float32 points; truncated?")
    scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    bad = ~np.isfinite(scan[:, :3]).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {len(scan)} points have NaN or inf coordinates, first at row {int(np.flatnonzero(bad)[0])}")
    return scan


def read_npy(path) -> np.ndarray:
    """One .npy array, refusing what np.load would accept or crash on: an .npz archive under an .npy
    name, an empty or truncated file, pickled objects."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic.startswith(b"PK"):
        raise ValueError(f"{path}: is an .npz archive (zip), not an .npy array; rename it or save the array with np.save")
    if magic != b"\x93NUMPY":
        raise ValueError(f"{path}: not an .npy array ({'empty file' if not magic else 'no NUMPY header'})")
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise ValueError(f"{path}: not a readable npy array ({exc})") from None
    if data.dtype.kind not in "biuf":  # complex: the imaginary part would be dropped without a word
        raise ValueError(f"{path}: holds {data.dtype} values; point and pose files hold real numbers")
    return data


def read_point_file(path) -> PointFile:
    """Read a .pcd, .ply (vertex x, y, z and any other vertex properties), .npy ([N, >= 3]) or KITTI .bin
    ([N, 4] float32) file. Raises ValueError naming the file for an unknown suffix, a truncated or
    malformed file, or NaN/inf coordinates, and FileNotFoundError when it does not exist."""
    path = Path(path)
    if path.suffix not in POINT_SUFFIXES:
        raise ValueError(f"{path}: unknown point file type {path.suffix!r}; known: {', '.join(POINT_SUFFIXES)}")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such point file")
    if path.suffix == ".pcd":
        cloud = read_pcd(path)
        fields = {k: v for k, v in cloud.fields.items() if k not in ("x", "y", "z")}
        return PointFile(_check_points(cloud.points.astype(np.float64), path), fields, path)
    if path.suffix == ".bin":
        raw = read_kitti_bin(path)
        return PointFile(_check_points(raw[:, :3].astype(np.float64), path), {"intensity": raw[:, 3]}, path)
    if path.suffix == ".npy":
        data = read_npy(path)
        if data.ndim != 2 or data.shape[1] < 3 or not np.issubdtype(data.dtype, np.number):
            raise ValueError(f"{path}: expected an [N, >=3] array (x y z, then per-point values), got shape {list(data.shape)}")
        fields = {"values": data[:, 3:]} if data.shape[1] > 3 else {}
        return PointFile(_check_points(data[:, :3].astype(np.float64), path), fields, path)
    else:  # .ply
        import trimesh

        try:
            loaded = trimesh.load(path, process=False)
        except Exception as exc:  # trimesh raises many types for a broken file
            raise ValueError(f"{path}: not a readable PLY ({type(exc).__name__}: {exc})") from None
        raw = loaded.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
        names = tuple(raw.keys()) if isinstance(raw, dict) else (raw.dtype.names or ()) if raw is not None else ()
        if all(a in names for a in "xyz"):
            # the raw vertex table: trimesh's own vertex list may drop or merge NaN rows
            vertices = np.stack([np.asarray(raw[a], np.float64).reshape(-1) for a in "xyz"], axis=1)
        else:
            vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
        fields = {name: np.asarray(raw[name]).reshape(len(vertices), -1).squeeze(1) if np.asarray(raw[name]).size == len(vertices)
                  else np.asarray(raw[name]) for name in names if name not in ("x", "y", "z")}
        return PointFile(_check_points(vertices, path), fields, path)
