"""``evsemmap batch``: map long sequences on every core of a machine, or on a Ray cluster, into a map
store (core/map_store.py).

BKI maps are sums, so partial maps of disjoint scan sets add up exactly. A run:

1. plans: the inputs' insertions (scans, or bins of camera-labelled frames) are cut into chunks of
   consecutive insertions (``--chunk-frames`` frames, by default chosen from the inputs' total frames
   alone, see choose_chunk_frames; rounded to whole bins, so per-insertion rules see what
   ``evsemmap map`` shows them); the map origin is that ``evsemmap map`` picks (the first scan's);
2. maps each chunk in a worker into a partial map, written per spatial tile under ``STORE/work``
   (a chunk is done when its folder is renamed into place, so a killed worker leaves nothing that
   counts);
3. folds, in the driver while the workers map, every finished chunk's partials into the store's
   tiles, in chunk order (so the sums do not depend on which chunk finished first), and deletes them:
   a tile is final as soon as the last chunk touching it is folded, and the disk holds the tiles plus
   the partials of chunks not yet folded. Each tile records the last chunk folded into it, so a
   resumed run folds every chunk into every tile exactly once;
4. writes ``STORE/store.json`` last.

A rerun of the same command skips finished chunks and folds what is left, so an interrupted run
finishes without counting any chunk twice; a worker that dies is replaced and its chunk mapped again.
The same inputs give the same store, byte for byte, whatever the executor, worker count or completion
order.

The package: ``planning`` (options, chunks, the probe and the memory check), ``worker`` (the task a worker
runs, map_chunk, and the worker process's set-up), ``executors`` (in this process, a local process pool),
``ray_executor`` (Ray), ``reduction`` (the driver's tile folding), ``store`` (the store lock, the work
folder's records, store.json) and ``run`` (run_batch, which ties them together).
"""

from .executors import InlineExecutor, LocalExecutor, stuck_error
from .planning import (
    DRIVER_OVERHEAD_BYTES,
    WORKER_OVERHEAD_BYTES,
    BatchOptions,
    Chunk,
    bytes_per_voxel,
    check_memory,
    choose_chunk_frames,
    plan_batch,
    probe,
    split_inputs,
)
from .ray_executor import RayExecutor, check_ray_address
from .reduction import TileFolder
from .run import run_batch
from .store import store_lock, write_store_from_mapper
from .worker import CHUNK_STAGES, Context, FaultPlan, map_chunk

__all__ = [
    "BatchOptions", "CHUNK_STAGES", "Chunk", "Context", "DRIVER_OVERHEAD_BYTES", "FaultPlan", "InlineExecutor",
    "LocalExecutor", "RayExecutor", "TileFolder", "WORKER_OVERHEAD_BYTES", "bytes_per_voxel", "check_memory",
    "check_ray_address", "choose_chunk_frames", "map_chunk", "plan_batch", "probe", "run_batch", "split_inputs", "store_lock",
    "stuck_error", "write_store_from_mapper",
]
