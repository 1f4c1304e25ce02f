"""The released EvSemMap's block models as one gather kernel (docs/compatibility.md §4) (Warp).

In the release every block holding points trains a model on the points of its extended block (itself and
its 6 face neighbours) and predicts for the blocks of that extended block that hold points. So a point of
block M reaches a target block T through every occupied model block N with N in M's extended block and T
in N's; targets lie within L1 distance 2 of M. Here each target block is one thread: it finds or inserts
its cells once (through the map's brick cache, as ``kernels.block_gather`` does), then walks the points of
its up to 25 source blocks once, each weighted by how many models carry it (``block_models`` computes both
tables), against all of its cells: a point's kernel values for all cells without branches, which the
compiler turns into vector code (8 cells per AVX-512 register), and the Bayes sums as vectors over the
cells. No model is ever built, no atomics are used, and the order of every sum is fixed, so the map does
not depend on threads. Dempster fusion multiplies commonality ratios and takes their logarithm every 40
factors instead of once per contribution.

The gather kernel is made per (class count, cells per block, fusion) (``gather_release_kernel``) from the
block gathers' one traversal (``kernels.block_gather.block_gather_kernel``); its loops are not unrolled (a
much faster cold compile at the same speed).

numpy twins: ``evsemmap_warp/reference/release.py`` (a literal block-by-block model loop, and the tables).
"""

import functools

import warp as wp

from . import MODULE_OPTIONS
from .block_gather import block_gather_kernel, block_rows_type
from .hash_table import KEY_OFFSET, block_cell, pack_key
from .indexing import nonnegative
from .scatter import ONE64, ZERO64, FUSION_DEMPSTER, discounted_belief, sbki_voxel_center, tally_row, uncommitted_mass

wp.set_module_options(MODULE_OPTIONS)

f64 = wp.float64
_MAX_FACTORS = wp.constant(wp.float64(40.0))  # 1e6^(40 + 7) = 1e282 < float64's 1.8e308


def _sparse_kernel_polynomial(degree: int = 14):
    """Power-series coefficients in s = 2x - 1 of the sparse kernel's shape on x = d / l in [0, 1],
    k(x) = (2 + cos 2 pi x)(1 - x) / 3 + sin(2 pi x) / (2 pi), from a Chebyshev fit: max error 2.5e-9,
    below float32's resolution of the release's own float32 arithmetic; a few FMAs where the C++ calls
    float32 cos and sin."""
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
    s = f64(2.0) * x - ONE64
    s2 = s * s
    s4 = s2 * s2
    c = _POLY_COEFFS
    q0 = (c[0] + c[1] * s) + (c[2] + c[3] * s) * s2
    q1 = (c[4] + c[5] * s) + (c[6] + c[7] * s) * s2
    q2 = (c[8] + c[9] * s) + (c[10] + c[11] * s) * s2
    q3 = (c[12] + c[13] * s) + c[14] * s2
    k = (q0 + q1 * s4) + (q2 + q3 * s4) * (s4 * s4)
    # A select, not an early return, so that loops over cells vectorise.
    return wp.where(x >= ONE64, 0.0, float(wp.max(k, ZERO64)) * sf2)


@wp.func
def integer_power(x: wp.float64, m: int) -> wp.float64:
    """x^m for 0 <= m <= 7 (a model count) by squaring, without a loop."""
    x2 = x * x
    out = ONE64
    if m & 1 != 0:
        out = out * x
    if m & 2 != 0:
        out = out * x2
    if m & 4 != 0:
        out = out * (x2 * x2)
    return out


@functools.cache
def release_blocks_struct(num_classes: int):
    """The gather inputs' struct for K = num_classes: the target ``blocks`` [B], their source blocks
    ``source_blocks`` [B, 25] (indices into ``blocks``, -1 for none) and model counts ``source_mult``, the
    (point, block) rows of block s at ``point_start[s]:point_start[s + 1]`` (``points`` float32 m,
    ``class_weights`` [P] K-vectors, ``uncertainty``), the kernel ``length`` (m, ell * e), ``sigma0`` and
    ``resolution`` (m)."""
    vec_k = vector_type(num_classes)

    @wp.struct
    class ReleaseBlocks:
        blocks: wp.array(dtype=wp.vec3i)
        source_blocks: wp.array2d(dtype=int)
        source_mult: wp.array2d(dtype=int)
        point_start: wp.array(dtype=int)
        points: wp.array(dtype=wp.vec3)
        class_weights: wp.array(dtype=vec_k)
        uncertainty: wp.array(dtype=wp.float64)
        length: wp.float64
        sigma0: float
        resolution: float

    return ReleaseBlocks


