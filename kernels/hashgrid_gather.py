"""Gather integration of the radius kernel through ``wp.HashGrid`` (Warp): the third strategy next to
the atomic scatter (``kernels.scatter``) and sort-then-reduce (``kernels.sorted_scatter``), for the
clean sparse kernel with Bayes fusion.

1. ``mark_reached``: every voxel a point's kernel reaches goes into a scan-local key set (the same
   ranges and distance test as the scatter).
2. ``gather_voxels``: one thread per reached voxel finds or inserts it in the map once, asks the hash
   grid of the scan's points for its neighbours within the longest length, keeps those whose own
   length reaches the voxel centre, and adds their sums into its row once. No atomics on the map; the
   neighbour order is fixed by the grid build, so the map does not depend on threads or devices.

numpy twin: ``evsemmap_warp/reference/hashgrid_gather.py``.
"""

import warp as wp

from .hash_table import table_find_or_insert, unpack_key, pack_key
from .scatter import _EXTRA, _HALF, _ONE, _ZERO, COL_HITS, COL_TOUCHED, COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY, sparse_kernel, voxel_of

wp.set_module_options({"enable_backward": False})

f64 = wp.float64


@wp.kernel
def mark_reached(points: wp.array(dtype=wp.vec3d), lengths: wp.array(dtype=wp.float64), resolution: wp.float64,
                 grid_offset: wp.float64, scan_keys: wp.array(dtype=wp.int64), scan_rows: wp.array(dtype=int),
                 scan_count: wp.array(dtype=int), max_count: int, failed: wp.array(dtype=int)):
    i = wp.tid()
    p = points[i]
    reach = lengths[i]
    reach2 = reach * reach
    for ix in range(voxel_of(p[0] - reach, resolution, grid_offset), voxel_of(p[0] + reach, resolution, grid_offset) + 1):
        dx = (f64(ix) + _HALF) * resolution + grid_offset - p[0]
        for iy in range(voxel_of(p[1] - reach, resolution, grid_offset), voxel_of(p[1] + reach, resolution, grid_offset) + 1):
            dy = (f64(iy) + _HALF) * resolution + grid_offset - p[1]
            for iz in range(voxel_of(p[2] - reach, resolution, grid_offset), voxel_of(p[2] + reach, resolution, grid_offset) + 1):
                dz = (f64(iz) + _HALF) * resolution + grid_offset - p[2]
                if dx * dx + dy * dy + dz * dz < reach2:
                    if table_find_or_insert(scan_keys, scan_rows, scan_count, max_count, pack_key(ix, iy, iz)) < 0:
                        failed[0] = 1


@wp.kernel
def gather_voxels(scan_keys: wp.array(dtype=wp.int64), grid: wp.uint64, points: wp.array(dtype=wp.vec3d),
                  lengths: wp.array(dtype=wp.float64), longest: wp.float64, labels: wp.array(dtype=int),
                  class_weights: wp.array2d(dtype=wp.float64), use_labels: int, point_uncertainty: wp.array(dtype=wp.float64),
                  resolution: wp.float64, grid_offset: wp.float64, sigma0: wp.float64, table_keys: wp.array(dtype=wp.int64),
                  slot_rows: wp.array(dtype=int), key_count: wp.array(dtype=int), max_count: int, voxel_data: wp.array2d(dtype=wp.float64),
                  failed: wp.array(dtype=int), update_count: wp.array(dtype=wp.int64)):
    s = wp.tid()
    key = scan_keys[s]
    if key == wp.int64(-1):
        return
    row = table_find_or_insert(table_keys, slot_rows, key_count, max_count, key)
    if row < 0:
        failed[s] = 1
        return
    v = unpack_key(key)
    cx = (f64(v[0]) + _HALF) * resolution + grid_offset
    cy = (f64(v[1]) + _HALF) * resolution + grid_offset
    cz = (f64(v[2]) + _HALF) * resolution + grid_offset
    num_classes = voxel_data.shape[1] - _EXTRA
    weight_sum = _ZERO
    weighted_u = _ZERO
    hits = int(0)
    query = wp.hash_grid_query(grid, wp.vec3d(cx, cy, cz), longest)
    i = int(0)
    while wp.hash_grid_query_next(query, i):
        p = points[i]
        dx = cx - p[0]
        dy = cy - p[1]
        dz = cz - p[2]
        d2 = dx * dx + dy * dy + dz * dz
        length = lengths[i]
        if d2 < length * length:
            w = sparse_kernel(wp.sqrt(d2), length, sigma0)
            if use_labels == 1:
                voxel_data[row, labels[i]] = voxel_data[row, labels[i]] + w
            else:
                for c in range(num_classes):
                    voxel_data[row, c] = voxel_data[row, c] + w * class_weights[i, c]
            weight_sum += w
            weighted_u += w * point_uncertainty[i]
            hits += 1
    voxel_data[row, num_classes + COL_WEIGHT] = voxel_data[row, num_classes + COL_WEIGHT] + weight_sum
    voxel_data[row, num_classes + COL_WEIGHTED_UNCERTAINTY] = voxel_data[row, num_classes + COL_WEIGHTED_UNCERTAINTY] + weighted_u
    voxel_data[row, num_classes + COL_HITS] = voxel_data[row, num_classes + COL_HITS] + f64(hits)
    voxel_data[row, num_classes + COL_TOUCHED] = _ONE
    wp.atomic_add(update_count, 0, wp.int64(hits))
