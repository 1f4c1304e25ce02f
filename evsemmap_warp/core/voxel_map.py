"""The sparse voxel map: a Warp hash table of voxel keys plus per-voxel arrays on one device.

Voxel i spans [i r + o, (i + 1) r + o) on every axis in coordinates relative to the map origin
(r = resolution, o = grid offset, 0 except for the S-CSM compatibility grid), so its center is
(i + 0.5) r + o. Per voxel the map keeps one float64 row of ``data`` [capacity, K + 5], rows in the
order the voxels were inserted (the table's ``slot_rows`` says which row a slot's voxel has):

* K columns of kernel-weighted evidence added so far; the Dirichlet concentrations are prior +
  evidence (stored without the prior so that fresh rows are zero pages and maps merge by addition);
* the sum of kernel weights and of weight * input uncertainty;
* the number of contributions;
* the sum of weight * (z - z_c), z a point's height and z_c the voxel center's: its weighted mean height
  (``VoxelArrays.mean_height_offset``; the clean modes keep it, the compat modes leave it 0, kernels/scatter.py);
* the touched flag (1 once any update landed).

float64, because evidence on a ground voxel of a long drive passes float32's 2^24 integer limit.
The table grows (2x: keys and row numbers rehashed; on the CPU the rows stay where they are, elsewhere
the used ones are copied once) before it passes ``max_load`` and whenever a launch runs out of room;
the points or blocks that could not be inserted are relaunched, so a voxel is never dropped or
overwritten (``launch_until_done``). The block-gather kernels also keep a brick cache (a block's first
row, by its first cell; ``_allocate_brick_cache``). The map is storage: the table, the rows, growth,
read-out and lookup, and the grow-and-relaunch protocol every launch runs through; which kernels a
method launches, and how, is its integrator's (``core.integrators``); payloads and files live elsewhere.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass

import numpy as np

from ..methods.device_scratch import DeviceScratch
from ..limits import MemoryBudgetError, available_memory, describe_bytes
from ..voxel_keys import check_index_range, column_bounds, pack_voxel_keys, take_rows, unpack_voxel_keys, within_index_range
from . import host_memory
from ._staging import Staging
from .warp_runtime import init_warp, resolve_device

wp = init_warp()

from ..kernels import hash_table as ht  # noqa: E402
from ..kernels import load_once  # noqa: E402
from ..kernels import scatter as sc  # noqa: E402

EXTRA_COLUMNS = sc.EXTRA_COLUMNS

MIN_CAPACITY = 16
# Inside one launch the table may fill up to this fraction before insertions fail and it grows;
# between launches it is kept at or below max_load.
LAUNCH_FILL_LIMIT = 0.75
# The most values of a scan status read back with a launch's counters (``gather_counted_blocks``).
MAX_SCAN_STATUS = 8


@dataclass
class VoxelArrays:
    """Host copy of every stored voxel, in ascending key order (x, then y, then z index); indices
    are relative to the map origin."""

    index: np.ndarray  # [V, 3] int64 voxel indices
    evidence: np.ndarray  # [V, K] float64; concentrations are prior + evidence
    weight_sum: np.ndarray  # [V] float64
    weighted_uncertainty_sum: np.ndarray  # [V] float64
    hits: np.ndarray  # [V] int64
    touched: np.ndarray  # [V] bool
    weighted_height_sum: np.ndarray  # [V] float64: sum of weight * (z - the voxel center's z), m

    @classmethod
    def from_rows(cls, index: np.ndarray, rows: np.ndarray) -> "VoxelArrays":
        """The arrays of voxels ``index`` [V, 3] from their value rows [V, K + EXTRA_COLUMNS] (evidence, then
        the bookkeeping columns), copied."""
        k = rows.shape[1] - EXTRA_COLUMNS
        return cls(index=np.asarray(index, np.int64), evidence=rows[:, :k].copy(),
                   weight_sum=rows[:, k + sc.COL_WEIGHT].copy(), weighted_uncertainty_sum=rows[:, k + sc.COL_WEIGHTED_UNCERTAINTY].copy(),
                   hits=rows[:, k + sc.COL_HITS].astype(np.int64), touched=rows[:, k + sc.COL_TOUCHED] > 0,
                   weighted_height_sum=rows[:, k + sc.COL_WEIGHTED_HEIGHT].copy())

    def rows(self) -> np.ndarray:
        """The [V, K + 5] float64 layout of the table's data array."""
        return np.column_stack([self.evidence, self.weight_sum, self.weighted_uncertainty_sum,
                                self.hits.astype(np.float64), self.weighted_height_sum, self.touched.astype(np.float64)])

    def mean_height_offset(self) -> np.ndarray:
        """[V] how far (m) the weighted mean height of the points that reached each voxel lies above its
        center: the weighted height sum over the weight sum; 0 where no weight landed, and in the compat
        modes' maps, which keep no heights (their mean height is the center)."""
        return np.divide(self.weighted_height_sum, self.weight_sum, out=np.zeros(len(self.weight_sum)), where=self.weight_sum > 0)


