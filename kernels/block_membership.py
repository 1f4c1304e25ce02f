"""Which blocks hold each point, as S-BKI's and the release's inclusive box tests decide (Warp).

Block k spans [k B - B/2, k B + B/2] per axis in float32 (docs/compatibility.md §1): a point on a shared
face belongs to both blocks. ``block_membership_masks`` finds each point's nearest block (float64 rounding
of p / B) and tests it and its 26 neighbours; one thread walks all points (launch with dim=1), as the
per-scan preprocessing runs one scan per worker. ``membership_counts`` and ``membership_pairs`` then list
the (point, block) pairs in the order the block gathers sum them, in place of numpy's 27 selection passes
(both faster than their numpy forms: docs/performance.md).

The parallel forms (``membership_masks_parallel`` to ``membership_blocks``) list the same pairs in the same
order on a device: each point writes its pairs, bit by bit, after the exclusive scan of the points' pair
counts, and a stable radix sort by bit puts them shift by shift (``methods.sbki_device``).

numpy twin: ``evsemmap_warp/reference/block_membership.py``.
"""

import warp as wp

from . import MODULE_OPTIONS
from .indexing import nonnegative

wp.set_module_options(MODULE_OPTIONS)

# Bit (sx + 1) * 9 + (sy + 1) * 3 + (sz + 1) of a mask: the point lies in block nearest + (sx, sy, sz).
NEAREST_BIT = 13


@wp.func
def _axis_bits(p: float, k: wp.int64, size: float, half: float) -> int:
    """Bits 0, 1, 2: p lies in block k - 1, k, k + 1 on this axis."""
    below = float(k - wp.int64(1)) * size
    center = float(k) * size
    above = float(k + wp.int64(1)) * size
    return (wp.where(below - half <= p and p <= below + half, 1, 0) | wp.where(center - half <= p and p <= center + half, 2, 0)
            | wp.where(above - half <= p and p <= above + half, 4, 0))


@wp.func
def _nearest(p: float, size: wp.float64) -> wp.int64:
    return wp.int64(wp.floor(wp.float64(p) / size + wp.float64(0.5)))


@wp.func
def _membership(points: wp.array(dtype=wp.vec3), i: int, size: float, nearest: wp.array2d(dtype=wp.int64)) -> int:
    """Writes point i's nearest block to nearest[i]; returns the 27-bit mask of its blocks."""
    half = size / 2.0
    size64 = wp.float64(size)
    p = points[i]
    kx = _nearest(p[0], size64)
    ky = _nearest(p[1], size64)
    kz = _nearest(p[2], size64)
    nearest[i, 0] = kx
    nearest[i, 1] = ky
    nearest[i, 2] = kz
    x = _axis_bits(p[0], kx, size, half)
    y = _axis_bits(p[1], ky, size, half)
    z = _axis_bits(p[2], kz, size, half)
    # bit sy * 3 + sz of yz: in y's block sy and z's block sz; then the same with x above it
    yz = (y & 1) * z | ((y >> 1) & 1) * (z << 3) | ((y >> 2) & 1) * (z << 6)
    return (x & 1) * yz | ((x >> 1) & 1) * (yz << 9) | ((x >> 2) & 1) * (yz << 18)


@wp.kernel
def block_membership_masks(points: wp.array(dtype=wp.vec3), size: float, nearest: wp.array2d(dtype=wp.int64), masks: wp.array(dtype=int)):
    """nearest[i] = round(points[i] / size) per axis (in float64), masks[i] = the 27-bit mask of the
    blocks nearest[i] + (-1..1)^3 whose closed float32 box holds the point. One thread (a while loop:
    ``kernels.indexing``)."""
    n = points.shape[0]
    i = int(0)
    while i < n:
        masks[i] = _membership(points, i, size, nearest)
        i += 1


@wp.func
def _shift_of_bit(bit: int) -> wp.vec3l:
    return wp.vec3l(wp.int64(bit / 9 - 1), wp.int64((bit / 3) % 3 - 1), wp.int64(bit % 3 - 1))


@wp.kernel
def membership_counts(masks: wp.array(dtype=int), counts: wp.array(dtype=int)):
    """counts[bit] = how many masks have ``bit`` set (counts start at zero). One thread."""
    n = masks.shape[0]
    i = int(0)
    while i < n:
        mask = masks[i]
        if mask == 1 << NEAREST_BIT:  # nearly every point: inside its nearest block only
            counts[NEAREST_BIT] = counts[NEAREST_BIT] + 1
        else:
            for bit in range(27):
                if (mask >> bit) & 1 == 1:
                    counts[bit] = counts[bit] + 1
        i += 1


