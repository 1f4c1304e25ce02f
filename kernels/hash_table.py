"""Open-addressing hash table of voxel indices, with each voxel's value row in insertion order (Warp).

Keys are int3 voxel indices relative to the map origin, packed into one int64 (21 bits per axis,
offset 2**20; ``evsemmap_warp/voxel_keys.py`` packs the same way on the host), slots are found
by a splitmix64 hash of their 2x2x2 brick and linear probing, insertion claims a slot with ``atomic_cas``.
Beside each slot the table keeps its voxel's row (``slot_rows``, row + 1; 0 while the slot is empty):
rows are handed out densely in insertion order (row = the key count before the insertion), so callers
keep per-voxel values in ``[rows, ...]`` arrays that keep their rows when the table grows, and a grown
table rehashes keys and row numbers only (values indexed by slot would have to move row by row at
every growth, and take twice the memory). An insertion
fails (returns -1) instead of overfilling the table once ``max_count`` keys are in; the host then grows
the table and re-runs the failed work, so nothing is ever dropped. The block-gather kernels keep a
second table of the same layout, the brick cache (a block's first cell -> its first row,
``table_insert_row``; ``VoxelMap._allocate_brick_cache`` says why).

Kernels see a table as one ``HashTable`` struct (keys, slot rows, key count and the fill limit of the
launch); ``hash_table(...)`` makes one on the host. The voxel table, the brick cache and the scan-local
key set of ``kernels.hashgrid_gather`` are all of this one type.

numpy twin: ``evsemmap_warp/reference/hash_table.py``.
"""

from typing import Any

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
EMPTY_KEY = -1
# Voxel indices must satisfy -KEY_OFFSET <= i < KEY_OFFSET on every axis.
INDEX_LIMIT = KEY_OFFSET

_KEY_OFFSET = wp.constant(KEY_OFFSET)
_FIELD_MASK = wp.constant(wp.int64((1 << KEY_BITS) - 1))
_EMPTY = wp.constant(wp.int64(EMPTY_KEY))
# Adding 1 to every 21-bit field puts a brick's cells {2b - 1, 2b} at fields {2c, 2c + 1}: shifted
# right by one the fields give the brick, their low bits the cell in it. (The largest index's field
# carries into its neighbour: that changes its hash only.)
_BRICK_ROUND = wp.constant(wp.int64((1 << 42) | (1 << 21) | 1))
_BRICK_LOW_BITS = wp.constant(wp.int64((1 << 42) | (1 << 21) | 1))
_BRICK_MASK = wp.constant(wp.int64((((1 << 20) - 1) << 42) | (((1 << 20) - 1) << 21) | ((1 << 20) - 1)))


@wp.struct
class HashTable:
    """A table as kernels see it: ``keys`` [capacity] (EMPTY_KEY where free), ``slot_rows`` [capacity]
    (row + 1 of the slot's key, 0 while free), ``key_count`` [1] and ``max_count``, the keys an
    insertion may fill the table up to in this launch."""

    keys: wp.array(dtype=wp.int64)
    slot_rows: wp.array(dtype=int)
    key_count: wp.array(dtype=int)
    max_count: int


def hash_table(keys, slot_rows, key_count, max_count: int) -> HashTable:
    """The ``HashTable`` struct over a table's device arrays (host side, no copy)."""
    table = HashTable()
    table.keys = keys
    table.slot_rows = slot_rows
    table.key_count = key_count
    table.max_count = int(max_count)
    return table


@wp.func
def pack_key(ix: int, iy: int, iz: int) -> wp.int64:
    """One int64 key of voxel index (ix, iy, iz), each -2^20 <= i < 2^20 (relative to the map origin): 21
    bits per axis, offset by 2^20 (``voxel_keys.pack_voxel_keys`` on the host)."""
    return (
        (wp.int64(ix + _KEY_OFFSET) << wp.int64(42))
        | (wp.int64(iy + _KEY_OFFSET) << wp.int64(21))
        | wp.int64(iz + _KEY_OFFSET)
    )


@wp.func
def unpack_key(key: wp.int64) -> wp.vec3i:
    """The voxel index (ix, iy, iz) a ``pack_key`` key holds."""
    return wp.vec3i(
        int((key >> wp.int64(42)) & _FIELD_MASK) - _KEY_OFFSET,
        int((key >> wp.int64(21)) & _FIELD_MASK) - _KEY_OFFSET,
        int(key & _FIELD_MASK) - _KEY_OFFSET,
    )


