"""Radius-search-and-scatter kernels: one launch integrates one scan into the voxel map (Warp).

Each point visits the voxels its weight function can reach, finds or inserts them in the hash
table and atomically adds weight * y into their Dirichlet concentrations. The traversal is written
once, in ``walk_kernel``: a kernel factory that loops over the voxels a point reaches and calls, per
voxel, a *visit* (small ``@wp.func``s captured with ``wp.static``); the scatter, the pair listing of
``kernels.sorted_scatter`` and the reached-voxel marking of ``kernels.hashgrid_gather`` are visits. The
scatter's visit is built from a weight rule (one ``@wp.func`` per method) and an evidence rule (one per
payload kind and fusion); ``mode`` picks where a point reaches and its weight rule:

* ``MODE_RADIUS``: the paper's sparse kernel k'(d, l_i, sigma0) on every voxel whose center lies
  strictly within the point's own length l_i (S-BKI, EBS and the ablations, "clean" mode).
* ``MODE_OWN_VOXEL``: weight 1 on the voxel containing the point (S-CSM, clean mode).
* ``MODE_SBKI_BLOCKS``: the original S-BKI rule: the sparse kernel evaluated as the C++ does
  (scaled coordinates, float32, negatives clamped), restricted to voxels whose block is the
  point's owner block or one of its 6 face neighbours.
* ``MODE_SBKI_OWN_BLOCK``: the original S-CSM rule: weight 1 on the owner block's single cell.
* ``MODE_STENCIL``: ConvBKI: every voxel of the (2h + 1)^3 cube around the point's voxel, with a
  per-class weight looked up by offset in ``stencil_weights`` (distances between voxel centers).

``fusion`` 1 (Dempster-Shafer, docs/algorithm.md §3.7, radius mode): instead of adding w * y, each point's belief
masses b (``class_weights``) are discounted by min(w, 1) and the voxel accumulates the log
commonality ratios log(1 + b'_c / u'), u' = 1 - sum b'. Dempster's rule multiplies commonalities, so
these sums fuse any number of points in any order; ``mapping.summarize_beliefs`` turns them back
into masses. ``scatter_block_targets`` is SEE-CSOM's block-gated traversal.

Every (mode, fusion, payload kind) is its own kernel, built when this module is imported
(``scatter_kernel`` picks one): nothing in a kernel's per-point loop branches on a method. Kernels read
a scan as one ``ScanPoints`` struct, the method's numbers as one ``ScatterParams`` and write through one
``MapTarget`` (the table as a ``kernels.hash_table.HashTable``, the value rows, the failure flags and
the update count); ``tally_row`` is the one place a row's bookkeeping columns are written.

In the clean modes a point finds or inserts each voxel and adds to it in one pass when the table
has room for every voxel of its span; otherwise it first runs an insert pass over them, and a point
whose insertion fails there (table full) adds nothing. A failed point is flagged in ``failed``; the
host grows the table and relaunches only those points, so each point lands exactly once. Threads
of a CPU launch run one after another, so there a point that found room cannot fail and the map is
the same as with two passes throughout; on a GPU other points may fill the room it saw, so a point
that stops in its adding pass records how many of its voxels it had added, and its relaunch resumes
after them. The compat modes only add: their target cells are inserted beforehand.

Arithmetic is float64 throughout (positions relative to the map origin, weights, sums), so evidence
keeps growing on long drives and a far-away scan maps exactly as the same scan near the origin; only
the S-BKI compatibility kernel runs in float32, as the C++ does. A voxel's data lie together in one
row of ``voxel_data`` [capacity, K + 5]: K evidence columns, then the weight sum, the weight *
uncertainty sum, the contribution count, the weighted height sum and the touched flag (counts in float64
are exact to 2^53). The weighted height sum is sum w (z - z_c) over the voxel's contributions, z the
point's height and z_c the voxel center's: the weight-sum-weighted mean height of the points that reached
the voxel, below the voxel size, is z_c + that sum / the weight sum. Kept as an offset from the center,
each term is bounded by the kernel's reach, so the sum grows as the weight sum does, not with the map's
altitude, and keeps float64's digits on a long drive; and an offset from a voxel's center does not
depend on the map origin, so maps of other origins merge by adding it as they add the other sums. Only
the clean modes' kernels keep it (``add_height``); the compat modes reproduce the originals' rows and
leave it 0 (their mean height is the center).

numpy twin: ``evsemmap_warp/reference/scatter.py``.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp

from . import MODULE_OPTIONS
from .hash_table import HashTable, block_cell, block_first_cell, pack_key, table_find, table_find_or_insert

wp.set_module_options(MODULE_OPTIONS)

MODE_RADIUS = 0
MODE_OWN_VOXEL = 1
MODE_SBKI_BLOCKS = 2
MODE_SBKI_OWN_BLOCK = 3
MODE_STENCIL = 4
FUSION_BAYES = 0
FUSION_DEMPSTER = 1
# Belief masses are clamped to [0, 1 - BELIEF_EPSILON] (docs/algorithm.md §3.7).
BELIEF_EPSILON = 1e-6
# Columns of voxel_data after the K evidence columns (touched stays last: the file codecs store it as a bit).
EXTRA_COLUMNS = 5
COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY, COL_HITS, COL_WEIGHTED_HEIGHT, COL_TOUCHED = range(5)  # offsets from K

# How far past the length the compat scatter searches, a margin: the float32 kernel (pi written as the
# C++'s 3.1415926f) is zero from 0.984 ell on (``kernels.block_gather.SBKI_ZERO_BEYOND``).
SBKI_REACH_FACTOR = 1.05

f64 = wp.float64


def _series_coefficient(n: int) -> float:
    from math import factorial

    return 1.0 / (3.0 * factorial(2 * n)) - 1.0 / factorial(2 * n + 1)


# c_2 .. c_11 of the series in sparse_kernel: ten terms are exact to float64 for t < 1/4.
_C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11 = (wp.constant(f64(_series_coefficient(n))) for n in range(2, 12))
# ZERO64, ONE64 and EXTRA_COLUMNS_CONST are the family's shared constants (block_gather, release,
# sorted_scatter and hashgrid_gather use them too); the rest are this module's own.
ZERO64 = wp.constant(f64(0.0))
_HALF = wp.constant(f64(0.5))
ONE64 = wp.constant(f64(1.0))
_QUARTER = wp.constant(f64(0.25))
_THREE = wp.constant(f64(3.0))
_TWO_PI = wp.constant(f64(6.283185307179586))
_SBKI_PI = wp.constant(3.1415926)
_SBKI_REACH = wp.constant(f64(SBKI_REACH_FACTOR))
_BELIEF_EPSILON = wp.constant(f64(BELIEF_EPSILON))
EXTRA_COLUMNS_CONST = wp.constant(EXTRA_COLUMNS)


@wp.func
def sparse_kernel(d: wp.float64, length: wp.float64, sigma0: wp.float64) -> wp.float64:
    """k'(d, l, sigma0) (docs/algorithm.md §3.3) for d < l, in float64.

    Near the support edge the closed form is the difference of two O(1 - d/l) terms. With t = 1 - d/l
    and a = 2 pi t the kernel is sigma0 t f(a), f(a) = (2 + cos a) / 3 - sin(a) / a =
    sum_{n>=2} (-1)^n c_n a^(2n), c_n = 1/(3 (2n)!) - 1/(2n+1)!; for t < 1/4 the series is used.
    """
    x = d / length
    t = ONE64 - x
    if t <= ZERO64:
        return ZERO64
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
    return wp.max(sigma0 * ((f64(2.0) + wp.cos(a)) * t / _THREE + wp.sin(a) / _TWO_PI), ZERO64)


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
    (tests/test_scatter.py). libm's sinf and cosf are calls the compiler cannot inline or vectorise (their
    cost: docs/performance.md); this form is inline FMAs, identical on every device,
    and closer to the exact value (glibc's float32 results are off the correctly rounded ones for
    ~1.3 % of arguments here, numpy's for ~15 %)."""
    x = f64(a)
    q = wp.rint(x * _TWO_OVER_PI)
    r = (x - q * _PIO2_HI) - q * _PIO2_LO
    r2 = r * r
    s = r + r * r2 * (_SIN3 + r2 * (_SIN5 + r2 * (_SIN7 + r2 * (_SIN9 + r2 * _SIN11))))
    c = ONE64 + r2 * (_COS2 + r2 * (_COS4 + r2 * (_COS6 + r2 * (_COS8 + r2 * (_COS10 + r2 * _COS12)))))
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
    """``sbki_sparse_kernel_scaled`` of the cell center and the point, each divided by ell as the C++ does."""
    return sbki_sparse_kernel_scaled(cell / ell, point / ell, sf2)




