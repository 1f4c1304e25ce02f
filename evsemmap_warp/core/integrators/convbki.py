"""ConvBKI (docs/compatibility.md §2): the scan voxelised (``methods.convbki``), then each occupied voxel
scattered onto its per-class stencil (the scatter family's MODE_STENCIL)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ...config import MappingConfig, Media
from ...kernels import scatter as sc
from ...methods import convbki
from ..shards import ShardLanes, split_over_shards, total_updates
from ..voxel_map import VoxelMap
from .base import IntegrationStats, Launch, ScanNeeds, ScanPayload, integrate_at_launch
from .scatter import scatter


class ConvBkiIntegrator:
    """Points are voxelised first (evidence summed per voxel, as its authors do: softmax vectors, or
    label counts for one-hot media); each occupied voxel then scatters onto its stencil."""

    needs = ScanNeeds()
    grid_offset_m = 0.0

    def __init__(self, config: MappingConfig, num_classes: int):
        self.config = config
        if config.convbki.lengths_file:
            self.lengths = convbki.load_lengths(config.convbki.lengths_file, num_classes)
        else:
            self.lengths = convbki.default_lengths(num_classes)
        self.weights = convbki.stencil_weights(self.lengths, config.resolution_m, config.convbki.stencil_half)

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """``integrate_at_launch``."""
        return integrate_at_launch(self, scan)

    def kernel_modules(self, device: str) -> list:
        """The stencil scatter's module."""
        return [sc.scatter_kernel(sc.MODE_STENCIL, sc.FUSION_BAYES, False).module]

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, lanes: ShardLanes | None = None) -> IntegrationStats:
        """Voxelise one scan (evidence, uncertainty and counts summed per voxel) and scatter each occupied
        voxel onto its stencil in ``shards``; returns the insertion's stats."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points), kept_points=len(scan.points))
        if len(scan.points) == 0:
            return stats
        k = scan.num_classes
        evidence = np.eye(k)[scan.labels] if c.media is Media.ONEHOT else scan.probabilities
        voxels, summed = convbki.voxelise(scan.points, np.column_stack([evidence, scan.uncertainty, np.ones(len(evidence))]), c.resolution_m)
        centers = (voxels + 0.5) * c.resolution_m
        mean_uncertainty = summed[:, k] / summed[:, k + 1]

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            return scatter_stencil(shard, centers[part], np.full(len(part), c.resolution_m), mean_uncertainty[part], summed[part, :k],
                                   self.weights)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(centers), job))
        return stats


def scatter_stencil(shard: VoxelMap, centers: np.ndarray, lengths: np.ndarray, uncertainty: np.ndarray, class_weights: np.ndarray,
                    stencil_weights: np.ndarray) -> int:
    """Each point of ``centers`` [N, 3] (m) adds its class weights [N, K], times the stencil's weights
    [(2h + 1)^3, K] at each offset, to the voxels within h cells of its own (the scatter family's
    MODE_STENCIL) in ``shard``; returns updates."""
    side = round(len(stencil_weights) ** (1 / 3))
    if side**3 != len(stencil_weights) or side % 2 == 0:
        raise ValueError(f"stencil_weights must have (2h + 1)^3 rows, got {len(stencil_weights)}")
    if len(centers) == 0:
        return 0
    half = side // 2
    stencil = shard.staging.upload("stencil_weights", stencil_weights, wp.float64, np.float64)
    return scatter(shard, centers, lengths, uncertainty, mode=sc.MODE_STENCIL, sigma0=1.0, reach=(half + 1) * shard.resolution_m,
                   class_weights=class_weights, stencil_weights=stencil, stencil_half=half)
