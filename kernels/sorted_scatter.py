"""Sort-then-reduce integration of the radius kernel (Warp): the deterministic alternative to the
atomic scatter of ``kernels.scatter`` (MODE_RADIUS, Bayes fusion).

1. ``count_pairs``: how many voxels each point's kernel reaches (the scatter's traversal,
   ``kernels.scatter.walk_kernel``, with a counting visit); an exclusive scan turns counts into offsets.
2. ``expand_pairs``: one (voxel key, pair id) per reached voxel (the same traversal); the pairs are
   radix-sorted by key (``wp.utils.radix_sort_pairs``, stable: a voxel's pairs stay in point order).
3. ``mark_heads`` + a scan number the distinct voxels; ``reduce_voxels``: one thread per distinct voxel
   finds or inserts it once and adds its pairs' sums into its row once. No atomics on the map, and
   every sum runs in a fixed order, so the map is the same bit for bit on any device and thread count.

numpy twin: ``evsemmap_warp/reference/sorted_scatter.py`` (and ``reference/scatter.py``'s ``scatter_points`` with MODE_RADIUS).
"""

import warp as wp

from . import MODULE_OPTIONS
from .hash_table import pack_key, table_find_or_insert, unpack_key
from .scatter import (EXTRA_COLUMNS_CONST, ZERO64, REACH_BALL, MapTarget, ScanPoints, ScatterParams, Span, Visit, add_height, add_label_evidence,
                      add_weighted_evidence, count_from_zero, end_nothing, height_offset, sparse_weight, tally_row, touch_row, walk_kernel)

wp.set_module_options(MODULE_OPTIONS)

f64 = wp.float64


@wp.struct
class PairCounts:
    """``counts`` [N]: how many voxels point i reaches."""

    counts: wp.array(dtype=int)


@wp.struct
class PairList:
    """Point i's pairs at ``offsets[i]``...: the voxel's key, the pair's own index (the sort's payload),
    the point and its weight."""

    offsets: wp.array(dtype=int)
    keys: wp.array(dtype=wp.int64)
    ids: wp.array(dtype=int)
    point: wp.array(dtype=int)
    weight: wp.array(dtype=wp.float64)


@wp.func
def _count_voxel(scan: ScanPoints, params: ScatterParams, out: PairCounts, t: int, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64,
                 span: Span, counter: wp.int64) -> wp.int64:
    return counter + wp.int64(1)


@wp.func
def _store_count(scan: ScanPoints, out: PairCounts, t: int, i: int, counter: wp.int64):
    out.counts[i] = int(counter)


@wp.func
def _from_offset(scan: ScanPoints, out: PairList, t: int, i: int) -> wp.int64:
    return wp.int64(out.offsets[i])


@wp.func
def _write_pair(scan: ScanPoints, params: ScatterParams, out: PairList, t: int, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64,
                span: Span, counter: wp.int64) -> wp.int64:
    k = int(counter)
    out.keys[k] = pack_key(cell[0], cell[1], cell[2])
    out.ids[k] = k
    out.point[k] = i
    out.weight[k] = sparse_weight(scan, params, i, p, cell, d2, span, ZERO64)
    return counter + wp.int64(1)


# (scan: ScanPoints with points and lengths, params: ScatterParams, out): thread i walks point i.
count_pairs = walk_kernel(REACH_BALL, Visit(PairCounts, count_from_zero, _count_voxel, _store_count, indexed=False), module=__name__)
expand_pairs = walk_kernel(REACH_BALL, Visit(PairList, _from_offset, _write_pair, end_nothing, indexed=False), module=__name__)


@wp.kernel
def mark_heads(sorted_keys: wp.array(dtype=wp.int64), heads: wp.array(dtype=int)):
    """Kernel, one thread per sorted pair: heads[i] = 1 where a run of equal keys starts (i = 0 or a key
    other than the one before), else 0."""
    i = wp.tid()
    if i == 0 or sorted_keys[i] != sorted_keys[i - 1]:
        heads[i] = 1
    else:
        heads[i] = 0