@wp.func
def sbki_voxel_center(ix: int, iy: int, iz: int, resolution: float, grid_offset: float) -> wp.vec3:
    """A cell center in float32, as the compat kernel evaluates it."""
    return wp.vec3(
        (float(ix) + 0.5) * resolution + grid_offset,
        (float(iy) + 0.5) * resolution + grid_offset,
        (float(iz) + 0.5) * resolution + grid_offset,
    )


@wp.func
def voxel_center(ix: int, iy: int, iz: int, resolution: wp.float64, grid_offset: wp.float64) -> wp.vec3d:
    """Center (m, relative to the map origin) of voxel (ix, iy, iz) on the lattice of edge ``resolution``
    offset by ``grid_offset``."""
    return wp.vec3d(
        (f64(ix) + _HALF) * resolution + grid_offset,
        (f64(iy) + _HALF) * resolution + grid_offset,
        (f64(iz) + _HALF) * resolution + grid_offset,
    )


@wp.func
def voxel_of(p: wp.float64, resolution: wp.float64, grid_offset: wp.float64) -> int:
    """Index of the voxel holding coordinate ``p`` (m, relative to the map origin) on one axis: floor((p -
    grid_offset) / resolution)."""
    return int(wp.floor((p - grid_offset) / resolution))


@wp.func
def center_offset(i: int, resolution: wp.float64, grid_offset: wp.float64, p: wp.float64) -> wp.float64:
    """Voxel i's center minus p on one axis (m)."""
    return (f64(i) + _HALF) * resolution + grid_offset - p


@wp.func
def block_of_voxel(i: int, cells_per_block: int) -> int:
    """Index of the S-BKI block (``cells_per_block`` cells a side) that holds voxel ``i`` on one axis."""
    # Cell j of block b is voxel b * n - n / 2 + j (n even), or voxel b when n == 1.
    half = cells_per_block / 2
    q = i + half
    b = q / cells_per_block
    if q < 0 and b * cells_per_block != q:
        b = b - 1
    return b


# ---------------------------------------------------------------------------- what kernels read and write
@wp.struct
class ScanPoints:
    """One scan's points as the kernels read them; a kernel reads only some, the others may stay unset.
    ``point_ids`` [T]: the point each thread takes (a relaunch passes the ones that failed); ``points``
    [N] (m, float64, relative to the map origin); ``lengths`` [N] kernel lengths (m); ``uncertainty`` [N];
    the payload, ``labels`` [N] or ``class_weights`` [N, K]; ``owner_blocks`` [N]: the S-BKI modes' blocks."""

    point_ids: wp.array(dtype=int)
    points: wp.array(dtype=wp.vec3d)
    lengths: wp.array(dtype=wp.float64)
    uncertainty: wp.array(dtype=wp.float64)
    labels: wp.array(dtype=int)
    class_weights: wp.array2d(dtype=wp.float64)
    owner_blocks: wp.array(dtype=wp.vec3i)