def release_blocks(*, blocks, source_blocks, source_mult, point_start, points, class_weights, uncertainty, length: float, sigma0: float,
                   resolution: float):
    """The ``release_blocks_struct`` of class_weights' K over device arrays."""
    inputs = release_blocks_struct(class_weights.dtype._length_)()
    inputs.blocks, inputs.source_blocks, inputs.source_mult, inputs.point_start = blocks, source_blocks, source_mult, point_start
    inputs.points, inputs.class_weights, inputs.uncertainty = points, class_weights, uncertainty
    inputs.length, inputs.sigma0, inputs.resolution = wp.float64(length), float(sigma0), float(resolution)
    return inputs


@functools.cache
def gather_release_kernel(num_classes: int, cells_per_block: int = 2, *, fusion: int = 0, prefetch: bool = True):
    """The gather kernel for K = num_classes, blocks of cells_per_block^3 cells and ``fusion`` (Bayes or
    Dempster, FUSION_*; one Warp module per form, compiled on first use); ``prefetch`` off: the form
    without it, for the study."""
    n = cells_per_block
    n3 = n * n * n
    dempster = fusion == FUSION_DEMPSTER
    Inputs = release_blocks_struct(num_classes)
    cell_sums = wp.types.matrix(shape=(n3, num_classes), dtype=wp.float64)
    # Sums per class and cell, cells along the rows: a point's class row adds to all cells as vectors.
    class_cell_sums = wp.types.matrix(shape=(num_classes, n3), dtype=wp.float64)
    cell_scalars = wp.types.vector(length=n3, dtype=wp.float64)
    cell_rows = block_rows_type(n3)
    cell_centers = wp.types.matrix(shape=(n3, 3), dtype=wp.float32)

    # One function over ~80 lines, and its per-block work one Warp function: the cell sums are local
    # vectors and matrices, which a Warp function takes and returns by value, so a helper per step would
    # copy the block's sums in and out for every point instead of adding to them in registers.
    @wp.func
    def gather_release_block(scan: Inputs, b: int, first: wp.vec3i, rows: cell_rows, voxel_data: wp.array2d(dtype=wp.float64)) -> wp.float64:
        """Target block b, holding its n^3 cells' sums: the points of its source blocks (one row per (point,
        block holding it) pair), each counted source_mult[b, :] times, are read once and weighed against
        every cell (independent chains the CPU overlaps); then k(d) * y (Bayes) or the log commonality
        ratios (Dempster) and the bookkeeping columns go into each cell's row once. Returns the
        contributions."""
        centers = cell_centers()
        for j in range(n3):
            cell = block_cell(first, j, n)
            center = sbki_voxel_center(cell[0], cell[1], cell[2], scan.resolution, 0.0)
            centers[j, 0] = center[0]
            centers[j, 1] = center[1]
            centers[j, 2] = center[2]
        sigma0 = scan.sigma0
        reach = float(scan.length)
        reach2 = reach * reach
        inverse_length = ONE64 / scan.length
        evidence = class_cell_sums()
        # Dempster: products of commonality ratios (each at most 1 / BELIEF_EPSILON = 1e6), folded into the
        # log sums after at most _MAX_FACTORS ratios: about 1 log per cell and class per 40 points instead of 1 per point.
        commonality = cell_sums()
        factors = cell_scalars()
        if wp.static(dempster):
            for j in range(n3):
                for c in range(num_classes):
                    commonality[j, c] = ONE64
        weight_sum = cell_scalars()
        weighted_u = cell_scalars()
        hits = cell_scalars()
        for o in range(scan.source_blocks.shape[1]):
            s = scan.source_blocks[b, o]
            if s >= 0:
                models = scan.source_mult[b, o]
                mult = f64(models)
                for q in range(scan.point_start[s], scan.point_start[s + 1]):
                    p = scan.points[q]
                    y = scan.class_weights[q]
                    u = scan.uncertainty[q]
                    # Kernel values for all cells without branches (0 beyond reach), which vectorise;
                    # adding 0 leaves a sum as it was.
                    weights = cell_scalars()
                    for j in range(n3):
                        dx = centers[j, 0] - p[0]
                        dy = centers[j, 1] - p[1]
                        dz = centers[j, 2] - p[2]
                        d2 = dx * dx + dy * dy + dz * dz
                        weights[j] = wp.where(d2 < reach2, f64(release_sparse_kernel(d2, inverse_length, sigma0)), ZERO64)
                    if wp.static(dempster):
                        # Cell by cell, only where the kernel is positive: faster than as vectors over
                        # all cells (docs/performance.md, "Measurements behind the code's choices").
                        for j in range(n3):
                            w = weights[j]
                            if w > ZERO64:
                                wb = wp.min(w, ONE64)
                                committed = ZERO64
                                for c in range(num_classes):
                                    committed += discounted_belief(y[c], wb)
                                inverse_uncommitted = ONE64 / uncommitted_mass(committed)
                                for c in range(num_classes):
                                    ratio = ONE64 + discounted_belief(y[c], wb) * inverse_uncommitted
                                    commonality[j, c] = commonality[j, c] * integer_power(ratio, models)
                                # each point multiplies in at most 1e6^7 = 1e42; fold before 1e250 could overflow
                                factors[j] = factors[j] + mult
                                if factors[j] > _MAX_FACTORS:
                                    for c in range(num_classes):
                                        evidence[c, j] = evidence[c, j] + wp.log(commonality[j, c])
                                        commonality[j, c] = ONE64
                                    factors[j] = ZERO64
                    else:
                        for c in range(num_classes):
                            for j in range(n3):
                                evidence[c, j] = evidence[c, j] + mult * weights[j] * y[c]
                    for j in range(n3):
                        weight_sum[j] = weight_sum[j] + mult * weights[j]
                        weighted_u[j] = weighted_u[j] + mult * weights[j] * u
                        hits[j] = hits[j] + wp.where(weights[j] > ZERO64, mult, ZERO64)
        total_hits = ZERO64
        for j in range(n3):
            row = rows[j]
            for c in range(num_classes):
                if wp.static(dempster):
                    evidence[c, j] = evidence[c, j] + wp.log(commonality[j, c])
                voxel_data[row, c] = voxel_data[row, c] + evidence[c, j]
            tally_row(voxel_data, row, num_classes, weight_sum[j], weighted_u[j], hits[j])
            total_hits += hits[j]
        return total_hits

    return block_gather_kernel(Inputs, gather_release_block, cells_per_block=n, prefetch=prefetch)


