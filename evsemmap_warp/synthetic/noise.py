"""Smooth deterministic noise shared by the terrain and the surface patterns."""

from __future__ import annotations

import numpy as np


def value_noise(xy: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth pseudo-random field in [0, 1) at points ``xy`` [..., 2] (m), feature size ``scale`` (m):
    a hashed lattice, bilinearly blended with a smoothstep. Deterministic for a seed."""
    p = np.asarray(xy, np.float64) / scale
    cell = np.floor(p)
    f = p - cell
    f = f * f * (3 - 2 * f)
    i, j = cell[..., 0].astype(np.int64), cell[..., 1].astype(np.int64)

    def corner(di, dj):
        h = (i + di) * 374761393 + (j + dj) * 668265263 + seed * 2147483647
        h = (h ^ (h >> 13)) * 1274126177
        return ((h ^ (h >> 16)) & 0xFFFF) / 65536.0

    top = corner(0, 0) * (1 - f[..., 0]) + corner(1, 0) * f[..., 0]
    bottom = corner(0, 1) * (1 - f[..., 0]) + corner(1, 1) * f[..., 0]
    return top * (1 - f[..., 1]) + bottom * f[..., 1]