@wp.struct
class ScatterParams:
    """The lattice (voxel i spans [i r + o, (i + 1) r + o) per axis, r = ``resolution``, o = ``grid_offset``,
    m) and the weight rules' numbers: ``sigma0``, ``cells_per_block`` (S-BKI blocks per axis),
    ``stencil_weights`` [(2h + 1)^3, K] and ``stencil_half`` h (ConvBKI)."""

    resolution: wp.float64
    grid_offset: wp.float64
    sigma0: wp.float64
    cells_per_block: int
    stencil_weights: wp.array2d(dtype=wp.float64)
    stencil_half: int


@wp.struct
class MapTarget:
    """Where a launch writes: the voxel table, its value rows ``voxel_data`` [capacity, K + 5], ``failed``
    [T] (0, or the thread's work did not fit: relaunched after the table grew; the scatter writes 1 + how
    many of its voxels the point had added, and reads it back in the relaunch) and ``update_count`` [1]."""

    table: HashTable
    voxel_data: wp.array2d(dtype=wp.float64)
    failed: wp.array(dtype=int)
    update_count: wp.array(dtype=wp.int64)


@wp.struct
class Span:
    """The voxels a point may reach: index ranges lo..hi per axis, its owner (S-BKI block, or ConvBKI's
    voxel) and the squared reach (m^2) of the distance test."""

    lo: wp.vec3i
    hi: wp.vec3i
    owner: wp.vec3i
    reach2: wp.float64


@wp.func
def touch_row(voxel_data: wp.array2d(dtype=wp.float64), row: int):
    """Mark a row touched: the first access every kernel makes to a row it will add to. On the CPU a
    fresh row's page, read first, maps the shared zero page and faults a second time on the write that
    follows; written first, it faults once. The read-first order doubled the S-BKI gather's faults, and
    faults of two shards contend (docs/performance.md measures what it cost; tests/test_page_faults.py)."""
    voxel_data[row, voxel_data.shape[1] - EXTRA_COLUMNS_CONST + COL_TOUCHED] = ONE64


@wp.func
def tally_row(voxel_data: wp.array2d(dtype=wp.float64), row: int, num_classes: int, weight: wp.float64,
              weighted_uncertainty: wp.float64, hits: wp.float64):
    """A row's bookkeeping: weight sum += weight, weight * uncertainty sum += weighted_uncertainty,
    contribution count += hits (the row was marked touched first, ``touch_row``). Every kernel that
    writes a row goes through here: the scatter once per contribution, the gathers once per voxel with
    their sums (atomic adds, which on the CPU are the plain adds)."""
    wp.atomic_add(voxel_data, row, num_classes + COL_WEIGHT, weight)
    wp.atomic_add(voxel_data, row, num_classes + COL_WEIGHTED_UNCERTAINTY, weighted_uncertainty)
    wp.atomic_add(voxel_data, row, num_classes + COL_HITS, hits)


@wp.func
def height_offset(iz: int, resolution: wp.float64, grid_offset: wp.float64, z: wp.float64) -> wp.float64:
    """z - the center height of voxel layer iz (m): what a point at height z adds, times its weight, to the
    voxel's weighted height sum."""
    return -center_offset(iz, resolution, grid_offset, z)


@wp.func
def add_height(voxel_data: wp.array2d(dtype=wp.float64), row: int, weighted_height: wp.float64):
    """A row's weighted height sum += weighted_height (sum of w (z - z_c), the clean modes' kernels only)."""
    wp.atomic_add(voxel_data, row, voxel_data.shape[1] - EXTRA_COLUMNS_CONST + COL_WEIGHTED_HEIGHT, weighted_height)


# ---------------------------------------------------------------------------- evidence rules (payload kind, fusion)
# (scan, params, voxel_data, row, i, w, stencil_row) -> the weight the row's bookkeeping records.
@wp.func
def add_label_evidence(scan: ScanPoints, params: ScatterParams, voxel_data: wp.array2d(dtype=wp.float64), row: int, i: int,
                       w: wp.float64, stencil_row: int) -> wp.float64:
    """One-hot payload: w into the point's label column."""
    wp.atomic_add(voxel_data, row, scan.labels[i], w)
    return w


@wp.func
def add_weighted_evidence(scan: ScanPoints, params: ScatterParams, voxel_data: wp.array2d(dtype=wp.float64), row: int, i: int,
                          w: wp.float64, stencil_row: int) -> wp.float64:
    """Class-weight payload, Bayes fusion: w * y_k into column k."""
    for c in range(voxel_data.shape[1] - EXTRA_COLUMNS_CONST):
        wp.atomic_add(voxel_data, row, c, w * scan.class_weights[i, c])
    return w


@wp.func
def discounted_belief(mass: wp.float64, discount: wp.float64) -> wp.float64:
    """A point's belief mass discounted by its kernel weight (``discount``, at most 1), clamped to [0, 1 -
    BELIEF_EPSILON] (docs/algorithm.md §3.7)."""
    return wp.clamp(mass * discount, ZERO64, ONE64 - _BELIEF_EPSILON)


