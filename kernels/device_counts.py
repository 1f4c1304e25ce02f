"""Counts that stay on the device (Warp): the compatibility modes' device preprocessing launches each
kernel over a scratch array's whole capacity, and each thread past the count its stage found (a [1] int
array on the device) returns, so that no count is read back to size the next arrays
(``methods.device_scratch``).

``bounded_count``: a stage whose rows may outgrow the room reserved for them records its total in the
scan's status and passes on what fits, raising the status's overflow flag where not all did (the scan is
then redone with more room). ``gated_count``: the target blocks' count, or none where the scan
overflowed, so that a scan that ran out of room changes no voxel.

numpy twin: ``evsemmap_warp/reference/device_counts.py``.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# The sort key of the rows past a count: after every leaf and block position (a stable radix sort over a
# scratch array's whole capacity keeps them last, whatever its end bit, since they have every bit set).
PAST_COUNT_KEY = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
# The scan status's slots (an int array on the device, read back with the launch's counters).
STATUS_OVERFLOW = wp.constant(0)


def _bounded_count_kernel(total_type):
    @wp.kernel(module=__name__)
    def bounded_count(total: wp.array(dtype=total_type), capacity: int, slot: int, status: wp.array(dtype=int), count: wp.array(dtype=int)):
        """One thread: status[slot] = total[0] (at most the largest int); count[0] = min(total[0], capacity);
        status[STATUS_OVERFLOW] = 1 where the total exceeds the capacity."""
        value = wp.int64(total[0])
        status[slot] = int(wp.min(value, wp.int64(2147483647)))
        count[0] = int(wp.min(value, wp.int64(capacity)))
        if value > wp.int64(capacity):
            status[STATUS_OVERFLOW] = 1

    return bounded_count


# Concrete types only (a generic kernel would be built at its first launch, maybe on a worker thread): an
# int total (a prefix sum's last value), and an int64 one for a sum that can outgrow an int (the free
# samples of far rays).
bounded_count = _bounded_count_kernel(wp.int32)
bounded_wide_count = _bounded_count_kernel(wp.int64)


@wp.kernel
def gated_count(total: wp.array(dtype=int), status: wp.array(dtype=int), count: wp.array(dtype=int)):
    """One thread: count[0] = total[0], or 0 where status[STATUS_OVERFLOW] is set."""
    count[0] = wp.where(status[STATUS_OVERFLOW] != 0, 0, total[0])
