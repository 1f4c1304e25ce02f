"""What a map knows: a voxel is known when its evidence, summed over classes, is at least a threshold (the
layers' ``min_evidence``, LayerSettings). Below it a voxel holds only the tails of kernels centered elsewhere:
its class probabilities are nearly the prior's. The layers, the viewer, ``evsemmap info`` and the exports all ask
this module, so that "known" means one thing wherever a map is read."""

from __future__ import annotations

import numpy as np


def evidence_sums(evidence: np.ndarray) -> np.ndarray:
    """[V] float64: each voxel's evidence [V, K] summed over its classes (what ``is_known`` compares)."""
    return np.asarray(evidence, np.float64).sum(axis=1)


def is_known(sums: np.ndarray, min_evidence: float) -> np.ndarray:
    """[V] bool: the voxels whose evidence sums (``evidence_sums``) reach ``min_evidence``."""
    return np.asarray(sums, np.float64) >= min_evidence