@wp.func
def uncommitted_mass(committed: wp.float64) -> wp.float64:
    """The mass a point's discounted beliefs leave uncommitted, at least BELIEF_EPSILON."""
    return wp.max(ONE64 - committed, _BELIEF_EPSILON)


@wp.func
def add_belief_evidence(scan: ScanPoints, params: ScatterParams, voxel_data: wp.array2d(dtype=wp.float64), row: int, i: int,
                        w: wp.float64, stencil_row: int) -> wp.float64:
    """Dempster fusion: the point's belief masses (``class_weights``) discounted by min(w, 1), added as
    log commonality ratios log(1 + b'_k / u'); the bookkeeping records min(w, 1)."""
    discount = wp.min(w, ONE64)
    num_classes = voxel_data.shape[1] - EXTRA_COLUMNS_CONST
    committed = ZERO64
    for c in range(num_classes):
        committed += discounted_belief(scan.class_weights[i, c], discount)
    uncommitted = uncommitted_mass(committed)
    for c in range(num_classes):
        wp.atomic_add(voxel_data, row, c, wp.log(ONE64 + discounted_belief(scan.class_weights[i, c], discount) / uncommitted))
    return discount


@wp.func
def add_stencil_evidence(scan: ScanPoints, params: ScatterParams, voxel_data: wp.array2d(dtype=wp.float64), row: int, i: int,
                         w: wp.float64, stencil_row: int) -> wp.float64:
    """ConvBKI: per class, the stencil's weight for this offset times y_k."""
    for c in range(voxel_data.shape[1] - EXTRA_COLUMNS_CONST):
        wp.atomic_add(voxel_data, row, c, params.stencil_weights[stencil_row, c] * scan.class_weights[i, c])
    return w


# ---------------------------------------------------------------------------- weight rules, one per method
@dataclass(frozen=True)
class WeightRule:
    """What a point gives a voxel it reaches. ``screen`` (scan, params, i, cell, span) -> float64: positive
    where the voxel takes part at all (both passes: a voxel screened out is not even inserted);
    ``weight`` (scan, params, i, p, cell, d2, span, screened) -> float64, in the adding pass, d2 the
    squared distance (m^2) from the point to the voxel center; ``positive_only``: nothing is added
    where the weight is not positive (the C++ S-BKI adds only positive kernel values)."""

    screen: Any
    weight: Any
    positive_only: bool = False


@wp.func
def stencil_row(cell: wp.vec3i, owner: wp.vec3i, half: int) -> int:
    """Row of ``stencil_weights`` for the offset of ``cell`` from ``owner`` (both within ``half``)."""
    side = 2 * half + 1
    return ((cell[0] - owner[0] + half) * side + (cell[1] - owner[1] + half)) * side + (cell[2] - owner[2] + half)


@wp.func
def every_voxel(scan: ScanPoints, params: ScatterParams, i: int, cell: wp.vec3i, span: Span) -> wp.float64:
    """A ``screen`` that lets every voxel in a point's span take part (weight 1)."""
    return ONE64


@wp.func
def convbki_mass(scan: ScanPoints, params: ScatterParams, i: int, cell: wp.vec3i, span: Span) -> wp.float64:
    """ConvBKI's screen: the point's stencil mass at this offset, sum_k stencil[offset, k] y_k (offsets
    that add nothing are skipped)."""
    row = stencil_row(cell, span.owner, params.stencil_half)
    mass = ZERO64
    for c in range(params.stencil_weights.shape[1]):
        mass += params.stencil_weights[row, c] * scan.class_weights[i, c]
    return mass


@wp.func
def sparse_weight(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64, span: Span,
                  screened: wp.float64) -> wp.float64:
    """S-BKI, EBS, the ablations and Dempster (clean): k'(d, l_i, sigma0)."""
    return sparse_kernel(wp.sqrt(d2), scan.lengths[i], params.sigma0)


@wp.func
def count_weight(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64, span: Span,
                 screened: wp.float64) -> wp.float64:
    """S-CSM: 1 (the walk reaches the one voxel or block cell the point counts in)."""
    return ONE64


@wp.func
def sbki_compat_weight(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64, span: Span,
                       screened: wp.float64) -> wp.float64:
    """The original S-BKI: its float32 sparse kernel of the float32 point, cell center, ell and sf2."""
    center = sbki_voxel_center(cell[0], cell[1], cell[2], float(params.resolution), float(params.grid_offset))
    point = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    return f64(sbki_sparse_kernel(center, point, float(scan.lengths[i]), float(params.sigma0)))


@wp.func
def convbki_weight(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d, cell: wp.vec3i, d2: wp.float64, span: Span,
                   screened: wp.float64) -> wp.float64:
    """ConvBKI: the stencil mass the screen found (the evidence goes in per class)."""
    return screened


@wp.func
def see_csom_weight(center: wp.vec3d, p: wp.vec3d, length: wp.float64) -> wp.float64:
    """SEE-CSOM's triangular kernel max(0, 1 - d / l)."""
    return wp.max(ONE64 - wp.length(center - p) / length, ZERO64)


SPARSE_RULE = WeightRule(every_voxel, sparse_weight)
COUNT_RULE = WeightRule(every_voxel, count_weight)
SBKI_COMPAT_RULE = WeightRule(every_voxel, sbki_compat_weight, positive_only=True)
CONVBKI_RULE = WeightRule(convbki_mass, convbki_weight)


