"""Integrators: one job each, the map handed in, all behind one protocol (``Integrator``): made from
(config, num_classes) through the registry (``make_integrator``, keyed by the integration method: the
compatibility mode and the kernel), each declares what it needs of a scan (``ScanNeeds``: the sensor
origin, the payload kinds) and the kernel modules it runs (``kernel_modules(device)``: the Mapper compiles
those, and only those, before its first scan), and turns a validated scan into its launch with
``prepare(scan, device)`` (host work only, no map access); the launch runs the kernels on the shards.

* ``PointKernelIntegrator``: the paper's clean algorithm (docs/algorithm.md §3) for S-CSM, S-BKI, EBS and the
  ablations: optional per-insertion uncertainty threshold, optional adaptive length, one scatter.
  With ``fusion: dempster`` the same scatter fuses belief masses instead (docs/algorithm.md §3.7).
* ``ConvBkiIntegrator``: ConvBKI (docs/compatibility.md §2): voxelise, then a per-class stencil scatter.
* ``SeeCsomIntegrator``: SEE-CSOM (docs/compatibility.md §3): block statistics, then a block-gated scatter.
* ``SbkiCompatIntegrator``: the original S-BKI / S-CSM C++ (docs/compatibility.md §1).
* ``ReleaseCompatIntegrator``: the release mode, the released EvSemMap C++ for ebs and dempster (docs/compatibility.md §4).

All receive the map as a list of shards (``core._shards``: each CPU worker scatters a contiguous part of
the scan into its own shard; the block gathers put each block in the shard its index picks, so their
maps do not depend on the number of workers).
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np
import warp as wp

from ..config import Compat, Fusion, Kernel, MappingConfig, Media, PayloadType, ScatterStrategy, ThresholdScope
from ..kernels import block_gather, block_membership, device_counts, free_space, radix_sort, release, voxel_grid
from ..kernels import hashgrid_gather as hg
from ..kernels import scatter as sc
from ..kernels import sorted_scatter as ss
from ..methods import convbki, release_compat, release_device, sbki_compat, sbki_device, see_csom
from ..methods.device_scratch import STATUS_KEPT_POINTS, STATUS_OVERFLOW, DeviceScratch, ScratchPool
from ..voxel_keys import column_bounds, take_rows
from ._shards import PendingUpdates, ShardLanes, block_shard, for_each_shard, split_over_shards, total_updates, when_done
from .voxel_map import VoxelMap
from .warp_runtime import device_calls

@dataclass
class ScanPayload:
    """A validated scan: points [N, 3] float64 (m, relative to the map origin when an integrator gets them),
    input uncertainty [N] (K / S for alpha, 1 - max p for probabilities, 0 for labels), the ``payload``
    as given ([N] labels, or [N, K] alpha or probabilities, float32 or float64), the class count K, the
    payload rows' sums [N] (float64, None for labels) and ``sensor_origin`` [3] (m, float64, same frame
    as the points): set for the integrators whose ``needs`` read it, None for the others.
    ``probabilities`` [N, K] and ``labels`` [N] are derived when first asked for (the release mode asks
    for the probabilities of the rows it keeps only, ``probability_rows``, and never for labels)."""

    points: np.ndarray
    uncertainty: np.ndarray
    payload: np.ndarray
    num_classes: int
    row_sums: np.ndarray | None = None
    sensor_origin: np.ndarray | None = None
    # The Mapper's check_room(new_voxels): refuses (MemoryBudgetError) a scan whose new voxels its tables'
    # memory budget cannot hold, so that a preparation sized by the voxels it makes asks before allocating for them.
    check_room: Callable[[int], None] | None = None

    @functools.cached_property
    def probabilities(self) -> np.ndarray:
        """[N, K] float64 class probabilities: alpha / S, the probabilities normalised, or one-hot labels."""
        return self.probability_rows(slice(None))

    def probability_rows(self, rows) -> np.ndarray:
        """``probabilities[rows]`` (an index array, a mask or a slice), computed for those rows only."""
        if "probabilities" in self.__dict__:
            return self.probabilities[rows]
        if self.row_sums is None:
            return np.eye(self.num_classes)[self.payload[rows]]
        return np.asarray(self.payload[rows], dtype=np.float64) / self.row_sums[rows][:, None]

    @functools.cached_property
    def labels(self) -> np.ndarray:
        """[N] class ids: the payload itself when it is [N] labels, else its row argmax (computed when
        first asked for)."""
        if self.payload.ndim == 1:
            return self.payload
        if len(self.payload) == 0:
            return np.zeros(0, np.int64)
        return np.argmax(self.payload, axis=1)


@dataclass
class IntegrationStats:
    """What one insertion did: its input points, the points kept (after the uncertainty threshold in the
    clean mode, training points in the sbki mode), the voxel updates made (point-voxel contributions), and
    the threshold u applied (None without one)."""

    input_points: int = 0
    kept_points: int = 0  # after the uncertainty threshold (clean) or as training points (sbki)
    voxel_updates: int = 0
    uncertainty_threshold: float | None = None


def dirichlet_beliefs(probabilities: np.ndarray, uncertainty: np.ndarray) -> np.ndarray:
    """The belief masses [N, K] the Dempster-Shafer fusion takes from Dirichlet points: b_k = (alpha_k - 1) / S
    = p_k - u / K (docs/algorithm.md §3.7), clipped to [0, 1]."""
    return np.clip(probabilities - uncertainty[:, None] / probabilities.shape[1], 0.0, 1.0)


def uncertainty_quantile_mask(uncertainty: np.ndarray, keep_quantile: float) -> tuple[np.ndarray, float]:
    """Keep u <= t with t the floor(N q)-th smallest u (0-based, clamped to N - 1); ties are kept."""
    n = len(uncertainty)
    k = min(int(np.floor(n * keep_quantile)), n - 1)
    threshold = float(np.partition(uncertainty, k)[k])
    return uncertainty <= threshold, threshold


def per_class_quantile_mask(uncertainty: np.ndarray, predicted: np.ndarray, keep_quantile: float) -> np.ndarray:
    """``uncertainty_quantile_mask`` within each predicted class: each class keeps its own surest share."""
    keep = np.ones(len(uncertainty), dtype=bool)
    for label in np.unique(predicted):
        rows = np.flatnonzero(predicted == label)
        keep[rows] = uncertainty_quantile_mask(uncertainty[rows], keep_quantile)[0]
    return keep


def threshold_mask(config: MappingConfig, uncertainty: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The points of one insertion that the uncertainty threshold keeps (``config.threshold_scope``: over the
    insertion, or per ``predicted`` class), and the threshold u when there is one (None per class)."""
    if config.threshold_scope is ThresholdScope.PREDICTED_CLASS:
        return per_class_quantile_mask(uncertainty, predicted, config.keep_quantile), None
    return uncertainty_quantile_mask(uncertainty, config.keep_quantile)


