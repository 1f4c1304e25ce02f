"""Integrators: one job each, the map handed in. ``prepare`` turns a validated scan into its launch
(host work only, no map access); the launch runs the kernels on the shards.

* ``KernelIntegrator``: the paper's clean algorithm (docs/algorithm.md §3) for S-CSM, S-BKI, EBS and the
  ablations: optional per-insertion uncertainty threshold, optional adaptive length, one scatter.
  With ``fusion: dempster`` the same scatter fuses belief masses instead (docs/algorithm.md §3.7).
* ``ConvBkiIntegrator``: ConvBKI (docs/compatibility.md §2): voxelise, then a per-class stencil scatter.
* ``SeeCsomIntegrator``: SEE-CSOM (docs/compatibility.md §3): block statistics, then a block-gated scatter.
* ``SbkiCompatIntegrator``: the original S-BKI / S-CSM C++ (docs/compatibility.md §1).
* ``ReleaseCompatIntegrator``: the released EvSemMap C++ for ebs and dempster (docs/compatibility.md §4).

All receive the map as a list of shards. Warp runs a CPU launch on one core, so on the CPU each
worker thread scatters a contiguous part of the scan into its own shard (never a shared one: CPU
"atomics" are plain read-modify-writes); readers add the shards up (``sum_voxel_arrays``). The block
gathers (the S-BKI and release modes) split by target block instead, each block always in the shard
its index picks (``block_shard``), so their maps do not depend on the number of workers. A shard's
jobs run on its own lane (``ShardLanes``), in the order they were submitted: a shard may go on to the
next scan while another is still on this one, and a launch's voxel updates may still be pending
(``PendingUpdates``) when it returns.
"""

from __future__ import annotations

import functools
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import warp as wp

from ..config import Fusion, Kernel, MappingConfig, Media
from ..kernels import block_gather, release
from ..kernels import scatter as sc
from ..methods import convbki, evsemmap_release, sbki_compat, see_csom
from ..voxel_keys import take_rows
from .voxel_map import VoxelMap, block_model_tables

# Below this many points per shard, splitting a launch costs more than it saves.
MIN_POINTS_PER_SHARD = 4096


@dataclass
class ScanPayload:
    """A validated scan: points [N, 3] float64 (m, relative to the map origin when an integrator gets
    them), class probabilities [N, K], input uncertainty [N] (K / S for alpha, 1 - max p for
    probabilities, 0 for labels), and ``labels`` [N]: ``label_scores`` itself when it is [N], else its
    row argmax, computed when first asked for (the release mode never asks; 5 % of its time)."""

    points: np.ndarray
    probabilities: np.ndarray
    uncertainty: np.ndarray
    label_scores: np.ndarray

    @functools.cached_property
    def labels(self) -> np.ndarray:
        if self.label_scores.ndim == 1:
            return self.label_scores
        if len(self.label_scores) == 0:
            return np.zeros(0, np.int64)
        return np.argmax(self.label_scores, axis=1)


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


class ShardLanes:
    """One thread per shard: a shard's jobs run one at a time in the order they were submitted, so its
    map is the same as when the scans run one after another, while the shards need not wait for each
    other at the end of every scan (that barrier left a core idle while the slower shard finished:
    the S-BKI mode at free_res 4 on 2 workers kept 1.61-1.75 of 2 cores busy with it, 1.81-1.91
    without, and took 0.90-1.00 instead of 1.01-1.07 s, alternating runs)."""

    def __init__(self, count: int):
        self._lanes = [ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"evsemmap-shard{i}") for i in range(count)]

    def submit(self, index: int, job, *args) -> Future:
        return self._lanes[index].submit(job, *args)


@dataclass
class PendingUpdates:
    """Voxel updates of a launch whose jobs may still run on the shards' lanes (ints and futures)."""

    parts: list

    def wait(self) -> None:
        """Returns once every part has finished, failed or not."""
        for part in self.parts:
            if isinstance(part, Future):
                part.exception()

    def result(self) -> int:
        """Waits for every part (all of them, even after one failed), then adds them up or raises."""
        self.wait()
        return sum(part.result() if isinstance(part, Future) else part for part in self.parts)


