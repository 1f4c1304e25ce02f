"""SEE-CSOM (docs/compatibility.md §3): its training data, per-block statistics that pick each point's
target blocks and lengths (``methods.see_csom``), then the block-gated scatter
(``kernels.scatter.scatter_block_targets``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ...config import MappingConfig
from ...kernels import free_space, load_once, radix_sort, voxel_grid
from ...kernels import scatter as sc
from ...methods import sbki_compat, see_csom
from ...voxel_keys import column_bounds
from ..shards import split_over_shards, total_updates
from ..voxel_map import VoxelMap
from .base import IntegrationStats, Launch, ScanPayload, free_samples_need, launch_step


class SeeCsomIntegrator:
    """Training data as its code builds it (VoxelGrid with majority labels, the sensor origin as the
    one free sample: its configs' free_resolution of 1000 m), then block statistics and the scatter."""

    grid_offset_m = 0.0

    def __init__(self, config: MappingConfig, num_classes: int):
        self.config = config
        self.num_classes = num_classes
        self.needs = free_samples_need(config.method)

    def kernel_modules(self, device: str) -> list:
        """The training data's modules, then the block-targets scatter's."""
        return [voxel_grid, radix_sort, free_space, sc]

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Training data and block statistics (host work, no map access); the launch scatters."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        points, labels, _ = sbki_compat.training_data(scan.points, scan.labels, scan.sensor_origin, ds_resolution_m=c.sbki.ds_resolution_m,
                                                      free_resolution_m=1000.0, max_range_m=c.sbki.max_range_m)
        points = points.astype(np.float64)
        stats.kept_points = len(points)
        if len(points) == 0:
            return launch_step(stats)
        owners, lengths = see_csom.block_targets(points, labels, self.num_classes, c.resolution_m)
        unc = np.zeros(len(points))

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            return scatter_block_targets(shard, points[part], labels[part], unc[part], owners[part], lengths[part], see_csom.CELLS_PER_BLOCK)

        return launch_step(stats, lambda shards, lanes: total_updates(split_over_shards(shards, lanes, len(points), job)))


def scatter_block_targets(shard: VoxelMap, points: np.ndarray, labels: np.ndarray, point_uncertainty: np.ndarray,
                          owner_blocks: np.ndarray, target_lengths: np.ndarray, cells_per_block: int) -> int:
    """SEE-CSOM's block-gated scatter (``kernels.scatter.scatter_block_targets``); returns updates."""
    n = len(points)
    if n == 0:
        return 0
    lo, hi = column_bounds(np.asarray(owner_blocks, np.int64))
    shard.check_block_range(np.stack([lo - 1, hi + 1]), cells_per_block)  # a point's targets: its owner block's neighbours
    load_once(sc, shard.device)
    d = shard.device
    upload = shard.staging.upload
    scan = sc.scan_points(points=upload("points", np.reshape(points, (-1, 3)), wp.vec3d, np.float64), labels=upload("labels", labels, wp.int32, np.int32),
                          uncertainty=upload("uncertainty", point_uncertainty, wp.float64, np.float64),
                          owner_blocks=upload("owner_blocks", owner_blocks, wp.vec3i, np.int32))
    lengths = upload("target_lengths", target_lengths, wp.float64, np.float64)
    params = sc.scatter_params(resolution=shard.resolution_m, grid_offset=shard.grid_offset_m, cells_per_block=cells_per_block)

    def launch(ids, failed):
        scan.point_ids = ids
        wp.launch(sc.scatter_block_targets, dim=len(ids), device=d, inputs=[scan, lengths, params, shard.target(failed)])

    return shard.launch_until_done(n, launch, may_insert=True, kind="block_targets", most_new=n * 7 * cells_per_block**3,
                                   fails_only_when_full=True, resumes=True)
