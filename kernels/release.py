"""The released EvSemMap's block models as one gather kernel (docs/compatibility.md §4) (Warp).

In the release every block holding points trains a model on the points of its extended block (itself
and its 6 face neighbours) and predicts for the blocks of that extended block that hold points. So a
point of block M reaches a target block T through every occupied model block N with N in M's
extended block and T in N's; targets lie within L1 distance 2 of M. Here each target block is one
thread: it finds or inserts its cells once (through the map's brick cache, as ``kernels.block_gather``
does), then walks the points of its up to 25 source blocks once,
each weighted by how many models carry it (``block_models`` computes both tables), against all of its
cells: a point's kernel values for all cells without branches, which the compiler turns into vector
code (8 cells per AVX-512 register), and the Bayes sums as vectors over the cells. No model is ever
built, no atomics are used, and the order of every sum is fixed, so the map does not depend on threads. Dempster fusion multiplies
commonality ratios and takes their logarithm every 40 factors instead of once per contribution.

On the shared bench this form took about half the time of one thread per cell adding into the table
row per contribution (measured while building it; tools/bench_integrate.py has the current figures).
The gather kernel is made per (class count, cells per block) (``gather_release_kernel``); its loops
are not unrolled (a 4 s cold compile instead of 30 s, at the same speed).

numpy twins: ``evsemmap_warp/reference/release.py`` (a literal block-by-block model loop, and the
tables).
"""

import functools

import warp as wp

from .hash_table import PREFETCH_AHEAD, PREFETCH_NEARER, find_block_rows, pack_key, prefetch_brick
from .scatter import (_BELIEF_EPSILON, _ONE, _ZERO, COL_HITS, COL_TOUCHED, COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY,
                      FUSION_DEMPSTER, sbki_voxel_center)

wp.set_module_options({"enable_backward": False})

f64 = wp.float64
_MAX_FACTORS = wp.constant(wp.float64(40.0))  # 1e6^(40 + 7) = 1e282 < float64's 1.8e308


def _sparse_kernel_polynomial(degree: int = 14):
    """Power-series coefficients in s = 2x - 1 of the sparse kernel's shape on x = d / l in [0, 1],
    k(x) = (2 + cos 2 pi x)(1 - x) / 3 + sin(2 pi x) / (2 pi), from a Chebyshev fit: max error 2.5e-9,
    below float32's resolution of the release's own float32 arithmetic; a few FMAs where the C++ calls
    float32 cos and sin (the largest single cost per candidate when this was built)."""
    import numpy as np
    from numpy.polynomial import chebyshev

    x = np.linspace(0.0, 1.0, 20001)
    shape = (2 + np.cos(2 * np.pi * x)) * (1 - x) / 3 + np.sin(2 * np.pi * x) / (2 * np.pi)
    return chebyshev.cheb2poly(chebyshev.chebfit(2 * x - 1, shape, degree))


_POLY = _sparse_kernel_polynomial()
_vec_poly = wp.types.vector(length=len(_POLY), dtype=wp.float64)
_POLY_COEFFS = wp.constant(_vec_poly(*[float(c) for c in _POLY]))
assert len(_POLY) == 15, "release_sparse_kernel's Estrin scheme is written for degree 14"


@wp.func
def release_sparse_kernel(d2: float, inverse_length: wp.float64, sf2: float) -> float:
    """The release's covSparseUnc for a float32 squared distance d2: the distance over ell * e in double
    (times its reciprocal: within an ulp of the C++'s division), the kernel shape (polynomial above, by
    Estrin's scheme: four dependent steps instead of fourteen), times sf2, rounded to float32; 0 from
    d = l on."""
    x = f64(wp.sqrt(d2)) * inverse_length
    s = f64(2.0) * x - _ONE
    s2 = s * s
    s4 = s2 * s2
    c = _POLY_COEFFS
    q0 = (c[0] + c[1] * s) + (c[2] + c[3] * s) * s2
    q1 = (c[4] + c[5] * s) + (c[6] + c[7] * s) * s2
    q2 = (c[8] + c[9] * s) + (c[10] + c[11] * s) * s2
    q3 = (c[12] + c[13] * s) + c[14] * s2
    k = (q0 + q1 * s4) + (q2 + q3 * s4) * (s4 * s4)
    # A select, not an early return, so that loops over cells vectorise.
    return wp.where(x >= _ONE, 0.0, float(wp.max(k, _ZERO)) * sf2)


