"""Device arrays kept from scan to scan, so that a warm map allocates nothing per scan (the compatibility
modes' device preprocessing, ``sbki_device`` and ``release_device``, and the clean mode's sorted and
hash-grid strategies, ``core.voxel_map``), and the prefix sums over them.

The compatibility modes' preprocessing reads no count back: each stage's rows are a ``Rows``, an array
whose capacity the host knows (a bound, or for the free samples and the (point, block) pairs, whose
bound is far above their count, the room reserved for them) and whose count stays on the device, and
each kernel runs over the capacity, its threads past the count returning. A scan's ``status`` (on the
device) records what the reserved stages counted and whether one ran out of room; it is read back with
the gather's counters, the scan's one read. A scan that ran out of room changes no voxel (its gather
sees no target block) and is redone with room for what it counted (``DeviceScratch.learn``): the
reservations are the pool's, so later scans start with that room.

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

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import device_counts

_GROWTH = 1.5

# The slots of a scan's status (``DeviceScratch.status``), counted on the device and read back with the
# gather's counters: whether a stage ran out of its reserved room, the points the scan kept (the training
# set, or the release's capped points), and the totals of the two reserved stages.
STATUS_OVERFLOW = 0
STATUS_KEPT_POINTS = 1
STATUS_FREE_ROWS = 2
STATUS_PAIRS = 3
STATUS_SLOTS = 4
_RESERVED = (STATUS_FREE_ROWS, STATUS_PAIRS)


@dataclass
class Rows:
    """The first ``count`` rows of ``array``: the count a [1] int array on the device, at most the array's
    capacity (its first dimension), which the host knows."""

    array: wp.array
    count: wp.array

    @property
    def capacity(self) -> int:
        """The rows the array has room for."""
        return self.array.shape[0]

    def numpy(self) -> np.ndarray:
        """The counted rows, read back (the count, then the rows: two reads, for tests and fallbacks)."""
        return self.array.numpy()[:int(self.count.numpy()[0])]


class DeviceScratch:
    """One prepared scan's device arrays on ``device``, reused by the next scan that takes this set."""

    def __init__(self, device: str, reservations: dict | None = None):
        self.device = device
        self.in_use = False
        self._buffers: dict[tuple, wp.array] = {}
        self._pinned: dict[tuple, wp.array] = {}  # host staging of ``upload``, by the same keys
        # Whether ``upload`` copies into kept buffers (a GPU's path; a test sets it on the CPU backend) or
        # hands a CPU kernel numpy's memory itself.
        self.copies_uploads = not wp.get_device(device).is_cpu
        self._requests: Counter = Counter()
        self._reservations = {} if reservations is None else reservations
        self.status: wp.array | None = None
        # The status of this scan's run that ran out of room (``learn``), for its redo; None for a new scan.
        self.redo_status: np.ndarray | None = None

    def begin(self) -> "DeviceScratch":
        """Start a scan, or its redo: the requests from each line count from the first again, and the
        scan's status is zeroed."""
        self._requests.clear()
        self.status = self.zeros(STATUS_SLOTS, int)
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

    def count(self, value: int) -> wp.array:
        """A count the host knows, as a [1] int array on the device."""
        return self.full(1, int(value), int)

    def room(self, slot: int, guess: int, bound: int) -> int:
        """The rows reserved for the stage whose total the status keeps in ``slot``: ``guess`` (from the
        scan's size), or more where scans that ran out of room asked for more (``learn``); at least 1, at
        most ``bound``."""
        return max(1, min(int(bound), max(int(guess), self._reservations.get(slot, 0))))

    def bounded(self, total: wp.array, capacity: int, slot: int) -> wp.array:
        """The count of a stage's rows, ``total`` (a [1] int or int64 array on the device) up to ``capacity``;
        the total goes to the status's ``slot``, and the overflow flag is raised where it exceeds the capacity."""
        caller = sys._getframe(1)
        count = self._view((caller.f_code.co_filename, caller.f_lineno), 1, int)
        kernel = device_counts.bounded_wide_count if total.dtype == wp.int64 else device_counts.bounded_count
        wp.launch(kernel, dim=1, device=self.device, inputs=[total, int(capacity), int(slot), self.status, count])
        return count

    def learn(self, status: np.ndarray) -> None:
        """After a run that ran out of room (its ``status``, read back): room for half again what it
        counted in each reserved stage, kept for later scans too."""
        for slot in _RESERVED:
            need = int(int(status[slot]) * _GROWTH) + 1
            if need > self._reservations.get(slot, 0):
                self._reservations[slot] = need
        self.redo_status = np.asarray(status).copy()

    def upload(self, values: np.ndarray, dtype) -> wp.array:
        """Host values as a device array: numpy's memory itself on the CPU, else a copy into a kept buffer,
        queued without waiting from a kept pinned host buffer (a copy from pageable memory would wait, and
        so would the host's next scan). The set's pinned buffers are written again only by a later scan that
        takes the set, after this scan's launch has read its outcome back, so the copy has been made."""
        values = np.ascontiguousarray(values)
        if not self.copies_uploads:
            return wp.array(values, dtype=dtype, device="cpu", copy=False)
        caller = sys._getframe(1)
        site = (caller.f_code.co_filename, caller.f_lineno)
        host = wp.array(values, dtype=dtype, device="cpu", copy=False)
        out = self._view(site, host.shape, dtype)
        if host.size:
            key = (site, self._requests[site] - 1)
            staged = np.ascontiguousarray(host.numpy())  # in ``dtype``'s layout: the bytes the device copy reads
            pinned = self._pinned.get(key)
            if pinned is None or pinned.size < staged.nbytes:
                pinned = self._pinned[key] = wp.empty(max(staged.nbytes, int((0 if pinned is None else pinned.size) * _GROWTH)), dtype=wp.uint8,
                                                      device="cpu", pinned=wp.get_device(self.device).is_cuda)
            pinned.numpy()[:staged.nbytes] = staged.reshape(-1).view(np.uint8)
            wp.copy(out, wp.array(ptr=pinned.ptr, shape=host.shape, dtype=dtype, device="cpu"))
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
        self._reservations: dict[str, dict] = {}  # per device, shared by its sets (``DeviceScratch.room``)
        self._lock = threading.Lock()

    def take(self, device: str) -> DeviceScratch:
        """A free set of ``device``, held until its ``release``, ready for a new scan."""
        with self._lock:
            sets = self._sets.setdefault(str(device), [])
            scratch = next((s for s in sets if not s.in_use), None)
            if scratch is None:
                scratch = DeviceScratch(device, self._reservations.setdefault(str(device), {}))
                sets.append(scratch)
            scratch.in_use = True
            scratch.redo_status = None
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


def last_of(values: wp.array) -> wp.array:
    """The last value of a device array [n > 0], as a [1] view on the device (the total of a prefix sum)."""
    n = values.shape[0]
    return values[n - 1:n]


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
