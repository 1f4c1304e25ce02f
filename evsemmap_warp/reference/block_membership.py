"""numpy twin of ``evsemmap_warp.kernels.block_membership``."""

from __future__ import annotations

import numpy as np


def block_membership_masks(points: np.ndarray, size: np.float32) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points, np.float32)
    size = np.float32(size)
    half = np.float32(size / np.float32(2.0))
    nearest = np.floor(points.astype(np.float64) / np.float64(size) + 0.5).astype(np.int64)
    masks = np.zeros(len(points), np.int64)
    for bit, shift in enumerate((x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)):
        centre = ((nearest + np.array(shift)).astype(np.float32) * size).astype(np.float32)
        inside = ((centre - half <= points) & (points <= centre + half)).all(axis=1)
        masks[inside] |= 1 << bit
    return nearest, masks