# What an integrator's ``prepare`` returns: the map update itself, launch(shards, lanes) -> stats (whose
# voxel_updates may be PendingUpdates).
Launch = Callable[[list[VoxelMap], Optional[ShardLanes]], IntegrationStats]


class SensorOrigin(enum.Enum):
    """Whether an integrator reads a scan's sensor origin."""

    UNUSED = "unused"  # never read (the scan's ``sensor_origin`` stays None)
    OPTIONAL = "optional"  # read when given (validated); else the map origin stands in
    REQUIRED = "required"  # a scan without one is refused


@dataclass(frozen=True)
class ScanNeeds:
    """What an integrator needs of a scan beyond points and payload, declared so that the Mapper checks
    every scan the same way: the sensor origin (and, when required, why: the refusal's reason), and the
    payload kinds it integrates (others are refused with ``payload_reason``)."""

    sensor_origin: SensorOrigin = SensorOrigin.UNUSED
    sensor_origin_reason: str = ""
    payload_types: frozenset = frozenset(PayloadType)
    payload_reason: str = ""


class Integrator(Protocol):
    """One integration method: made from (config, num_classes) by ``make_integrator``, it holds only its
    parameters. ``needs``: what it reads of a scan; ``grid_offset_m``: where its voxel lattice lies (m;
    0 but for S-CSM's half-shifted cells); ``prepare(scan, device)``: host work on a validated scan in map
    coordinates (no map access), returning the launch that updates the shards."""

    needs: ScanNeeds
    grid_offset_m: float

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Host work on a validated scan in map coordinates, without touching the map; returns the launch
        that updates the shards."""

    def kernel_modules(self, device: str) -> list:
        """The kernel modules its preparation and launches run for a map on ``device`` (modules of
        ``kernels``, or the Warp modules of the kernels its factories make): the Mapper compiles or loads
        them before its first scan, in the calling thread (``Mapper._load_kernels``)."""


# (compat, kernel) -> the integrator class of that integration method (``register_integrator``).
INTEGRATORS: dict[tuple[Compat, Kernel], type] = {}


def register_integrator(compat: Compat, *kernels: Kernel):
    """Class decorator: the integrator of mode ``compat`` with each of ``kernels``."""

    def register(cls):
        for kernel in kernels:
            if (compat, kernel) in INTEGRATORS:
                raise ValueError(f"two integrators for {compat.value} mode with the {kernel.value} kernel")
            INTEGRATORS[compat, kernel] = cls
        return cls

    return register


def scatter_fusion(config: MappingConfig) -> int:
    """The kernels' fusion constant (``kernels.scatter.FUSION_*``) of the config's ``fusion``."""
    return sc.FUSION_DEMPSTER if config.fusion is Fusion.DEMPSTER else sc.FUSION_BAYES


def preprocesses_on_device(integrator, device: str) -> bool:
    """Whether a compat integrator's preparation runs on the map's ``device`` (its
    ``preprocess_on_device``; None: on a GPU) rather than on the host."""
    if integrator.preprocess_on_device is not None:
        return integrator.preprocess_on_device
    return wp.get_device(device).is_cuda


def integrate_at_launch(integrator, scan: ScanPayload) -> Launch:
    """The launch of an integrator whose host work runs with its kernels (``integrate``): only the scan's
    class probabilities for soft media are derived ahead, here, on the preparing thread (off the launch's
    path when scans are prepared ahead)."""
    if integrator.config.media is not Media.ONEHOT:
        _ = scan.probabilities
    return lambda shards, lanes=None: integrator.integrate(shards, scan, lanes)


def make_integrator(config: MappingConfig, num_classes: int) -> Integrator:
    """The integrator of ``config``'s method (its compatibility mode and kernel) for K = num_classes."""
    try:
        cls = INTEGRATORS[config.compat, config.kernel]
    except KeyError:
        raise ValueError(f"no integrator for mapping.compat {config.compat.value} with mapping.kernel {config.kernel.value}") from None
    return cls(config, num_classes)