@wp.kernel
def segment_starts(heads: wp.array(dtype=int), head_rank: wp.array(dtype=int), starts: wp.array(dtype=int)):
    """starts[v] = first sorted pair of distinct voxel v (head_rank: inclusive scan of heads)."""
    i = wp.tid()
    if heads[i] == 1:
        starts[head_rank[i] - 1] = i


@wp.struct
class SortedPairs:
    """The pairs sorted by key: distinct voxel v owns sorted pairs ``starts[v]`` .. ``starts[v + 1] - 1``
    (the last runs to ``count``); ``keys`` and ``ids`` sorted, ``point`` and ``weight`` by pair id."""

    starts: wp.array(dtype=int)
    count: int
    keys: wp.array(dtype=wp.int64)
    ids: wp.array(dtype=int)
    point: wp.array(dtype=int)
    weight: wp.array(dtype=wp.float64)


def _reduce_kernel(evidence):
    @wp.kernel(module=__name__)
    def reduce_voxels(pairs: SortedPairs, scan: ScanPoints, params: ScatterParams, out: MapTarget):
        """Distinct voxel v: one find-or-insert, then its row gets the sums of its pairs, in pair order
        (the evidence through ``evidence``, the bookkeeping and the weighted height once)."""
        v = wp.tid()
        first = pairs.starts[v]
        last = pairs.count
        if v + 1 < pairs.starts.shape[0]:
            last = pairs.starts[v + 1]
        row = table_find_or_insert(out.table, pairs.keys[first])
        if row < 0:
            out.failed[v] = 1
            return
        touch_row(out.voxel_data, row)
        iz = unpack_key(pairs.keys[first])[2]
        weight_sum = ZERO64
        weighted_u = ZERO64
        weighted_h = ZERO64
        for j in range(first, last):
            pair = pairs.ids[j]
            i = pairs.point[pair]
            w = pairs.weight[pair]
            wp.static(evidence)(scan, params, out.voxel_data, row, i, w, 0)
            weight_sum += w
            weighted_u += w * scan.uncertainty[i]
            weighted_h += w * height_offset(iz, params.resolution, params.grid_offset, scan.points[i][2])
        tally_row(out.voxel_data, row, out.voxel_data.shape[1] - EXTRA_COLUMNS_CONST, weight_sum, weighted_u, f64(last - first))
        add_height(out.voxel_data, row, weighted_h)

    return reduce_voxels


_REDUCE_KERNELS = {True: _reduce_kernel(add_label_evidence), False: _reduce_kernel(add_weighted_evidence)}


def reduce_voxels_kernel(use_labels: bool):
    """``reduce_voxels`` (pairs: SortedPairs, scan: ScanPoints, params: ScatterParams, out: MapTarget) for
    labels or class weights."""
    return _REDUCE_KERNELS[bool(use_labels)]


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"reduce_voxels": reduce_voxels_kernel}


def sorted_pairs(*, starts, count: int, keys, ids, point, weight) -> SortedPairs:
    """The ``SortedPairs`` struct (host side, no copy) over the sorted pairs and the start of each distinct
    key's run."""
    pairs = SortedPairs()
    pairs.starts, pairs.count, pairs.keys, pairs.ids, pairs.point, pairs.weight = starts, int(count), keys, ids, point, weight
    return pairs


def pair_counts(counts) -> PairCounts:
    """The ``PairCounts`` struct (host side, no copy): ``counts`` [N], the voxels each point reaches."""
    out = PairCounts()
    out.counts = counts
    return out


def pair_list(*, offsets, keys, ids, point, weight) -> PairList:
    """The ``PairList`` struct (host side, no copy): where each point's pairs start, and the pairs' keys,
    ids, points and weights."""
    out = PairList()
    out.offsets, out.keys, out.ids, out.point, out.weight = offsets, keys, ids, point, weight
    return out
