"""Integrators: one job each, the map handed in. They turn a validated scan into kernel launches.

* ``KernelIntegrator``: the paper's clean algorithm (spec 3.11) for S-CSM, S-BKI, EBS and the
  ablations: optional per-insertion uncertainty threshold, optional adaptive length, one scatter.
* ``SbkiCompatIntegrator``: the original S-BKI / S-CSM C++ (reference_sbki.md section 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import sbki_compat
from .config import Kernel, MappingConfig, Media
from .kernels import scatter as sc
from .voxel_map import VoxelMap


@dataclass
class ScanPayload:
    """A validated scan: points [N, 3] float64 (world, m), class probabilities [N, K], input
    uncertainty [N] (K / S for alpha, 1 - max p for probabilities, 0 for labels), labels [N]."""

    points: np.ndarray
    probabilities: np.ndarray
    uncertainty: np.ndarray
    labels: np.ndarray


@dataclass
class IntegrationStats:
    input_points: int = 0
    kept_points: int = 0  # after the uncertainty threshold (clean) or as training points (sbki)
    voxel_updates: int = 0
    new_voxels: int = 0
    uncertainty_threshold: float | None = None


def uncertainty_quantile_mask(uncertainty: np.ndarray, keep_quantile: float) -> tuple[np.ndarray, float]:
    """Keep u <= t with t the floor(N q)-th smallest u (0-based, clamped to N - 1); ties are kept."""
    n = len(uncertainty)
    k = min(int(np.floor(n * keep_quantile)), n - 1)
    threshold = float(np.partition(uncertainty, k)[k])
    return uncertainty <= threshold, threshold


class KernelIntegrator:
    def __init__(self, config: MappingConfig):
        self.config = config

    def kernel_lengths(self, uncertainty: np.ndarray) -> np.ndarray:
        c = self.config
        if c.adaptive_length:
            return c.length_m * c.beta * np.exp(1.0 - c.gamma * uncertainty)
        return np.full(len(uncertainty), c.length_m)

    def integrate(self, voxel_map: VoxelMap, scan: ScanPayload) -> IntegrationStats:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep = np.ones(len(scan.points), dtype=bool)
        if c.uncertainty_threshold:
            keep, stats.uncertainty_threshold = uncertainty_quantile_mask(scan.uncertainty, c.keep_quantile)
        points, unc = scan.points[keep], scan.uncertainty[keep]
        stats.kept_points = len(points)
        before = voxel_map.voxel_count
        media = {"labels": scan.labels[keep]} if c.media is Media.ONEHOT else {"class_weights": scan.probabilities[keep]}
        if c.kernel is Kernel.COUNT:
            stats.voxel_updates = voxel_map.scatter(points, np.full(len(points), c.resolution_m), unc, mode=sc.MODE_OWN_VOXEL, sigma0=1.0, **media)
        else:
            stats.voxel_updates = voxel_map.scatter(points, self.kernel_lengths(unc), unc, mode=sc.MODE_RADIUS, sigma0=c.sigma0, **media)
        stats.new_voxels = voxel_map.voxel_count - before
        return stats


class SbkiCompatIntegrator:
    """S-BKI (sparse kernel) or S-CSM (count kernel, one-cell blocks on the half-shifted grid)."""

    def __init__(self, config: MappingConfig):
        self.config = config
        self.block_depth = 1 if config.kernel is Kernel.COUNT else config.block_depth
        self.cells_per_block = 2 ** (self.block_depth - 1)
        self.block_size = sbki_compat.block_size_m(config.resolution_m, self.block_depth)

    @staticmethod
    def grid_offset_m(config: MappingConfig) -> float:
        # S-CSM cells are centred on multiples of r (blocks of one cell), half a cell off the BKI grid.
        return -0.5 * config.resolution_m if config.kernel is Kernel.COUNT else 0.0

    def integrate(self, voxel_map: VoxelMap, scan: ScanPayload, sensor_origin: np.ndarray) -> IntegrationStats:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        points, labels, _ = sbki_compat.training_data(
            scan.points, scan.labels, sensor_origin,
            ds_resolution_m=c.ds_resolution_m, free_resolution_m=c.free_resolution_m, max_range_m=c.max_range_m,
        )
        stats.kept_points = len(points)
        if len(points) == 0:
            return stats
        point_ids, owners = sbki_compat.block_memberships(points, self.block_size)
        before = voxel_map.voxel_count
        is_csm = c.kernel is Kernel.COUNT
        voxel_map.insert_blocks(sbki_compat.test_blocks(owners), self.cells_per_block, mark_touched=not is_csm)
        stats.voxel_updates = voxel_map.scatter(
            points[point_ids].astype(np.float64),
            np.full(len(point_ids), c.resolution_m if is_csm else c.length_m),
            np.zeros(len(point_ids)),
            mode=sc.MODE_SBKI_OWN_BLOCK if is_csm else sc.MODE_SBKI_BLOCKS,
            sigma0=1.0 if is_csm else c.sigma0,
            labels=labels[point_ids],
            owner_blocks=owners,
            cells_per_block=self.cells_per_block,
        )
        stats.new_voxels = voxel_map.voxel_count - before
        return stats
