"""The clean mode's point kernels (docs/algorithm.md §3): S-BKI, EBS, the Prob. ablations and
Dempster-Shafer (the sparse kernel), S-CSM (the counting model). Each point scatters into the voxels
its kernel reaches, through one of three strategies (``mapping.clean.scatter_strategy``): the atomic
scatter (``integrators.scatter``), sort-then-reduce (``kernels.sorted_scatter``) or the hash-grid gather
(``kernels.hashgrid_gather``), the same map summed in a fixed order."""

from __future__ import annotations

import numpy as np
import warp as wp

from ...config import ConfigError, Kernel, MappingConfig, Media, ScatterStrategy
from ...kernels import hash_table as ht
from ...kernels import hashgrid_gather as hg
from ...kernels import load_once
from ...kernels import scatter as sc
from ...kernels import sorted_scatter as ss
from ...methods import convbki
from ...methods.device_scratch import counts_with_room, inclusive_scan, last_value, offsets_and_total
from ..shards import ShardLanes, split_over_shards, total_updates
from ..voxel_map import LAUNCH_FILL_LIMIT, VoxelMap, next_pow2
from .base import IntegrationStats, Launch, ScanNeeds, ScanPayload, dirichlet_beliefs, integrate_at_launch, scatter_fusion, threshold_mask
from .scatter import radius_scan, scatter


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
        self.gains = learned_class_gains(config, num_classes) if config.class_gains else None

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
        if self.gains is not None:
            media = media * self.gains
        mode, fusion, strategy = self._scatter_form()
        if fusion == sc.FUSION_DEMPSTER:
            media = dirichlet_beliefs(media, unc)
        if mode == sc.MODE_OWN_VOXEL:
            sigma0, lengths = 1.0, np.full(len(points), c.resolution_m)
        else:
            sigma0, lengths = c.sigma0, self.kernel_lengths(unc)
        if lanes is not None and len(points):  # each shard checks its own part: the whole scan first, so a refusal writes nothing
            shards[0].check_reach(points, float(np.max(lengths)))

        def job(shard: VoxelMap, part: np.ndarray) -> int:
            kw = {"labels": media[part]} if onehot else {"class_weights": media[part]}
            if strategy is ScatterStrategy.SORTED:
                return scatter_sorted(shard, points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            if strategy is ScatterStrategy.GATHER:
                return scatter_hashgrid(shard, points[part], lengths[part], unc[part], sigma0=sigma0, **kw)
            reach = float(np.max(lengths[part], initial=0.0))
            return scatter(shard, points[part], lengths[part], unc[part], mode=mode, sigma0=sigma0, fusion=fusion, reach=reach, **kw)

        stats.voxel_updates = total_updates(split_over_shards(shards, lanes, len(points), job))
        return stats


def learned_class_gains(config: MappingConfig, num_classes: int | None) -> np.ndarray:
    """[K] the class gains of ``mapping.class_gains`` (``methods.convbki.class_gains``) from the learned
    lengths in ``mapping.convbki.lengths_file``; a ConfigError names the key when there is no file."""
    if not config.convbki.lengths_file:
        raise ConfigError(f"mapping.convbki.lengths_file = '': method {config.method} (class_gains: true) scales each class by the "
                          f"kernel mass of its learned ConvBKI lengths; learn them with `evsemmap train-convbki` and name the file")
    if num_classes is None:
        raise ValueError("class gains need the map's class count")
    lengths = convbki.load_lengths(config.convbki.lengths_file, num_classes)
    return convbki.class_gains(lengths, config.resolution_m, config.convbki.stencil_half)


def scatter_sorted(shard: VoxelMap, points: np.ndarray, lengths: np.ndarray, point_uncertainty: np.ndarray, *, sigma0: float,
                   labels: np.ndarray | None = None, class_weights: np.ndarray | None = None) -> int:
    """The radius kernel (MODE_RADIUS, Bayes) by sort-then-reduce (``kernels.sorted_scatter``): the
    same map as ``scatter``, summed in a fixed order (bit-identical on every device). Returns updates."""
    n = len(points)
    if n == 0:
        return 0
    shard.check_reach(points, float(np.max(lengths)))
    load_once(ss, shard.device)
    d = shard.device
    scan = radius_scan(shard, points, lengths, point_uncertainty, labels, class_weights)
    params = sc.scatter_params(resolution=shard.resolution_m, grid_offset=shard.grid_offset_m, sigma0=sigma0)
    scratch = shard.scratch.begin()
    counts = counts_with_room(n, scratch)
    wp.launch(ss.count_pairs, dim=n, device=d, inputs=[scan, params, ss.pair_counts(counts)])
    offsets, pairs = offsets_and_total(counts, scratch)
    if pairs == 0:
        return 0
    keys = scratch.empty(2 * pairs, wp.int64)  # radix_sort_pairs needs room for 2x
    ids = scratch.empty(2 * pairs, int)
    pair_point = scratch.empty(pairs, int)
    pair_weight = scratch.empty(pairs, wp.float64)
    wp.launch(ss.expand_pairs, dim=n, device=d, inputs=[scan, params, ss.pair_list(offsets=offsets, keys=keys, ids=ids, point=pair_point,
                                                                                     weight=pair_weight)])
    wp.utils.radix_sort_pairs(keys, ids, pairs)
    heads = scratch.empty(pairs, int)
    wp.launch(ss.mark_heads, dim=pairs, device=d, inputs=[keys, heads])
    rank = inclusive_scan(heads, scratch)
    distinct = last_value(rank)
    starts = scratch.empty(distinct, int)
    wp.launch(ss.segment_starts, dim=pairs, device=d, inputs=[heads, rank, starts])
    shard.reserve(distinct)  # every distinct voxel fits: the reduction never fails for room
    sorted_pairs = ss.sorted_pairs(starts=starts, count=pairs, keys=keys, ids=ids, point=pair_point, weight=pair_weight)
    shard.launch_reserved(distinct, lambda failed: wp.launch(ss.reduce_voxels_kernel(labels is not None), dim=distinct, device=d, inputs=[
        sorted_pairs, scan, params, shard.target(failed)]), "the sorted reduction")
    return pairs


def scatter_hashgrid(shard: VoxelMap, points: np.ndarray, lengths: np.ndarray, point_uncertainty: np.ndarray, *, sigma0: float,
                     labels: np.ndarray | None = None, class_weights: np.ndarray | None = None) -> int:
    """The radius kernel (MODE_RADIUS, Bayes) in gather form through ``wp.HashGrid``
    (``kernels.hashgrid_gather``): the same map as ``scatter``, each voxel summed once in the grid's
    fixed neighbour order. Returns updates."""
    n = len(points)
    if n == 0:
        return 0
    longest = float(np.max(lengths))
    shard.check_reach(points, longest)
    load_once(hg, shard.device)
    d = shard.device
    scan = radius_scan(shard, points, lengths, point_uncertainty, labels, class_weights)
    params = sc.scatter_params(resolution=shard.resolution_m, grid_offset=shard.grid_offset_m, sigma0=sigma0)
    # The scan's reached voxels, in a key set sized for a voxel per point and grown when it is not enough.
    scratch = shard.scratch.begin()
    capacity = next_pow2(4 * n + 16)
    while True:
        scan_keys = scratch.full(capacity, ht.EMPTY_KEY, wp.int64)
        scan_rows = scratch.zeros(capacity, wp.int32)
        count_and_failed = scratch.zeros(2, int)  # the key set's count and its failure flag, read together
        reached = hg.reached_keys(ht.hash_table(scan_keys, scan_rows, count_and_failed[0:1], max(1, int(capacity * LAUNCH_FILL_LIMIT))),
                                  count_and_failed[1:2])
        wp.launch(hg.mark_reached, dim=n, device=d, inputs=[scan, params, reached])
        reached_count, key_set_failed = (int(value) for value in count_and_failed.numpy())
        if not key_set_failed:
            break
        capacity *= 4
    grid = shard.kept.get("hash_grid")
    if grid is None:
        grid = shard.kept["hash_grid"] = wp.HashGrid(128, 128, 128, device=d, dtype=wp.float64)
    grid.build(scan.points, longest)
    shard.reserve(reached_count)  # every reached voxel fits: the gather never fails for room
    return shard.launch_reserved(capacity, lambda failed: wp.launch(hg.gather_voxels_kernel(labels is not None), dim=capacity, device=d, inputs=[
        scan_keys, grid.id, wp.float64(longest), scan, params, shard.target(failed)]), "the hash-grid gather")
