"""Stable least-significant-digit radix sort of int64 values by a bit field, for host preprocessing (Warp).

The callers pack a key above each value's position (``methods.sbki_compat.stable_sort``) and sort by the
key bits only. Each kernel runs as one thread (launch with dim=1 on the CPU): the per-scan preprocessing
already runs one scan per worker thread, and a sequential pass streams through memory in order. The digit
histograms come from one read per three passes (``digit_histograms``); each pass then moves the values
into their digit's range (``radix_scatter``) in input order, which is what makes the sort stable. Digits
of up to 13 bits (``methods.sbki_compat.MAX_RADIX_DIGIT_BITS``): a pass over more write streams costs more
per value, but fewer passes gain more. Against numpy's sort, which is scalar on the CPU: docs/performance.md.
The loops are ``while`` loops over indices passed through ``indexing.nonnegative`` (that module says why).

numpy twin: ``evsemmap_warp/reference/radix_sort.py``.
"""

import warp as wp

from . import MODULE_OPTIONS
from .indexing import nonnegative

wp.set_module_options(MODULE_OPTIONS)


# Passes one ``digit_histograms`` launch counts.
HISTOGRAM_PASSES = 3


@wp.kernel
def digit_histograms(values: wp.array(dtype=wp.int64), lowest_bit: int, digit_bits: int, passes: int,
                     first: wp.array(dtype=int), second: wp.array(dtype=int), third: wp.array(dtype=int)):
    """Counts of the digits of up to three passes (bits lowest_bit + p * digit_bits and up, p < passes): pass
    0 in ``first``, 1 in ``second``, 2 in ``third`` (arrays of the passes not counted are not touched).
    Three flat arrays rather than one [passes, digits] array with a loop over passes, which is slower."""
    mask = (wp.int64(1) << wp.int64(digit_bits)) - wp.int64(1)
    shift0 = wp.int64(lowest_bit)
    shift1 = wp.int64(lowest_bit + digit_bits)
    shift2 = wp.int64(lowest_bit + 2 * digit_bits)
    n = values.shape[0]
    i = int(0)
    while i < n:
        value = values[i]
        d0 = nonnegative(int((value >> shift0) & mask))
        first[d0] = first[d0] + 1
        if passes > 1:
            d1 = nonnegative(int((value >> shift1) & mask))
            second[d1] = second[d1] + 1
        if passes > 2:
            d2 = nonnegative(int((value >> shift2) & mask))
            third[d2] = third[d2] + 1
        i += 1


@wp.kernel
def radix_scatter(values_in: wp.array(dtype=wp.int64), shift: int, digit_bits: int, next_slot: wp.array(dtype=int),
                  values_out: wp.array(dtype=wp.int64)):
    """One pass: value i goes to next_slot[its digit], which then moves on; next_slot starts as the
    exclusive prefix sum of the pass's digit counts."""
    mask = (wp.int64(1) << wp.int64(digit_bits)) - wp.int64(1)
    n = values_in.shape[0]
    i = int(0)
    while i < n:
        value = values_in[i]
        digit = nonnegative(int((value >> wp.int64(shift)) & mask))
        slot = next_slot[digit]
        next_slot[digit] = slot + 1
        values_out[nonnegative(slot)] = value
        i += 1


@wp.kernel
def sorted_runs(packed: wp.array(dtype=wp.int64), position_bits: int, order: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64),
                run_count: wp.array(dtype=int)):
    """One thread over values packed as key << position_bits | position and sorted: order[k] = value k's
    position; starts[r] = where run r of equal keys begins, starts[R] = the value count; run_count[0] = R.
    One pass where numpy's unpacking and run search took five."""
    shift = wp.int64(position_bits)
    mask = (wp.int64(1) << shift) - wp.int64(1)
    n = packed.shape[0]
    runs = int(0)
    previous = wp.int64(0)
    k = int(0)
    while k < n:
        value = packed[k]
        key = value >> shift
        order[k] = value & mask
        if k == 0 or key != previous:
            starts[runs] = wp.int64(k)
            runs += 1
            previous = key
        k += 1
    starts[runs] = wp.int64(n)
    run_count[0] = runs
