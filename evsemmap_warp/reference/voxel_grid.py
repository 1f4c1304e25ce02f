"""numpy twins of ``evsemmap_warp.kernels.voxel_grid``."""

from __future__ import annotations

import numpy as np


def leaf_indices(points, inverse_leaf, lowest, leaves_x, leaves_y) -> np.ndarray:
    """Twin of ``kernels.voxel_grid.leaf_indices``: each point's VoxelGrid leaf index, floor(p *
    inverse_leaf) - lowest per axis in float32, x fastest [N] int64."""
    rel = np.floor(np.asarray(points, np.float32) * np.float32(inverse_leaf)).astype(np.int64) - np.asarray(lowest, np.int64)
    return rel[:, 0] + rel[:, 1] * leaves_x + rel[:, 2] * (leaves_x * leaves_y)


def leaf_centroids(points, order, starts, counts) -> np.ndarray:
    """Each leaf's float32 centroid: its points in leaf order added one by one in float32 (from zero, as
    PCL's CentroidPoint does; np.add.accumulate is sequential, np.add.reduce pairwise), over the count."""
    points = np.asarray(points, np.float32)[np.asarray(order, np.int64)]
    sums = np.zeros((len(starts), 3), np.float32)
    for leaf, (start, count) in enumerate(zip(np.asarray(starts, np.int64), np.asarray(counts, np.int64))):
        sums[leaf] = np.add.accumulate(np.vstack([np.zeros((1, 3), np.float32), points[start:start + count]]), axis=0, dtype=np.float32)[-1]
    return (sums / np.asarray(counts)[:, None].astype(np.float32)).astype(np.float32)


def leaf_majority_labels(sorted_labels, starts, counts) -> np.ndarray:
    """Twin of ``kernels.voxel_grid.leaf_majority_labels``: each leaf's most frequent label among
    sorted_labels[start:start + count], the smallest on ties [L] int64."""
    sorted_labels = np.asarray(sorted_labels, np.int64)
    majority = np.empty(len(starts), np.int64)
    for leaf, (start, count) in enumerate(zip(np.asarray(starts, np.int64), np.asarray(counts, np.int64))):
        values, votes = np.unique(sorted_labels[start:start + count], return_counts=True)
        majority[leaf] = values[np.argmax(votes)]  # unique sorts ascending; argmax takes the first maximum
    return majority
