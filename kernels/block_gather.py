"""The original S-BKI's block update as a gather kernel (docs/compatibility.md §1) (Warp).

S-BKI predicts, for every test block T (a block holding points or a face neighbour of one), from the
points of the blocks of T's extended block (T and its 6 face neighbours). Here one thread per test
block finds or inserts its cells once, reads those points once and weighs each against all of T's
cells, with the same float64 reach test and float32 kernel as the scatter form (``kernels.scatter``
MODE_SBKI_BLOCKS): one table probe per cell instead of two per update, no atomics, and a fixed order
for every sum. A point beyond reach of the block's cell-centre box is skipped with one test.

The kernel is made per (class count, cells per block) (``gather_sbki_kernel``); its loops are not
unrolled (a 4 s cold compile instead of 30 s, at the same speed).

numpy twin: ``evsemmap_warp/reference/block_gather.py``.
"""

import functools

import warp as wp

from .hash_table import pack_key, table_find_or_insert
from .scatter import _HALF, _ONE, _ZERO, COL_HITS, COL_TOUCHED, COL_WEIGHT, SBKI_REACH_FACTOR, sbki_sparse_kernel, sbki_voxel_center

wp.set_module_options({"enable_backward": False})

f64 = wp.float64


# A point is skipped when its squared distance to the block's cell-centre box exceeds the squared reach
# by this factor: the reach test is a filter (the kernel is zero from length on, the reach is 1.05 length).
BOX_SKIP_MARGIN = 1.0 + 1e-9


@wp.func
def box_distance2(lo: wp.vec3d, hi: wp.vec3d, p: wp.vec3d):
    """Squared distance from p to the box [lo, hi] (0 inside)."""
    dx = wp.max(wp.max(lo[0] - p[0], p[0] - hi[0]), _ZERO)
    dy = wp.max(wp.max(lo[1] - p[1], p[1] - hi[1]), _ZERO)
    dz = wp.max(wp.max(lo[2] - p[2], p[2] - hi[2]), _ZERO)
    return dx * dx + dy * dy + dz * dz


@functools.cache
def gather_sbki_kernel(num_classes: int, cells_per_block: int):
    n = cells_per_block
    n3 = n * n * n
    cell_sums = wp.types.matrix(shape=(n3, num_classes), dtype=wp.float64)
    cell_scalars = wp.types.vector(length=n3, dtype=wp.float64)
    cell_slots = wp.types.vector(length=n3, dtype=int)

    @wp.kernel(module="unique", module_options={"max_unroll": 1})
    def gather_sbki_blocks(
        test_blocks: wp.array(dtype=wp.vec3i),
        launch_ids: wp.array(dtype=int),
        block_ids: wp.array(dtype=int),
        sources: wp.array2d(dtype=int),
        point_start: wp.array(dtype=int),
        points: wp.array(dtype=wp.vec3d),
        labels: wp.array(dtype=int),
        length: wp.float64,
        sigma0: wp.float64,
        resolution: wp.float64,
        grid_offset: wp.float64,
        table_keys: wp.array(dtype=wp.int64),
        key_count: wp.array(dtype=int),
        max_count: int,
        voxel_data: wp.array2d(dtype=wp.float64),
        failed: wp.array(dtype=int),
        update_count: wp.array(dtype=wp.int64),
    ):
        """Test block test_blocks[block_ids[launch_ids[t]]]: its cells are found or inserted (none fits:
        failed[t], nothing added) and marked touched; for each of its 7 source blocks sources[b, :] (-1:
        holds no points; block s owns points point_start[s]:point_start[s + 1]), each point adds the S-BKI
        kernel (where positive) for its label to every cell whose centre lies within 1.05 * length."""
        t = wp.tid()
        b = block_ids[launch_ids[t]]
        first = test_blocks[b] * n - wp.vec3i(n // 2, n // 2, n // 2)
        # The block's cells are found or inserted first: a block that does not fit adds nothing and is
        # relaunched after the table grew.
        slots = cell_slots()
        for j in range(n3):
            slot = table_find_or_insert(table_keys, key_count, max_count, pack_key(first[0] + j // (n * n), first[1] + (j // n) % n, first[2] + j % n))
            if slot < 0:
                failed[t] = 1
                return
            slots[j] = slot
        reach = length * f64(SBKI_REACH_FACTOR)
        reach2 = reach * reach
        length32 = float(length)
        sigma32 = float(sigma0)
        resolution32 = float(resolution)
        offset32 = float(grid_offset)
        evidence = cell_sums()
        weight_sum = cell_scalars()
        hits = cell_scalars()
        # The cell centres' box: a point beyond reach of it is beyond reach of every cell centre, so it
        # is skipped with one test (the margin covers rounding differences between the two forms).
        box_lo = wp.vec3d((f64(first[0]) + _HALF) * resolution + grid_offset, (f64(first[1]) + _HALF) * resolution + grid_offset,
                          (f64(first[2]) + _HALF) * resolution + grid_offset)
        box_hi = wp.vec3d((f64(first[0] + n - 1) + _HALF) * resolution + grid_offset, (f64(first[1] + n - 1) + _HALF) * resolution + grid_offset,
                          (f64(first[2] + n - 1) + _HALF) * resolution + grid_offset)
        skip2 = reach2 * f64(BOX_SKIP_MARGIN)
        for f in range(sources.shape[1]):
            s = sources[b, f]
            if s >= 0:
                for q in range(point_start[s], point_start[s + 1]):
                    p = points[q]
                    if box_distance2(box_lo, box_hi, p) > skip2:
                        continue
                    p32 = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
                    label = labels[q]
                    for j in range(n3):
                        ix = first[0] + j // (n * n)
                        iy = first[1] + (j // n) % n
                        iz = first[2] + j % n
                        dx = (f64(ix) + _HALF) * resolution + grid_offset - p[0]
                        dy = (f64(iy) + _HALF) * resolution + grid_offset - p[1]
                        dz = (f64(iz) + _HALF) * resolution + grid_offset - p[2]
                        if dx * dx + dy * dy + dz * dz < reach2:
                            w = f64(sbki_sparse_kernel(sbki_voxel_center(ix, iy, iz, resolution32, offset32), p32, length32, sigma32))
                            if w > _ZERO:  # the C++ adds only positive kernel values
                                evidence[j, label] = evidence[j, label] + w
                                weight_sum[j] = weight_sum[j] + w
                                hits[j] = hits[j] + f64(1.0)
        total = _ZERO
        for j in range(n3):
            slot = slots[j]
            voxel_data[slot, num_classes + COL_TOUCHED] = _ONE
            for c in range(num_classes):
                voxel_data[slot, c] = voxel_data[slot, c] + evidence[j, c]
            voxel_data[slot, num_classes + COL_WEIGHT] = voxel_data[slot, num_classes + COL_WEIGHT] + weight_sum[j]
            voxel_data[slot, num_classes + COL_HITS] = voxel_data[slot, num_classes + COL_HITS] + hits[j]
            total += hits[j]
        wp.atomic_add(update_count, 0, wp.int64(total))

    return gather_sbki_blocks


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_sbki_blocks": gather_sbki_kernel}