@wp.func
def hash_slot(key: wp.int64, mask: int) -> int:
    """Home slot of ``key`` in a table of ``mask + 1`` slots (a power of two): the eight cells of a 2x2x2
    brick get neighbouring slots, bricks are spread by the splitmix64 finaliser."""
    # The 2x2x2 brick of cells {2b - 1, 2b} per axis (an S-BKI / release block, at block depth 2)
    # hashes to 8 neighbouring home slots: a block's cells share cache lines and pages of the table
    # and its value rows. The brick's key goes through the splitmix64 finaliser, so neighbouring
    # bricks land far apart and probe runs stay short.
    rounded = key + _BRICK_ROUND
    brick = (rounded >> wp.int64(1)) & _BRICK_MASK
    cell = rounded & _BRICK_LOW_BITS
    h = wp.uint64(brick)
    h = (h ^ (h >> wp.uint64(30))) * wp.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> wp.uint64(27))) * wp.uint64(0x94D049BB133111EB)
    h = h ^ (h >> wp.uint64(31))
    local = wp.uint64(((cell >> wp.int64(40)) & wp.int64(4)) | ((cell >> wp.int64(20)) & wp.int64(2)) | (cell & wp.int64(1)))
    return int(((h << wp.uint64(3)) | local) & wp.uint64(mask))


# How many threads ahead a brick is prefetched (``prefetch_brick``; 4 to 64 measured alike on CPU).
PREFETCH_AHEAD = wp.constant(16)
# ... and how many threads ahead its rows are, once its brick-cache line has arrived.
PREFETCH_NEARER = wp.constant(8)


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
__builtin_prefetch(&keys.data[slot]);
__builtin_prefetch(&slot_rows.data[slot]);
#endif
""")
def _prefetch_slot(keys: wp.array(dtype=wp.int64), slot_rows: wp.array(dtype=int), slot: int): ...


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
// The first row of the brick whose first cell's key is ``key``, from the brick cache's line at its home
// slot (the entry, if cached, is almost always in that line). A prefetch of a wrong or past-the-end
// address is harmless (it never faults).
const int64_t mask = brick_keys.shape[0] - 1;
for (int64_t probe = 0; probe < 8; ++probe) {
    const int64_t at = (slot + probe) & mask;
    if (brick_keys.data[at] != key) continue;
    const int stored = brick_rows.data[at];
    if (stored > 0) {
        const char* row = (const char*)data.data + (size_t)(stored - 1) * data.strides[0];
        const int bytes = rows * data.strides[0];
        for (int offset = 0; offset < bytes; offset += 64) __builtin_prefetch(row + offset, 1);
    }
    break;
}
#endif
""")
def _prefetch_brick_rows(brick_keys: wp.array(dtype=wp.int64), brick_rows: wp.array(dtype=int), data: wp.array2d(dtype=wp.float64),
                         slot: int, key: wp.int64, rows: int): ...


@wp.func
def prefetch_brick(table: HashTable, bricks: HashTable, data: wp.array2d(dtype=wp.float64), first_cell_ahead: wp.vec3i,
                   first_cell_nearer: wp.vec3i, cells: int):
    """Ask the CPU to start loading a brick's lines of the brick cache and of the table (its cells' slots,
    for a brick not cached yet), and the value rows of a nearer brick whose cache line was asked for
    earlier (bricks given by their first cell, lowest index per axis, at their home slots). A hint only,
    compiled out on CUDA.

    A serial CPU launch walks its threads in order, and a thread that waits for its brick's cache lines
    waits alone: the core's reorder window holds about one block's work. Kernels that visit one brick per
    thread call this with the bricks PREFETCH_AHEAD and PREFETCH_NEARER threads ahead: the rows' place is
    read from a cache line that has arrived by then (tools/kernel_study.py times the gather kernels with
    and without it)."""
    ahead = pack_key(first_cell_ahead[0], first_cell_ahead[1], first_cell_ahead[2])
    _prefetch_slot(bricks.keys, bricks.slot_rows, hash_slot(ahead, bricks.keys.shape[0] - 1))
    _prefetch_slot(table.keys, table.slot_rows, hash_slot(ahead, table.keys.shape[0] - 1))
    nearer = pack_key(first_cell_nearer[0], first_cell_nearer[1], first_cell_nearer[2])
    _prefetch_brick_rows(bricks.keys, bricks.slot_rows, data, hash_slot(nearer, bricks.keys.shape[0] - 1), nearer, cells)


