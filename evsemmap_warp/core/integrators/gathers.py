"""The block gathers' launch, shared by S-BKI's (``kernels.block_gather``) and the release mode's
(``kernels.release``) gather kernels: each target block finds or inserts its cells and adds its sums
once, in the shard its index picks; with inputs a device prepared, the gather also reads the scan's
status back (``counted_gather_launch``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ...kernels import load_once
from ...methods.device_scratch import STATUS_KEPT_POINTS, STATUS_OVERFLOW, DeviceScratch, ScratchPool
from ..shards import PendingUpdates, ShardLanes, block_shard, for_each_shard, total_updates, when_done
from ..voxel_map import VoxelMap
from ..warp_runtime import device_calls
from .base import IntegrationStats, Launch, launch_step


def gather_blocks(shard: VoxelMap, kernel, scan, block_ids: np.ndarray, *, block_count: int, cells_per_block: int, kind: str) -> int:
    """A block-gather kernel (``kernels.block_gather`` or ``kernels.release``, made for this class
    count and block size) over the target blocks ``block_ids`` (of the ``block_count`` blocks of
    ``scan``): each block finds or inserts its cells and adds its sums once; blocks that did not fit
    are relaunched after the table grew. ``scan``: the kernel's inputs struct (``block_gather.SbkiBlocks``,
    ``release.release_blocks_struct``; device arrays shared by the shards). Returns updates."""
    if len(block_ids) == 0:
        return 0
    ids = shard.staging.upload("block_ids", block_ids, int, np.int32)
    count = shard.staging.upload("block_count", np.array([block_count]), int, np.int32)
    return _gather(shard, kernel, scan, len(block_ids), ids, count, cells_per_block=cells_per_block, kind=kind, exact_most=True)


def gather_counted_blocks(shard: VoxelMap, kernel, scan, capacity: int, block_count: wp.array, scan_status: wp.array, *, cells_per_block: int,
                          kind: str) -> tuple[int, np.ndarray]:
    """``gather_blocks`` over every target block of ``scan`` when a device counted them: block_count
    (a [1] int array on the device) of at most ``capacity``. Returns updates and ``scan_status`` (an int
    array on the device, what the scan's preprocessing counted), read back with the launch's counters."""
    # The table grows for as many new voxels as the last such launch made (the capacity is a bound,
    # far above the count on most scans).
    updates = _gather(shard, kernel, scan, capacity, shard.thread_ids(capacity), block_count, cells_per_block=cells_per_block,
                      kind=kind, exact_most=False, scan_status=scan_status)
    return updates, shard.counted_status


def _gather(shard: VoxelMap, kernel, scan, n: int, ids: wp.array, block_count: wp.array, *, cells_per_block: int, kind: str, exact_most: bool,
            scan_status: wp.array | None = None) -> int:
    """The block gather over n launch ids (block ids[launch id]), the table and brick cache grown for it."""
    d = shard.device

    def launch(pending, failed):
        wp.launch(kernel, dim=len(pending), device=d, inputs=[pending, ids, block_count, scan, shard.table(), shard.brick_table(), shard.data,
                                                              failed, shard.update_count])

    return shard.launch_until_done(n, launch, may_insert=True, kind=kind, most_new=n * cells_per_block**3, exact_most=exact_most,
                                   fails_only_when_full=True, brick_cells=cells_per_block, scan_status=scan_status)


def releasing(run, scratch: DeviceScratch):
    """``run`` (shards, lanes) -> updates, releasing ``scratch`` once its kernels are done: when it returns,
    or when its shard jobs have (``when_done``); also when it fails."""

    def run_then_release(shards: list[VoxelMap], lanes: ShardLanes | None):
        try:
            updates = run(shards, lanes)
        except BaseException:
            scratch.release()
            raise
        when_done(updates, scratch.release)
        return updates

    return run_then_release


def block_gather_run(blocks: np.ndarray, cells_per_block: int, kernel_factory, scan, kind: str):
    """run(shards, lanes) -> updates for a block-gather kernel (``kernel_factory(K, cells per block)``)
    over target ``blocks`` [B, 3] (the blocks of ``scan``, its inputs struct): the key range is checked
    before any launch, and each block is gathered in the shard its index picks, so a cell is always summed
    in the same shard in the same order and the map is bit for bit the same for any number of workers."""

    def run(shards: list[VoxelMap], lanes: ShardLanes | None) -> int | PendingUpdates:
        kernel = kernel_factory(shards[0].num_classes, cells_per_block)
        load_once(kernel.module, shards[0].device)  # compiled or loaded before the shards' threads launch it
        return _gather_over_shards(shards, lanes, kernel, scan, blocks, cells_per_block, kind)

    return run


def _gather_over_shards(shards, lanes, kernel, scan, blocks: np.ndarray, cells_per_block: int, kind: str) -> int | PendingUpdates:
    shards[0].check_block_range(blocks, cells_per_block)
    owner = block_shard(blocks, len(shards))

    def job(shard: VoxelMap, index: int) -> int:
        return gather_blocks(shard, kernel, scan, np.flatnonzero(owner == index), block_count=len(blocks), cells_per_block=cells_per_block, kind=kind)

    return total_updates(for_each_shard(shards, lanes, job))


def counted_gather_launch(stats: IntegrationStats, pool: ScratchPool, device: str, build, cells_per_block: int, kernel_factory, kind: str) -> Launch:
    """The launch of a block gather whose inputs the map's device prepared without reading a count back:
    ``build(scratch)`` -> (the kernel's inputs struct, their ``sbki_device.DeviceBlocks``), or the Launch of
    the host path where the device path does not apply, run with a set of ``pool``'s scratch.

    The gather reads the scan's status back with its counters, the scan's one read (a map of one shard
    whose blocks' box lies within the key range; otherwise the status and the blocks are read for the key
    range check and the shards' split). A scan whose status says it ran out of room gathered nothing: it is
    built again with room for what it counted and gathered again, in the launch. ``stats.kept_points``
    comes from the status."""
    with pool.taken(device) as scratch, device_calls(device):
        built = build(scratch)
    if not isinstance(built, tuple):  # the host path
        scratch.release()
        return built

    def run(shards: list[VoxelMap], lanes: ShardLanes | None) -> int | PendingUpdates:
        kernel = kernel_factory(shards[0].num_classes, cells_per_block)
        load_once(kernel.module, shards[0].device)  # compiled or loaded before the shards' threads launch it
        scan, targets = built
        while True:
            if len(shards) == 1 and targets.box is not None and VoxelMap.block_range_holds(np.stack(targets.box), cells_per_block):
                updates, status = gather_counted_blocks(shards[0], kernel, scan, targets.capacity, targets.count, targets.status,
                                                        cells_per_block=cells_per_block, kind=kind)
            else:
                status = targets.status.numpy()
                updates = 0 if status[STATUS_OVERFLOW] else _gather_over_shards(shards, lanes, kernel, scan, targets.host(), cells_per_block, kind)
            if not status[STATUS_OVERFLOW]:
                stats.kept_points = int(status[STATUS_KEPT_POINTS])
                return updates
            scratch.learn(status)
            rebuilt = build(scratch.begin())
            if not isinstance(rebuilt, tuple):  # with all its rows, the scan takes the host path (its blocks are too spread)
                host = rebuilt(shards, lanes)
                stats.kept_points = host.kept_points
                return host.voxel_updates
            scan, targets = rebuilt

    return launch_step(stats, releasing(run, scratch))
