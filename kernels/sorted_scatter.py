"""Sort-then-reduce integration of the radius kernel (Warp): the deterministic alternative to the
atomic scatter of ``kernels.scatter`` (MODE_RADIUS, Bayes fusion).

1. ``count_pairs``: how many voxels each point's kernel reaches (the same ranges and distance test as
   the atomic scatter); an exclusive scan turns counts into offsets.
2. ``expand_pairs``: one (voxel key, pair id) per reached voxel; the pairs are radix-sorted by key
   (``wp.utils.radix_sort_pairs``, stable: a voxel's pairs stay in point order).
3. ``mark_heads`` + a scan number the distinct voxels; ``reduce_voxels``: one thread per distinct voxel
   finds or inserts it once and adds its pairs' sums into its row once. No atomics on the map, and
   every sum runs in a fixed order, so the map is the same bit for bit on any device and thread count.

numpy twin: ``evsemmap_warp/reference/scatter.py`` (``scatter_points`` with MODE_RADIUS).
"""

import warp as wp

from .hash_table import pack_key, table_find_or_insert
from .scatter import _HALF, _ONE, _ZERO, COL_HITS, COL_TOUCHED, COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY, sparse_kernel, voxel_of

wp.set_module_options({"enable_backward": False})

f64 = wp.float64


@wp.func
def _axis_range(p: wp.float64, reach: wp.float64, resolution: wp.float64, grid_offset: wp.float64) -> wp.vec2i:
    return wp.vec2i(voxel_of(p - reach, resolution, grid_offset), voxel_of(p + reach, resolution, grid_offset))


@wp.kernel
def count_pairs(points: wp.array(dtype=wp.vec3d), lengths: wp.array(dtype=wp.float64), resolution: wp.float64,
                grid_offset: wp.float64, counts: wp.array(dtype=int)):
    i = wp.tid()
    p = points[i]
    reach = lengths[i]
    reach2 = reach * reach
    rx = _axis_range(p[0], reach, resolution, grid_offset)
    ry = _axis_range(p[1], reach, resolution, grid_offset)
    rz = _axis_range(p[2], reach, resolution, grid_offset)
    n = int(0)
    for ix in range(rx[0], rx[1] + 1):
        dx = (f64(ix) + _HALF) * resolution + grid_offset - p[0]
        for iy in range(ry[0], ry[1] + 1):
            dy = (f64(iy) + _HALF) * resolution + grid_offset - p[1]
            for iz in range(rz[0], rz[1] + 1):
                dz = (f64(iz) + _HALF) * resolution + grid_offset - p[2]
                if dx * dx + dy * dy + dz * dz < reach2:
                    n += 1
    counts[i] = n


@wp.kernel
def expand_pairs(points: wp.array(dtype=wp.vec3d), lengths: wp.array(dtype=wp.float64), resolution: wp.float64,
                 grid_offset: wp.float64, sigma0: wp.float64, offsets: wp.array(dtype=int),
                 pair_keys: wp.array(dtype=wp.int64), pair_ids: wp.array(dtype=int),
                 pair_point: wp.array(dtype=int), pair_weight: wp.array(dtype=wp.float64)):
    """Write point i's pairs at offsets[i]...: key, its own index (the sort's payload), point, weight."""
    i = wp.tid()
    p = points[i]
    length = lengths[i]
    reach2 = length * length
    rx = _axis_range(p[0], length, resolution, grid_offset)
    ry = _axis_range(p[1], length, resolution, grid_offset)
    rz = _axis_range(p[2], length, resolution, grid_offset)
    k = offsets[i]
    for ix in range(rx[0], rx[1] + 1):
        dx = (f64(ix) + _HALF) * resolution + grid_offset - p[0]
        for iy in range(ry[0], ry[1] + 1):
            dy = (f64(iy) + _HALF) * resolution + grid_offset - p[1]
            for iz in range(rz[0], rz[1] + 1):
                dz = (f64(iz) + _HALF) * resolution + grid_offset - p[2]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < reach2:
                    pair_keys[k] = pack_key(ix, iy, iz)
                    pair_ids[k] = k
                    pair_point[k] = i
                    pair_weight[k] = sparse_kernel(wp.sqrt(d2), length, sigma0)
                    k += 1


@wp.kernel
def mark_heads(sorted_keys: wp.array(dtype=wp.int64), heads: wp.array(dtype=int)):
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


@wp.kernel
def reduce_voxels(starts: wp.array(dtype=int), pair_count: int, sorted_keys: wp.array(dtype=wp.int64),
                  sorted_ids: wp.array(dtype=int), pair_point: wp.array(dtype=int), pair_weight: wp.array(dtype=wp.float64),
                  labels: wp.array(dtype=int), class_weights: wp.array2d(dtype=wp.float64), use_labels: int,
                  point_uncertainty: wp.array(dtype=wp.float64), table_keys: wp.array(dtype=wp.int64),
                  slot_rows: wp.array(dtype=int), key_count: wp.array(dtype=int), max_count: int, voxel_data: wp.array2d(dtype=wp.float64),
                  failed: wp.array(dtype=int)):
    """Distinct voxel v: its pairs are sorted pairs starts[v] .. starts[v + 1] - 1 (the last runs to
    pair_count). One find-or-insert, then its row gets the sums of its pairs, in pair order."""
    v = wp.tid()
    first = starts[v]
    last = pair_count
    if v + 1 < starts.shape[0]:
        last = starts[v + 1]
    row = table_find_or_insert(table_keys, slot_rows, key_count, max_count, sorted_keys[first])
    if row < 0:
        failed[v] = 1
        return
    num_classes = voxel_data.shape[1] - 4
    weight_sum = _ZERO
    weighted_u = _ZERO
    for j in range(first, last):
        pair = sorted_ids[j]
        i = pair_point[pair]
        w = pair_weight[pair]
        if use_labels == 1:
            voxel_data[row, labels[i]] = voxel_data[row, labels[i]] + w
        else:
            for c in range(num_classes):
                voxel_data[row, c] = voxel_data[row, c] + w * class_weights[i, c]
        weight_sum += w
        weighted_u += w * point_uncertainty[i]
    voxel_data[row, num_classes + COL_WEIGHT] = voxel_data[row, num_classes + COL_WEIGHT] + weight_sum
    voxel_data[row, num_classes + COL_WEIGHTED_UNCERTAINTY] = voxel_data[row, num_classes + COL_WEIGHTED_UNCERTAINTY] + weighted_u
    voxel_data[row, num_classes + COL_HITS] = voxel_data[row, num_classes + COL_HITS] + f64(last - first)
    voxel_data[row, num_classes + COL_TOUCHED] = _ONE
