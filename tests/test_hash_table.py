"""The Warp hash table against its serial numpy twin: same slots, same lookups, growth, overflow."""

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.kernels import hash_table as ht
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.reference import hash_table as ref
from evsemmap_warp.core.voxel_map import VoxelMap
from evsemmap_warp.voxel_keys import pack_voxel_keys, unpack_voxel_keys


def _insert(keys_np, capacity, max_count, device):
    table = wp.full(capacity, ht.EMPTY_KEY, dtype=wp.int64, device=device)
    count = wp.zeros(1, dtype=int, device=device)
    slots = wp.empty(len(keys_np), dtype=int, device=device)
    if len(keys_np):
        wp.launch(ht.insert_keys, dim=len(keys_np), inputs=[wp.array(keys_np, dtype=wp.int64, device=device), table, count, max_count, slots], device=device)
    return table.numpy(), int(count.numpy()[0]), slots.numpy()


def _random_keys(rng, n, spread=50):
    index = rng.integers(-spread, spread, size=(n, 3))
    return ref.pack_key(index)


def test_pack_matches_reference_and_round_trips():
    rng = np.random.default_rng(1)
    index = rng.integers(-ht.INDEX_LIMIT, ht.INDEX_LIMIT, size=(1000, 3))
    index[0] = [-ht.INDEX_LIMIT, -ht.INDEX_LIMIT, -ht.INDEX_LIMIT]
    index[1] = [ht.INDEX_LIMIT - 1] * 3
    keys = pack_voxel_keys(index)
    np.testing.assert_array_equal(keys, ref.pack_key(index))
    np.testing.assert_array_equal(unpack_voxel_keys(keys), index)
    assert (keys >= 0).all() and (keys != ht.EMPTY_KEY).all()


@pytest.mark.parametrize("n, capacity", [(0, 16), (1, 16), (500, 2048), (3000, 4096)])
def test_insert_matches_serial_reference_on_cpu(n, capacity):
    rng = np.random.default_rng(n)
    keys = _random_keys(rng, n, spread=8)  # many duplicates
    table, count, slots = _insert(keys, capacity, capacity, "cpu")
    ref_table = np.full(capacity, ref.EMPTY_KEY, dtype=np.int64)
    ref_count = [0]
    ref_slots = ref.insert_keys(keys, ref_table, ref_count, capacity)
    # The CPU launch is serial in thread order, so even the slot numbers agree with the twin.
    np.testing.assert_array_equal(slots, ref_slots)
    np.testing.assert_array_equal(table, ref_table)
    assert count == ref_count[0] == len(np.unique(keys))


def test_insert_and_lookup_on_device(device):
    rng = np.random.default_rng(7)
    keys = _random_keys(rng, 4000)
    table, count, slots = _insert(keys, 8192, 8192, device)
    assert count == len(np.unique(keys))
    np.testing.assert_array_equal(table[slots], keys)  # every key sits where it was reported
    absent = ref.pack_key(rng.integers(1000, 2000, size=(300, 3)))
    probe = np.concatenate([keys, absent])
    out = wp.empty(len(probe), dtype=int, device=device)
    wp.launch(ht.lookup_keys, dim=len(probe), inputs=[wp.array(probe, dtype=wp.int64, device=device), wp.array(table, dtype=wp.int64, device=device), out], device=device)
    found = out.numpy()
    np.testing.assert_array_equal(found[: len(keys)], slots)
    assert (found[len(keys):] == -1).all()
    np.testing.assert_array_equal(found, ref.lookup_keys(probe, table))


def test_forced_collisions_in_a_tiny_table():
    # 16 slots, 12 distinct keys: long probe chains and wrap-around at the table end.
    keys = ref.pack_key(np.array([[i, 0, 0] for i in range(12)]))
    table, count, slots = _insert(keys, 16, 16, "cpu")
    assert count == 12 and len(set(slots)) == 12
    homes = [ref.hash_slot(k, 15) for k in keys]
    assert len(set(homes)) < 12, "the test wants at least one collision of home slots"
    assert (slots != np.array(homes)).any()
    np.testing.assert_array_equal(table[slots], keys)


def test_full_table_refuses_instead_of_overwriting():
    keys = ref.pack_key(np.array([[i, i, 0] for i in range(20)]))
    table, count, slots = _insert(keys, 16, 10, "cpu")
    assert count == 10
    assert (slots[:10] >= 0).all() and (slots[10:] == -1).all()
    np.testing.assert_array_equal(table[slots[:10]], keys[:10])  # nothing inserted was overwritten