@wp.func
def integer_power(x: wp.float64, m: int) -> wp.float64:
    """x^m for 0 <= m <= 7 (a model count) by squaring, without a loop."""
    x2 = x * x
    out = _ONE
    if m & 1 != 0:
        out = out * x
    if m & 2 != 0:
        out = out * x2
    if m & 4 != 0:
        out = out * (x2 * x2)
    return out


@functools.cache
def gather_release_kernel(num_classes: int, cells_per_block: int = 2, *, prefetch: bool = True):
    """The gather kernel for K = num_classes and blocks of cells_per_block^3 cells (one Warp module per
    form, compiled on first use); ``prefetch`` off: the form without it, for the study."""
    n = cells_per_block
    n3 = n * n * n
    vec_k = wp.types.vector(length=num_classes, dtype=wp.float64)
    cell_sums = wp.types.matrix(shape=(n3, num_classes), dtype=wp.float64)
    # Sums per class and cell, cells along the rows: a point's class row adds to all cells as vectors.
    class_cell_sums = wp.types.matrix(shape=(num_classes, n3), dtype=wp.float64)
    cell_scalars = wp.types.vector(length=n3, dtype=wp.float64)
    cell_rows = wp.types.vector(length=n3, dtype=int)
    cell_centres = wp.types.matrix(shape=(n3, 3), dtype=wp.float32)

    @wp.kernel(module="unique", module_options={"max_unroll": 1})
    def gather_release_blocks(
        blocks: wp.array(dtype=wp.vec3i),
        launch_ids: wp.array(dtype=int),
        block_ids: wp.array(dtype=int),
        source_blocks: wp.array2d(dtype=int),
        source_mult: wp.array2d(dtype=int),
        point_start: wp.array(dtype=int),
        points: wp.array(dtype=wp.vec3),
        class_weights: wp.array(dtype=vec_k),
        point_uncertainty: wp.array(dtype=wp.float64),
        length: wp.float64,
        sigma0: float,
        resolution: float,
        fusion: int,
        table_keys: wp.array(dtype=wp.int64),
        slot_rows: wp.array(dtype=int),
        key_count: wp.array(dtype=int),
        max_count: int,
        brick_keys: wp.array(dtype=wp.int64),
        brick_rows: wp.array(dtype=int),
        brick_count: wp.array(dtype=int),
        brick_max_count: int,
        voxel_data: wp.array2d(dtype=wp.float64),
        failed: wp.array(dtype=int),
        update_count: wp.array(dtype=wp.int64),
    ):
        """One thread per target block blocks[block_ids[launch_ids[t]]], holding its n^3 cells' sums: the points of
        its source blocks source_blocks[b, :] (indices into ``blocks``, -1 for none; block s owns points
        point_start[s]:point_start[s + 1], one row per (point, block holding it) pair), each counted
        source_mult[b, :] times, are read once and weighed against every cell (independent chains the
        CPU overlaps). Finds or inserts the cells first (none fits: failed[t], nothing added), then adds
        k(d) * y (Bayes) or the log commonality ratios (Dempster) and the bookkeeping columns once per cell."""
        t = wp.tid()
        half = wp.vec3i(n // 2, n // 2, n // 2)
        if wp.static(prefetch):
            last = launch_ids.shape[0] - 1
            prefetch_brick(table_keys, slot_rows, brick_keys, brick_rows, voxel_data, blocks[block_ids[launch_ids[wp.min(t + PREFETCH_AHEAD, last)]]] * n - half,
                           blocks[block_ids[launch_ids[wp.min(t + PREFETCH_NEARER, last)]]] * n - half, n3)
        b = block_ids[launch_ids[t]]
        first = blocks[b] * n - half
        # The block's cells are found or inserted first: a block that does not fit adds nothing and is
        # relaunched after the table grew.
        rows = find_block_rows(cell_rows(), table_keys, slot_rows, key_count, max_count, brick_keys, brick_rows, brick_count, brick_max_count, first, n)
        if rows[0] < 0:
            failed[t] = 1
            return
        centres = cell_centres()
        for j in range(n3):
            centre = sbki_voxel_center(first[0] + j // (n * n), first[1] + (j // n) % n, first[2] + j % n, resolution, 0.0)
            centres[j, 0] = centre[0]
            centres[j, 1] = centre[1]
            centres[j, 2] = centre[2]
        reach = float(length)
        reach2 = reach * reach
        inverse_length = _ONE / length
        evidence = class_cell_sums()
        # Dempster: products of commonality ratios (each at most 1 / BELIEF_EPSILON = 1e6), folded into the
        # log sums after at most _MAX_FACTORS ratios: about 1 log per cell and class per 40 points instead of 1 per point.
        commonality = cell_sums()
        factors = cell_scalars()
        if fusion == FUSION_DEMPSTER:
            for j in range(n3):
                for c in range(num_classes):
                    commonality[j, c] = _ONE
        weight_sum = cell_scalars()
        weighted_u = cell_scalars()
        hits = cell_scalars()
        for o in range(source_blocks.shape[1]):
            s = source_blocks[b, o]
            if s >= 0:
                mult = f64(source_mult[b, o])
                for q in range(point_start[s], point_start[s + 1]):
                    p = points[q]
                    y = class_weights[q]
                    u = point_uncertainty[q]
                    # Kernel values for all cells without branches (0 beyond reach), which vectorise;
                    # adding 0 leaves a sum as it was.
                    weights = cell_scalars()
                    for j in range(n3):
                        dx = centres[j, 0] - p[0]
                        dy = centres[j, 1] - p[1]
                        dz = centres[j, 2] - p[2]
                        d2 = dx * dx + dy * dy + dz * dz
                        weights[j] = wp.where(d2 < reach2, f64(release_sparse_kernel(d2, inverse_length, sigma0)), _ZERO)
                    if fusion == FUSION_DEMPSTER:
                        # Cell by cell, only where the kernel is positive: as vectors over all cells
                        # (ratios of exactly 1 out of reach) this loop measured 1.7x slower.
                        for j in range(n3):
                            w = weights[j]
                            if w > _ZERO:
                                wb = wp.min(w, _ONE)
                                committed = _ZERO
                                for c in range(num_classes):
                                    committed += wp.clamp(y[c] * wb, _ZERO, _ONE - _BELIEF_EPSILON)
                                inverse_uncommitted = _ONE / wp.max(_ONE - committed, _BELIEF_EPSILON)
                                for c in range(num_classes):
                                    ratio = _ONE + wp.clamp(y[c] * wb, _ZERO, _ONE - _BELIEF_EPSILON) * inverse_uncommitted
                                    commonality[j, c] = commonality[j, c] * integer_power(ratio, source_mult[b, o])
                                # each point multiplies in at most 1e6^7 = 1e42; fold before 1e250 could overflow
                                factors[j] = factors[j] + mult
                                if factors[j] > _MAX_FACTORS:
                                    for c in range(num_classes):
                                        evidence[c, j] = evidence[c, j] + wp.log(commonality[j, c])
                                        commonality[j, c] = _ONE
                                    factors[j] = _ZERO
                    else:
                        for c in range(num_classes):
                            for j in range(n3):
                                evidence[c, j] = evidence[c, j] + mult * weights[j] * y[c]
                    for j in range(n3):
                        weight_sum[j] = weight_sum[j] + mult * weights[j]
                        weighted_u[j] = weighted_u[j] + mult * weights[j] * u
                        hits[j] = hits[j] + wp.where(weights[j] > _ZERO, mult, _ZERO)
        k = num_classes
        total_hits = _ZERO
        for j in range(n3):
            row = rows[j]
            voxel_data[row, num_classes + COL_TOUCHED] = _ONE
            for c in range(num_classes):
                if fusion == FUSION_DEMPSTER:
                    evidence[c, j] = evidence[c, j] + wp.log(commonality[j, c])
                voxel_data[row, c] = voxel_data[row, c] + evidence[c, j]
            voxel_data[row, k + COL_WEIGHT] = voxel_data[row, k + COL_WEIGHT] + weight_sum[j]
            voxel_data[row, k + COL_WEIGHTED_UNCERTAINTY] = voxel_data[row, k + COL_WEIGHTED_UNCERTAINTY] + weighted_u[j]
            voxel_data[row, k + COL_HITS] = voxel_data[row, k + COL_HITS] + hits[j]
            total_hits += hits[j]
        wp.atomic_add(update_count, 0, wp.int64(total_hits))

    return gather_release_blocks


@wp.func
def _grid_index(grid: wp.array3d(dtype=int), lo: wp.vec3i, b: wp.vec3i) -> int:
    g = b - lo
    return grid[g[0], g[1], g[2]]


@wp.kernel
def block_models(blocks: wp.array(dtype=wp.vec3i), grid: wp.array3d(dtype=int), lo: wp.vec3i,
                 target_offsets: wp.array(dtype=wp.vec3i), face_offsets: wp.array(dtype=wp.vec3i),
                 models_by_mask: wp.array2d(dtype=int), source_blocks: wp.array2d(dtype=int), source_mult: wp.array2d(dtype=int)):
    """For block b and every target offset o: the block at blocks[b] + o (its index from ``grid``, a
    dense map of the scan's blocks over their bounding box widened by 3; -1 none) and the number of
    its models that predict for blocks[b]. Those models are the occupied blocks blocks[b] + f (f a face
    offset or 0) that also lie in the source's extended block, so the count is
    models_by_mask[o, mask of the occupied f]: 7 lookups per block where testing every (o, f) took 25 x 7.
    One thread per block (one per block and offset took ~1.5x as long on the CPU, where each thread
    has a fixed cost)."""
    b = wp.tid()
    occupied = int(0)
    for f in range(face_offsets.shape[0]):
        if _grid_index(grid, lo, blocks[b] + face_offsets[f]) >= 0:
            occupied = occupied | (1 << f)
    for o in range(target_offsets.shape[0]):
        index = _grid_index(grid, lo, blocks[b] + target_offsets[o])
        source_blocks[b, o] = index
        source_mult[b, o] = wp.where(index >= 0, models_by_mask[o, occupied], 0)


@wp.func
def _line_is_nearer(p: float, lo: float, ds: float, i: wp.int64, last: wp.int64) -> int:
    """1 where the C++ loop stops at line i (i <= last and p - line < next line - p, in float32), else 0."""
    nearer = wp.where(p - (lo + float(i) * ds) < (lo + float(i + wp.int64(1)) * ds) - p, 1, 0)
    return nearer & wp.where(i <= last, 1, 0)


@wp.func
def _snap_from(p: float, lo: float, hi: float, ds: float, i: wp.int64, last: wp.int64) -> float:
    """The C++ loop from line i on."""
    while i <= last:
        if _line_is_nearer(p, lo, ds, i, last) != 0:
            return lo + float(i) * ds
        i += wp.int64(1)
    return hi


@wp.func
def _snap(p: float, lo: float, hi: float, ds: float, last: wp.int64) -> float:
    i = wp.int64((p - lo) / ds) - wp.int64(1)
    # The loop ends at its second or third line for every point inside [lo, hi]: those three tests are
    # made as integer selects, without branches or an early return (as the loop: 41 against 14 ns per point),
    # and the loop goes on from the fourth line only where none holds.
    at0 = _line_is_nearer(p, lo, ds, i, last)
    at1 = _line_is_nearer(p, lo, ds, i + wp.int64(1), last)
    at2 = _line_is_nearer(p, lo, ds, i + wp.int64(2), last)
    line = lo + float(i + wp.int64(wp.where(at0 != 0, 0, wp.where(at1 != 0, 1, 2)))) * ds
    if (at0 | at1 | at2) == 0:
        line = _snap_from(p, lo, hi, ds, i + wp.int64(3), last)
    return line


@wp.kernel
def snap_to_lines(points: wp.array(dtype=wp.vec3), lo: wp.vec3, hi: wp.vec3, ds: float, snapped: wp.array(dtype=wp.vec3)):
    """The release's coord_to_voxel_center_coord per axis, in float32 as its loop runs: from
    i = trunc((p - lo) / ds) - 1 up to trunc((hi - lo) / ds), the first line lo + i ds with
    p - line < next line - p; none: hi. One thread walks all points (launch with dim=1)."""
    last = wp.vec3l(wp.int64((hi[0] - lo[0]) / ds), wp.int64((hi[1] - lo[1]) / ds), wp.int64((hi[2] - lo[2]) / ds))
    for n in range(points.shape[0]):
        p = points[n]
        snapped[n] = wp.vec3(_snap(p[0], lo[0], hi[0], ds, last[0]), _snap(p[1], lo[1], hi[1], ds, last[1]), _snap(p[2], lo[2], hi[2], ds, last[2]))


@wp.kernel
def keep_first_per_block(cells: wp.array(dtype=int), cap: int, counts: wp.array(dtype=int), keep: wp.array(dtype=wp.uint8)):
    """keep[i] = 1 for the first ``cap`` points (input order) of each cell of a dense grid of blocks;
    ``counts`` zeroed, one entry per cell. One thread walks all points (launch with dim=1): one pass
    where the numpy form sorted the keys."""
    for i in range(cells.shape[0]):
        c = cells[i]
        seen = counts[c]
        keep[i] = wp.uint8(wp.where(seen < cap, 1, 0))
        counts[c] = seen + 1


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_release_blocks": gather_release_kernel}


def vector_type(num_classes: int):
    """The per-point class-weight row type the kernel for K classes reads."""
    return wp.types.vector(length=num_classes, dtype=wp.float64)
