"""numpy twin of ``evsemmap_warp.kernels.voxel_grid``."""

from __future__ import annotations

import numpy as np


def leaf_indices(points, inverse_leaf, lowest, leaves_x, leaves_y) -> np.ndarray:
    rel = np.floor(np.asarray(points, np.float32) * np.float32(inverse_leaf)).astype(np.int64) - np.asarray(lowest, np.int64)
    return rel[:, 0] + rel[:, 1] * leaves_x + rel[:, 2] * (leaves_x * leaves_y)


def leaf_centroids(points, order, starts, counts) -> np.ndarray:
    """Each leaf's float32 centroid from numpy's add.reduceat over the points in leaf order."""
    points = np.asarray(points, np.float32)
    if len(starts) == 0:
        return np.zeros((0, 3), np.float32)
    sums = np.add.reduceat(points[order], starts, axis=0, dtype=np.float32)
    return (sums / np.asarray(counts)[:, None].astype(np.float32)).astype(np.float32)
