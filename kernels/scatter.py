"""Radius-search-and-scatter kernels: one launch integrates one scan into the voxel map (Warp).

Each point visits the voxels its weight function can reach, finds or inserts them in the hash
table and atomically adds weight * y into their Dirichlet concentrations. The traversal is
written once; what changes between methods is the small weight rule chosen by ``mode``:

* ``MODE_RADIUS``: the paper's sparse kernel k'(d, l_i, sigma0) on every voxel whose centre lies
  strictly within the point's own length l_i (S-BKI, EBS and the ablations, "clean" mode).
* ``MODE_OWN_VOXEL``: weight 1 on the voxel containing the point (S-CSM, clean mode).
* ``MODE_SBKI_BLOCKS``: the original S-BKI rule: the sparse kernel evaluated as the C++ does
  (scaled coordinates, float32, negatives clamped), restricted to voxels whose block is the
  point's owner block or one of its 6 face neighbours.
* ``MODE_SBKI_OWN_BLOCK``: the original S-CSM rule: weight 1 on the owner block's single cell.
* ``MODE_STENCIL``: ConvBKI: every voxel of the (2h + 1)^3 cube around the point's voxel, with a
  per-class weight looked up by offset in ``stencil_weights`` (distances between voxel centres).

``fusion`` 1 (Dempster-Shafer, docs/algorithm.md §3.7, radius mode): instead of adding w * y, each point's belief
masses b (``class_weights``) are discounted by min(w, 1) and the voxel accumulates the log
commonality ratios log(1 + b'_c / u'), u' = 1 - sum b'. Dempster's rule multiplies commonalities, so
these sums fuse any number of points in any order; ``mapping.summarize_beliefs`` turns them back
into masses. ``scatter_block_targets`` is SEE-CSOM's block-gated traversal.

In the clean modes every point runs two passes over its voxels: the first finds or inserts all
of them, the second adds. A point whose insertion fails (table full) adds nothing and is flagged
in ``failed``; the host grows the table and relaunches only those points, so each point lands
exactly once. The compat modes only add: their target cells are inserted beforehand.

Arithmetic is float64 throughout (positions relative to the map origin, weights, sums), so evidence
keeps growing on long drives and a far-away scan maps exactly as the same scan near the origin; only
the S-BKI compatibility kernel runs in float32, as the C++ does. A voxel's data lie together in one
row of ``voxel_data`` [capacity, K + 4]: K evidence columns, then the weight sum, the weight *
uncertainty sum, the contribution count and the touched flag (counts in float64 are exact to 2^53).

numpy twin: ``evsemmap_warp/reference/scatter.py``.
"""

import warp as wp

from .hash_table import pack_key, table_find, table_find_or_insert

wp.set_module_options({"enable_backward": False})

MODE_RADIUS = 0
MODE_OWN_VOXEL = 1
MODE_SBKI_BLOCKS = 2
MODE_SBKI_OWN_BLOCK = 3
MODE_STENCIL = 4
FUSION_BAYES = 0
FUSION_DEMPSTER = 1
# Belief masses are clamped to [0, 1 - BELIEF_EPSILON] (docs/algorithm.md §3.7).
BELIEF_EPSILON = 1e-6
# Columns of voxel_data after the K evidence columns.
EXTRA_COLUMNS = 4
COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY, COL_HITS, COL_TOUCHED = range(4)  # offsets from K

# How far past the length the compat scatter searches, a margin: the float32 kernel (pi written as the
# C++'s 3.1415926f) is zero from 0.984 ell on (``kernels.block_gather.SBKI_ZERO_BEYOND``).
SBKI_REACH_FACTOR = 1.05

f64 = wp.float64


def _series_coefficient(n: int) -> float:
    from math import factorial

    return 1.0 / (3.0 * factorial(2 * n)) - 1.0 / factorial(2 * n + 1)