def launch_step(stats: IntegrationStats, run=None) -> Launch:
    """The launch that runs ``run(shards, lanes) -> voxel updates`` (nothing when None) into ``stats``."""

    def launch(shards: list[VoxelMap], lanes: ShardLanes | None = None) -> IntegrationStats:
        if run is not None:
            stats.voxel_updates = run(shards, lanes)
        return stats

    return launch


@register_integrator(Compat.CLEAN, Kernel.SPARSE, Kernel.COUNT)
class PointKernelIntegrator:
    """Each point through its own kernel, in the clean mode: the sparse kernel (S-BKI, EBS and the Prob.
    ablations, Dempster-Shafer) on a true radius search around the point, or the counting model (S-CSM)
    in the point's own voxel (docs/algorithm.md §3). Applies the uncertainty threshold and the adaptive length when the config asks
    for them, then scatters each point into the voxels whose centers lie within its length, through
    ``mapping.clean.scatter_strategy``."""

    needs = ScanNeeds()
    grid_offset_m = 0.0

    def __init__(self, config: MappingConfig, num_classes: int | None = None):
        self.config = config

    def kernel_lengths(self, uncertainty: np.ndarray) -> np.ndarray:
        """Each point's kernel length (m) from its uncertainty u [N]: l * beta * exp(1 - gamma u) with the
        adaptive length, else l."""
        c = self.config
        if c.adaptive_length:
            return c.length_m * c.beta * np.exp(1.0 - c.gamma * uncertainty)
        return np.full(len(uncertainty), c.length_m)

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """``integrate_at_launch``."""
        return integrate_at_launch(self, scan)

    def _scatter_form(self) -> tuple[int, int, ScatterStrategy]:
        """(scatter mode, fusion, strategy): the strategy applies to the radius kernel only."""
        c = self.config
        mode = sc.MODE_OWN_VOXEL if c.kernel is Kernel.COUNT else sc.MODE_RADIUS
        fusion = scatter_fusion(c)
        return mode, fusion, c.clean.scatter_strategy if mode == sc.MODE_RADIUS else ScatterStrategy.ATOMIC

    def kernel_modules(self, device: str) -> list:
        """The module of its one scatter kernel, or of its scatter strategy's kernels."""
        mode, fusion, strategy = self._scatter_form()
        by_strategy = {ScatterStrategy.SORTED: ss, ScatterStrategy.GATHER: hg}
        return [by_strategy[strategy] if strategy in by_strategy else sc.scatter_kernel(mode, fusion, self.config.media is Media.ONEHOT).module]

    def integrate(self, shards: list[VoxelMap], scan: ScanPayload, lanes: ShardLanes | None = None) -> IntegrationStats:
        """Threshold, lengths and media of one scan, then its scatter into ``shards`` (the points split over
        them, on ``lanes`` when given); returns the insertion's stats. Raises ValueError, before anything
        is written, when a point's kernel would reach past the map's key range."""
        c = self.config
        stats = IntegrationStats(input_points=len(scan.points))
        keep = np.ones(len(scan.points), dtype=bool)
        if c.uncertainty_threshold:
            keep, stats.uncertainty_threshold = threshold_mask(c, scan.uncertainty, scan.labels)
        points, unc = scan.points[keep], scan.uncertainty[keep]
        stats.kept_points = len(points)
        onehot = c.media is Media.ONEHOT
        media = scan.labels[keep] if onehot else scan.probability_rows(keep)
        mode, fusion, strategy = self._scatter_form()
        if fusion == sc.FUSION_DEMPSTER:
            media = dirichlet_beliefs(media, unc)
        if mode == sc.MODE_OWN_VOXEL:
            sigma0, lengths = 1.0, np.full(len(points), c.resolution_m)
        else:
            sigma0, lengths = c.sigma0, self.kernel_lengths(unc)
        if lanes is not None and len(points):  # each shard checks its own part: the whole scan first, so a refusal writes nothing
            shards[0]._check_reach(points, float(np.max(lengths)))

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            kw = {"labels": media[part]} if onehot else {"class_weights": media[part]}
            if strategy is ScatterStrategy.SORTED:
                return shard.scatter_sorted(points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            if strategy is ScatterStrategy.GATHER:
                return shard.scatter_hashgrid(points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            return shard.scatter(points[part], lengths[part], unc[part], mode=mode, sigma0=sigma0, fusion=fusion, **kw)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(points), job))
        return stats


