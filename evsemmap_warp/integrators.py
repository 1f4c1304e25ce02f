"""Integrators: one job each, the map handed in. They turn a validated scan into kernel launches.

* ``KernelIntegrator``: the paper's clean algorithm (spec 3.11) for S-CSM, S-BKI, EBS and the
  ablations: optional per-insertion uncertainty threshold, optional adaptive length, one scatter.
* ``SbkiCompatIntegrator``: the original S-BKI / S-CSM C++ (reference_sbki.md section 4).

Both receive the map as a list of shards. Warp runs a CPU launch on one core, so on the CPU each
worker thread scatters a contiguous part of the scan into its own shard (never a shared one: CPU
"atomics" are plain read-modify-writes); readers add the shards up (``sum_voxel_arrays``).
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from . import sbki_compat
from .config import Kernel, MappingConfig, Media
from .kernels import scatter as sc
from .voxel_map import VoxelMap

# Below this many points per shard, splitting a launch costs more than it saves.
MIN_POINTS_PER_SHARD = 4096


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
    uncertainty_threshold: float | None = None


def uncertainty_quantile_mask(uncertainty: np.ndarray, keep_quantile: float) -> tuple[np.ndarray, float]:
    """Keep u <= t with t the floor(N q)-th smallest u (0-based, clamped to N - 1); ties are kept."""
    n = len(uncertainty)
    k = min(int(np.floor(n * keep_quantile)), n - 1)
    threshold = float(np.partition(uncertainty, k)[k])
    return uncertainty <= threshold, threshold


def split_over_shards(shards: list[VoxelMap], executor: Executor | None, n: int, job) -> list:
    """Run job(shard, index_range) on contiguous parts of range(n), one part per shard, in parallel."""
    parts = max(1, min(len(shards), n // MIN_POINTS_PER_SHARD))
    if parts == 1 or executor is None:
        return [job(shards[0], np.arange(n))]
    return list(executor.map(job, shards[:parts], np.array_split(np.arange(n), parts)))


class KernelIntegrator:
    def __init__(self, config: MappingConfig):
        self.config = config

    def kernel_lengths(self, uncertainty: np.ndarray) -> np.ndarray:
        c = self.config
        if c.adaptive_length:
            return c.length_m * c.beta * np.exp(1.0 - c.gamma * uncertainty)
        return np.full(len(uncertainty), c.length_m)

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, executor: Executor | None = None) -> IntegrationStats:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep = np.ones(len(scan.points), dtype=bool)
        if c.uncertainty_threshold:
            keep, stats.uncertainty_threshold = uncertainty_quantile_mask(scan.uncertainty, c.keep_quantile)
        points, unc = scan.points[keep], scan.uncertainty[keep]
        stats.kept_points = len(points)
        onehot = c.media is Media.ONEHOT
        media = scan.labels[keep] if onehot else scan.probabilities[keep]
        if c.kernel is Kernel.COUNT:
            mode, sigma0, lengths = sc.MODE_OWN_VOXEL, 1.0, np.full(len(points), c.resolution_m)
        else:
            mode, sigma0, lengths = sc.MODE_RADIUS, c.sigma0, self.kernel_lengths(unc)

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            kw = {"labels": media[part]} if onehot else {"class_weights": media[part]}
            return shard.scatter(points[part], lengths[part], unc[part], mode=mode, sigma0=sigma0, **kw)

        stats.voxel_updates = sum(split_over_shards(shards, executor, len(points), job))
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

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, sensor_origin: np.ndarray, executor: Executor | None = None) -> IntegrationStats:
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
        is_csm = c.kernel is Kernel.COUNT

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            # Each shard holds the test blocks of its own points, so its targets are all present;
            # a block in several shards is or-ed to touched when they are added up.
            shard.insert_blocks(sbki_compat.test_blocks(owners[part]), self.cells_per_block, mark_touched=not is_csm)
            ids = point_ids[part]
            return shard.scatter(
                points[ids].astype(np.float64),
                np.full(len(ids), c.resolution_m if is_csm else c.length_m),
                np.zeros(len(ids)),
                mode=sc.MODE_SBKI_OWN_BLOCK if is_csm else sc.MODE_SBKI_BLOCKS,
                sigma0=1.0 if is_csm else c.sigma0,
                labels=labels[ids],
                owner_blocks=owners[part],
                cells_per_block=self.cells_per_block,
            )

        stats.voxel_updates = sum(split_over_shards(shards, executor, len(point_ids), job))
        return stats