# c_2 .. c_11 of the series in sparse_kernel: ten terms are exact to float64 for t < 1/4.
_C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11 = (wp.constant(f64(_series_coefficient(n))) for n in range(2, 12))
_ZERO = wp.constant(f64(0.0))
_HALF = wp.constant(f64(0.5))
_ONE = wp.constant(f64(1.0))
_QUARTER = wp.constant(f64(0.25))
_THREE = wp.constant(f64(3.0))
_TWO_PI = wp.constant(f64(6.283185307179586))
_SBKI_PI = wp.constant(3.1415926)
_SBKI_REACH = wp.constant(f64(SBKI_REACH_FACTOR))
_BELIEF_EPSILON = wp.constant(f64(BELIEF_EPSILON))
_EXTRA = wp.constant(EXTRA_COLUMNS)


@wp.func
def sparse_kernel(d: wp.float64, length: wp.float64, sigma0: wp.float64) -> wp.float64:
    """k'(d, l, sigma0) (docs/algorithm.md §3.3) for d < l, in float64.

    Near the support edge the closed form is the difference of two O(1 - d/l) terms. With t = 1 - d/l
    and a = 2 pi t the kernel is sigma0 t f(a), f(a) = (2 + cos a) / 3 - sin(a) / a =
    sum_{n>=2} (-1)^n c_n a^(2n), c_n = 1/(3 (2n)!) - 1/(2n+1)!; for t < 1/4 the series is used.
    """
    x = d / length
    t = _ONE - x
    if t <= _ZERO:
        return _ZERO
    if t < _QUARTER:
        a = _TWO_PI * t
        a2 = a * a
        s = _C10 - a2 * _C11
        s = _C9 - a2 * s
        s = _C8 - a2 * s
        s = _C7 - a2 * s
        s = _C6 - a2 * s
        s = _C5 - a2 * s
        s = _C4 - a2 * s
        s = _C3 - a2 * s
        s = _C2 - a2 * s
        return sigma0 * t * a2 * a2 * s
    a = _TWO_PI * x
    return wp.max(sigma0 * ((f64(2.0) + wp.cos(a)) * t / _THREE + wp.sin(a) / _TWO_PI), _ZERO)


def _taylor(first_power: int, terms: int):
    from math import factorial

    return [wp.constant(f64((-1) ** n / factorial(2 * n + first_power))) for n in range(1, terms + 1)]


_SIN3, _SIN5, _SIN7, _SIN9, _SIN11 = _taylor(1, 5)
_COS2, _COS4, _COS6, _COS8, _COS10, _COS12 = _taylor(0, 6)
# pi / 2 in two parts, the first with 33 significant bits, so that q * _PIO2_HI is exact for the small
# quadrant counts q here (Cody-Waite reduction).
_PIO2_HI = wp.constant(f64(1.5707963267341256))
_PIO2_LO = wp.constant(f64(6.077100506506192e-11))
_TWO_OVER_PI = wp.constant(f64(0.6366197723675814))


@wp.func
def sincos_float32(a: float) -> wp.vec2:
    """(sin a, cos a) rounded to float32 from a float64 evaluation, for |a| up to a few hundred.

    The argument is reduced to |r| <= pi/4 around the nearest multiple of pi/2, where Taylor series to
    r^11 and r^12 are accurate to 1e-11, far below float32's resolution: the result is the correctly
    rounded float32 except where the exact value lies within ~1e-11 ulp of a rounding boundary
    (tests/test_scatter.py). libm's sinf and cosf are calls the compiler cannot inline or vectorise and
    took about a third of the S-BKI gather kernel; this form is inline FMAs, identical on every device,
    and closer to the exact value (glibc's float32 results are off the correctly rounded ones for
    ~1.3 % of arguments here, numpy's for ~15 %)."""
    x = f64(a)
    q = wp.rint(x * _TWO_OVER_PI)
    r = (x - q * _PIO2_HI) - q * _PIO2_LO
    r2 = r * r
    s = r + r * r2 * (_SIN3 + r2 * (_SIN5 + r2 * (_SIN7 + r2 * (_SIN9 + r2 * _SIN11))))
    c = _ONE + r2 * (_COS2 + r2 * (_COS4 + r2 * (_COS6 + r2 * (_COS8 + r2 * (_COS10 + r2 * _COS12)))))
    # sin and cos of r + q pi / 2, by selects rather than branches: the quadrant changes from cell to cell,
    # and a loop over cells can vectorise (rint rather than round for the same reason: either nearest
    # integer reduces to |r| <= pi / 4).
    quadrant = int(q) & 3
    odd = (quadrant & 1) == 1
    sin_a = wp.where(odd, c, s)
    cos_a = wp.where(odd, s, c)
    sin_a = wp.where(quadrant >= 2, -sin_a, sin_a)
    cos_a = wp.where(quadrant == 1 or quadrant == 2, -cos_a, cos_a)
    return wp.vec2(float(sin_a), float(cos_a))