def total_updates(parts: list):
    """The sum of the parts' updates: an int, or PendingUpdates while some still run."""
    return PendingUpdates(parts) if any(isinstance(part, Future) for part in parts) else sum(parts)


# What an integrator's ``prepare`` returns: the map update itself, launch(shards, lanes) -> stats (whose
# voxel_updates may be PendingUpdates).
Launch = Callable[[list[VoxelMap], Optional[ShardLanes]], IntegrationStats]


def launch_step(stats: IntegrationStats, run=None) -> Launch:
    """The launch that runs ``run(shards, lanes) -> voxel updates`` (nothing when None) into ``stats``."""

    def launch(shards: list[VoxelMap], lanes: ShardLanes | None = None) -> IntegrationStats:
        if run is not None:
            stats.voxel_updates = run(shards, lanes)
        return stats

    return launch


def for_each_shard(shards: list[VoxelMap], lanes: ShardLanes | None, job) -> list:
    """job(shard, shard index) for every shard: on the shards' lanes (futures) when there are lanes."""
    if lanes is None:
        return [job(shard, i) for i, shard in enumerate(shards)]
    return [lanes.submit(i, job, shard, i) for i, shard in enumerate(shards)]


def split_over_shards(shards: list[VoxelMap], lanes: ShardLanes | None, n: int, job) -> list:
    """job(shard, index_range) on contiguous parts of range(n), one part per shard (fewer for small n),
    on the shards' lanes (futures) when there are lanes."""
    if lanes is None:
        return [job(shards[0], np.arange(n))]
    parts = max(1, min(len(shards), n // MIN_POINTS_PER_SHARD))
    return [lanes.submit(i, job, shards[i], part) for i, part in enumerate(np.array_split(np.arange(n), parts))]


class KernelIntegrator:
    def __init__(self, config: MappingConfig):
        self.config = config

    def kernel_lengths(self, uncertainty: np.ndarray) -> np.ndarray:
        c = self.config
        if c.adaptive_length:
            return c.length_m * c.beta * np.exp(1.0 - c.gamma * uncertainty)
        return np.full(len(uncertainty), c.length_m)

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Nothing worth doing ahead: the launch runs ``integrate``."""
        return lambda shards, lanes=None: self.integrate(shards, scan, lanes)

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, lanes: ShardLanes | None = None) -> IntegrationStats:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep = np.ones(len(scan.points), dtype=bool)
        if c.uncertainty_threshold:
            keep, stats.uncertainty_threshold = uncertainty_quantile_mask(scan.uncertainty, c.keep_quantile)
        points, unc = scan.points[keep], scan.uncertainty[keep]
        stats.kept_points = len(points)
        onehot = c.media is Media.ONEHOT
        media = scan.labels[keep] if onehot else scan.probabilities[keep]
        fusion = sc.FUSION_DEMPSTER if c.fusion is Fusion.DEMPSTER else sc.FUSION_BAYES
        if fusion == sc.FUSION_DEMPSTER:
            # belief masses b_k = (alpha_k - 1) / S = p_k - u / K (docs/algorithm.md §3.7)
            media = np.clip(media - unc[:, None] / media.shape[1], 0.0, 1.0)
        if c.kernel is Kernel.COUNT:
            mode, sigma0, lengths = sc.MODE_OWN_VOXEL, 1.0, np.full(len(points), c.resolution_m)
        else:
            mode, sigma0, lengths = sc.MODE_RADIUS, c.sigma0, self.kernel_lengths(unc)

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            kw = {"labels": media[part]} if onehot else {"class_weights": media[part]}
            if c.scatter_strategy == "sorted" and mode == sc.MODE_RADIUS:
                return shard.scatter_sorted(points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            if c.scatter_strategy == "gather" and mode == sc.MODE_RADIUS:
                return shard.scatter_hashgrid(points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            return shard.scatter(points[part], lengths[part], unc[part], mode=mode, sigma0=sigma0, fusion=fusion, **kw)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(points), job))
        return stats


class ConvBkiIntegrator:
    """Points are voxelised first (evidence summed per voxel, as its authors do: softmax vectors, or
    label counts for one-hot media); each occupied voxel then scatters onto its stencil."""

    def __init__(self, config: MappingConfig, num_classes: int):
        self.config = config
        if config.convbki_lengths_file:
            self.lengths = convbki.load_lengths(config.convbki_lengths_file, num_classes)
        else:
            self.lengths = convbki.default_lengths(num_classes)
        self.weights = convbki.stencil_weights(self.lengths, config.resolution_m, config.convbki_stencil_half)

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Nothing worth doing ahead: the launch runs ``integrate``."""
        return lambda shards, lanes=None: self.integrate(shards, scan, lanes)

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, lanes: ShardLanes | None = None) -> IntegrationStats:
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points), kept_points=len(scan.points))
        if len(scan.points) == 0:
            return stats
        k = scan.probabilities.shape[1]
        evidence = np.eye(k)[scan.labels] if c.media is Media.ONEHOT else scan.probabilities
        voxels, summed = convbki.voxelise(scan.points, np.column_stack([evidence, scan.uncertainty, np.ones(len(evidence))]), c.resolution_m)
        centres = (voxels + 0.5) * c.resolution_m
        mean_uncertainty = summed[:, k] / summed[:, k + 1]

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            return shard.scatter(centres[part], np.full(len(part), c.resolution_m), mean_uncertainty[part], mode=sc.MODE_STENCIL,
                                 sigma0=1.0, class_weights=summed[part, :k], stencil_weights=self.weights)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(centres), job))
        return stats


