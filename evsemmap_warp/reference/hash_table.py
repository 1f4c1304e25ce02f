"""numpy twin of ``evsemmap_warp.kernels.hash_table``: the same packing, hash and linear probing,
run serially in Python so that the CPU kernel's slot and row assignment can be checked exactly. A table
is its keys and ``slot_rows`` (row + 1 per slot, 0 while empty); rows are handed out in insertion order."""

from __future__ import annotations

import numpy as np

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
EMPTY_KEY = -1
_M64 = (1 << 64) - 1


def pack_key(index: np.ndarray) -> np.ndarray:
    """[..., 3] int voxel indices -> [...] int64 keys."""
    index = np.asarray(index, dtype=np.int64) + KEY_OFFSET
    return (index[..., 0] << 42) | (index[..., 1] << 21) | index[..., 2]


def unpack_key(keys: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.hash_table.unpack_key``: the voxel indices [..., 3] that packed int64 keys hold."""
    keys = np.asarray(keys, dtype=np.int64)
    field = (1 << KEY_BITS) - 1
    return np.stack([(keys >> 42) & field, (keys >> 21) & field, keys & field], axis=-1) - KEY_OFFSET


def hash_slot(key: int, mask: int) -> int:
    """Twin of ``kernels.hash_table.hash_slot``: the home slot of ``key`` in a table of ``mask + 1`` slots."""
    rounded = int(key) + ((1 << 42) | (1 << 21) | 1)
    brick = (rounded >> 1) & ((((1 << 20) - 1) << 42) | (((1 << 20) - 1) << 21) | ((1 << 20) - 1))
    local = ((rounded >> 40) & 4) | ((rounded >> 20) & 2) | (rounded & 1)
    h = brick & _M64
    h = ((h ^ (h >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    h = ((h ^ (h >> 27)) * 0x94D049BB133111EB) & _M64
    h ^= h >> 31
    return (((h & 0x7FFFFFFF) << 3) | local) & mask


def _probe(table_keys: np.ndarray, key: int) -> int:
    """The slot holding ``key``, or the empty slot its probe run ends at; -1 when neither (a full table)."""
    mask = len(table_keys) - 1
    slot = hash_slot(key, mask)
    for _ in range(len(table_keys)):
        if table_keys[slot] == key or table_keys[slot] == EMPTY_KEY:
            return slot
        slot = (slot + 1) & mask
    return -1


def table_find_slot(table_keys: np.ndarray, key: int) -> int:
    """Twin of ``kernels.hash_table.table_find_slot``: the slot holding ``key`` in ``table_keys``, or -1 when
    it is absent."""
    if key == EMPTY_KEY:
        return -1
    slot = _probe(table_keys, key)
    return slot if slot >= 0 and table_keys[slot] == key else -1


def table_find(table_keys: np.ndarray, slot_rows: np.ndarray, key: int) -> int:
    """Row of ``key``, -1 when absent."""
    slot = table_find_slot(table_keys, key)
    return -1 if slot < 0 else int(slot_rows[slot]) - 1


def table_find_or_insert(table_keys: np.ndarray, slot_rows: np.ndarray, key_count: list[int], max_count: int, key: int) -> int:
    """Row of ``key``, inserting it (next row) if absent; -1 when the table holds max_count keys."""
    if key == EMPTY_KEY:
        return -1
    slot = _probe(table_keys, key)
    if slot < 0:
        return -1
    if table_keys[slot] == key:
        return int(slot_rows[slot]) - 1
    if key_count[0] >= max_count:
        return -1
    table_keys[slot] = key
    slot_rows[slot] = key_count[0] + 1
    key_count[0] += 1
    return key_count[0] - 1


def insert_keys(keys_in: np.ndarray, table_keys: np.ndarray, slot_rows: np.ndarray, key_count: list[int], max_count: int) -> np.ndarray:
    """Serial insertion in input order; mutates the table and ``key_count``, returns rows."""
    return np.array([table_find_or_insert(table_keys, slot_rows, key_count, max_count, int(k)) for k in keys_in], dtype=np.int64)


def lookup_keys(keys_in: np.ndarray, table_keys: np.ndarray, slot_rows: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.hash_table.lookup_keys``: the row of each key of ``keys_in`` [N], -1 where absent."""
    return np.array([table_find(table_keys, slot_rows, int(k)) for k in keys_in], dtype=np.int64)


def lookup_points(points: np.ndarray, resolution: float, grid_offset: float, table_keys: np.ndarray, slot_rows: np.ndarray) -> np.ndarray:
    """Row of each point's voxel; -1 outside the key range or where the voxel is not stored."""
    index = np.floor((np.asarray(points, dtype=np.float64) - grid_offset) / resolution)
    inside = np.all((index >= -KEY_OFFSET) & (index < KEY_OFFSET), axis=-1)
    rows = np.full(len(index), -1, dtype=np.int64)
    rows[inside] = lookup_keys(pack_key(index[inside].astype(np.int64)), table_keys, slot_rows)
    return rows


def rehash(old_keys: np.ndarray, old_slot_rows: np.ndarray, new_capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """The grown table's keys and slot rows: every key moves to its slot in the new table with its row."""
    new_keys = np.full(new_capacity, EMPTY_KEY, dtype=np.int64)
    new_slot_rows = np.zeros(new_capacity, dtype=np.int64)
    mask = new_capacity - 1
    for i, key in enumerate(old_keys):
        if key != EMPTY_KEY:
            slot = hash_slot(int(key), mask)
            while new_keys[slot] != EMPTY_KEY:
                slot = (slot + 1) & mask
            new_keys[slot], new_slot_rows[slot] = key, old_slot_rows[i]
    return new_keys, new_slot_rows


def gather_rows(src: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """src[rows[i]] for every i."""
    return np.asarray(src)[np.asarray(rows, dtype=np.int64)]


def read_counters(key_count: np.ndarray, update_count: np.ndarray, brick_count: np.ndarray, scan_status: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.hash_table.read_counters``: [key count, update count, brick count, *scan status] as int64."""
    return np.array([key_count[0], update_count[0], brick_count[0], *scan_status], dtype=np.int64)