@wp.kernel
def membership_pairs(masks: wp.array(dtype=int), nearest: wp.array2d(dtype=wp.int64), next_pair: wp.array(dtype=int),
                     point_ids: wp.array(dtype=wp.int64), blocks: wp.array2d(dtype=wp.int64)):
    """Every (point, block) pair of the masks, shift by shift (bit order), points ascending within a
    shift: pair next_pair[bit] (which then moves on; it starts at the exclusive prefix sum of
    ``membership_counts``) is point i and block nearest[i] + the bit's shift. One thread (a while loop and
    nonnegative indices: ``kernels.indexing``)."""
    n = masks.shape[0]
    i = int(0)
    while i < n:
        mask = masks[i]
        # Nearly every point lies inside its nearest block only: its pair written directly (the bit loop
        # below gives the same pair; running it for these points doubled this kernel's time).
        if mask == 1 << NEAREST_BIT:
            pair = nonnegative(next_pair[NEAREST_BIT])
            next_pair[NEAREST_BIT] = pair + 1
            point_ids[pair] = wp.int64(i)
            blocks[pair, 0] = nearest[i, 0]
            blocks[pair, 1] = nearest[i, 1]
            blocks[pair, 2] = nearest[i, 2]
        else:
            for bit in range(27):
                if (mask >> bit) & 1 == 1:
                    pair = nonnegative(next_pair[bit])
                    next_pair[bit] = pair + 1
                    point_ids[pair] = wp.int64(i)
                    shift = _shift_of_bit(bit)
                    blocks[pair, 0] = nearest[i, 0] + shift[0]
                    blocks[pair, 1] = nearest[i, 1] + shift[1]
                    blocks[pair, 2] = nearest[i, 2] + shift[2]
        i += 1


# ------------------------------------------------------------------ parallel forms (one thread per point or pair)


@wp.kernel
def membership_masks_parallel(points: wp.array(dtype=wp.vec3), point_count: wp.array(dtype=int), size: float, nearest: wp.array2d(dtype=wp.int64),
                              masks: wp.array(dtype=int), pair_counts: wp.array(dtype=int)):
    """``block_membership_masks``, one thread per point of point_count[0]; pair_counts[i] = the blocks
    holding point i, 0 past the count."""
    i = wp.tid()
    if i >= point_count[0]:
        pair_counts[i] = 0
        return
    mask = _membership(points, i, size, nearest)
    masks[i] = mask
    count = int(0)
    for bit in range(27):
        count += (mask >> bit) & 1
    pair_counts[i] = count


@wp.kernel
def membership_pairs_by_point(masks: wp.array(dtype=int), point_count: wp.array(dtype=int), first_pair: wp.array(dtype=int),
                              pair_capacity: int, bits: wp.array(dtype=wp.int64), point_ids: wp.array(dtype=wp.int64)):
    """Point i's pairs at first_pair[i] on (an exclusive scan of the pair counts), in bit order: their
    bits and the point, for the point_count[0] points; pairs from pair_capacity on are not written (the
    caller sees their count). A stable sort by bit then lists them as ``membership_pairs`` does."""
    i = wp.tid()
    if i >= point_count[0]:
        return
    mask = masks[i]
    pair = first_pair[i]
    for bit in range(27):
        if (mask >> bit) & 1 == 1 and pair < pair_capacity:
            bits[pair] = wp.int64(bit)
            point_ids[pair] = wp.int64(i)
            pair += 1


@wp.kernel
def membership_blocks(bits: wp.array(dtype=wp.int64), point_ids: wp.array(dtype=wp.int64), pair_count: wp.array(dtype=int),
                      nearest: wp.array2d(dtype=wp.int64), blocks: wp.array2d(dtype=wp.int64)):
    """blocks[k] = the nearest block of pair k's point + its bit's shift, for the pair_count[0] pairs."""
    k = wp.tid()
    if k >= pair_count[0]:
        return
    i = int(point_ids[k])
    shift = _shift_of_bit(int(bits[k]))
    for axis in range(3):
        blocks[k, axis] = nearest[i, axis] + shift[axis]
