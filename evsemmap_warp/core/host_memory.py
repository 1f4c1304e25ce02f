"""Host memory for the CPU voxel tables: zeroed arrays on their own anonymous mappings, and the address
space reservation a growing table's rows live in (``VoxelMap``'s storage on the CPU). Each choice here
concerns the tables' own memory only: nothing in this module changes a setting of the process."""

from __future__ import annotations

import mmap
import resource
import sys
from pathlib import Path

import numpy as np


def lazily_zeroed(shape, dtype, populate: bool = False) -> np.ndarray:
    """A zeroed host array on its own anonymous mapping, without numpy's transparent-huge-page advice.

    Where the OS compacts memory for advised huge pages (THP defrag "madvise"), the first writes into a
    freshly grown table stall, and a growing map keeps faulting fresh memory in (docs/performance.md,
    "Measurements behind the code's choices").

    ``populate``: map the pages at once (Linux's MAP_POPULATE, where the platform has it), for memory that
    will nearly all be written soon, such as a table grown at a quarter of its slots or more: one populating
    call costs less than the faults it replaces."""
    dtype = np.dtype(dtype)
    count = int(np.prod(shape, dtype=np.int64))
    if count == 0:
        return np.zeros(shape, dtype)
    if populate and hasattr(mmap, "MAP_POPULATE"):
        memory = mmap.mmap(-1, count * dtype.itemsize, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | mmap.MAP_POPULATE)
    else:
        memory = mmap.mmap(-1, count * dtype.itemsize)
    return np.frombuffer(memory, dtype=dtype, count=count).reshape(shape)


# On the CPU a table's value rows live in one reservation of address space this large (its pages are
# mapped only as rows are written, and Linux's default overcommit does not count it against memory:
# MAP_NORESERVE), so a growing table neither moves nor copies its rows: copying them at each growth
# faults every used row in again (docs/performance.md, "Measurements behind the code's choices").
ROW_RESERVATION_BYTES = 1 << 34
_MAP_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000)  # Linux's value; Python names it from 3.13 on


def reservation_allowed() -> bool:
    """Whether a table may reserve address space beyond what it holds: on Linux, with no address-space
    limit (``ulimit -v``: a reservation would count against it, and so against the tables' memory budget,
    ``limits.available_memory``) and no strict overcommit (vm.overcommit_memory 2 charges the whole
    reservation to the system's commit limit)."""
    if not sys.platform.startswith("linux"):
        return False
    if resource.getrlimit(resource.RLIMIT_AS)[0] != resource.RLIM_INFINITY:
        return False
    try:
        return Path("/proc/sys/vm/overcommit_memory").read_text().strip() != "2"
    except OSError:
        return False


def reserved_zeros(rows: int, columns: int) -> np.ndarray | None:
    """A lazily zeroed float64 [rows, columns] array in address space reserved without committing
    memory, or None where that is not allowed (``reservation_allowed``) or the OS refuses it (the caller
    then allocates what it needs and copies its rows when it grows)."""
    if not reservation_allowed():
        return None
    try:
        memory = mmap.mmap(-1, rows * columns * 8, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _MAP_NORESERVE)
    except (OSError, ValueError, OverflowError):
        return None
    return np.frombuffer(memory, dtype=np.float64).reshape(rows, columns)