@register_integrator(Compat.CLEAN, Kernel.COMPOUND)
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
            return shard.scatter(centers[part], np.full(len(part), c.resolution_m), mean_uncertainty[part], mode=sc.MODE_STENCIL,
                                 sigma0=1.0, class_weights=summed[part, :k], stencil_weights=self.weights)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(centers), job))
        return stats


def _free_samples_need(method: str) -> ScanNeeds:
    return ScanNeeds(SensorOrigin.REQUIRED, f"{method} adds the sensor origin (and free-space rays) as free samples")


@register_integrator(Compat.CLEAN, Kernel.TRIANGULAR)
class SeeCsomIntegrator:
    """Training data as its code builds it (VoxelGrid with majority labels, the sensor origin as the
    one free sample: its configs' free_resolution of 1000 m), then block statistics and the scatter."""

    grid_offset_m = 0.0

    def __init__(self, config: MappingConfig, num_classes: int):
        self.config = config
        self.num_classes = num_classes
        self.needs = _free_samples_need(config.method)

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
            return shard.scatter_block_targets(points[part], labels[part], unc[part], owners[part], lengths[part], see_csom.CELLS_PER_BLOCK)

        return launch_step(stats, lambda shards, lanes: total_updates(split_over_shards(shards, lanes, len(points), job)))