@wp.func
def sbki_sparse_kernel_scaled(cell: wp.vec3, point: wp.vec3, sf2: float) -> float:
    """The sparse kernel as S-BKI's covSparse computes it, from coordinates already divided by ell:
    float32 arithmetic, negatives -> 0, with the correctly rounded float32 sine and cosine
    (``sincos_float32``; the C++ takes Eigen's vectorised approximations, within an ulp or two of them)."""
    offset = cell - point
    d = wp.sqrt(offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2])
    a = d * 2.0 * _SBKI_PI
    sin_cos = sincos_float32(a)
    k = ((2.0 + sin_cos[1]) * (1.0 - d) / 3.0 + sin_cos[0] / (2.0 * _SBKI_PI)) * sf2
    return wp.max(k, 0.0)


@wp.func
def sbki_sparse_kernel(cell: wp.vec3, point: wp.vec3, ell: float, sf2: float) -> float:
    """``sbki_sparse_kernel_scaled`` of the cell centre and the point, each divided by ell as the C++ does."""
    return sbki_sparse_kernel_scaled(cell / ell, point / ell, sf2)


@wp.func
def sbki_voxel_center(ix: int, iy: int, iz: int, resolution: float, grid_offset: float) -> wp.vec3:
    """A cell centre in float32, as the compat kernel evaluates it."""
    return wp.vec3(
        (float(ix) + 0.5) * resolution + grid_offset,
        (float(iy) + 0.5) * resolution + grid_offset,
        (float(iz) + 0.5) * resolution + grid_offset,
    )


@wp.func
def voxel_center(ix: int, iy: int, iz: int, resolution: wp.float64, grid_offset: wp.float64) -> wp.vec3d:
    return wp.vec3d(
        (f64(ix) + _HALF) * resolution + grid_offset,
        (f64(iy) + _HALF) * resolution + grid_offset,
        (f64(iz) + _HALF) * resolution + grid_offset,
    )


@wp.func
def voxel_of(p: wp.float64, resolution: wp.float64, grid_offset: wp.float64) -> int:
    return int(wp.floor((p - grid_offset) / resolution))


@wp.func
def block_of_voxel(i: int, cells_per_block: int) -> int:
    # Cell j of block b is voxel b * n - n / 2 + j (n even), or voxel b when n == 1.
    half = cells_per_block / 2
    q = i + half
    b = q / cells_per_block
    if q < 0 and b * cells_per_block != q:
        b = b - 1
    return b


@wp.func
def reach_of(mode: int, length: wp.float64, resolution: wp.float64) -> wp.float64:
    """How far from the point a target voxel centre may lie."""
    if mode == MODE_SBKI_BLOCKS:
        return length * _SBKI_REACH
    if mode == MODE_RADIUS:
        return length
    return resolution  # own voxel / own block: the range below is a single voxel anyway


@wp.func
def range_end(mode: int, p: wp.vec3d, reach: wp.float64, owner: wp.vec3i, resolution: wp.float64, grid_offset: wp.float64, side: int) -> wp.vec3i:
    """First (side -1) or last (side +1) voxel index per axis that a point may reach."""
    if mode == MODE_SBKI_OWN_BLOCK:
        return owner
    if mode == MODE_STENCIL:  # owner is the point's voxel, reach the stencil's half width in voxels
        h = int(reach)
        return owner + wp.vec3i(side * h, side * h, side * h)
    r = reach
    if mode == MODE_OWN_VOXEL:
        r = _ZERO
    s = f64(side)
    return wp.vec3i(
        voxel_of(p[0] + s * r, resolution, grid_offset),
        voxel_of(p[1] + s * r, resolution, grid_offset),
        voxel_of(p[2] + s * r, resolution, grid_offset),
    )


