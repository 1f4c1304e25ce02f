"""Host side of the hash table's key layout (``kernels/hash_table.py`` defines it): voxel indices
relative to the map origin, 21 bits per axis, packed into one int64. Packing refuses indices outside
the key range instead of wrapping them onto voxels near the origin."""

from __future__ import annotations

import numpy as np

from .kernels.hash_table import KEY_BITS, KEY_OFFSET
from .limits import INDEX_LIMIT  # the key range, beside the other limits (its value is the key layout's)


# Rows folded into one for column_bounds: numpy reduces along axis 0 fast over wide rows only (on the
# bench's [700 k, 3] float32 free samples about a third of the time of a pass per column).
_FOLDED_ROWS = 256


def column_bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column minimum and maximum of a [N, D] array (N > 0; NaN where a column holds one): the same as
    min/max(axis=0), which numpy runs much slower on narrow arrays. The rows are folded _FOLDED_ROWS at a
    time into wide rows, each reduced in one pass, then the folds and the rows left over."""
    values = np.asarray(values)
    columns = values.shape[1]
    folded = len(values) - len(values) % _FOLDED_ROWS
    parts = [values[folded:]] if folded < len(values) else []
    if folded:
        wide = np.ascontiguousarray(values[:folded]).reshape(-1, columns * _FOLDED_ROWS)
        parts += [np.minimum.reduce(wide, axis=0).reshape(-1, columns), np.maximum.reduce(wide, axis=0).reshape(-1, columns)]
    stacked = np.concatenate(parts)
    return (np.array([stacked[:, d].min() for d in range(columns)], dtype=values.dtype),
            np.array([stacked[:, d].max() for d in range(columns)], dtype=values.dtype))


def take_rows(values: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """values[rows] for an [N, ...] array and integer row indices: np.take, which copies rows of a few numbers
    faster than fancy indexing."""
    return np.take(values, rows, axis=0)


def within_index_range(index: np.ndarray) -> bool:
    """Whether every index [..., 3] lies in [-INDEX_LIMIT, INDEX_LIMIT)."""
    index = np.asarray(index)
    return not index.size or (int(index.min()) >= -INDEX_LIMIT and int(index.max()) < INDEX_LIMIT)


def check_index_range(index: np.ndarray, what: str = "voxel indices", resolution_m: float | None = None) -> None:
    """Raise ValueError when any index [..., 3] lies outside [-INDEX_LIMIT, INDEX_LIMIT)."""
    index = np.asarray(index)
    if not within_index_range(index):
        span = "" if resolution_m is None else (f": one map spans at most +-{INDEX_LIMIT * resolution_m:.0f} m around its origin "
                                                f"at {resolution_m} m voxels (split the data into maps of separate areas)")
        raise ValueError(f"{what} reach {int(index.min())}..{int(index.max())}, outside the key range "
                         f"[{-INDEX_LIMIT}, {INDEX_LIMIT}) voxels around the map origin{span}")


def voxel_index_of(points: np.ndarray, resolution_m: float, grid_offset_m: float, origin_index) -> np.ndarray:
    """[M, 3] int64 global voxel index of each world point [M, 3]: floor((p - origin - offset) / r) +
    origin_index with origin = origin_index * r, the arithmetic of the kernels (which see points
    relative to the map origin, in float64). Everything that asks "which voxel holds this point"
    (queries of maps and stores, tile routing) asks here, so that a point on a voxel or tile face far
    from (0, 0, 0) gets the voxel the mapper wrote. NaN/inf give 0 (callers reject them first)."""
    origin_index = np.asarray(origin_index, np.int64).reshape(3)
    origin = origin_index.astype(np.float64) * resolution_m
    with np.errstate(invalid="ignore", over="ignore"):
        local = np.floor((np.asarray(points, np.float64).reshape(-1, 3) - origin - grid_offset_m) / resolution_m)
    return np.nan_to_num(local, posinf=0, neginf=0).clip(-2**62, 2**62).astype(np.int64) + origin_index


def pack_voxel_keys(index: np.ndarray) -> np.ndarray:
    """[V, 3] voxel indices -> the table's int64 keys; their order is x, then y, then z index."""
    check_index_range(index)
    index = np.asarray(index, dtype=np.int64) + KEY_OFFSET
    return (index[:, 0] << 42) | (index[:, 1] << 21) | index[:, 2]


def unpack_voxel_keys(keys: np.ndarray) -> np.ndarray:
    """The voxel indices [N, 3] int64 that packed keys [N] hold (the inverse of ``pack_voxel_keys``)."""
    field = (1 << KEY_BITS) - 1
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([(keys >> 42) & field, (keys >> 21) & field, keys & field], axis=1) - KEY_OFFSET
