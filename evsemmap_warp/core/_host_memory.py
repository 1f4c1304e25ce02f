"""Host memory for the CPU voxel tables: zeroed arrays on their own anonymous mappings, and the address
space reservation a growing table's rows live in (``VoxelMap``'s storage on the CPU)."""

from __future__ import annotations

import contextlib
import mmap
import sys
import threading

import numpy as np


def lazily_zeroed(shape, dtype, populate: bool = False) -> np.ndarray:
    """A zeroed host array on its own anonymous mapping, without numpy's transparent-huge-page advice.

    numpy advises huge pages for large arrays; where the OS compacts memory on such faults (THP defrag
    "madvise", as on this project's VMs) the first writes into a freshly grown table stall, and a growing map
    keeps faulting fresh memory in (docs/performance.md, "Measurements behind the code's choices").

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
# mapped only as rows are written, and Linux does not count it against memory: MAP_NORESERVE), so a
# growing table neither moves nor copies its rows. Copying them at each growth faulted every used row
# in again (S-BKI mode at free_res 4, one thread, alternating runs: 1.58 s with the copies, 1.35 s
# without; 118 k against 70 k page faults).
ROW_RESERVATION_BYTES = 1 << 34
_MAP_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000)  # Linux's value; Python names it from 3.13 on


def reserved_zeros(rows: int, columns: int) -> np.ndarray | None:
    """A lazily zeroed float64 [rows, columns] array in address space reserved without committing
    memory, or None where the platform or its overcommit policy refuses (the caller then allocates)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        memory = mmap.mmap(-1, rows * columns * 8, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _MAP_NORESERVE)
    except (OSError, ValueError, OverflowError):
        return None
    return np.frombuffer(memory, dtype=np.float64).reshape(rows, columns)


# numpy's switch for its huge-page advice (a private function, numpy >= 1.20; None where it is absent).
_SET_HUGE_PAGE_ADVICE = getattr(getattr(getattr(np, "_core", None), "multiarray", None), "_set_madvise_hugepage", None) or getattr(
    getattr(getattr(np, "core", None), "multiarray", None), "_set_madvise_hugepage", None)
_advice_lock = threading.Lock()
_advice_off_depth = 0
_advice_before = True


@contextlib.contextmanager
def without_huge_page_advice():
    """numpy's transparent-huge-page advice off while the block runs (nested and concurrent uses keep it
    off until the last one ends, which restores the setting found), for work that allocates large arrays
    once and reads them once, such as a map's read-out: on this project's VMs a huge page's first touch
    costs more than the small pages it replaces (``lazily_zeroed`` avoids the advice for the tables).
    The advice only places memory; results are the same with it or without it."""
    global _advice_off_depth, _advice_before
    if _SET_HUGE_PAGE_ADVICE is None:
        yield
        return
    with _advice_lock:
        if _advice_off_depth == 0:
            _advice_before = bool(_SET_HUGE_PAGE_ADVICE(False))
        _advice_off_depth += 1
    try:
        yield
    finally:
        with _advice_lock:
            _advice_off_depth -= 1
            if _advice_off_depth == 0:
                _SET_HUGE_PAGE_ADVICE(_advice_before)