class TableBudget:
    """The memory the voxel tables of one map (a Mapper's shards) may take together, checked before any of
    them is allocated or grown, so that an input reaching far more voxels than any estimate foresaw is
    refused in one line (``MemoryBudgetError``) instead of ending in the OS's out-of-memory killer.
    ``limit_bytes``: the budget (``Mapper``'s ``max_memory``, ``--max-memory``); None: at each growth,
    the memory the process may still take (``limits.available_memory``, or the GPU's free memory) plus
    what the tables hold already."""

    def __init__(self, limit_bytes: int | None = None):
        self.limit_bytes = None if limit_bytes is None else int(limit_bytes)
        self._held: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # VoxelMap -> the bytes admitted for it
        self._lock = threading.Lock()  # shards grow on their own threads

    def admit(self, table: "VoxelMap", need: int, what: str, *, record: bool = True) -> None:
        """Record (``record``) that ``table`` will take ``need`` bytes, or raise MemoryBudgetError (nothing recorded)."""
        with self._lock:
            others = sum(held for key, held in self._held.items() if key is not table)
            if self.limit_bytes is not None:
                budget, source = self.limit_bytes, "max_memory (--max-memory)"
            else:
                free = available_memory() if table.device == "cpu" else wp.get_device(table.device).free_memory
                budget = free + sum(self._held.values())
                source = f"the memory available on {table.device} (set --max-memory / Mapper max_memory to choose it)"
            if others + need > budget:
                shards = f" beside {describe_bytes(others)} of the map's other shards" if others else ""
                raise MemoryBudgetError(
                    f"the voxel table would need {describe_bytes(need)} ({what}){shards}, over the memory budget of "
                    f"{describe_bytes(budget)}, {source}: the input reaches far more voxels than a map should (check the "
                    f"sensor origin, the units of the points and lengths, mapping.sbki.max_range_m), or the budget is too small "
                    f"for this map")
            if record:
                self._held[table] = int(need)


def next_pow2(n: int) -> int:
    """The least power of two >= n (1 for n <= 1)."""
    return 1 << max(int(n) - 1, 0).bit_length()