@register_integrator(Compat.SBKI, Kernel.SPARSE, Kernel.COUNT)
class SbkiCompatIntegrator:
    """S-BKI (sparse kernel) or S-CSM (count kernel, one-cell blocks on the half-shifted grid)."""

    def __init__(self, config: MappingConfig, num_classes: int | None = None):
        self.config = config
        self.needs = _free_samples_need(config.method)
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
            shard.insert_blocks(sbki_compat.test_blocks(owners[part]), self.cells_per_block, mark_touched=False)
            ids = point_ids[part]
            return shard.scatter(points[ids].astype(np.float64), np.full(len(ids), c.resolution_m), np.zeros(len(ids)),
                                 mode=sc.MODE_SBKI_OWN_BLOCK, sigma0=1.0, labels=labels[ids], owner_blocks=owners[part],
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
        # numpy's takes here measured faster than the sorted_block_points kernel on Warp's CPU backend (free_res 0.5,
        # 30 bench scans: ~0.19 s against 0.27 s); scaled in place, as scale_points scales
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


@register_integrator(Compat.RELEASE, Kernel.SPARSE)
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


def releasing(run, scratch: DeviceScratch):
    """``run`` (shards, lanes) -> updates, releasing ``scratch`` once its kernels are done: when it returns,
    or when its shard jobs have (``when_done``); also when it fails."""

    def run_then_release(shards: list[VoxelMap], lanes: ShardLanes | None):
        try:
            updates = run(shards, lanes)
        except BaseException:
            scratch.release()
            raise
        when_done(updates, scratch.release)
        return updates

    return run_then_release


def block_gather_run(blocks: np.ndarray, cells_per_block: int, kernel_factory, scan, kind: str):
    """run(shards, lanes) -> updates for a block-gather kernel (``kernel_factory(K, cells per block)``)
    over target ``blocks`` [B, 3] (the blocks of ``scan``, its inputs struct): the key range is checked
    before any launch, and each block is gathered in the shard its index picks, so a cell is always summed
    in the same shard in the same order and the map is bit for bit the same for any number of workers."""

    def run(shards: list[VoxelMap], lanes: ShardLanes | None) -> int | PendingUpdates:
        kernel = kernel_factory(shards[0].num_classes, cells_per_block)
        shards[0].load_kernel(kernel)
        return _gather_over_shards(shards, lanes, kernel, scan, blocks, cells_per_block, kind)

    return run


def _gather_over_shards(shards, lanes, kernel, scan, blocks: np.ndarray, cells_per_block: int, kind: str) -> int | PendingUpdates:
    shards[0].check_block_range(blocks, cells_per_block)
    owner = block_shard(blocks, len(shards))

    def job(shard: VoxelMap, index: int) -> int:
        return shard.gather_blocks(kernel, scan, np.flatnonzero(owner == index), block_count=len(blocks), cells_per_block=cells_per_block, kind=kind)

    return total_updates(for_each_shard(shards, lanes, job))


def counted_gather_launch(stats: IntegrationStats, pool: ScratchPool, device: str, build, cells_per_block: int, kernel_factory, kind: str) -> Launch:
    """The launch of a block gather whose inputs the map's device prepared without reading a count back:
    ``build(scratch)`` -> (the kernel's inputs struct, their ``sbki_device.DeviceBlocks``), or the Launch of
    the host path where the device path does not apply, run with a set of ``pool``'s scratch.

    The gather reads the scan's status back with its counters, the scan's one read (a map of one shard
    whose blocks' box lies within the key range; otherwise the status and the blocks are read for the key
    range check and the shards' split). A scan whose status says it ran out of room gathered nothing: it is
    built again with room for what it counted and gathered again, in the launch. ``stats.kept_points``
    comes from the status."""
    with pool.taken(device) as scratch, device_calls(device):
        built = build(scratch)
    if not isinstance(built, tuple):  # the host path
        scratch.release()
        return built

    def run(shards: list[VoxelMap], lanes: ShardLanes | None) -> int | PendingUpdates:
        kernel = kernel_factory(shards[0].num_classes, cells_per_block)
        shards[0].load_kernel(kernel)
        scan, targets = built
        while True:
            if len(shards) == 1 and targets.box is not None and VoxelMap.block_range_holds(np.stack(targets.box), cells_per_block):
                updates, status = shards[0].gather_counted_blocks(kernel, scan, targets.capacity, targets.count, targets.status,
                                                                  cells_per_block=cells_per_block, kind=kind)
            else:
                status = targets.status.numpy()
                updates = 0 if status[STATUS_OVERFLOW] else _gather_over_shards(shards, lanes, kernel, scan, targets.host(), cells_per_block, kind)
            if not status[STATUS_OVERFLOW]:
                stats.kept_points = int(status[STATUS_KEPT_POINTS])
                return updates
            scratch.learn(status)
            rebuilt = build(scratch.begin())
            if not isinstance(rebuilt, tuple):  # with all its rows, the scan takes the host path (its blocks are too spread)
                host = rebuilt(shards, lanes)
                stats.kept_points = host.kept_points
                return host.voxel_updates
            scan, targets = rebuilt

    return launch_step(stats, releasing(run, scratch))