@wp.struct
class BlockLookup:
    """Where a scan's blocks are: a dense ``grid`` of their indices over their bounding box widened by 3,
    from ``lo`` (-1 where none), or, for blocks spread too wide for one, their packed keys ``keys``
    ascending (block s has keys[s])."""

    grid: wp.array3d(dtype=int)
    lo: wp.vec3i
    keys: wp.array(dtype=wp.int64)


@wp.func
def grid_block_index(lookup: BlockLookup, b: wp.vec3i) -> int:
    """Index of block ``b`` (block coordinates) in a dense ``BlockLookup``'s grid; -1 where no block of the
    scan is."""
    g = b - lookup.lo
    return lookup.grid[g[0], g[1], g[2]]


@wp.func
def searched_block_index(lookup: BlockLookup, b: wp.vec3i) -> int:
    """Binary search of b's packed key (-1: absent, or outside the key range)."""
    for axis in range(3):
        if b[axis] < -KEY_OFFSET or b[axis] >= KEY_OFFSET:
            return -1
    key = pack_key(b[0], b[1], b[2])
    lo = int(0)
    hi = lookup.keys.shape[0]
    while lo < hi:
        mid = (lo + hi) / 2
        if lookup.keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < lookup.keys.shape[0]:
        if lookup.keys[lo] == key:
            return lo
    return -1


