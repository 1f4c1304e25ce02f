"""The release mode (``mapping.compat: release``, docs/compatibility.md §4), the released EvSemMap C++ for
ebs and dempster: the per-scan uncertainty cut and per-block cap (``methods.release_compat``), then the
block models as one gather kernel (``kernels.release``; after the cut on the map's device on a GPU,
``methods.release_device``)."""

from __future__ import annotations

import functools

import numpy as np
import warp as wp

from ...config import MappingConfig, PayloadType
from ...kernels import block_gather, block_membership, device_counts, radix_sort, release, voxel_grid
from ...kernels import scatter as sc
from ...methods import release_compat, release_device, sbki_compat
from ...methods.device_scratch import DeviceScratch, ScratchPool
from ...voxel_keys import take_rows
from .base import IntegrationStats, Launch, ScanNeeds, ScanPayload, SensorOrigin, dirichlet_beliefs, launch_step, preprocesses_on_device, scatter_fusion
from .gathers import block_gather_run, counted_gather_launch


class ReleaseCompatIntegrator:
    """The release mode (``mapping.compat: release``), the released EvSemMap: per-scan uncertainty cut,
    the per-block cap (``methods.release_compat``), then the block models as one gather kernel (``kernels.release``).
    Takes alpha payloads."""

    grid_offset_m = 0.0

    def __init__(self, config: MappingConfig, num_classes: int | None = None):
        self.config = config
        # The release reads the sensor origin only for its range filter.
        self.needs = ScanNeeds(
            SensorOrigin.REQUIRED if config.sbki.max_range_m is not None else SensorOrigin.OPTIONAL,
            "the release mode's range filter (mapping.sbki.max_range_m) measures from the sensor origin",
            frozenset({PayloadType.ALPHA}),
            "the release mode reproduces the released EvSemMap, which reads evidential alpha (its uncertainty cut is K / sum(alpha))")
        self.cells_per_block = 2 ** (config.sbki.block_depth - 1)
        self.block_size = sbki_compat.block_size_m(config.resolution_m, config.sbki.block_depth)
        self.length = release_compat.kernel_length(config.length_m)
        # kernel factory (class count, cells per block) -> the gather kernel; the study swaps in other forms
        self.gather_kernel = release.gather_release_kernel
        # Where the preprocessing after the cut runs (methods.release_device): as SbkiCompatIntegrator's.
        self.preprocess_on_device: bool | None = None
        self._scratch = ScratchPool()
        self.num_classes = num_classes

    def kernel_modules(self, device: str) -> list:
        """The cut's and cap's modules, the memberships' and the block grouping's (on the device also the
        sorted rows'), and the gather kernel's of its fusion."""
        fusion = scatter_fusion(self.config)
        if self.num_classes is None:
            return [release, radix_sort, block_membership, block_gather]
        gather = self.gather_kernel(self.num_classes, self.cells_per_block, fusion=fusion).module
        if preprocesses_on_device(self, device):
            return [release, voxel_grid, block_membership, block_gather, device_counts, release.sorted_rows_kernel(self.num_classes, fusion == sc.FUSION_DEMPSTER).module, gather]
        return [release, radix_sort, block_membership, block_gather, gather]

    def cut_points(self, scan: ScanPayload, sensor_origin: np.ndarray) -> np.ndarray:
        """Indices of the scan's points within range that the uncertainty cut keeps."""
        c = self.config
        keep = np.arange(len(scan.points))
        if c.sbki.max_range_m is not None:
            keep = keep[np.linalg.norm(scan.points.astype(np.float32).astype(np.float64) - sensor_origin, axis=1) <= c.sbki.max_range_m]
        cut, _ = release_compat.uncertainty_cut(scan.uncertainty[keep], c.keep_quantile)
        return keep[cut]

    def training_points(self, scan: ScanPayload, sensor_origin: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
        """Indices of the scan's points the models train on, and how many each step kept."""
        c = self.config
        keep = self.cut_points(scan, sensor_origin)
        counts = {"after_cut": len(keep)}
        if len(keep):
            blocks = release_compat.snapped_block_keys(scan.points[keep], c.sbki.ds_resolution_m, self.block_size)
            keep = keep[release_compat.first_per_block(blocks, c.release_block_cap)]
        counts["after_ds"] = len(keep)
        return keep, counts

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """The cut, the cap, memberships and the block models' tables (no map access; after the cut on the
        map's device for a GPU map); the launch runs the gather kernel."""
        if preprocesses_on_device(self, device):
            return self._prepare_on_device(scan, device)
        return self._prepare_on_host(scan, device)

    def _prepare_on_host(self, scan: ScanPayload, device: str) -> Launch:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep, _ = self.training_points(scan, scan.sensor_origin)
        stats.kept_points = len(keep)
        if len(keep) == 0:
            return launch_step(stats)
        points = scan.points[keep].astype(np.float32)
        pair_points, member_blocks = sbki_compat.block_memberships(points, self.block_size)
        models = release_compat.release_blocks(member_blocks, device=device)
        fusion = scatter_fusion(c)
        sorted_points = pair_points[models.pair_order]
        sorted_rows = keep[sorted_points]
        weights = scan.probability_rows(sorted_rows)
        unc = scan.uncertainty[sorted_rows]
        if fusion == sc.FUSION_DEMPSTER:
            weights = dirichlet_beliefs(weights, unc)
        d = device
        scan = release.release_blocks(
            blocks=wp.array(models.blocks.astype(np.int32), dtype=wp.vec3i, device=d, copy=False),
            source_blocks=wp.array(models.source_blocks, dtype=int, device=d, copy=False),
            source_mult=wp.array(models.source_mult, dtype=int, device=d, copy=False),
            point_start=wp.array(models.point_start.astype(np.int32), dtype=int, device=d, copy=False),
            points=wp.array(take_rows(points, sorted_points), dtype=wp.vec3, device=d, copy=False),
            class_weights=wp.array(np.ascontiguousarray(weights, dtype=np.float64), dtype=release.vector_type(weights.shape[1]), device=d, copy=False),
            uncertainty=wp.array(np.ascontiguousarray(unc, dtype=np.float64), dtype=wp.float64, device=d, copy=False),
            length=self.length, sigma0=c.sigma0, resolution=c.resolution_m)
        kernel_factory = functools.partial(self.gather_kernel, fusion=fusion)
        return launch_step(stats, block_gather_run(models.blocks, self.cells_per_block, kernel_factory, scan, "release_gather"))

    def _prepare_on_device(self, scan: ScanPayload, device: str) -> Launch:
        """``prepare`` with the work after the cut on the map's device (``methods.release_device``), no count
        read back (``counted_gather_launch``); the host path where the blocks are too spread for its dense grid."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep = self.cut_points(scan, scan.sensor_origin)
        if len(keep) == 0:
            stats.kept_points = 0
            return launch_step(stats)
        fusion = scatter_fusion(c)
        points, probabilities, uncertainty = scan.points[keep], scan.probability_rows(keep), scan.uncertainty[keep]

        def build(scratch: DeviceScratch):
            inputs = release_device.release_inputs_on_device(
                points, probabilities, uncertainty, ds_resolution_m=c.sbki.ds_resolution_m, block_size=self.block_size,
                cap=c.release_block_cap, dempster=fusion == sc.FUSION_DEMPSTER, device=device, scratch=scratch)
            if inputs is None:
                return self._prepare_on_host(scan, device)
            blocks = release.release_blocks(
                blocks=inputs.targets.blocks, source_blocks=inputs.source_blocks, source_mult=inputs.source_mult, point_start=inputs.point_start,
                points=inputs.points, class_weights=inputs.class_weights, uncertainty=inputs.uncertainty, length=self.length, sigma0=c.sigma0,
                resolution=c.resolution_m)
            return blocks, inputs.targets

        kernel_factory = functools.partial(self.gather_kernel, fusion=fusion)
        return counted_gather_launch(stats, self._scratch, device, build, self.cells_per_block, kernel_factory, "release_gather")