def _block_cells_bounds(blocks: np.ndarray, cells_per_block: int) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest voxel index per axis of the cells of blocks [B, 3] (B > 0)."""
    lo, hi = column_bounds(np.asarray(blocks, np.int64))
    first_lo, first_hi = (b * cells_per_block - cells_per_block // 2 for b in (lo, hi))
    return first_lo, first_hi + cells_per_block - 1


class VoxelMap:
    """One sparse voxel map on one device: a hash table of voxel keys and a float64 value row per voxel, and
    the protocol through which the integrators' launches add evidence to it (see the module's
    description). ``num_classes`` K >= 2; ``resolution_m`` the voxel edge (m); ``grid_offset_m`` the
    lattice's offset (m, 0 but for S-CSM's half-shifted grid); ``prior`` alpha0; ``device`` a Warp device
    name; ``initial_capacity`` slots (rounded up to a power of two); ``max_load`` the fill the table grows at, in [0.05, 0.75];
    ``memory_budget`` the ``TableBudget`` it shares with the map's other shards (None: one of its own,
    of the memory available). Raises ValueError for values outside those ranges, MemoryBudgetError
    for a table the budget does not hold."""

    def __init__(
        self,
        num_classes: int,
        resolution_m: float,
        *,
        prior: float = 1.0,
        grid_offset_m: float = 0.0,
        device: str | None = "cpu",
        initial_capacity: int = 1 << 16,
        max_load: float = 0.5,
        memory_budget: TableBudget | None = None,
    ):
        if num_classes < 2:
            raise ValueError(f"num_classes must be >= 2, got {num_classes}")
        if not resolution_m > 0:
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        if not 0.05 <= max_load <= LAUNCH_FILL_LIMIT:
            raise ValueError(f"max_load must lie in [0.05, {LAUNCH_FILL_LIMIT}], got {max_load}")
        self.num_classes = int(num_classes)
        self.resolution_m = float(resolution_m)
        self.grid_offset_m = float(grid_offset_m)
        self.prior = float(prior)
        self.max_load = float(max_load)
        self.device = resolve_device(device)
        self.memory_budget = memory_budget if memory_budget is not None else TableBudget()
        self.brick_capacity = 0
        self.grow_count = 0
        self._last_new_voxels: dict[str, int] = {}  # per kind of launch: how many voxels the last one made
        load_once(ht, self.device)  # every launch reads its counters back through it
        # Reused by every launch, so that a warm scan allocates nothing: the failure flags (all zero between
        # launches), the thread ids 0..n-1 (both grown to powers of two), the launch's update count, and the
        # counters read back after it (key count, update count, brick count, and the status of the scan a
        # block gather's inputs were counted in on the device) in one copy.
        self._failure_flags = None
        self._thread_ids = None
        self.update_count = wp.zeros(1, dtype=wp.int64, device=self.device)
        self._counters = wp.zeros(3 + MAX_SCAN_STATUS, dtype=wp.int64, device=self.device)
        self._no_scan_status = wp.zeros(0, dtype=int, device=self.device)
        self._scan_status = self._no_scan_status
        self.counted_status = np.zeros(0, np.int64)  # the scan status the last launch given one read back
        self._counted_updates = 0
        # What the integrators' launches on this shard keep from scan to scan (the shard's scans run one
        # after another on its thread, and a GPU runs a scan's kernels in stream order): the scans' inputs
        # reach the device through ``staging``'s buffers (pinned, on a GPU); ``scratch`` holds their work
        # arrays, ``kept`` other objects (a hash grid), by a name their integrator gives.
        self.staging = Staging(self.device)
        self.scratch = DeviceScratch(self.device)
        self.kept: dict[str, object] = {}
        self._allocate(max(MIN_CAPACITY, next_pow2(initial_capacity)))

    # ------------------------------------------------------------------ storage
    def _filled(self, shape, value, dtype, *, populate: bool = False):
        """``populate``: the memory will nearly all be written soon (see host_memory.lazily_zeroed)."""
        if self.device == "cpu":
            # Wrapping host memory (lazily zeroed pages) is ~10x faster than wp.full here.
            host = host_memory.lazily_zeroed(shape, wp.dtype_to_numpy(dtype), populate=populate or value != 0)
            if value != 0:
                host.fill(value)
            return wp.array(host, dtype=dtype, device="cpu", copy=False)
        return wp.full(shape, value, dtype=dtype, device=self.device)

    def _bytes_at(self, capacity: int, brick_capacity: int) -> int:
        """Bytes a table of ``capacity`` slots and a brick cache of ``brick_capacity`` take once filled to
        max_load: each slot's key and row (int64, int32) and the value rows (K + 5 float64) of the voxels
        it then holds; a GPU allocates a row for every slot at once."""
        rows = int(np.ceil(self.max_load * capacity)) if self.device == "cpu" else capacity
        return 12 * (capacity + brick_capacity) + 8 * (self.num_classes + EXTRA_COLUMNS) * rows

    def _admit(self, capacity: int, brick_capacity: int) -> None:
        """Refuse (MemoryBudgetError, before anything is allocated) a table the memory budget does not hold."""
        self.memory_budget.admit(self, self._bytes_at(capacity, brick_capacity), self._describe(capacity))

    def _describe(self, capacity: int) -> str:
        return f"{capacity:,} slots for up to {int(self.max_load * capacity):,} voxels of {self.num_classes + EXTRA_COLUMNS} float64 columns"

    def _allocate(self, capacity: int) -> None:
        self._admit(capacity, MIN_CAPACITY)
        self.capacity = capacity
        self.keys = self._filled(capacity, ht.EMPTY_KEY, wp.int64)
        self.slot_rows = self._filled(capacity, 0, wp.int32)
        self.key_count = wp.zeros(1, dtype=int, device=self.device)
        # The key count as last read back, None once a launch may have inserted since (``table``).
        self._known_count: int | None = 0
        self._row_store = None
        self.data = self._row_array(capacity, 0, None)
        self._allocate_brick_cache(MIN_CAPACITY)

    def _allocate_brick_cache(self, capacity: int) -> None:
        """The brick cache of the block-gather kernels: a table like the voxel table, keyed by a block's first
        cell, holding its first row, for blocks whose cells have consecutive rows. Blocks of the gather
        kernels are inserted whole, so on the CPU nearly all are cached: a block is then found with one probe
        in a table about cells-per-block times smaller (fits the CPU's caches where the voxel table does not)
        instead of one probe per cell (docs/performance.md, "How the engine gets there"). Rows never move
        while the map lives, so an entry stays true; the cache is dropped with the rows (``_allocate``). On a
        GPU concurrent inserters interleave rows, so few blocks are cached there and most are found cell by
        cell."""
        self.brick_capacity = capacity
        self.brick_keys = self._filled(capacity, ht.EMPTY_KEY, wp.int64)
        self.brick_rows = self._filled(capacity, 0, wp.int32)
        self.brick_count = wp.zeros(1, dtype=int, device=self.device)
        # The brick cache's key count as last read back (``_read_counters``): only the block gathers insert
        # into it, and each reads its counters after its launch, so the count is known before the next.
        self._known_bricks = 0

    def _grow_brick_cache(self, new_blocks: int = 0) -> None:
        """Rehash the brick cache into a larger table: before a launch, until ``new_blocks`` more fit
        under LAUNCH_FILL_LIMIT (where the kernels stop caching; a block not cached is found by its
        cells), after one until it is at or below max_load."""
        count = self._known_bricks
        capacity = self.brick_capacity
        while count + new_blocks > (LAUNCH_FILL_LIMIT if new_blocks else self.max_load) * capacity:
            capacity *= 2
        if capacity == self.brick_capacity:
            return
        self._admit(self.capacity, capacity)
        self.brick_capacity = capacity
        self.brick_keys, self.brick_rows = self._rehashed(self.brick_keys, self.brick_rows, capacity)

    def _rehashed(self, old_keys, old_slot_rows, capacity: int):
        """(keys, slot rows) of a table of ``capacity`` slots holding the old table's keys and rows."""
        keys = self._filled(capacity, ht.EMPTY_KEY, wp.int64)
        # A grown table is at least a quarter full once what it was grown for is in: its slot rows are
        # written all over, so they are mapped at once (see host_memory.lazily_zeroed).
        slot_rows = self._filled(capacity, 0, wp.int32, populate=True)
        wp.launch(ht.rehash, dim=len(old_keys), inputs=[old_keys, old_slot_rows, keys, slot_rows], device=self.device)
        return keys, slot_rows

    def _row_array(self, capacity: int, used_rows: int, old):
        """A zeroed [capacity, K + 5] row array holding the first ``used_rows`` rows of ``old``: on the CPU
        a view of the table's row reservation (host_memory.ROW_RESERVATION_BYTES), which a grown table reuses in place."""
        columns = self.num_classes + EXTRA_COLUMNS
        if self.device != "cpu":
            rows = wp.zeros((capacity, columns), dtype=wp.float64, device=self.device)
            if used_rows:
                wp.copy(rows, old, count=used_rows * columns)
            return rows
        store = self._row_store
        if store is None or len(store) < capacity or (old is not None and old.ptr != store.ctypes.data):
            store = host_memory.reserved_zeros(max(capacity, host_memory.ROW_RESERVATION_BYTES // (8 * columns)), columns)
            if store is None:
                store = host_memory.lazily_zeroed((capacity, columns), np.float64)
            if used_rows:
                store[:used_rows] = old.numpy()[:used_rows]
            self._row_store = store
        return wp.array(store[:capacity], dtype=wp.float64, device="cpu", copy=False)

    @property
    def voxel_count(self) -> int:
        """Number of voxels stored (a device-to-host read, unless no launch could have inserted since the
        count was last read)."""
        if self._known_count is None:
            self._known_count = int(self.key_count.numpy()[0])
        return self._known_count

    def table(self) -> ht.HashTable:
        """The voxel table as kernels take it, with this launch's fill limit (make one per launch: the
        table's arrays change when it grows). A launch given it may insert, so the key count the host
        knows is dropped."""
        self._known_count = None
        return ht.hash_table(self.keys, self.slot_rows, self.key_count, self._launch_fill_limit())

    def brick_table(self) -> ht.HashTable:
        """The brick cache as kernels take it (``_allocate_brick_cache``), with this launch's fill limit."""
        return ht.hash_table(self.brick_keys, self.brick_rows, self.brick_count, self._launch_fill_limit(self.brick_capacity))

    def target(self, failed) -> sc.MapTarget:
        """Where a launch writes (``kernels.scatter.MapTarget``): the voxel table, the rows, its failure
        flags ``failed`` and the update count."""
        return sc.map_target(self.table(), self.data, failed, self.update_count)

    @property
    def table_bytes(self) -> int:
        """Bytes the table holds: per slot of the voxel table and of the brick cache its key and row (int64, int32), per row K + 5 float64 columns.
        The row array has a row for every slot (each voxel holds a slot), but on the CPU its pages are
        mapped only as rows are used, so there the rows of the stored voxels count; a GPU allocates all."""
        rows = self.voxel_count if self.device == "cpu" else self.capacity
        return 12 * (self.capacity + self.brick_capacity) + 8 * (self.num_classes + EXTRA_COLUMNS) * rows

    def _launch_fill_limit(self, capacity: int | None = None) -> int:
        """Keys a launch may fill the voxel table (or a table of ``capacity`` slots) up to."""
        return max(1, int((self.capacity if capacity is None else capacity) * LAUNCH_FILL_LIMIT))

    def _capacity_for(self, new_voxels: int) -> int:
        """The slots ``reserve(new_voxels)`` grows the table to."""
        needed = self.voxel_count + int(new_voxels)
        capacity = self.capacity
        while needed > self.max_load * capacity:
            capacity *= 2
        return capacity

    def reserve(self, new_voxels: int) -> None:
        """Grow until ``new_voxels`` more keys fit under max_load."""
        capacity = self._capacity_for(new_voxels)
        if capacity != self.capacity:
            self.grow(capacity)

    def check_room(self, new_voxels: int) -> None:
        """Raise MemoryBudgetError where ``reserve(new_voxels)`` would grow the table past its memory
        budget; allocates nothing."""
        capacity = self._capacity_for(new_voxels)
        if capacity != self.capacity:
            self.memory_budget.admit(self, self._bytes_at(capacity, self.brick_capacity), self._describe(capacity), record=False)

    def grow(self, new_capacity: int) -> None:
        """Rehash into a table of ``new_capacity`` slots (a power of two); voxels keep their rows."""
        new_capacity = next_pow2(new_capacity)
        count = self.voxel_count
        if new_capacity < count / LAUNCH_FILL_LIMIT:
            raise ValueError(f"cannot shrink the table to {new_capacity} slots: it holds {count} voxels")
        self._admit(new_capacity, self.brick_capacity)
        old_data = self.data
        self.capacity = new_capacity
        self.keys, self.slot_rows = self._rehashed(self.keys, self.slot_rows, new_capacity)
        self.data = self._row_array(new_capacity, count, old_data)
        self.grow_count += 1

    # ------------------------------------------------------------------ launches
    def _check_index_range(self, lo_index: np.ndarray, hi_index: np.ndarray) -> None:
        """Refuse a launch whose points would reach voxels outside the key range (before any write)."""
        check_index_range(np.array([np.min(lo_index), np.max(hi_index)]), "the points' kernels", self.resolution_m)

    def check_block_range(self, blocks: np.ndarray, cells_per_block: int) -> None:
        """Refuse blocks [B, 3] (block b holds voxels b n - n/2 ... b n + n/2 - 1) whose cells lie outside the key range."""
        if len(blocks) == 0:
            return
        self._check_index_range(*_block_cells_bounds(blocks, cells_per_block))

    @staticmethod
    def block_range_holds(blocks: np.ndarray, cells_per_block: int) -> bool:
        """Whether every cell of blocks [B, 3] (or of the box their bounds span) lies in the key range."""
        return not len(blocks) or within_index_range(np.stack(_block_cells_bounds(blocks, cells_per_block)))

    def check_reach(self, points: np.ndarray, reach: float) -> None:
        """Refuse points whose kernels, reaching ``reach`` metres, would touch voxels outside the key range."""
        lo, hi = column_bounds(points)
        self._check_index_range(np.floor((lo - reach - self.grid_offset_m) / self.resolution_m),
                                np.floor((hi + reach - self.grid_offset_m) / self.resolution_m))

    def _failure_flags_for(self, n: int):
        """n failure flags, all zero (a view of the reused buffer)."""
        if self._failure_flags is None or len(self._failure_flags) < n:
            self._failure_flags = wp.zeros(next_pow2(n), dtype=int, device=self.device)
        return self._failure_flags[:n]

    def thread_ids(self, n: int):
        """The ids 0..n-1 (a view of the reused buffer)."""
        if self._thread_ids is None or len(self._thread_ids) < n:
            self._thread_ids = wp.array(np.arange(next_pow2(n), dtype=np.int32), dtype=int, device=self.device)
        return self._thread_ids[:n]

    def _read_counters(self) -> int:
        """The key count, the last launches' update count and the brick cache's key count (and the scan
        status a launch was given), read back in one copy; returns the key count."""
        wp.launch(ht.read_counters, dim=1, inputs=[self.key_count, self.update_count, self.brick_count, self._scan_status, self._counters],
                  device=self.device)
        counters = self._counters.numpy()
        key_count, self._counted_updates, self._known_bricks = (int(value) for value in counters[:3])
        self.counted_status = counters[3:3 + self._scan_status.shape[0]].copy()
        self._known_count = key_count
        return key_count

    def launch_until_done(self, n: int, launch, *, may_insert: bool, kind: str, most_new: int, exact_most: bool = False,
                          fails_only_when_full: bool = False, resumes: bool = False, brick_cells: int = 0,
                          scan_status: wp.array | None = None) -> int:
        """launch(ids, failed) over range(n), relaunching the failed ids after the table grew; returns the
        updates the launches counted in ``update_count`` (zeroed first).

        The table is first grown for as many new voxels as the previous launch of this kind made, at
        most ``most_new``; for the first launch of a kind, for none, or for ``most_new`` when that is
        the launch's own bound (``exact_most``: whole blocks, every cell new in a map's first scan,
        where growing step by step relaunched most blocks three times) or the map is on a GPU (whose
        threads insert at once: a table far too small is overfilled before they see its limit). A wrong
        guess costs a relaunch of the items that did not fit, never a voxel.

        ``fails_only_when_full``: the launch's items fail only where an insertion found the table at the
        launch's fill limit (the inserting scatters, the block gathers), and the key count never drops, so
        a launch that leaves it below that limit failed nowhere: its flags are not read, and a warm scan
        reads its launch's outcome back once (``_read_counters``).

        ``resumes``: a relaunched item is handed its flag as the failed launch left it (the scatter's flag
        says where its point stopped), else a zero flag.

        ``brick_cells``: the items are whole blocks of that many cells a side, cached in the brick cache
        (the block gathers): it grows for them before the launch and back under max_load after.
        ``scan_status``: an int array on the device (at most MAX_SCAN_STATUS values) read back with the
        launch's counters, into ``counted_status``."""
        if scan_status is not None and scan_status.shape[0] > MAX_SCAN_STATUS:
            raise ValueError(f"a scan status of {scan_status.shape[0]} values; at most {MAX_SCAN_STATUS} are read back")
        if brick_cells:
            self._grow_brick_cache(n if exact_most else self._last_new_voxels.get(kind, 0) // brick_cells**3)
        self._scan_status = self._no_scan_status if scan_status is None else scan_status
        try:
            self._launch_and_relaunch(n, launch, may_insert=may_insert, kind=kind, most_new=most_new, exact_most=exact_most,
                                      fails_only_when_full=fails_only_when_full, resumes=resumes)
        finally:
            self._scan_status = self._no_scan_status
        if brick_cells:
            self._grow_brick_cache()
        return self._counted_updates

    def _launch_and_relaunch(self, n: int, launch, *, may_insert: bool, kind: str, most_new: int, exact_most: bool,
                             fails_only_when_full: bool, resumes: bool) -> None:
        """``launch_until_done``'s launches, the updates then in ``_counted_updates``."""
        first_guess = most_new if exact_most or self.device != "cpu" else 0
        self.reserve(min(most_new, self._last_new_voxels.get(kind, first_guess)) if may_insert else 0)
        before = self.voxel_count
        self.update_count.zero_()
        pending = None  # None: every item, in order
        resume_flags = None
        try:
            while True:
                count = n if pending is None else len(pending)
                failed = self._failure_flags_for(count)
                if resume_flags is not None:
                    wp.copy(failed, wp.array(resume_flags, dtype=int, device=self.device))
                limit = self._launch_fill_limit()
                launch(self.thread_ids(n) if pending is None else wp.array(pending, dtype=int, device=self.device, copy=False), failed)
                if fails_only_when_full and self._read_counters() < limit:
                    break
                flags = failed.numpy()
                flagged = flags != 0
                retry = np.flatnonzero(flagged).astype(np.int32) if pending is None else pending[flagged]
                if not len(retry):
                    break
                resume_flags = flags[flagged] if resumes else None
                failed.zero_()
                if not may_insert:
                    raise RuntimeError(f"{len(retry)} items reached voxels that were never inserted (a bug)")
                self.grow(self.capacity * 2)
                pending = retry
        except BaseException:
            self._failure_flags = None  # flags a failed launch may have set are never read as a later launch's
            raise
        if not fails_only_when_full:
            self._read_counters()
        self._last_new_voxels[kind] = self.voxel_count - before
        self.reserve(0)

    def launch_reserved(self, n: int, launch, what: str) -> int:
        """launch(failed) over n items after the table was reserved for every voxel they may insert, then
        its counters read back once; returns the updates counted in ``update_count``. Its failure flags
        are read only when the key count reached the launch's fill limit, the one case where an insertion
        can fail (one that did is a bug)."""
        limit = self._launch_fill_limit()
        failed = self._failure_flags_for(n)
        self.update_count.zero_()
        launch(failed)
        if self._read_counters() >= limit and failed.numpy().any():
            self._failure_flags = None  # its flags are never read as a later launch's
            raise RuntimeError(f"{what} ran out of table room after reserving it (a bug)")
        self.reserve(0)
        return self._counted_updates

    def insert_voxels(self, voxel_index: np.ndarray) -> np.ndarray:
        """Insert voxel indices [V, 3]; returns their rows (growing as needed)."""
        keys = wp.array(pack_voxel_keys(voxel_index), dtype=wp.int64, device=self.device, copy=False)
        self.reserve(len(voxel_index))
        while True:
            rows = wp.empty(len(voxel_index), dtype=int, device=self.device)
            wp.launch(ht.insert_keys, dim=len(voxel_index), inputs=[keys, self.table(), rows], device=self.device)
            rows_np = rows.numpy()
            if (rows_np >= 0).all():
                return rows_np
            self.grow(self.capacity * 2)

    def lookup_points(self, points: np.ndarray) -> np.ndarray:
        """Row of the voxel containing each point [M, 3], -1 where that voxel is not stored."""
        if len(points) == 0:
            return np.zeros(0, dtype=np.int64)
        rows = wp.empty(len(points), dtype=int, device=self.device)
        wp.launch(ht.lookup_points, dim=len(points), device=self.device,
                  inputs=[_points_array(points, self.device), wp.float64(self.resolution_m), wp.float64(self.grid_offset_m), self.table(), rows])
        return rows.numpy().astype(np.int64)

    # ------------------------------------------------------------------ host views
    def stored_keys_and_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """The stored keys in ascending order and their rows."""
        keys = self.keys.numpy()
        slots = np.flatnonzero(keys != ht.EMPTY_KEY)
        slots = slots[np.argsort(keys[slots], kind="stable")]
        return keys[slots], self.slot_rows.numpy()[slots].astype(np.int64) - 1

    def stored_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """The stored keys in ascending order and a host copy of their [V, K + 5] value rows."""
        keys, rows = self.stored_keys_and_rows()
        return keys, take_rows(self.data.numpy(), rows)

    def arrays(self) -> VoxelArrays:
        """A host copy of every stored voxel (``VoxelArrays``), in ascending key order; indices relative to
        the map origin."""
        keys, rows = self.stored_rows()
        return VoxelArrays.from_rows(unpack_voxel_keys(keys), rows)

    def rows_at(self, rows: np.ndarray) -> np.ndarray:
        """The [len(rows), K + 5] data rows at the given row indices (zeros for -1); copies only those
        rows to the host."""
        rows = np.asarray(rows, dtype=np.int64)
        out = np.zeros((len(rows), self.num_classes + EXTRA_COLUMNS))
        hit = np.flatnonzero(rows >= 0)
        if len(hit):
            if self.device == "cpu":
                out[hit] = self.data.numpy()[rows[hit]]
            else:
                picked = wp.empty((len(hit), out.shape[1]), dtype=wp.float64, device=self.device)
                wp.launch(ht.gather_rows, dim=len(hit), device=self.device,
                          inputs=[self.data, wp.array(rows[hit].astype(np.int32), dtype=int, device=self.device, copy=False), picked])
                out[hit] = picked.numpy()
        return out

    def load_arrays(self, voxels: VoxelArrays) -> None:
        """Replace the contents with ``voxels`` (exactly: the values are copied, not re-added)."""
        self._allocate(max(MIN_CAPACITY, next_pow2(int(len(voxels.index) / self.max_load) + 1)))
        rows = self.insert_voxels(voxels.index) if len(voxels.index) else np.zeros(0, np.int64)
        if self.device == "cpu":
            self.data.numpy()[rows] = voxels.rows()  # a view of the host rows
        else:
            data = np.zeros((self.capacity, self.num_classes + EXTRA_COLUMNS))
            data[rows] = voxels.rows()
            self.data = wp.array(data, dtype=wp.float64, device=self.device, copy=False)


def _points_array(points: np.ndarray, device: str):
    return wp.array(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), dtype=wp.vec3d, device=device, copy=False)


def sum_shard_rows(parts: list[tuple[np.ndarray, np.ndarray]]) -> VoxelArrays:
    """Union of a map's shards given as ``VoxelMap.stored_rows`` (keys relative to one origin and value
    rows), adding evidence, weights and hits and or-ing touched (``add_duplicate_voxels``). BKI updates
    are sums, so this is exact up to float64 summation order."""
    if len(parts) == 1:
        keys, rows = parts[0]
        return VoxelArrays.from_rows(unpack_voxel_keys(keys), rows)
    return _add_duplicate_keys(np.concatenate([keys for keys, _ in parts]), np.concatenate([rows for _, rows in parts]))


def add_duplicate_voxels(index: np.ndarray, rows: np.ndarray) -> VoxelArrays:
    """One row per distinct voxel of ``index`` [N, 3] (relative to the origin), in key order: the
    [N, K + 5] data rows of repeated voxels are added, their touched flags or-ed."""
    return _add_duplicate_keys(pack_voxel_keys(np.asarray(index, np.int64).reshape(-1, 3)), rows)


def _add_duplicate_keys(keys: np.ndarray, rows: np.ndarray) -> VoxelArrays:
    """``add_duplicate_voxels`` of packed keys [N]. A voxel's rows add left to right in input order from
    zero, as np.add.at into zeros adds them (the bits the store's ``fold`` gives): a stable sort keeps
    that order, each run's first row plus 0.0 starts its sum (0 + x: a -0.0 becomes 0.0), and the k-th
    rows of all runs are added in step k, one step per row of the longest run (a voxel's shards or
    partials; np.add.reduceat does not add left to right). np.unique and np.add.at took most of a
    two-shard map's read-out."""
    rows = np.asarray(rows, np.float64)
    if len(keys) == 0:
        return VoxelArrays.from_rows(np.zeros((0, 3), np.int64), np.zeros((0, rows.shape[1])))
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    summed = take_rows(rows, order[starts])
    summed += 0.0
    if len(starts) < len(keys):
        lengths = np.diff(np.r_[starts, len(keys)])
        run = np.repeat(np.arange(len(starts)), lengths)
        place = np.arange(len(keys)) - starts[run]
        for k in range(1, int(lengths.max())):
            kth = np.flatnonzero(place == k)
            summed[run[kth]] += take_rows(rows, order[kth])
    summed[:, -1] = np.minimum(summed[:, -1], 1.0)  # touched is or-ed, not added
    return VoxelArrays.from_rows(unpack_voxel_keys(sorted_keys[starts]), summed)
