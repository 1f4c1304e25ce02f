"""Sharding: on the CPU each worker thread integrates into its own shard of the map (never a shared one:
Warp's CPU "atomics" are plain read-modify-writes); readers add the shards up. A shard's jobs run on
its own lane (``ShardLanes``), in the order they were submitted, and a launch's voxel updates may still
be pending (``PendingUpdates``) when it returns. Scatters split a scan into contiguous parts, one per
shard (``split_over_shards``); the block gathers put each block in the shard its index picks
(``block_shard``), so their maps do not depend on the number of workers."""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .voxel_map import VoxelMap

# Below this many points per shard, splitting a launch costs more than it saves.
MIN_POINTS_PER_SHARD = 4096


class ShardLanes:
    """One thread per shard: a shard's jobs run one at a time in the order they were submitted, so its map is the
    same as when the scans run one after another, while the shards need not wait for each other at the end of
    every scan (that barrier left a core idle while the slower shard finished; docs/performance.md has the
    measurement)."""

    def __init__(self, count: int):
        self._lanes = [ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"evsemmap-shard{i}") for i in range(count)]

    def submit(self, index: int, job, *args) -> Future:
        """Run ``job(*args)`` on shard ``index``'s thread after the jobs submitted to it before; returns its
        Future."""
        return self._lanes[index].submit(job, *args)


@dataclass
class PendingUpdates:
    """Voxel updates of a launch whose jobs may still run on the shards' lanes (ints and futures)."""

    parts: list

    def wait(self) -> None:
        """Returns once every part has finished, failed or not."""
        for part in self.parts:
            if isinstance(part, Future):
                part.exception()

    def result(self) -> int:
        """Waits for every part (all of them, even after one failed), then adds them up or raises."""
        self.wait()
        return sum(part.result() if isinstance(part, Future) else part for part in self.parts)


def when_done(updates, callback) -> None:
    """callback() once ``updates`` are final: now for an int, else when every job of the PendingUpdates has
    finished (failed or not)."""
    futures = [part for part in updates.parts if isinstance(part, Future)] if isinstance(updates, PendingUpdates) else []
    if not futures:
        callback()
        return
    remaining = [len(futures)]
    lock = threading.Lock()

    def one_done(_future):
        with lock:
            remaining[0] -= 1
            last = remaining[0] == 0
        if last:
            callback()

    for future in futures:
        future.add_done_callback(one_done)


def total_updates(parts: list):
    """The sum of the parts' updates: an int, or PendingUpdates while some still run."""
    return PendingUpdates(parts) if any(isinstance(part, Future) for part in parts) else sum(parts)


def for_each_shard(shards: list[VoxelMap], lanes: ShardLanes | None, job) -> list:
    """job(shard, shard index) for every shard: on the shards' lanes (futures) when there are lanes."""
    if lanes is None:
        return [job(shard, i) for i, shard in enumerate(shards)]
    return [lanes.submit(i, job, shard, i) for i, shard in enumerate(shards)]


def split_over_shards(shards: list[VoxelMap], lanes: ShardLanes | None, n: int, job) -> list:
    """job(shard, index_range) on contiguous parts of range(n), one part per shard (fewer for small n),
    on the shards' lanes (futures) when there are lanes."""
    if lanes is None:
        return [job(shards[0], np.arange(n))]
    parts = max(1, min(len(shards), n // MIN_POINTS_PER_SHARD))
    return [lanes.submit(i, job, shards[i], part) for i, part in enumerate(np.array_split(np.arange(n), parts))]


def block_shard(blocks: np.ndarray, shards: int) -> np.ndarray:
    """The shard of each block [B, 3]: a fixed hash of its index, so it never depends on the scan."""
    b = np.asarray(blocks, dtype=np.int64)
    return ((b[:, 0] * 73856093) ^ (b[:, 1] * 19349663) ^ (b[:, 2] * 83492791)) % shards
