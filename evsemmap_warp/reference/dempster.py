"""Sequential numpy reference of the Dempster-Shafer method (docs/algorithm.md §3.7), point by point in the order
given, exactly as the rule is written: the engine's order-free log-commonality formulation
(kernels/scatter.py, fusion 1) is held against it. Not a kernel twin (no kernel of this name)."""

from __future__ import annotations

import numpy as np

from .scatter import BELIEF_EPSILON, sparse_kernel


def fuse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dempster's rule on singleton masses a, b [K] with the rest on the frame."""
    ua, ub = 1.0 - a.sum(), 1.0 - b.sum()
    conflict = a.sum() * b.sum() - (a * b).sum()  # sum over i != j of a_i b_j
    return np.clip((a * b + a * ub + b * ua) / (1.0 - conflict), 0.0, 1.0 - BELIEF_EPSILON)


def dempster_map(points: np.ndarray, beliefs: np.ndarray, lengths: np.ndarray, voxels: np.ndarray,
                 resolution: float, sigma0: float) -> np.ndarray:
    """Masses [V, K] of ``voxels`` [V, 3] (indices) after fusing, for each voxel, every point within its
    kernel length, discounted by min(k, 1), one after another (the voxel starts vacuous)."""
    centers = (np.asarray(voxels, np.float64) + 0.5) * resolution
    out = np.zeros((len(voxels), beliefs.shape[1]))
    for v, center in enumerate(centers):
        masses = np.zeros(beliefs.shape[1])
        for p, b, length in zip(points, beliefs, lengths):
            d = np.linalg.norm(center - p)
            if d < length:
                w = min(float(sparse_kernel(np.array([d]), np.array([length]), sigma0)[0]), 1.0)
                masses = fuse(masses, np.clip(b * w, 0.0, 1.0 - BELIEF_EPSILON))
        out[v] = masses
    return out