# ---------------------------------------------------------------------------- where a point reaches
@wp.func
def _ball(p: wp.vec3d, reach: wp.float64, owner: wp.vec3i, params: ScatterParams) -> Span:
    span = Span()
    span.lo = wp.vec3i(voxel_of(p[0] - reach, params.resolution, params.grid_offset), voxel_of(p[1] - reach, params.resolution, params.grid_offset),
                       voxel_of(p[2] - reach, params.resolution, params.grid_offset))
    span.hi = wp.vec3i(voxel_of(p[0] + reach, params.resolution, params.grid_offset), voxel_of(p[1] + reach, params.resolution, params.grid_offset),
                       voxel_of(p[2] + reach, params.resolution, params.grid_offset))
    span.owner = owner
    span.reach2 = reach * reach
    return span


@wp.func
def _own_voxel(p: wp.vec3d, params: ScatterParams) -> wp.vec3i:
    return wp.vec3i(voxel_of(p[0], params.resolution, params.grid_offset), voxel_of(p[1], params.resolution, params.grid_offset),
                    voxel_of(p[2], params.resolution, params.grid_offset))


@wp.func
def ball_span(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d) -> Span:
    """Voxels whose center lies within the point's length."""
    return _ball(p, scan.lengths[i], wp.vec3i(0, 0, 0), params)


@wp.func
def block_ball_span(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d) -> Span:
    """Voxels within SBKI_REACH_FACTOR lengths, in the owner block or a face neighbour of it."""
    return _ball(p, scan.lengths[i] * _SBKI_REACH, scan.owner_blocks[i], params)


@wp.func
def own_voxel_span(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d) -> Span:
    """The voxel holding the point."""
    span = Span()
    span.lo = _own_voxel(p, params)
    span.hi = span.lo
    return span


@wp.func
def own_block_span(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d) -> Span:
    """The owner block's one cell (S-CSM's blocks of one cell)."""
    span = Span()
    span.owner = scan.owner_blocks[i]
    span.lo = span.owner
    span.hi = span.owner
    return span


@wp.func
def cube_span(scan: ScanPoints, params: ScatterParams, i: int, p: wp.vec3d) -> Span:
    """The (2h + 1)^3 voxels around the point's voxel (ConvBKI's stencil)."""
    span = Span()
    span.owner = _own_voxel(p, params)
    h = params.stencil_half
    span.lo = span.owner - wp.vec3i(h, h, h)
    span.hi = span.owner + wp.vec3i(h, h, h)
    return span


REACH_BALL, REACH_BLOCK_BALL, REACH_OWN_VOXEL, REACH_OWN_BLOCK, REACH_CUBE = range(5)
_SPAN_OF = {REACH_BALL: ball_span, REACH_BLOCK_BALL: block_ball_span, REACH_OWN_VOXEL: own_voxel_span, REACH_OWN_BLOCK: own_block_span,
            REACH_CUBE: cube_span}


# ---------------------------------------------------------------------------- the traversal
@dataclass(frozen=True)
class Visit:
    """What ``walk_kernel`` does per point and per voxel it reaches (``@wp.func``s; ``Out`` the wp.struct
    the kernel writes through):

    * ``begin(scan, out, t, i) -> int64``: the point's counter at the start;
    * ``insert(scan, params, out, t, i, cell, span) -> int``: the first pass (None: no first pass),
      negative when the point must stop (it flagged itself for a relaunch);
    * ``step(scan, params, out, t, i, p, cell, d2, span, counter) -> int64``: the (second) pass,
      negative when the point must stop;
    * ``end(scan, out, t, i, counter)``: after a point's last voxel;
    * ``plan(scan, params, out, t, i, span) -> int``: with an insert pass, where the point starts: -1
      the insert pass; k >= 0 only the adding pass, past the first k voxels it reaches (None: the
      insert pass);
    * ``stop(scan, out, t, i, done, counter)``: a point whose step returned < 0 after ``done`` voxels
      of its adding pass (None: nothing).

    ``indexed``: thread t takes point scan.point_ids[t] (else point t)."""

    Out: Any
    begin: Any
    step: Any
    end: Any
    insert: Any = None
    plan: Any = None
    stop: Any = None
    indexed: bool = True


@wp.func
def _insert_nothing(scan: ScanPoints, params: ScatterParams, out: Any, t: int, i: int, cell: wp.vec3i, span: Span) -> int:
    return 0


@wp.func
def _plan_insert_pass(scan: ScanPoints, params: ScatterParams, out: Any, t: int, i: int, span: Span) -> int:
    return -1


@wp.func
def _stop_quietly(scan: ScanPoints, out: Any, t: int, i: int, done: int, counter: wp.int64):
    pass


@wp.func
def count_from_zero(scan: ScanPoints, out: Any, t: int, i: int) -> wp.int64:
    """A visit's ``begin`` whose counter starts at 0."""
    return wp.int64(0)


@wp.func
def end_nothing(scan: ScanPoints, out: Any, t: int, i: int, counter: wp.int64):
    """A visit's ``end`` with nothing to write."""
    pass