def test_lookup_points_uses_floor_of_the_grid(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    vm.insert_voxels(np.array([[0, 0, 0], [-1, -1, -1], [1, 0, 0]]))
    pts = np.array([[0.0, 0.0, 0.0], [0.49, 0.49, 0.49], [-0.01, -0.2, -0.5], [0.5, 0.0, 0.0], [0.5, 0.5, 0.0]])
    slots = vm.lookup_points(pts)
    keys = vm.keys.numpy()
    got = [tuple(unpack_voxel_keys(keys[[s]])[0]) if s >= 0 else None for s in slots]
    assert got == [(0, 0, 0), (0, 0, 0), (-1, -1, -1), (1, 0, 0), None]
    np.testing.assert_array_equal(slots, ref.lookup_points(pts.astype(np.float32), 0.5, 0.0, keys))


def test_growth_keeps_every_key_and_value(device):
    vm = VoxelMap(4, 0.1, device=device, initial_capacity=16)
    rng = np.random.default_rng(3)
    index = np.unique(rng.integers(-30, 30, size=(2000, 3)), axis=0)
    slots = vm.insert_voxels(index)
    assert vm.grow_count >= 1 and vm.voxel_count == len(index)
    values = rng.random((len(index), 4))
    hits = rng.integers(0, 1000, len(index))
    data = vm.data.numpy().copy()
    data[slots, :4] = values
    data[slots, 4 + sc.COL_HITS] = hits
    vm.data = wp.array(data, dtype=wp.float64, device=device)
    old_keys = vm.keys.numpy().copy()
    vm.grow(vm.capacity * 4)
    ref_keys, ref_new_slot = ref.rehash(old_keys, vm.capacity)
    if device == "cpu":
        np.testing.assert_array_equal(vm.keys.numpy(), ref_keys)
    arrays = vm.arrays()
    order = np.lexsort(index.T[::-1])
    np.testing.assert_array_equal(arrays.index, index[order])
    np.testing.assert_array_equal(arrays.evidence, values[order])
    np.testing.assert_array_equal(arrays.hits, hits[order])


def test_lookup_points_outside_the_key_range_find_nothing_like_the_twin(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    vm.insert_voxels(np.array([[0, 0, 0], [ht.INDEX_LIMIT - 1, 0, 0], [-ht.INDEX_LIMIT, 0, 0]]))
    limit = ht.INDEX_LIMIT * 0.5
    pts = np.array([[0.1, 0.1, 0.1], [limit - 0.1, 0.1, 0.1], [-limit + 0.1, 0.1, 0.1], [limit + 0.1, 0.1, 0.1],
                    [2 * limit + 0.1, 0.1, 0.1], [0.1, -3 * limit, 0.1], [1e300, 0, 0], [-1e300, 0, 0]])
    slots = vm.lookup_points(pts)
    np.testing.assert_array_equal(slots, ref.lookup_points(pts, 0.5, 0.0, vm.keys.numpy()))
    assert (slots[:3] >= 0).all() and (slots[3:] == -1).all()


def test_gather_rows_matches_the_twin(device):
    rng = np.random.default_rng(9)
    src = rng.random((50, 7))
    for rows in (np.array([3], np.int32), np.array([0, 49, 0], np.int32), rng.integers(0, 50, 200).astype(np.int32)):
        dst = wp.empty((len(rows), 7), dtype=wp.float64, device=device)
        wp.launch(ht.gather_rows, dim=len(rows), inputs=[wp.array(src, dtype=wp.float64, device=device), wp.array(rows, dtype=int, device=device), dst], device=device)
        np.testing.assert_array_equal(dst.numpy(), ref.gather_rows(src, rows))


def test_rows_at_returns_zero_rows_for_missing_slots(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    slots = vm.insert_voxels(np.array([[0, 0, 0], [1, 0, 0]]))
    data = vm.data.numpy().copy()
    data[slots, 0] = [5.0, 7.0]
    vm.data = wp.array(data, dtype=wp.float64, device=device)
    rows = vm.rows_at(np.array([slots[1], -1, slots[0]]))
    np.testing.assert_array_equal(rows[:, 0], [7.0, 0.0, 5.0])
    assert vm.rows_at(np.zeros(0, np.int64)).shape == (0, 3 + sc.EXTRA_COLUMNS)


def test_a_blocks_cells_share_home_slots():
    # The 2x2x2 brick {2b - 1, 2b}^3 (an S-BKI / release block at depth 2) hashes to 8 neighbouring
    # home slots, so its cells share cache lines and pages; different bricks land apart.
    rng = np.random.default_rng(3)
    mask = (1 << 22) - 1
    for b in rng.integers(-1000, 1000, (50, 3)):
        cells = np.array([[2 * b[0] - 1 + i, 2 * b[1] - 1 + j, 2 * b[2] - 1 + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        homes = [ref.hash_slot(key, mask) for key in ref.pack_key(cells)]
        assert sorted(homes) == list(range(min(homes), min(homes) + 8)) and min(homes) % 8 == 0
    bricks = rng.integers(-1000, 1000, (2000, 3))
    homes = {ref.hash_slot(key, mask) // 8 for key in ref.pack_key(2 * bricks)}
    assert len(homes) > 0.99 * len(np.unique(bricks, axis=0))


def test_edge_of_the_key_range_hashes_like_the_twin():
    index = np.array([[ht.INDEX_LIMIT - 1] * 3, [-ht.INDEX_LIMIT] * 3, [ht.INDEX_LIMIT - 1, -ht.INDEX_LIMIT, 0]])
    keys = ref.pack_key(index)
    table, count, slots = _insert(keys, 64, 64, "cpu")
    ref_table = np.full(64, ref.EMPTY_KEY, dtype=np.int64)
    np.testing.assert_array_equal(slots, ref.insert_keys(keys, ref_table, [0], 64))
    np.testing.assert_array_equal(table, ref_table)
