"""Device arrays kept from scan to scan, so that a warm map allocates nothing per scan (the compatibility
modes' device preprocessing, ``sbki_device`` and ``release_device``, and the clean mode's sorted and
hash-grid strategies, ``core.voxel_map``), and the prefix sums over them that size the next arrays with
one read each.

A ``DeviceScratch`` holds one prepared scan's arrays: each array a view of a flat buffer kept for the
line of code that asks for it (and its n-th request from that line in this scan, since the VoxelGrid runs
twice per scan), grown by half again when a scan outgrows it. A scan's arrays are read by its launch,
which may come after later scans are prepared (``Mapper.integrate_many`` prepares scans ahead while
earlier ones launch), so a scan takes a set from a ``ScratchPool`` that no scan in flight holds, and its
launch gives it back once its kernels are done: there are as many sets as scans were ever in flight at
once.
"""

from __future__ import annotations

import sys
import threading
from collections import Counter
from contextlib import contextmanager

import numpy as np
import warp as wp

_GROWTH = 1.5


class DeviceScratch:
    """One prepared scan's device arrays on ``device``, reused by the next scan that takes this set."""

    def __init__(self, device: str):
        self.device = device
        self.in_use = False
        self._buffers: dict[tuple, wp.array] = {}
        self._requests: Counter = Counter()

    def begin(self) -> "DeviceScratch":
        """Start a scan: the requests from each line count from the first again."""
        self._requests.clear()
        return self

    def release(self) -> None:
        """The scan that held this set is done with it (its kernels have run)."""
        self.in_use = False

    def empty(self, shape, dtype) -> wp.array:
        """An uninitialised array of ``shape`` (an int or a tuple) and ``dtype`` on the device."""
        caller = sys._getframe(1)
        return self._view((caller.f_code.co_filename, caller.f_lineno), shape, dtype)

    def zeros(self, shape, dtype) -> wp.array:
        """``empty``, zeroed on the device."""
        caller = sys._getframe(1)
        out = self._view((caller.f_code.co_filename, caller.f_lineno), shape, dtype)
        out.zero_()
        return out

    def full(self, shape, value, dtype) -> wp.array:
        """``empty``, filled with ``value`` on the device."""
        caller = sys._getframe(1)
        out = self._view((caller.f_code.co_filename, caller.f_lineno), shape, dtype)
        out.fill_(value)
        return out

    def upload(self, values: np.ndarray, dtype) -> wp.array:
        """Host values as a device array: numpy's memory itself on the CPU, else a copy into a kept buffer."""
        values = np.ascontiguousarray(values)
        if wp.get_device(self.device).is_cpu:
            return wp.array(values, dtype=dtype, device="cpu", copy=False)
        caller = sys._getframe(1)
        host = wp.array(values, dtype=dtype, device="cpu", copy=False)
        out = self._view((caller.f_code.co_filename, caller.f_lineno), host.shape, dtype)
        if host.size:
            wp.copy(out, host)
        return out

    def _view(self, site: tuple, shape, dtype) -> wp.array:
        shape = (int(shape),) if np.isscalar(shape) else tuple(int(x) for x in shape)
        key = (site, self._requests[site])
        self._requests[site] += 1
        elements = int(np.prod(shape))
        if elements == 0:
            return wp.empty(shape, dtype=dtype, device=self.device)
        itemsize = wp.types.type_size_in_bytes(dtype)
        buffer = self._buffers.get(key)
        if buffer is None or buffer.size < elements * itemsize:
            old = 0 if buffer is None else buffer.size
            buffer = self._buffers[key] = wp.empty(max(elements * itemsize, int(old * _GROWTH)), dtype=wp.uint8, device=self.device)
        view = wp.array(ptr=buffer.ptr, shape=shape, dtype=dtype, device=self.device)
        view._scratch_buffer = buffer  # the view borrows the buffer's memory: keep it alive as long as the view
        return view


class ScratchPool:
    """``DeviceScratch`` sets per device: a scan takes one that no scan holds (a new one when every set is
    held) and releases it when its launch is done (thread-safe: scans are prepared on several threads)."""

    def __init__(self):
        self._sets: dict[str, list[DeviceScratch]] = {}
        self._lock = threading.Lock()

    def take(self, device: str) -> DeviceScratch:
        """A free set of ``device``, held until its ``release``, ready for a new scan."""
        with self._lock:
            sets = self._sets.setdefault(str(device), [])
            scratch = next((s for s in sets if not s.in_use), None)
            if scratch is None:
                scratch = DeviceScratch(device)
                sets.append(scratch)
            scratch.in_use = True
        return scratch.begin()

    @contextmanager
    def taken(self, device: str):
        """``take`` for the block: the set is released if the block raises; otherwise the caller hands it
        on (to the launch that releases it once its kernels are done, or releases it itself)."""
        scratch = self.take(device)
        try:
            yield scratch
        except BaseException:
            scratch.release()
            raise

    def sets(self, device: str) -> int:
        """How many sets ``device`` has: the most scans that held one at once."""
        return len(self._sets.get(str(device), []))


def inclusive_scan(values: wp.array, scratch: DeviceScratch) -> wp.array:
    """The inclusive prefix sums of a device array, on its device."""
    out = scratch.empty(values.shape, values.dtype)
    wp.utils.array_scan(values, out, inclusive=True)
    return out


def last_value(values: wp.array) -> int:
    """The last value of a device array (one small read back)."""
    return int(values[values.shape[0] - 1:].numpy()[0])


def counts_with_room(n: int, scratch: DeviceScratch) -> wp.array:
    """An int array for n counts and a trailing 0 (kernels write the first n): its ``offsets_and_total``
    are n offsets and their total in one read."""
    counts = scratch.empty(n + 1, int)
    counts[n:].fill_(0)
    return counts


def offsets_and_total(counts: wp.array, scratch: DeviceScratch) -> tuple[wp.array, int]:
    """The exclusive prefix sums of ``counts_with_room``'s counts [n + 1] (offsets[i] is where item i's
    rows start) and their total, read back once (offsets[n])."""
    offsets = scratch.empty(counts.shape, counts.dtype)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    return offsets, last_value(offsets)