def walk_kernel(reach: int, visit: Visit, *, module: str):
    """The one traversal: a kernel over points (scan: ScanPoints, params: ScatterParams, out:
    visit.Out) that calls ``visit`` for every voxel the point reaches (``reach``: REACH_*), x, then y,
    then z ascending; a ball's rows and columns outside the reach are skipped whole. ``module``: the Warp
    module the kernel belongs to (the module that builds it), or "unique" for a module of its own."""
    by_distance = reach in (REACH_BALL, REACH_BLOCK_BALL)
    by_block = reach == REACH_BLOCK_BALL
    span_of = _SPAN_OF[reach]
    first_pass = 0 if visit.insert is not None else 1
    insert = visit.insert if visit.insert is not None else _insert_nothing
    plan = visit.plan if visit.plan is not None else _plan_insert_pass
    stop = visit.stop if visit.stop is not None else _stop_quietly
    Out = visit.Out

    @wp.func
    def block_steps(i: int, owner_i: int, params: ScatterParams) -> int:
        """|block of voxel i - owner block| on one axis (0 but in the block-restricted reach)."""
        steps = int(0)
        if wp.static(by_block):
            steps = wp.abs(block_of_voxel(i, params.cells_per_block) - owner_i)
        return steps

    @wp.func
    def reached(partial_d2: wp.float64, steps: int, span: Span) -> bool:
        """Whether the voxels past this axis may be reached: the squared distance so far (m^2) within the
        reach and at most one block step so far."""
        near = steps <= 1
        if wp.static(by_distance):
            near = partial_d2 < span.reach2 and steps <= 1
        return near

    @wp.kernel(module=module, module_options=MODULE_OPTIONS if module == "unique" else None)
    def walk(scan: ScanPoints, params: ScatterParams, out: Out):
        t = wp.tid()
        i = t
        if wp.static(visit.indexed):
            i = scan.point_ids[t]
        p = scan.points[i]
        span = wp.static(span_of)(scan, params, i, p)
        counter = wp.static(visit.begin)(scan, out, t, i)
        start = wp.static(first_pass)
        skip = int(0)  # voxels of the adding pass a relaunch finds added already
        if wp.static(first_pass == 0):
            skip = wp.static(plan)(scan, params, out, t, i, span)
            if skip >= 0:
                start = 1
            else:
                skip = 0
        done = int(0)
        for pass_index in range(start, 2):
            for ix in range(span.lo[0], span.hi[0] + 1):
                dx = center_offset(ix, params.resolution, params.grid_offset, p[0])
                bx = block_steps(ix, span.owner[0], params)
                if reached(dx * dx, bx, span):
                    for iy in range(span.lo[1], span.hi[1] + 1):
                        dy = center_offset(iy, params.resolution, params.grid_offset, p[1])
                        dxy2 = dx * dx + dy * dy
                        bxy = bx + block_steps(iy, span.owner[1], params)
                        if reached(dxy2, bxy, span):
                            for iz in range(span.lo[2], span.hi[2] + 1):
                                dz = center_offset(iz, params.resolution, params.grid_offset, p[2])
                                d2 = dxy2 + dz * dz
                                if reached(d2, bxy + block_steps(iz, span.owner[2], params), span):
                                    cell = wp.vec3i(ix, iy, iz)
                                    if pass_index == 0:
                                        if wp.static(insert)(scan, params, out, t, i, cell, span) < 0:
                                            return
                                    else:
                                        if done >= skip:
                                            after = wp.static(visit.step)(scan, params, out, t, i, p, cell, d2, span, counter)
                                            if after < wp.int64(0):
                                                wp.static(stop)(scan, out, t, i, done, counter)
                                                return
                                            counter = after
                                        done += 1
        wp.static(visit.end)(scan, out, t, i, counter)

    return walk


# ---------------------------------------------------------------------------- the scatter
@wp.func
def plan_adding(out: MapTarget, t: int, new_voxels_at_most: wp.int64) -> int:
    """Where an inserting point starts (the module docstring says why): -1 with the insert pass, where
    the table may not have room for ``new_voxels_at_most`` more keys; k >= 0 with the adding pass alone,
    past the first k voxels it reaches (a relaunch: ``failed[t]`` holds 1 + the voxels it had added; 0
    for a point not yet started). Clears ``failed[t]``."""
    added = out.failed[t] - 1
    out.failed[t] = 0
    if added > 0:
        return added
    if wp.int64(out.table.key_count[0]) + new_voxels_at_most <= wp.int64(out.table.max_count):
        return 0
    return -1


@wp.func
def stop_adding(out: MapTarget, t: int, added: int, counter: wp.int64):
    """A point that stopped in its adding pass after ``added`` of its voxels: flagged for a relaunch that
    resumes there (``plan_adding``), its updates so far counted."""
    out.failed[t] = added + 1
    wp.atomic_add(out.update_count, 0, counter)


@wp.func
def _count_updates(scan: ScanPoints, out: MapTarget, t: int, i: int, counter: wp.int64):
    wp.atomic_add(out.update_count, 0, counter)