class SeeCsomIntegrator:
    """Training data as its code builds it (VoxelGrid with majority labels, the sensor origin as the
    one free sample: its configs' free_resolution of 1000 m), then block statistics and the scatter."""

    def __init__(self, config: MappingConfig, num_classes: int):
        self.config = config
        self.num_classes = num_classes

    def prepare(self, scan: ScanPayload, sensor_origin: np.ndarray, device: str) -> Launch:
        """Training data and block statistics (host work, no map access); the launch scatters."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        points, labels, _ = sbki_compat.training_data(scan.points, scan.labels, sensor_origin, ds_resolution_m=c.ds_resolution_m,
                                                      free_resolution_m=1000.0, max_range_m=c.max_range_m)
        points = points.astype(np.float64)
        stats.kept_points = len(points)
        if len(points) == 0:
            return launch_step(stats)
        owners, lengths = see_csom.block_targets(points, labels, self.num_classes, c.resolution_m)
        unc = np.zeros(len(points))

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            return shard.scatter_block_targets(points[part], labels[part], unc[part], owners[part], lengths[part], see_csom.CELLS_PER_BLOCK)

        return launch_step(stats, lambda shards, lanes: total_updates(split_over_shards(shards, lanes, len(points), job)))


class SbkiCompatIntegrator:
    """S-BKI (sparse kernel) or S-CSM (count kernel, one-cell blocks on the half-shifted grid)."""

    def __init__(self, config: MappingConfig):
        self.config = config
        self.block_depth = 1 if config.kernel is Kernel.COUNT else config.block_depth
        self.cells_per_block = 2 ** (self.block_depth - 1)
        self.block_size = sbki_compat.block_size_m(config.resolution_m, self.block_depth)
        # kernel factory (class count, cells per block) -> the S-BKI gather kernel; the study swaps in other forms
        self.gather_kernel = block_gather.gather_sbki_kernel

    @staticmethod
    def grid_offset_m(config: MappingConfig) -> float:
        # S-CSM cells are centred on multiples of r (blocks of one cell), half a cell off the BKI grid.
        return -0.5 * config.resolution_m if config.kernel is Kernel.COUNT else 0.0

    def prepare(self, scan: ScanPayload, sensor_origin: np.ndarray, device: str) -> Launch:
        """Training data, block memberships and the gather tables (host work, no map access); the
        launch runs the kernels."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        points, labels, _ = sbki_compat.training_data(
            scan.points, scan.labels, sensor_origin,
            ds_resolution_m=c.ds_resolution_m, free_resolution_m=c.free_resolution_m, max_range_m=c.max_range_m,
        )
        stats.kept_points = len(points)
        if len(points) == 0:
            return launch_step(stats)
        point_ids, owners = sbki_compat.block_memberships(points, self.block_size)
        if c.kernel is Kernel.COUNT:
            return launch_step(stats, lambda shards, lanes: self._scatter_counts(shards, points, labels, point_ids, owners, lanes))
        return launch_step(stats, self._gather_sparse(points, labels, point_ids, owners, device))

    def _scatter_counts(self, shards, points, labels, point_ids, owners, lanes) -> int | PendingUpdates:
        """S-CSM: each (point, block) pair adds 1 to its block's single cell."""
        c = self.config

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            # Each shard holds the test blocks of its own points, so its targets are all present.
            shard.insert_blocks(sbki_compat.test_blocks(owners[part]), self.cells_per_block, mark_touched=False)
            ids = point_ids[part]
            return shard.scatter(points[ids].astype(np.float64), np.full(len(ids), c.resolution_m), np.zeros(len(ids)),
                                 mode=sc.MODE_SBKI_OWN_BLOCK, sigma0=1.0, labels=labels[ids], owner_blocks=owners[part],
                                 cells_per_block=self.cells_per_block)

        return total_updates(split_over_shards(shards, lanes, len(point_ids), job))

    def _gather_sparse(self, points, labels, point_ids, owners, d: str):
        """S-BKI: every test block gathers from its extended block's points (``kernels.block_gather``).
        Builds the kernel's inputs; returns run(shards, lanes) -> updates."""
        c = self.config
        tables = sbki_compat.gather_tables(owners)
        sorted_points = point_ids[tables.pair_order]
        gather_inputs = [
            wp.array(tables.test_blocks.astype(np.int32), dtype=wp.vec3i, device=d, copy=False),
            wp.array(tables.sources, dtype=int, device=d, copy=False),
            wp.array(tables.point_start.astype(np.int32), dtype=int, device=d, copy=False),
            wp.array(block_gather.scale_points(take_rows(points, sorted_points), c.length_m), dtype=wp.vec3, device=d, copy=False),
            wp.array(np.ascontiguousarray(labels[sorted_points], dtype=np.int32), dtype=int, device=d, copy=False),
            wp.float64(c.length_m), wp.float64(c.sigma0), wp.float64(c.resolution_m), wp.float64(self.grid_offset_m(c)),
        ]

        return block_gather_run(tables.test_blocks, self.cells_per_block, self.gather_kernel, gather_inputs, "sbki_gather")