@wp.func
def record_contribution(voxel_data: wp.array2d(dtype=wp.float64), voxel_row: int, num_classes: int, w: wp.float64, u: wp.float64):
    """The per-voxel bookkeeping of one contribution: weight and weight * uncertainty sums, count, touched."""
    wp.atomic_add(voxel_data, voxel_row, num_classes + COL_WEIGHT, w)
    wp.atomic_add(voxel_data, voxel_row, num_classes + COL_WEIGHTED_UNCERTAINTY, w * u)
    wp.atomic_add(voxel_data, voxel_row, num_classes + COL_HITS, _ONE)
    voxel_data[voxel_row, num_classes + COL_TOUCHED] = _ONE


@wp.func
def block_step(mode: int, i: int, owner_i: int, cells_per_block: int) -> int:
    """|block of voxel i - owner block| on one axis (0 outside the block-restricted mode)."""
    if mode == MODE_SBKI_BLOCKS:
        return wp.abs(block_of_voxel(i, cells_per_block) - owner_i)
    return 0


@wp.kernel
def scatter_points(
    point_ids: wp.array(dtype=int),
    points: wp.array(dtype=wp.vec3d),
    labels: wp.array(dtype=int),
    class_weights: wp.array2d(dtype=wp.float64),
    lengths: wp.array(dtype=wp.float64),
    point_uncertainty: wp.array(dtype=wp.float64),
    owner_blocks: wp.array(dtype=wp.vec3i),
    mode: int,
    use_labels: int,
    resolution: wp.float64,
    grid_offset: wp.float64,
    sigma0: wp.float64,
    cells_per_block: int,
    fusion: int,
    stencil_weights: wp.array2d(dtype=wp.float64),
    stencil_half: int,
    table_keys: wp.array(dtype=wp.int64),
    slot_rows: wp.array(dtype=int),
    key_count: wp.array(dtype=int),
    max_count: int,
    voxel_data: wp.array2d(dtype=wp.float64),
    failed: wp.array(dtype=int),
    update_count: wp.array(dtype=wp.int64),
):
    """Integrate points[point_ids[t]] into the map.

    voxel_data[:, k] += weight * y_k (y one-hot labels[i] or class_weights[i]), then per contribution
    weight sum += weight, weight * uncertainty sum += weight * u, count += 1, touched = 1.
    """
    t = wp.tid()
    i = point_ids[t]
    p = points[i]
    length = lengths[i]
    owner = wp.vec3i(0, 0, 0)
    if mode == MODE_SBKI_BLOCKS or mode == MODE_SBKI_OWN_BLOCK:
        owner = owner_blocks[i]
    reach = reach_of(mode, length, resolution)
    if mode == MODE_STENCIL:
        owner = wp.vec3i(voxel_of(p[0], resolution, grid_offset), voxel_of(p[1], resolution, grid_offset), voxel_of(p[2], resolution, grid_offset))
        reach = f64(stencil_half)
    reach2 = reach * reach
    lo = range_end(mode, p, reach, owner, resolution, grid_offset, -1)
    hi = range_end(mode, p, reach, owner, resolution, grid_offset, 1)
    u = point_uncertainty[i]
    # The compat kernel sees the point, the length and the grid in float32, as the C++ does.
    p32 = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    length32 = float(length)
    sigma32 = float(sigma0)
    resolution32 = float(resolution)
    offset32 = float(grid_offset)
    # Only the radius modes test distances; the own-voxel/own-block ranges hold exactly the target.
    by_distance = mode == MODE_RADIUS or mode == MODE_SBKI_BLOCKS
    # Pass 0 inserts (clean modes only: compat targets were inserted by insert_block_cells),
    # pass 1 adds; a point whose insertion fails adds nothing and is retried after growth.
    first_pass = 1
    if mode == MODE_RADIUS or mode == MODE_OWN_VOXEL or mode == MODE_STENCIL:
        first_pass = 0
    side = 2 * stencil_half + 1
    num_classes = voxel_data.shape[1] - _EXTRA
    n_updates = wp.int64(0)
    for pass_index in range(first_pass, 2):
        for ix in range(lo[0], hi[0] + 1):
            dx = (f64(ix) + _HALF) * resolution + grid_offset - p[0]
            bx = block_step(mode, ix, owner[0], cells_per_block)
            if (not by_distance or dx * dx < reach2) and bx <= 1:
                for iy in range(lo[1], hi[1] + 1):
                    dy = (f64(iy) + _HALF) * resolution + grid_offset - p[1]
                    bxy = bx + block_step(mode, iy, owner[1], cells_per_block)
                    if (not by_distance or dx * dx + dy * dy < reach2) and bxy <= 1:
                        for iz in range(lo[2], hi[2] + 1):
                            dz = (f64(iz) + _HALF) * resolution + grid_offset - p[2]
                            d2 = dx * dx + dy * dy + dz * dz
                            bxyz = bxy + block_step(mode, iz, owner[2], cells_per_block)
                            # ConvBKI: the stencil row of this offset; offsets that add nothing are skipped.
                            row = int(0)
                            stencil_mass = _ONE
                            if mode == MODE_STENCIL:
                                row = ((ix - owner[0] + stencil_half) * side + (iy - owner[1] + stencil_half)) * side + (iz - owner[2] + stencil_half)
                                stencil_mass = _ZERO
                                for c in range(num_classes):
                                    stencil_mass += stencil_weights[row, c] * class_weights[i, c]
                            if (not by_distance or d2 < reach2) and bxyz <= 1 and stencil_mass > _ZERO:
                                key = pack_key(ix, iy, iz)
                                if pass_index == 0:
                                    if table_find_or_insert(table_keys, slot_rows, key_count, max_count, key) < 0:
                                        failed[t] = 1
                                        return
                                    continue
                                # The weight is needed only here, in the adding pass.
                                w = _ONE
                                if mode == MODE_RADIUS:
                                    w = sparse_kernel(wp.sqrt(d2), length, sigma0)
                                elif mode == MODE_STENCIL:
                                    w = stencil_mass
                                elif mode == MODE_SBKI_BLOCKS:
                                    w = f64(sbki_sparse_kernel(sbki_voxel_center(ix, iy, iz, resolution32, offset32), p32, length32, sigma32))
                                if mode != MODE_SBKI_BLOCKS or w > _ZERO:  # the C++ adds only positive kernel values
                                    voxel_row = table_find(table_keys, slot_rows, key)
                                    if voxel_row < 0:
                                        # Only reachable in the compat modes, if a target cell was not pre-inserted.
                                        failed[t] = 1
                                        return
                                    if use_labels == 1:
                                        wp.atomic_add(voxel_data, voxel_row, labels[i], w)
                                    elif mode == MODE_STENCIL:
                                        for c in range(num_classes):
                                            wp.atomic_add(voxel_data, voxel_row, c, stencil_weights[row, c] * class_weights[i, c])
                                    elif fusion == FUSION_DEMPSTER:
                                        w = wp.min(w, _ONE)
                                        committed = _ZERO
                                        for c in range(num_classes):
                                            committed += wp.clamp(class_weights[i, c] * w, _ZERO, _ONE - _BELIEF_EPSILON)
                                        uncommitted = wp.max(_ONE - committed, _BELIEF_EPSILON)
                                        for c in range(num_classes):
                                            b = wp.clamp(class_weights[i, c] * w, _ZERO, _ONE - _BELIEF_EPSILON)
                                            wp.atomic_add(voxel_data, voxel_row, c, wp.log(_ONE + b / uncommitted))
                                    else:
                                        for c in range(num_classes):
                                            wp.atomic_add(voxel_data, voxel_row, c, w * class_weights[i, c])
                                    record_contribution(voxel_data, voxel_row, num_classes, w, u)
                                    n_updates += wp.int64(1)
    wp.atomic_add(update_count, 0, n_updates)