def scatter_visit(rule: WeightRule, evidence, *, inserts: bool, heights: bool) -> Visit:
    """The scatter as a visit: the pass that adds the rule's weight through ``evidence`` (an evidence
    rule) to every voxel the rule's screen lets through and tallies the row; the point's update count
    goes to ``update_count`` at its end. ``inserts``: that pass finds or inserts its voxels, after a
    first pass that only inserts them where the table may not have room for the point's span (the
    module docstring says why). ``heights``: it adds the point's weighted height offset too (the clean
    modes; the compat modes keep the originals' rows)."""

    @wp.func
    def insert_voxel(scan: ScanPoints, params: ScatterParams, out: MapTarget, t: int, i: int, cell: wp.vec3i, span: Span) -> int:
        if wp.static(rule.screen)(scan, params, i, cell, span) > ZERO64:
            if table_find_or_insert(out.table, pack_key(cell[0], cell[1], cell[2])) < 0:
                out.failed[t] = 1
                return -1
        return 0

    @wp.func
    def plan_passes(scan: ScanPoints, params: ScatterParams, out: MapTarget, t: int, i: int, span: Span) -> int:
        extent = span.hi - span.lo + wp.vec3i(1, 1, 1)
        return plan_adding(out, t, wp.int64(extent[0]) * wp.int64(extent[1]) * wp.int64(extent[2]))

    @wp.func
    def stop_point(scan: ScanPoints, out: MapTarget, t: int, i: int, done: int, counter: wp.int64):
        stop_adding(out, t, done, counter)

    @wp.func
    def add_to_voxel(scan: ScanPoints, params: ScatterParams, out: MapTarget, t: int, i: int, p: wp.vec3d, cell: wp.vec3i,
                     d2: wp.float64, span: Span, counter: wp.int64) -> wp.int64:
        screened = wp.static(rule.screen)(scan, params, i, cell, span)
        if not (screened > ZERO64):
            return counter
        w = wp.static(rule.weight)(scan, params, i, p, cell, d2, span, screened)
        if wp.static(rule.positive_only):
            if not (w > ZERO64):
                return counter
        key = pack_key(cell[0], cell[1], cell[2])
        row = int(0)
        if wp.static(inserts):
            row = table_find_or_insert(out.table, key)  # -1: the table is full (stop_adding flags the point)
        else:
            row = table_find(out.table, key)  # -1 only if a target cell was not inserted beforehand (a bug)
        if row < 0:
            return wp.int64(-1)
        touch_row(out.voxel_data, row)
        tallied = wp.static(evidence)(scan, params, out.voxel_data, row, i, w, stencil_row(cell, span.owner, params.stencil_half))
        tally_row(out.voxel_data, row, out.voxel_data.shape[1] - EXTRA_COLUMNS_CONST, tallied, tallied * scan.uncertainty[i], ONE64)
        if wp.static(heights):
            add_height(out.voxel_data, row, tallied * height_offset(cell[2], params.resolution, params.grid_offset, p[2]))
        return counter + wp.int64(1)

    if not inserts:
        return Visit(MapTarget, count_from_zero, add_to_voxel, _count_updates, stop=stop_point)
    return Visit(MapTarget, count_from_zero, add_to_voxel, _count_updates, insert=insert_voxel, plan=plan_passes, stop=stop_point)


# mode -> (where a point reaches, its weight rule, whether the scatter inserts and keeps heights: the
# clean modes do both, the compat modes' targets are inserted beforehand, by insert_block_cells, and their
# rows are the originals')
SCATTER_MODES = {
    MODE_RADIUS: (REACH_BALL, SPARSE_RULE, True),
    MODE_OWN_VOXEL: (REACH_OWN_VOXEL, COUNT_RULE, True),
    MODE_SBKI_BLOCKS: (REACH_BLOCK_BALL, SBKI_COMPAT_RULE, False),
    MODE_SBKI_OWN_BLOCK: (REACH_OWN_BLOCK, COUNT_RULE, False),
    MODE_STENCIL: (REACH_CUBE, CONVBKI_RULE, True),
}


def _evidence_rule(mode: int, fusion: int, use_labels: bool):
    """The evidence rule of a combination, None where the combination is not one: the stencil and
    Dempster fusion read class weights, and Dempster discounts the sparse kernel (radius mode)."""
    if mode == MODE_STENCIL:
        return add_stencil_evidence if fusion == FUSION_BAYES and not use_labels else None
    if fusion == FUSION_DEMPSTER:
        return add_belief_evidence if mode == MODE_RADIUS and not use_labels else None
    return add_label_evidence if use_labels else add_weighted_evidence


def _scatter_kernels() -> dict:
    # Each combination is a module of its own: a map compiles the one scatter it launches, not all ten
    # (tools/bench_compile.py).
    kernels = {}
    for mode, (reach, rule, inserts) in SCATTER_MODES.items():
        for fusion in (FUSION_BAYES, FUSION_DEMPSTER):
            for use_labels in (True, False):
                evidence = _evidence_rule(mode, fusion, use_labels)
                if evidence is not None:
                    kernels[mode, fusion, use_labels] = walk_kernel(reach, scatter_visit(rule, evidence, inserts=inserts, heights=inserts),
                                                                    module="unique")
    return kernels


_SCATTER_KERNELS = _scatter_kernels()


def scatter_kernel(mode: int, fusion: int, use_labels: bool):
    """The scatter kernel (scan: ScanPoints, params: ScatterParams, target: MapTarget) of a mode, fusion
    and payload kind (labels, else class weights); ValueError for a combination that is not one."""
    try:
        return _SCATTER_KERNELS[mode, fusion, bool(use_labels)]
    except KeyError:
        raise ValueError(f"no scatter for mode {mode}, fusion {fusion} with {'labels' if use_labels else 'class weights'}: the stencil "
                         "and Dempster fusion read per-class weights, and Dempster fuses the sparse kernel (radius mode)") from None