def _block_models_kernel(block_index):
    @wp.kernel(module=__name__)
    def block_models(blocks: wp.array(dtype=wp.vec3i), block_count: wp.array(dtype=int), lookup: BlockLookup, target_offsets: wp.array(dtype=wp.vec3i),
                     face_offsets: wp.array(dtype=wp.vec3i), models_by_mask: wp.array2d(dtype=int), source_blocks: wp.array2d(dtype=int),
                     source_mult: wp.array2d(dtype=int)):
        """For block b and every target offset o: the block at blocks[b] + o (its index through ``lookup``;
        -1 none) and the number of its models that predict for blocks[b]. Those models are the occupied
        blocks blocks[b] + f (f a face offset or 0) that also lie in the source's extended block, so the
        count is models_by_mask[o, mask of the occupied f]: 7 lookups per block where testing every (o, f)
        took 25 x 7. One thread per block (of block_count[0]), not per block and offset: on the CPU each
        thread has a fixed cost."""
        b = wp.tid()
        if b >= block_count[0]:
            return
        occupied = int(0)
        for f in range(face_offsets.shape[0]):
            if wp.static(block_index)(lookup, blocks[b] + face_offsets[f]) >= 0:
                occupied = occupied | (1 << f)
        for o in range(target_offsets.shape[0]):
            index = wp.static(block_index)(lookup, blocks[b] + target_offsets[o])
            source_blocks[b, o] = index
            source_mult[b, o] = wp.where(index >= 0, models_by_mask[o, occupied], 0)

    return block_models


_BLOCK_MODELS = {True: _block_models_kernel(grid_block_index), False: _block_models_kernel(searched_block_index)}


def block_models_kernel(dense: bool):
    """``block_models`` (blocks, block_count, lookup: BlockLookup, target_offsets, face_offsets, models_by_mask,
    source_blocks, source_mult) through a dense grid or a binary search over the packed keys."""
    return _BLOCK_MODELS[bool(dense)]


def block_lookup(*, grid=None, lo=(0, 0, 0), keys=None) -> BlockLookup:
    """The ``BlockLookup`` struct (host side, no copy): a dense ``grid`` [X, Y, Z] of block indices from
    block coordinates ``lo``, or the scan's sorted packed block ``keys``."""
    lookup = BlockLookup()
    if grid is not None:
        lookup.grid = grid
    lookup.lo = wp.vec3i(*[int(v) for v in lo])
    if keys is not None:
        lookup.keys = keys
    return lookup


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


@wp.func
def _snap_point(p: wp.vec3, lo: wp.vec3, hi: wp.vec3, ds: float) -> wp.vec3:
    last = wp.vec3l(wp.int64((hi[0] - lo[0]) / ds), wp.int64((hi[1] - lo[1]) / ds), wp.int64((hi[2] - lo[2]) / ds))
    return wp.vec3(_snap(p[0], lo[0], hi[0], ds, last[0]), _snap(p[1], lo[1], hi[1], ds, last[1]), _snap(p[2], lo[2], hi[2], ds, last[2]))


@wp.kernel
def snap_to_lines(points: wp.array(dtype=wp.vec3), lo: wp.vec3, hi: wp.vec3, ds: float, snapped: wp.array(dtype=wp.vec3)):
    """The release's coord_to_voxel_center_coord per axis, in float32 as its loop runs: from
    i = trunc((p - lo) / ds) - 1 up to trunc((hi - lo) / ds), the first line lo + i ds with
    p - line < next line - p; none: hi. One thread walks all points (launch with dim=1; a while loop:
    ``kernels.indexing``)."""
    count = points.shape[0]
    n = int(0)
    while n < count:
        snapped[n] = _snap_point(points[n], lo, hi, ds)
        n += 1


@wp.kernel
def keep_first_per_block(cells: wp.array(dtype=int), cap: int, counts: wp.array(dtype=int), keep: wp.array(dtype=wp.uint8)):
    """keep[i] = 1 for the first ``cap`` points (input order) of each cell of a dense grid of blocks;
    ``counts`` zeroed, one entry per cell. One thread walks all points (launch with dim=1): one pass
    where the numpy form sorted the keys (a while loop and nonnegative indices: ``kernels.indexing``)."""
    n = cells.shape[0]
    i = int(0)
    while i < n:
        c = nonnegative(cells[i])
        seen = counts[c]
        keep[i] = wp.uint8(wp.where(seen < cap, 1, 0))
        counts[c] = seen + 1
        i += 1