@wp.func
def slot_row(slot_rows: wp.array(dtype=int), slot: int) -> int:
    """The row of an occupied slot (-1 for slot -1). On a GPU a key can be seen before its inserter has
    published the row: that reader waits for it (an atomic read, so the load is not hoisted), which needs
    a GPU that schedules a warp's threads independently (compute capability 7.0 or newer,
    ``core.warp_runtime.resolve_device``)."""
    if slot < 0:
        return -1
    stored = slot_rows[slot]
    while stored == 0:
        stored = wp.atomic_add(slot_rows, slot, 0)
    return stored - 1


@wp.func
def table_find_slot(keys: wp.array(dtype=wp.int64), key: wp.int64) -> int:
    """Slot holding ``key``, or -1 when it is absent (the empty sentinel is never a stored key)."""
    if key == _EMPTY:
        return -1
    mask = keys.shape[0] - 1
    slot = hash_slot(key, mask)
    for _probe in range(keys.shape[0]):
        k = keys[slot]
        if k == key:
            return slot
        if k == _EMPTY:
            return -1
        slot = (slot + 1) & mask
    return -1


@wp.func
def table_find(table: HashTable, key: wp.int64) -> int:
    """Row of ``key``, or -1 when it is absent."""
    return slot_row(table.slot_rows, table_find_slot(table.keys, key))


@wp.func
def _find_or_insert(table: HashTable, key: wp.int64, given_row: int) -> int:
    """Row of ``key``, inserting it if absent, with ``given_row`` or, for -1, the key count before it;
    -1 when the table is at ``max_count`` keys."""
    keys = table.keys
    mask = keys.shape[0] - 1
    slot = hash_slot(key, mask)
    for _probe in range(keys.shape[0]):
        k = keys[slot]
        if k == key:
            return slot_row(table.slot_rows, slot)
        if k == _EMPTY:
            # Read through the atomic unit: a GPU's plain load may see a count its SM cached, and thousands
            # of threads would then insert past the fill limit together (on the CPU a plain read-and-write).
            if wp.atomic_add(table.key_count, 0, 0) >= table.max_count:
                return -1
            old = wp.atomic_cas(keys, slot, _EMPTY, key)
            if old == _EMPTY:
                # Every key holds a slot, so rows never pass the capacity, even when concurrent GPU
                # inserters overshoot max_count.
                row = wp.atomic_add(table.key_count, 0, 1)
                if given_row >= 0:
                    row = given_row
                table.slot_rows[slot] = row + 1
                return row
            if old == key:
                return slot_row(table.slot_rows, slot)
        slot = (slot + 1) & mask
    return -1


@wp.func
def table_find_or_insert(table: HashTable, key: wp.int64) -> int:
    """Row of ``key``, inserting it if absent (its row: the key count before it); -1 when the table is
    at ``max_count`` keys (or for the empty sentinel, which no in-range index packs to)."""
    if key == _EMPTY:
        return -1
    return _find_or_insert(table, key, -1)


@wp.func
def table_insert_row(table: HashTable, key: wp.int64, row: int):
    """Store ``key`` with a row it was given (the brick cache: a brick's first row, found in the voxel
    table); nothing when the key is there already or the table holds ``max_count`` keys."""
    _find_or_insert(table, key, row)