@wp.func
def face_offset(j: int) -> wp.vec3i:
    """0: the block itself; 1..6: its face neighbours -x, +x, -y, +y, -z, +z."""
    if j == 0:
        return wp.vec3i(0, 0, 0)
    axis = (j - 1) / 2
    step = 2 * ((j - 1) % 2) - 1
    out = wp.vec3i(0, 0, 0)
    out[axis] = step
    return out


@wp.kernel
def scatter_block_targets(
    point_ids: wp.array(dtype=int),
    points: wp.array(dtype=wp.vec3d),
    labels: wp.array(dtype=int),
    point_uncertainty: wp.array(dtype=wp.float64),
    owner_blocks: wp.array(dtype=wp.vec3i),
    target_lengths: wp.array2d(dtype=wp.float64),
    resolution: wp.float64,
    grid_offset: wp.float64,
    cells_per_block: int,
    table_keys: wp.array(dtype=wp.int64),
    slot_rows: wp.array(dtype=int),
    key_count: wp.array(dtype=int),
    max_count: int,
    voxel_data: wp.array2d(dtype=wp.float64),
    failed: wp.array(dtype=int),
    update_count: wp.array(dtype=wp.int64),
):
    """SEE-CSOM (docs/compatibility.md §3.3): point i updates every cell of target block owner +
    face_offset(j) for each j with target_lengths[i, j] > 0 (the host decided which blocks may use this
    point and with which length), with the triangular kernel max(0, 1 - d / l). Every cell of a target
    block is touched, as the original updates all of a block's nodes. Two passes: insert, then add."""
    t = wp.tid()
    i = point_ids[t]
    p = points[i]
    u = point_uncertainty[i]
    n = cells_per_block
    num_classes = voxel_data.shape[1] - _EXTRA
    n_updates = wp.int64(0)
    for pass_index in range(2):
        for j in range(7):
            ell = target_lengths[i, j]
            if ell > _ZERO:
                first = (owner_blocks[i] + face_offset(j)) * n - wp.vec3i(n / 2, n / 2, n / 2)
                for jx in range(n):
                    for jy in range(n):
                        for jz in range(n):
                            ix = first[0] + jx
                            iy = first[1] + jy
                            iz = first[2] + jz
                            key = pack_key(ix, iy, iz)
                            if pass_index == 0:
                                if table_find_or_insert(table_keys, slot_rows, key_count, max_count, key) < 0:
                                    failed[t] = 1
                                    return
                            else:
                                voxel_row = table_find(table_keys, slot_rows, key)
                                w = wp.max(_ONE - wp.length(voxel_center(ix, iy, iz, resolution, grid_offset) - p) / ell, _ZERO)
                                wp.atomic_add(voxel_data, voxel_row, labels[i], w)
                                record_contribution(voxel_data, voxel_row, num_classes, w, u)
                                n_updates += wp.int64(1)
    wp.atomic_add(update_count, 0, n_updates)


