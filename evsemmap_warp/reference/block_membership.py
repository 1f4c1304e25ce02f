"""numpy twin of ``evsemmap_warp.kernels.block_membership``."""

from __future__ import annotations

import numpy as np


def block_membership_masks(points: np.ndarray, size: np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``kernels.block_membership.block_membership_masks``: each point's nearest block (float64
    rounding of p / size) [N, 3] and the 27-bit mask of the blocks around it whose closed float32 box
    holds it [N]."""
    points = np.asarray(points, np.float32)
    size = np.float32(size)
    half = np.float32(size / np.float32(2.0))
    nearest = np.floor(points.astype(np.float64) / np.float64(size) + 0.5).astype(np.int64)
    masks = np.zeros(len(points), np.int64)
    for bit, shift in enumerate((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)):
        center = ((nearest + np.array(shift)).astype(np.float32) * size).astype(np.float32)
        inside = ((center - half <= points) & (points <= center + half)).all(axis=1)
        masks[inside] |= 1 << bit
    return nearest, masks


def membership_counts(masks: np.ndarray) -> np.ndarray:
    """[27] how many masks have each bit set."""
    masks = np.asarray(masks, np.int64)
    return np.array([((masks >> bit) & 1).sum() for bit in range(27)], np.int64)


def membership_pairs(nearest: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(point ids [M], blocks [M, 3]) of every set bit of the masks: shift by shift in bit order,
    points ascending within a shift (``membership_counts`` and ``membership_pairs`` together)."""
    nearest, masks = np.asarray(nearest, np.int64).reshape(-1, 3), np.asarray(masks, np.int64)
    point_ids, blocks = [], []
    for bit, shift in enumerate((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)):
        ids = np.flatnonzero((masks >> bit) & 1)
        point_ids.append(ids)
        blocks.append(nearest[ids] + np.array(shift))
    return np.concatenate(point_ids), np.concatenate(blocks).reshape(-1, 3)


def membership_masks_parallel(points, size, count: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of ``membership_masks_parallel``: ``block_membership_masks`` of the first ``count`` points (None:
    all) and each point's pair count, 0 past them."""
    points = np.asarray(points)
    count = len(points) if count is None else count
    nearest, masks = block_membership_masks(points[:count], size)
    pair_counts = np.array([bin(int(m)).count("1") for m in masks], np.int32)
    return nearest, masks, np.r_[pair_counts, np.zeros(len(points) - count, np.int32)]


def membership_pairs_by_point(masks, first_pair, capacity: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``membership_pairs_by_point``: (bit, point) of every set bit, point by point, bits ascending,
    the first ``capacity`` of them (None: all)."""
    pairs = [(bit, i) for i, mask in enumerate(np.asarray(masks, np.int64)) for bit in range(27) if (int(mask) >> bit) & 1]
    assert len(pairs) == (int(first_pair[len(masks) - 1]) + bin(int(masks[-1])).count("1") if len(masks) else 0)
    pairs = pairs[:capacity]
    return np.array([b for b, _ in pairs], np.int64), np.array([i for _, i in pairs], np.int64)


def membership_blocks(bits, point_ids, nearest) -> np.ndarray:
    """Twin of ``membership_blocks``: each pair's block, its point's nearest block + its bit's shift [M, 3]."""
    bits = np.asarray(bits, np.int64)
    shifts = np.stack([bits // 9 - 1, (bits // 3) % 3 - 1, bits % 3 - 1], axis=1)
    return np.asarray(nearest, np.int64)[np.asarray(point_ids, np.int64)] + shifts