def scatter_inserts(mode: int) -> bool:
    """Whether the mode's scatter inserts its voxels (else they must be in the table beforehand)."""
    return SCATTER_MODES[mode][2]


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
def scatter_block_targets(scan: ScanPoints, target_lengths: wp.array2d(dtype=wp.float64), params: ScatterParams, out: MapTarget):
    """SEE-CSOM (docs/compatibility.md §3.3): point i updates every cell of target block owner +
    face_offset(j) for each j with target_lengths[i, j] > 0 (the host decided which blocks may use this
    point and with which length), with its triangular kernel (``see_csom_weight``). Every cell of a
    target block is touched, as the original updates all of a block's nodes. One pass that finds or
    inserts and adds, after an insert pass where the table may not have room (``plan_adding``)."""
    t = wp.tid()
    i = scan.point_ids[t]
    p = scan.points[i]
    u = scan.uncertainty[i]
    n = params.cells_per_block
    num_classes = out.voxel_data.shape[1] - EXTRA_COLUMNS_CONST
    n_updates = wp.int64(0)
    targets = int(0)
    for j in range(7):
        if target_lengths[i, j] > ZERO64:
            targets += 1
    skip = plan_adding(out, t, wp.int64(targets) * wp.int64(n * n * n))
    start = int(1)
    if skip < 0:
        start = 0
        skip = 0
    done = int(0)
    for pass_index in range(start, 2):
        for j in range(7):
            ell = target_lengths[i, j]
            if ell > ZERO64:
                first = block_first_cell(scan.owner_blocks[i] + face_offset(j), n)
                for c in range(n * n * n):
                    cell = block_cell(first, c, n)
                    key = pack_key(cell[0], cell[1], cell[2])
                    if pass_index == 0:
                        if table_find_or_insert(out.table, key) < 0:
                            out.failed[t] = 1
                            return
                    else:
                        if done >= skip:
                            row = table_find_or_insert(out.table, key)
                            if row < 0:
                                stop_adding(out, t, done, n_updates)
                                return
                            w = see_csom_weight(voxel_center(cell[0], cell[1], cell[2], params.resolution, params.grid_offset), p, ell)
                            touch_row(out.voxel_data, row)
                            tallied = add_label_evidence(scan, params, out.voxel_data, row, i, w, 0)
                            tally_row(out.voxel_data, row, num_classes, tallied, tallied * u, ONE64)
                            add_height(out.voxel_data, row, tallied * height_offset(cell[2], params.resolution, params.grid_offset, p[2]))
                            n_updates += wp.int64(1)
                        done += 1
    wp.atomic_add(out.update_count, 0, n_updates)


@wp.kernel
def insert_block_cells(block_ids: wp.array(dtype=int), blocks: wp.array(dtype=wp.vec3i), cells_per_block: int, mark_touched: int,
                       table: HashTable, voxel_data: wp.array2d(dtype=wp.float64), failed: wp.array(dtype=int)):
    """Insert every cell of blocks[block_ids[t]] (S-BKI/S-CSM test blocks); optionally mark touched."""
    t = wp.tid()
    n = cells_per_block
    first = block_first_cell(blocks[block_ids[t]], n)
    ok = int(1)
    for j in range(n * n * n):
        cell = block_cell(first, j, n)
        voxel_row = table_find_or_insert(table, pack_key(cell[0], cell[1], cell[2]))
        if voxel_row < 0:
            ok = 0
        elif mark_touched == 1:
            touch_row(voxel_data, voxel_row)
    if ok == 0:
        failed[t] = 1


@functools.cache
def weight_rule_kernel(mode: int):
    """A kernel that evaluates ``mode``'s weight rule at given (point, voxel) pairs: out[k] = the weight
    point pair_point[k] gives voxel pair_cell[k] (0 where the rule screens the voxel out), as the scatter
    computes it (for the rules' twin test; its own module, so the scatter's module is never rebuilt)."""
    reach, rule, _ = SCATTER_MODES[mode]
    span_of = _SPAN_OF[reach]

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def weight_rule_values(scan: ScanPoints, params: ScatterParams, pair_point: wp.array(dtype=int), pair_cell: wp.array(dtype=wp.vec3i),
                           out: wp.array(dtype=wp.float64)):
        k = wp.tid()
        i = pair_point[k]
        p = scan.points[i]
        cell = pair_cell[k]
        span = wp.static(span_of)(scan, params, i, p)
        dx = center_offset(cell[0], params.resolution, params.grid_offset, p[0])
        dy = center_offset(cell[1], params.resolution, params.grid_offset, p[1])
        dz = center_offset(cell[2], params.resolution, params.grid_offset, p[2])
        d2 = dx * dx + dy * dy + dz * dz
        screened = wp.static(rule.screen)(scan, params, i, cell, span)
        w = ZERO64
        if screened > ZERO64:
            w = wp.static(rule.weight)(scan, params, i, p, cell, d2, span, screened)
        out[k] = w

    return weight_rule_values


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"scatter_points": scatter_kernel, "weight_rule_values": weight_rule_kernel}


# ---------------------------------------------------------------------------- host side
def scan_points(*, point_ids=None, points=None, lengths=None, uncertainty=None, labels=None, class_weights=None,
                owner_blocks=None) -> ScanPoints:
    """A ``ScanPoints`` over device arrays (those not given stay unset)."""
    scan = ScanPoints()
    for name, value in (("point_ids", point_ids), ("points", points), ("lengths", lengths), ("uncertainty", uncertainty),
                        ("labels", labels), ("class_weights", class_weights), ("owner_blocks", owner_blocks)):
        if value is not None:
            setattr(scan, name, value)
    return scan


def scatter_params(*, resolution: float, grid_offset: float, sigma0: float = 1.0, cells_per_block: int = 1, stencil_weights=None,
                   stencil_half: int = 0) -> ScatterParams:
    """The ``ScatterParams`` struct (host side): the lattice (``resolution``, ``grid_offset``, m) and the
    weight rules' numbers; ``stencil_weights`` [(2h + 1)^3, K] and ``stencil_half`` h for ConvBKI."""
    params = ScatterParams()
    params.resolution = wp.float64(resolution)
    params.grid_offset = wp.float64(grid_offset)
    params.sigma0 = wp.float64(sigma0)
    params.cells_per_block = int(cells_per_block)
    if stencil_weights is not None:
        params.stencil_weights = stencil_weights
    params.stencil_half = int(stencil_half)
    return params


def map_target(table: HashTable, voxel_data, failed, update_count) -> MapTarget:
    """The ``MapTarget`` struct (host side, no copy): the voxel table, its value rows, the per-thread
    ``failed`` flags and the update counter a launch writes to."""
    target = MapTarget()
    target.table = table
    target.voxel_data = voxel_data
    target.failed = failed
    target.update_count = update_count
    return target