@wp.func
def block_cell(first: wp.vec3i, j: int, n: int) -> wp.vec3i:
    """Cell j of the block of n^3 cells whose first (lowest) cell is ``first``: x slowest, z fastest,
    the order every block kernel visits, inserts and sums a block's cells in."""
    return wp.vec3i(first[0] + j // (n * n), first[1] + (j // n) % n, first[2] + j % n)


@wp.func
def block_first_cell(block: wp.vec3i, n: int) -> wp.vec3i:
    """The first cell of block ``block`` (block b holds voxels b n - n/2 ... b n + n/2 - 1 per axis)."""
    return block * n - wp.vec3i(n / 2, n / 2, n / 2)


@wp.func
def find_block_rows(rows: Any, table: HashTable, bricks: HashTable, first: wp.vec3i, n: int):
    """The rows of a block's n^3 cells (``rows``, a vector of as many ints; cells in ``block_cell``
    order from its first cell ``first``), found or inserted; rows[0] = -1 when a cell did not fit. A
    block in the brick cache (``bricks``: first cell -> first row) has consecutive rows from its first;
    a block whose found or inserted rows are consecutive is cached, unless the cache holds its
    ``max_count`` blocks (``VoxelMap._allocate_brick_cache`` says why)."""
    brick_key = pack_key(first[0], first[1], first[2])
    first_row = table_find(bricks, brick_key)
    if first_row >= 0:
        for j in range(len(rows)):
            rows[j] = first_row + j
        return rows
    consecutive = int(1)
    for j in range(len(rows)):
        cell = block_cell(first, j, n)
        row = table_find_or_insert(table, pack_key(cell[0], cell[1], cell[2]))
        if row < 0:
            rows[0] = -1
            return rows
        rows[j] = row
        consecutive = consecutive & wp.where(row == rows[0] + j, 1, 0)
    if consecutive != 0:
        table_insert_row(bricks, brick_key, rows[0])
    return rows


@wp.kernel
def insert_keys(keys_in: wp.array(dtype=wp.int64), table: HashTable, rows_out: wp.array(dtype=int)):
    """Kernel, one thread per key: rows_out[i] = the row of keys_in[i], inserting it if absent
    (``table_find_or_insert``; -1 when the table is at its fill limit)."""
    i = wp.tid()
    rows_out[i] = table_find_or_insert(table, keys_in[i])


@wp.kernel
def lookup_keys(keys_in: wp.array(dtype=wp.int64), table: HashTable, rows_out: wp.array(dtype=int)):
    """Kernel, one thread per key: rows_out[i] = the row of keys_in[i], or -1 when it is absent
    (``table_find``)."""
    i = wp.tid()
    rows_out[i] = table_find(table, keys_in[i])


@wp.func
def voxel_index_of(x: wp.float64, resolution: wp.float64) -> int:
    """floor(x / resolution) as an int, or INDEX_LIMIT (outside the key range) when it does not fit."""
    f = wp.floor(x / resolution)
    index = int(_KEY_OFFSET)
    if f >= wp.float64(-_KEY_OFFSET) and f < wp.float64(_KEY_OFFSET):
        index = int(f)
    return index


@wp.kernel
def lookup_points(
    points: wp.array(dtype=wp.vec3d),
    resolution: wp.float64,
    grid_offset: wp.float64,
    table: HashTable,
    rows_out: wp.array(dtype=int),
):
    """Row of the voxel containing each point (voxel i spans [i r + o, (i + 1) r + o), coordinates
    relative to the map origin); -1 for points outside the key range or in voxels not stored."""
    i = wp.tid()
    p = points[i]
    ix = voxel_index_of(p[0] - grid_offset, resolution)
    iy = voxel_index_of(p[1] - grid_offset, resolution)
    iz = voxel_index_of(p[2] - grid_offset, resolution)
    if ix == _KEY_OFFSET or iy == _KEY_OFFSET or iz == _KEY_OFFSET:
        rows_out[i] = -1
    else:
        rows_out[i] = table_find(table, pack_key(ix, iy, iz))


@wp.kernel
def rehash(
    old_keys: wp.array(dtype=wp.int64),
    old_slot_rows: wp.array(dtype=int),
    new_keys: wp.array(dtype=wp.int64),
    new_slot_rows: wp.array(dtype=int),
):
    """Insert every key of the old table into the new one, with its row (rows stay where they are)."""
    i = wp.tid()
    key = old_keys[i]
    if key != _EMPTY:
        mask = new_keys.shape[0] - 1
        slot = hash_slot(key, mask)
        for _probe in range(new_keys.shape[0]):
            if wp.atomic_cas(new_keys, slot, _EMPTY, key) == _EMPTY:
                new_slot_rows[slot] = old_slot_rows[i]
                return
            slot = (slot + 1) & mask


@wp.kernel
def read_counters(key_count: wp.array(dtype=int), update_count: wp.array(dtype=wp.int64), brick_count: wp.array(dtype=int),
                  scan_status: wp.array(dtype=int), out: wp.array(dtype=wp.int64)):
    """Kernel, one thread: out = (a table's key count, a launch's update count, its brick cache's key
    count, then the values of ``scan_status``, what the scan's preprocessing counted on the device), so
    that the host reads a launch's outcome back in one copy."""
    out[0] = wp.int64(key_count[0])
    out[1] = update_count[0]
    out[2] = wp.int64(brick_count[0])
    for i in range(scan_status.shape[0]):
        out[3 + i] = wp.int64(scan_status[i])


@wp.kernel
def gather_rows(src: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=int), dst: wp.array2d(dtype=wp.float64)):
    """dst[i, :] = src[rows[i], :]: the rows a query needs, without copying the whole table to the host."""
    i = wp.tid()
    for c in range(src.shape[1]):
        dst[i, c] = src[rows[i], c]