# ------------------------------------------------------------------ parallel forms of the "ds" step and the rows
# (``methods.release_device``: the host path's results on a device, bit for bit)

# The C++'s block key shift (``methods.release_compat``): int64(x / size + BLOCK_KEY_SHIFT) - BLOCK_KEY_OFFSET.
BLOCK_KEY_SHIFT = wp.constant(wp.float64(524288.5))
BLOCK_KEY_OFFSET = wp.constant(wp.int64(524288))


@wp.kernel
def snapped_block_keys(points: wp.array(dtype=wp.vec3), lo: wp.vec3, hi: wp.vec3, ds: float, block_size: wp.float64,
                       keys: wp.array2d(dtype=wp.int64)):
    """keys[n] = the block point n is counted in by the "ds" step: its snapped point (``snap_to_lines``)
    hashed as the C++ hashes it, one thread per point."""
    n = wp.tid()
    s = _snap_point(points[n], lo, hi, ds)
    for axis in range(3):
        keys[n, axis] = wp.int64(wp.float64(s[axis]) / block_size + BLOCK_KEY_SHIFT) - BLOCK_KEY_OFFSET


@wp.kernel
def keep_first_sorted(order: wp.array(dtype=wp.int64), run_rank: wp.array(dtype=int), starts: wp.array(dtype=wp.int64), cap: int,
                      keep: wp.array(dtype=int)):
    """``keep_first_per_block`` from the points stably sorted by block (``order``; sorted position k in run
    run_rank[k] - 1, which starts at ``starts``): keep[point] = 1 for the first ``cap`` of each run."""
    k = wp.tid()
    keep[int(order[k])] = wp.where(wp.int64(k) - starts[run_rank[k] - 1] < wp.int64(cap), 1, 0)


@wp.kernel
def compact_indices(keep: wp.array(dtype=int), slot: wp.array(dtype=int), kept: wp.array(dtype=int)):
    """kept[slot[i] - 1] = i for every kept i (slot: the inclusive scan of keep): the kept, in order."""
    i = wp.tid()
    if keep[i] == 1:
        kept[slot[i] - 1] = i


@wp.kernel
def take_points(points: wp.array(dtype=wp.vec3), index: wp.array(dtype=int), count: wp.array(dtype=int), taken: wp.array(dtype=wp.vec3)):
    """taken[i] = points[index[i]] for the first count[0] indices."""
    i = wp.tid()
    if i >= count[0]:
        return
    taken[i] = points[index[i]]


@functools.cache
def sorted_rows_kernel(num_classes: int, dempster: bool):
    """rows(points, probabilities [N, K], uncertainty, kept, point_ids, order, pair_count, sorted points, class
    weights, sorted uncertainty): the gather kernel's rows in block order (the first pair_count[0]), row k of kept point
    kept[point_ids[order[k]]]; its class weights the probabilities or, for ``dempster``, the belief masses
    clip(p - u / K, 0, 1) (``core.integrators.dirichlet_beliefs``)."""
    vec_k = vector_type(num_classes)

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def sorted_rows(points: wp.array(dtype=wp.vec3), probabilities: wp.array2d(dtype=wp.float64), uncertainty: wp.array(dtype=wp.float64),
                    kept: wp.array(dtype=int), point_ids: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int64), pair_count: wp.array(dtype=int),
                    sorted_points: wp.array(dtype=wp.vec3), class_weights: wp.array(dtype=vec_k), sorted_uncertainty: wp.array(dtype=wp.float64)):
        k = wp.tid()
        if k >= pair_count[0]:
            return
        i = kept[int(point_ids[int(order[k])])]
        u = uncertainty[i]
        w = vec_k()
        for c in range(wp.static(num_classes)):
            p = probabilities[i, c]
            if wp.static(dempster):
                p = wp.clamp(p - u / wp.float64(wp.static(num_classes)), wp.float64(0.0), wp.float64(1.0))
            w[c] = p
        sorted_points[k] = points[i]
        class_weights[k] = w
        sorted_uncertainty[k] = u

    return sorted_rows


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_release_blocks": gather_release_kernel, "block_models": block_models_kernel, "sorted_rows": sorted_rows_kernel}


def vector_type(num_classes: int):
    """The per-point class-weight row type the kernel for K classes reads."""
    return wp.types.vector(length=num_classes, dtype=wp.float64)
