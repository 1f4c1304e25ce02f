"""numpy twins of ``evsemmap_warp.kernels.device_counts``."""

from __future__ import annotations

import numpy as np

PAST_COUNT_KEY = np.iinfo(np.int64).max
STATUS_OVERFLOW = 0


def bounded_count(total: int, capacity: int, slot: int, status) -> tuple[np.ndarray, int]:
    """Twin of ``bounded_count``: (the status with the total (at most the largest int32) in ``slot`` and the
    overflow flag raised where the total exceeds the capacity, the count that fits)."""
    status = np.array(status, np.int32)
    status[slot] = min(total, np.iinfo(np.int32).max)
    if total > capacity:
        status[STATUS_OVERFLOW] = 1
    return status, min(total, capacity)


# The int64 total's kernel computes the same.
bounded_wide_count = bounded_count


def gated_count(total: int, status) -> int:
    """Twin of ``gated_count``: the total, or 0 where the status's overflow flag is set."""
    return 0 if status[STATUS_OVERFLOW] else int(total)
