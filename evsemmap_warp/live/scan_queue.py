"""The bounded queue between receiving scans and mapping them: ``put`` never blocks the subscriber;
when mapping falls behind and the queue is full, the oldest scan is dropped, counted and reported."""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass


@dataclass
class ReceivedScan:
    """A cloud as it arrived: its CDR bytes, when it arrived and when its publisher sent it (the
    attachment's source timestamp, ns since the epoch; None without one), its sequence number."""

    cdr: bytes
    received_ns: int
    sent_ns: int | None = None
    sequence: int | None = None

    @property
    def origin_ns(self) -> int:
        """Where a scan's latency is counted from: when it was sent, else when it arrived."""
        return self.sent_ns if self.sent_ns is not None else self.received_ns


class ScanQueue:
    """At most ``capacity`` scans; ``on_drop(scan, dropped_total)`` is called (on the subscriber's thread)
    for each scan dropped to make room."""

    def __init__(self, capacity: int, on_drop=None):
        if capacity < 1:
            raise ValueError(f"queue capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.received = 0
        self.dropped = 0
        self.on_drop = on_drop

    def put(self, scan: ReceivedScan) -> None:
        """Add a scan; drop the oldest when full (never waits)."""
        dropped = None
        with self._cond:
            self.received += 1
            if len(self._items) >= self.capacity:
                dropped = self._items.popleft()
                self.dropped += 1
            self._items.append(scan)
            self._cond.notify()
            total = self.dropped
        if dropped is not None and self.on_drop is not None:
            self.on_drop(dropped, total)

    def get(self, timeout: float) -> ReceivedScan | None:
        """The oldest scan, waiting up to ``timeout`` seconds for one; None when none came."""
        end = time.monotonic() + timeout
        with self._cond:
            while not self._items:
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._items.popleft()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
