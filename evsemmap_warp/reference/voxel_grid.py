"""numpy twins of ``evsemmap_warp.kernels.voxel_grid``."""

from __future__ import annotations

import numpy as np

from .device_counts import PAST_COUNT_KEY


def leaf_indices(points, inverse_leaf, lowest, leaves_x, leaves_y, count: int | None = None) -> np.ndarray:
    """Twin of ``kernels.voxel_grid.leaf_indices``: each of the first ``count`` points' (None: all) VoxelGrid
    leaf index, floor(p * inverse_leaf) - lowest per axis in float32, x fastest, then ``PAST_COUNT_KEY`` [N] int64."""
    points = np.asarray(points, np.float32)
    count = len(points) if count is None else count
    rel = np.floor(points[:count] * np.float32(inverse_leaf)).astype(np.int64) - np.asarray(lowest, np.int64)
    leaf = rel[:, 0] + rel[:, 1] * leaves_x + rel[:, 2] * (leaves_x * leaves_y)
    return np.r_[leaf, np.full(len(points) - count, PAST_COUNT_KEY, np.int64)]


def packed_leaf_indices(points, inverse_leaf, lowest, leaves_x, leaves_y, position_bits: int) -> np.ndarray:
    """Twin of ``packed_leaf_indices``: each point's leaf index << position_bits | its position [N] int64."""
    return (leaf_indices(points, inverse_leaf, lowest, leaves_x, leaves_y) << position_bits) | np.arange(len(points), dtype=np.int64)


def leaf_centroids(points, order, starts, counts) -> np.ndarray:
    """Each leaf's float32 centroid: its points in leaf order added one by one in float32 (from zero, as
    PCL's CentroidPoint does; np.add.accumulate is sequential, np.add.reduce pairwise), over the count."""
    points = np.asarray(points, np.float32)[np.asarray(order, np.int64)]
    sums = np.zeros((len(starts), 3), np.float32)
    for leaf, (start, count) in enumerate(zip(np.asarray(starts, np.int64), np.asarray(counts, np.int64))):
        sums[leaf] = np.add.accumulate(np.vstack([np.zeros((1, 3), np.float32), points[start:start + count]]), axis=0, dtype=np.float32)[-1]
    return (sums / np.asarray(counts)[:, None].astype(np.float32)).astype(np.float32)


def leaf_centroids_of_sorted(points, packed, position_bits: int) -> np.ndarray:
    """Twin of ``leaf_centroids_of_sorted``: ``leaf_centroids`` of the runs of equal leaves among sorted
    packed values (leaf << position_bits | position) [L, 3]."""
    packed = np.asarray(packed, np.int64)
    keys = packed >> position_bits
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])[:len(packed)]
    return leaf_centroids(points, packed & ((1 << position_bits) - 1), starts, np.diff(np.r_[starts, len(packed)]))


def point_bounds(points, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``point_bounds``: the first ``count`` points' (None: all) per-axis float32 minimum and maximum
    [3], [3] (+inf, -inf for none)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)[:count]
    return points.min(axis=0, initial=np.inf), points.max(axis=0, initial=-np.inf)


def positions(n: int) -> np.ndarray:
    """Twin of ``positions``: 0 .. n - 1 (int64)."""
    return np.arange(n, dtype=np.int64)


def leaf_runs(sorted_leaf, count: int | None = None) -> np.ndarray:
    """Twin of ``leaf_runs``: 1 where one of the first ``count`` (None: all) sorted positions starts a new
    leaf, 0 elsewhere [N] (int32)."""
    sorted_leaf = np.asarray(sorted_leaf, np.int64)
    count = len(sorted_leaf) if count is None else count
    counted = sorted_leaf[:count]
    heads = np.r_[True, counted[1:] != counted[:-1]].astype(np.int32)[:count]
    return np.r_[heads, np.zeros(len(sorted_leaf) - count, np.int32)]


def leaf_starts(leaf_rank, count: int | None = None) -> np.ndarray:
    """Twin of ``leaf_starts``: each leaf's first sorted position among the first ``count`` (None: all), then
    that count [L + 1] (int64), from the inclusive scan of ``leaf_runs``."""
    leaf_rank = np.asarray(leaf_rank, np.int64)[:count]
    return np.r_[np.flatnonzero(np.diff(np.r_[0, leaf_rank]) != 0), len(leaf_rank)].astype(np.int64)


def leaf_centroids_parallel(points, order, starts, leaf_count: int) -> np.ndarray:
    """Twin of ``leaf_centroids_parallel``: ``leaf_centroids`` of the leaves starts[:leaf_count + 1] bound."""
    starts = np.asarray(starts, np.int64)[:leaf_count + 1]
    return leaf_centroids(points, order, starts[:-1], np.diff(starts))


def leaf_label_keys(order, leaf_rank, labels, label_min: int, label_span: int, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``leaf_label_keys``: (leaf number * label_span + label - label_min of each of the first ``count``
    (None: all) sorted positions, then ``PAST_COUNT_KEY``; the positions) [N], [N] (int64)."""
    order = np.asarray(order, np.int64)
    count = len(order) if count is None else count
    labels = np.asarray(labels, np.int64)[order[:count]]
    keys = (np.asarray(leaf_rank, np.int64)[:count] - 1) * label_span + labels - label_min
    return np.r_[keys, np.full(len(order) - count, PAST_COUNT_KEY, np.int64)], np.arange(len(order), dtype=np.int64)


def leaf_majority_labels(sorted_keys, starts, leaf_count: int, label_min: int, label_span: int) -> np.ndarray:
    """Twin of ``leaf_majority_labels``: each leaf's most frequent label among its sorted keys'
    labels (key % label_span + label_min), the smallest on ties [L] (int64)."""
    labels = np.asarray(sorted_keys, np.int64) % label_span + label_min
    starts = np.asarray(starts, np.int64)
    majority = np.empty(leaf_count, np.int64)
    for leaf in range(leaf_count):
        values, votes = np.unique(labels[starts[leaf]:starts[leaf + 1]], return_counts=True)
        majority[leaf] = values[np.argmax(votes)]  # unique sorts ascending; argmax takes the first maximum
    return majority
