"""The original S-BKI and S-CSM C++ (``mapping.compat: sbki``, docs/compatibility.md §1): training data
with free samples, block memberships (``methods.sbki_compat``), then S-BKI's block gather
(``kernels.block_gather``, its preprocessing on the map's device on a GPU, ``methods.sbki_device``) or
S-CSM's own-block counts (the test blocks' cells inserted, then the scatter family's MODE_SBKI_OWN_BLOCK)."""

from __future__ import annotations

from typing import Callable

import numpy as np
import warp as wp

from ...config import Kernel, MappingConfig
from ...kernels import block_gather, block_membership, device_counts, free_space, load_once, radix_sort, voxel_grid
from ...kernels import scatter as sc
from ...methods import sbki_compat, sbki_device
from ...methods.device_scratch import STATUS_OVERFLOW, DeviceScratch, ScratchPool
from ...voxel_keys import column_bounds, take_rows
from ..shards import PendingUpdates, split_over_shards, total_updates
from ..voxel_map import VoxelMap
from .base import IntegrationStats, Launch, ScanPayload, free_samples_need, launch_step, preprocesses_on_device
from .gathers import block_gather_run, counted_gather_launch
from .scatter import scatter


class SbkiCompatIntegrator:
    """S-BKI (sparse kernel) or S-CSM (count kernel, one-cell blocks on the half-shifted grid)."""

    def __init__(self, config: MappingConfig, num_classes: int | None = None):
        self.config = config
        self.needs = free_samples_need(config.method)
        self.block_depth = 1 if config.kernel is Kernel.COUNT else config.sbki.block_depth
        self.cells_per_block = 2 ** (self.block_depth - 1)
        self.block_size = sbki_compat.block_size_m(config.resolution_m, self.block_depth)
        # S-CSM cells are centered on multiples of r (blocks of one cell), half a cell off the BKI grid.
        self.grid_offset_m = -0.5 * config.resolution_m if config.kernel is Kernel.COUNT else 0.0
        # kernel factory (class count, cells per block) -> the S-BKI gather kernel; the study swaps in other forms
        self.gather_kernel = block_gather.gather_sbki_kernel
        # Where the S-BKI kernel's preprocessing runs: True, on the map's device by parallel kernels
        # (methods.sbki_device); False, on the host by one-thread kernels, one scan per worker, which is
        # faster on a CPU, where a launch runs on one core whatever its form; None, on the device for a
        # GPU map. The same map either way (tests/test_sbki_device.py sets True on the CPU).
        self.preprocess_on_device: bool | None = None
        self._scratch = ScratchPool()  # the device path's arrays, kept from scan to scan
        self.num_classes = num_classes

    def kernel_modules(self, device: str) -> list:
        """The training data's and memberships' modules, then the gather tables' and gather kernel's (S-BKI)
        or the block cells' insertion and the own-block scatter (S-CSM)."""
        training = [voxel_grid, radix_sort, free_space, block_membership, device_counts]
        if self.config.kernel is Kernel.COUNT:
            return training + [sc, sc.scatter_kernel(sc.MODE_SBKI_OWN_BLOCK, sc.FUSION_BAYES, True).module]
        gather = [] if self.num_classes is None else [self.gather_kernel(self.num_classes, self.cells_per_block).module]
        return training + [block_gather] + gather

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Training data, block memberships and the gather tables (host work, no map access; on the
        map's device for the S-BKI kernel on a GPU); the launch runs the kernels."""
        c = self.config
        on_device = preprocesses_on_device(self, device)
        if on_device and c.kernel is Kernel.SPARSE:
            return self._prepare_on_device(scan, device)
        points, labels, _ = sbki_compat.training_data(
            scan.points, scan.labels, scan.sensor_origin,
            ds_resolution_m=c.sbki.ds_resolution_m, free_resolution_m=c.sbki.free_resolution_m, max_range_m=c.sbki.max_range_m,
        )
        return self._launch_from_training_set(IntegrationStats(input_points=len(scan.points)), points, labels, device, scan.check_room)

    def _launch_from_training_set(self, stats: IntegrationStats, points: np.ndarray, labels: np.ndarray, device: str,
                                  check_room: Callable[[int], None] | None = None) -> Launch:
        """The host path from the training set on: block memberships, then the gather tables or the counts."""
        stats.kept_points = len(points)
        if len(points) == 0:
            return launch_step(stats)
        point_ids, owners = sbki_compat.block_memberships(points, self.block_size)
        if self.config.kernel is Kernel.COUNT:
            return launch_step(stats, lambda shards, lanes: self._scatter_counts(shards, points, labels, point_ids, owners, lanes))
        return launch_step(stats, self._gather_sparse(points, labels, point_ids, owners, device, check_room))

    def _prepare_on_device(self, scan: ScanPayload, device: str) -> Launch:
        """``prepare`` for the S-BKI kernel with the preprocessing on the map's device: the gather kernel's
        inputs never leave it, and no count is read back (``counted_gather_launch``). Blocks too spread for the
        dense grid: the host path from the training set. The arrays are a set of the integrator's scratch
        pool, held until the launch is done."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        if len(scan.points) == 0:
            stats.kept_points = 0
            return launch_step(stats)
        box = sbki_device.training_box(scan.points, scan.sensor_origin, c.sbki.ds_resolution_m)

        def build(scratch: DeviceScratch):
            points, labels = sbki_device.training_set(*sbki_device.training_arrays(
                scan.points, scan.labels, scan.sensor_origin, ds_resolution_m=c.sbki.ds_resolution_m,
                free_resolution_m=c.sbki.free_resolution_m, max_range_m=c.sbki.max_range_m, device=device, scratch=scratch, box=box), scratch)
            tables = sbki_device.gather_tables_on_device(points, labels, self.block_size, c.length_m, scratch, box)
            if tables is None:  # the host path from the training set, read back whole
                status = scratch.status.numpy()
                if status[STATUS_OVERFLOW]:
                    scratch.learn(status)
                    return build(scratch.begin())
                training_points = points.numpy()
                return self._launch_from_training_set(stats, training_points, labels.numpy()[:len(training_points)], device, scan.check_room)
            near_faces = sbki_device.near_face_masks(tables.scaled_points, tables.pair_count, tables.point_start, tables.blocks, tables.block_count,
                                                     **self._lattice(), scratch=scratch)
            inputs = block_gather.sbki_blocks(blocks=tables.tests, sources=tables.sources, point_start=tables.point_start,
                                              scaled_points=tables.scaled_points, labels=tables.labels, near_faces=near_faces,
                                              length=c.length_m, sigma0=c.sigma0, resolution=c.resolution_m, grid_offset=self.grid_offset_m)
            return inputs, tables.targets

        return counted_gather_launch(stats, self._scratch, device, build, self.cells_per_block, self.gather_kernel, "sbki_gather")

    def _scatter_counts(self, shards, points, labels, point_ids, owners, lanes) -> int | PendingUpdates:
        """S-CSM: each (point, block) pair adds 1 to its block's single cell."""
        c = self.config
        if lanes is not None and len(owners):  # the test blocks' bounds (owners +- 1), before any shard inserts its part
            lo, hi = column_bounds(np.asarray(owners, np.int64))
            shards[0].check_block_range(np.stack([lo - 1, hi + 1]), self.cells_per_block)

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            # Each shard holds the test blocks of its own points, so its targets are all present.
            insert_blocks(shard, sbki_compat.test_blocks(owners[part]), self.cells_per_block, mark_touched=False)
            ids = point_ids[part]
            return scatter(shard, points[ids].astype(np.float64), np.full(len(ids), c.resolution_m), np.zeros(len(ids)),
                           mode=sc.MODE_SBKI_OWN_BLOCK, sigma0=1.0, reach=None, labels=labels[ids], owner_blocks=owners[part],
                           cells_per_block=self.cells_per_block)

        return total_updates(split_over_shards(shards, lanes, len(point_ids), job))

    def _gather_sparse(self, points, labels, point_ids, owners, d: str, check_room: Callable[[int], None] | None = None):
        """S-BKI: every test block gathers from its extended block's points (``kernels.block_gather``).
        Builds the kernel's inputs; returns run(shards, lanes) -> updates."""
        c = self.config
        # Each block holding points is a test block of cells_per_block^3 new voxels at most: the table is asked
        # for them before the tables of their neighbours (several times larger) are built.
        tables = sbki_compat.gather_tables(owners, None if check_room is None else lambda blocks: check_room(blocks * self.cells_per_block**3))
        sorted_points = np.take(point_ids, tables.pair_order)
        # numpy's takes rather than the sorted_block_points kernel on Warp's CPU backend (docs/performance.md,
        # "Measurements behind the code's choices"); scaled in place, as scale_points scales
        scaled = take_rows(np.asarray(points, np.float32), sorted_points)
        scaled_points = wp.array(np.divide(scaled, np.float32(c.length_m), out=scaled), dtype=wp.vec3, device=d, copy=False)
        point_start = wp.array(tables.point_start.astype(np.int32), dtype=int, device=d, copy=False)
        near_faces = sbki_device.near_face_masks(scaled_points, wp.array([len(sorted_points)], dtype=int, device=d), point_start,
                                                 wp.array(tables.blocks.astype(np.int32), dtype=wp.vec3i, device=d),
                                                 wp.array([len(tables.blocks)], dtype=int, device=d), **self._lattice())
        scan = block_gather.sbki_blocks(
            blocks=wp.array(tables.test_blocks.astype(np.int32), dtype=wp.vec3i, device=d, copy=False),
            sources=wp.array(tables.sources, dtype=int, device=d, copy=False),
            point_start=point_start, scaled_points=scaled_points, near_faces=near_faces,
            labels=wp.array(np.take(np.asarray(labels).astype(np.int32), sorted_points), dtype=int, device=d, copy=False),
            length=c.length_m, sigma0=c.sigma0, resolution=c.resolution_m, grid_offset=self.grid_offset_m)
        return block_gather_run(tables.test_blocks, self.cells_per_block, self.gather_kernel, scan, "sbki_gather")

    def _lattice(self) -> dict:
        """The lattice and kernel length the near-face masks box the test blocks with."""
        return {"cells_per_block": self.cells_per_block, "resolution_m": self.config.resolution_m, "grid_offset_m": self.grid_offset_m,
                "length_m": self.config.length_m}


def insert_blocks(shard: VoxelMap, blocks: np.ndarray, cells_per_block: int, *, mark_touched: bool) -> None:
    """Insert every cell of each block [B, 3] (block b holds voxels b n - n/2 ... b n + n/2 - 1)."""
    if len(blocks) == 0:
        return
    blocks = np.ascontiguousarray(blocks, dtype=np.int32)
    shard.check_block_range(blocks, cells_per_block)
    load_once(sc, shard.device)
    d = shard.device
    blocks_wp = wp.array(blocks, dtype=wp.vec3i, device=d, copy=False)

    def launch(ids, failed):
        wp.launch(sc.insert_block_cells, dim=len(ids), device=d, inputs=[
            ids, blocks_wp, int(cells_per_block), int(mark_touched), shard.table(), shard.data, failed])

    shard.launch_until_done(len(blocks), launch, may_insert=True, kind="block_cells", most_new=len(blocks) * cells_per_block**3, exact_most=True,
                            fails_only_when_full=True)
