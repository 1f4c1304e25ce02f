"""Gather integration of the radius kernel through ``wp.HashGrid`` (Warp): the third strategy next to
the atomic scatter (``kernels.scatter``) and sort-then-reduce (``kernels.sorted_scatter``), for the
clean sparse kernel with Bayes fusion.

1. ``mark_reached``: every voxel a point's kernel reaches goes into a scan-local key set (the scatter's
   traversal, ``kernels.scatter.walk_kernel``, with a marking visit).
2. ``gather_voxels``: one thread per reached voxel finds or inserts it in the map once, asks the hash
   grid of the scan's points for its neighbours within the longest length, keeps those whose own
   length reaches the voxel center, and adds their sums into its row once. No atomics on the map; the
   neighbour order is fixed by the grid build, so the map does not depend on threads or devices.

numpy twin: ``evsemmap_warp/reference/hashgrid_gather.py``.
"""

import warp as wp

from . import MODULE_OPTIONS
from .hash_table import HashTable, pack_key, table_find_or_insert, unpack_key
from .scatter import (EXTRA_COLUMNS_CONST, ZERO64, REACH_BALL, MapTarget, ScanPoints, ScatterParams, Span, Visit, add_height, add_label_evidence,
                      add_weighted_evidence, center_offset, count_from_zero, end_nothing, height_offset, sparse_kernel, tally_row, touch_row,
                      walk_kernel)

wp.set_module_options(MODULE_OPTIONS)

f64 = wp.float64


@wp.struct
class ReachedKeys:
    """The scan's reached voxels (a key set with the voxel table's layout); ``failed`` [1] is set when
    it ran out of room."""

    keys: HashTable
    failed: wp.array(dtype=int)


@wp.func
def _mark_voxel(scan: ScanPoints, params: ScatterParams, out: ReachedKeys, t: int, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64,
                span: Span, counter: wp.int64) -> wp.int64:
    if table_find_or_insert(out.keys, pack_key(cell[0], cell[1], cell[2])) < 0:
        out.failed[0] = 1
        return wp.int64(-1)
    return counter


# (scan: ScanPoints with points and lengths, params: ScatterParams, out: ReachedKeys): thread i walks point i.
mark_reached = walk_kernel(REACH_BALL, Visit(ReachedKeys, count_from_zero, _mark_voxel, end_nothing, indexed=False), module=__name__)


def _gather_kernel(evidence):
    @wp.kernel(module=__name__)
    def gather_voxels(scan_keys: wp.array(dtype=wp.int64), grid: wp.uint64, longest: wp.float64, scan: ScanPoints, params: ScatterParams,
                      out: MapTarget):
        """Slot s of the reached-key set: its voxel's row gets the sparse kernel of every point within
        that point's own length, the evidence through ``evidence``, the bookkeeping and the weighted height once."""
        s = wp.tid()
        key = scan_keys[s]
        if key == wp.int64(-1):
            return
        row = table_find_or_insert(out.table, key)
        if row < 0:
            out.failed[s] = 1
            return
        touch_row(out.voxel_data, row)
        v = unpack_key(key)
        center = wp.vec3d(center_offset(v[0], params.resolution, params.grid_offset, ZERO64),
                          center_offset(v[1], params.resolution, params.grid_offset, ZERO64),
                          center_offset(v[2], params.resolution, params.grid_offset, ZERO64))
        weight_sum = ZERO64
        weighted_u = ZERO64
        weighted_h = ZERO64
        hits = int(0)
        query = wp.hash_grid_query(grid, center, longest)
        i = int(0)
        while wp.hash_grid_query_next(query, i):
            p = scan.points[i]
            dx = center[0] - p[0]
            dy = center[1] - p[1]
            dz = center[2] - p[2]
            d2 = dx * dx + dy * dy + dz * dz
            length = scan.lengths[i]
            if d2 < length * length:
                w = sparse_kernel(wp.sqrt(d2), length, params.sigma0)
                wp.static(evidence)(scan, params, out.voxel_data, row, i, w, 0)
                weight_sum += w
                weighted_u += w * scan.uncertainty[i]
                weighted_h += w * height_offset(v[2], params.resolution, params.grid_offset, p[2])
                hits += 1
        tally_row(out.voxel_data, row, out.voxel_data.shape[1] - EXTRA_COLUMNS_CONST, weight_sum, weighted_u, f64(hits))
        add_height(out.voxel_data, row, weighted_h)
        wp.atomic_add(out.update_count, 0, wp.int64(hits))

    return gather_voxels


_GATHER_KERNELS = {True: _gather_kernel(add_label_evidence), False: _gather_kernel(add_weighted_evidence)}


def gather_voxels_kernel(use_labels: bool):
    """``gather_voxels`` (scan_keys, grid, longest, scan: ScanPoints, params: ScatterParams, out: MapTarget)
    for labels or class weights."""
    return _GATHER_KERNELS[bool(use_labels)]


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_voxels": gather_voxels_kernel}


def reached_keys(keys: HashTable, failed) -> ReachedKeys:
    """The ``ReachedKeys`` struct over a key set (``hash_table``) and its ``failed`` [1] flag (host side, no
    copy)."""
    out = ReachedKeys()
    out.keys = keys
    out.failed = failed
    return out