@wp.kernel
def insert_block_cells(
    block_ids: wp.array(dtype=int),
    blocks: wp.array(dtype=wp.vec3i),
    cells_per_block: int,
    mark_touched: int,
    table_keys: wp.array(dtype=wp.int64),
    slot_rows: wp.array(dtype=int),
    key_count: wp.array(dtype=int),
    max_count: int,
    voxel_data: wp.array2d(dtype=wp.float64),
    failed: wp.array(dtype=int),
):
    """Insert every cell of blocks[block_ids[t]] (S-BKI/S-CSM test blocks); optionally mark touched."""
    t = wp.tid()
    b = blocks[block_ids[t]]
    n = cells_per_block
    touched_column = voxel_data.shape[1] - _EXTRA + COL_TOUCHED
    first = b * n - wp.vec3i(n / 2, n / 2, n / 2)
    ok = int(1)
    for jx in range(n):
        for jy in range(n):
            for jz in range(n):
                voxel_row = table_find_or_insert(table_keys, slot_rows, key_count, max_count, pack_key(first[0] + jx, first[1] + jy, first[2] + jz))
                if voxel_row < 0:
                    ok = 0
                elif mark_touched == 1:
                    voxel_data[voxel_row, touched_column] = _ONE
    if ok == 0:
        failed[t] = 1