class ReleaseCompatIntegrator:
    """The released EvSemMap (``mapping.compat: evsemmap``): per-scan uncertainty cut, the per-block
    cap (``methods.evsemmap_release``), then the block models as one gather kernel (``kernels.release``).
    Takes alpha payloads."""

    def __init__(self, config: MappingConfig):
        self.config = config
        self.cells_per_block = 2 ** (config.block_depth - 1)
        self.block_size = sbki_compat.block_size_m(config.resolution_m, config.block_depth)
        self.length = evsemmap_release.kernel_length(config.length_m)
        # kernel factory (class count, cells per block) -> the gather kernel; the study swaps in other forms
        self.gather_kernel = release.gather_release_kernel

    def training_points(self, scan: ScanPayload, sensor_origin: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
        """Indices of the scan's points the models train on, and how many each step kept."""
        c = self.config
        keep = np.arange(len(scan.points))
        if c.max_range_m > 0:
            keep = keep[np.linalg.norm(scan.points.astype(np.float32).astype(np.float64) - sensor_origin, axis=1) <= c.max_range_m]
        cut, _ = evsemmap_release.uncertainty_cut(scan.uncertainty[keep], c.keep_quantile)
        keep = keep[cut]
        counts = {"after_cut": len(keep)}
        if len(keep):
            blocks = evsemmap_release.snapped_block_keys(scan.points[keep], c.ds_resolution_m, self.block_size)
            keep = keep[evsemmap_release.first_per_block(blocks, c.release_block_cap)]
        counts["after_ds"] = len(keep)
        return keep, counts

    def prepare(self, scan: ScanPayload, sensor_origin: np.ndarray, device: str) -> Launch:
        """The cut, the cap, memberships and the block models' tables (no map access); the launch runs
        the gather kernel."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep, _ = self.training_points(scan, sensor_origin)
        stats.kept_points = len(keep)
        if len(keep) == 0:
            return launch_step(stats)
        points = scan.points[keep].astype(np.float32)
        pair_points, member_blocks = sbki_compat.block_memberships(points, self.block_size)
        models = evsemmap_release.release_blocks(member_blocks, lambda b, g, lo: block_model_tables(b, g, lo, device))
        fusion = sc.FUSION_DEMPSTER if c.fusion is Fusion.DEMPSTER else sc.FUSION_BAYES
        sorted_points = pair_points[models.pair_order]
        weights = take_rows(scan.probabilities[keep], sorted_points)
        unc = scan.uncertainty[keep][sorted_points]
        if fusion == sc.FUSION_DEMPSTER:
            weights = np.clip(weights - unc[:, None] / weights.shape[1], 0.0, 1.0)  # b_k = (alpha_k - 1) / S
        d = device
        gather_inputs = [
            wp.array(models.blocks.astype(np.int32), dtype=wp.vec3i, device=d, copy=False),
            wp.array(models.source_blocks, dtype=int, device=d, copy=False), wp.array(models.source_mult, dtype=int, device=d, copy=False),
            wp.array(models.point_start.astype(np.int32), dtype=int, device=d, copy=False),
            wp.array(take_rows(points, sorted_points), dtype=wp.vec3, device=d, copy=False),
            wp.array(np.ascontiguousarray(weights, dtype=np.float64), dtype=release.vector_type(weights.shape[1]), device=d, copy=False),
            wp.array(np.ascontiguousarray(unc, dtype=np.float64), dtype=wp.float64, device=d, copy=False),
            wp.float64(self.length), float(c.sigma0), float(c.resolution_m), int(fusion),
        ]

        return launch_step(stats, block_gather_run(models.blocks, self.cells_per_block, self.gather_kernel, gather_inputs, "release_gather"))


def block_gather_run(blocks: np.ndarray, cells_per_block: int, kernel_factory, gather_inputs: list, kind: str):
    """run(shards, lanes) -> updates for a block-gather kernel (``kernel_factory(K, cells per block)``)
    over target ``blocks`` [B, 3], whose arguments start with ``gather_inputs``: the key range is checked
    before any launch, and each block is gathered in the shard its index picks, so a cell is always
    summed in the same shard in the same order and the map is bit for bit the same for any number of
    workers."""

    def run(shards: list[VoxelMap], lanes: ShardLanes | None) -> int | PendingUpdates:
        shards[0].check_block_range(blocks, cells_per_block)
        owner = block_shard(blocks, len(shards))
        kernel = kernel_factory(shards[0].num_classes, cells_per_block)
        shards[0].load_kernel(kernel)

        def job(shard: VoxelMap, index: int) -> int:
            return shard.gather_blocks(kernel, gather_inputs, np.flatnonzero(owner == index), cells_per_block=cells_per_block, kind=kind)

        return total_updates(for_each_shard(shards, lanes, job))

    return run


def block_shard(blocks: np.ndarray, shards: int) -> np.ndarray:
    """The shard of each block [B, 3]: a fixed hash of its index, so it never depends on the scan."""
    b = np.asarray(blocks, dtype=np.int64)
    return ((b[:, 0] * 73856093) ^ (b[:, 1] * 19349663) ^ (b[:, 2] * 83492791)) % shards
