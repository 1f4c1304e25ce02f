"""The Warp hash table against its serial numpy twin: same slots and rows, same lookups, growth, overflow."""

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.kernels import hash_table as ht
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.reference import hash_table as ref
from evsemmap_warp.core.voxel_map import VoxelMap
from evsemmap_warp.voxel_keys import pack_voxel_keys, unpack_voxel_keys


def _insert(keys_np, capacity, max_count, device):
    """Insert into a fresh table; returns its keys, slot rows (row + 1), key count and each key's row."""
    table = wp.full(capacity, ht.EMPTY_KEY, dtype=wp.int64, device=device)
    slot_rows = wp.zeros(capacity, dtype=int, device=device)
    count = wp.zeros(1, dtype=int, device=device)
    rows = wp.empty(len(keys_np), dtype=int, device=device)
    if len(keys_np):
        wp.launch(ht.insert_keys, dim=len(keys_np), inputs=[wp.array(keys_np, dtype=wp.int64, device=device),
                                                             ht.hash_table(table, slot_rows, count, max_count), rows], device=device)
    return table.numpy(), slot_rows.numpy(), int(count.numpy()[0]), rows.numpy()


def _key_of_row(table, slot_rows):
    """row -> key for every stored key."""
    stored = np.flatnonzero(table != ht.EMPTY_KEY)
    out = np.full(len(stored), ht.EMPTY_KEY, np.int64)
    out[slot_rows[stored] - 1] = table[stored]
    return out


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
    table, slot_rows, count, rows = _insert(keys, capacity, capacity, "cpu")
    ref_table = np.full(capacity, ref.EMPTY_KEY, dtype=np.int64)
    ref_slot_rows = np.zeros(capacity, np.int64)
    ref_count = [0]
    ref_rows = ref.insert_keys(keys, ref_table, ref_slot_rows, ref_count, capacity)
    # The CPU launch is serial in thread order, so even the slot and row numbers agree with the twin.
    np.testing.assert_array_equal(rows, ref_rows)
    np.testing.assert_array_equal(table, ref_table)
    np.testing.assert_array_equal(slot_rows, ref_slot_rows)
    assert count == ref_count[0] == len(np.unique(keys))
    # rows are handed out densely, in first-insertion order
    _, first = np.unique(keys, return_index=True)
    np.testing.assert_array_equal(rows[np.sort(first)], np.arange(count))


def test_insert_and_lookup_on_device(device):
    rng = np.random.default_rng(7)
    keys = _random_keys(rng, 4000)
    table, slot_rows, count, rows = _insert(keys, 8192, 8192, device)
    assert count == len(np.unique(keys))
    assert sorted(set(rows.tolist())) == list(range(count))  # dense rows, one per distinct key
    np.testing.assert_array_equal(_key_of_row(table, slot_rows)[rows], keys)  # every key has the row it was given
    absent = ref.pack_key(rng.integers(1000, 2000, size=(300, 3)))
    probe = np.concatenate([keys, absent])
    out = wp.empty(len(probe), dtype=int, device=device)
    view = ht.hash_table(wp.array(table, dtype=wp.int64, device=device), wp.array(slot_rows, dtype=int, device=device), wp.zeros(1, dtype=int, device=device), 0)
    wp.launch(ht.lookup_keys, dim=len(probe), inputs=[wp.array(probe, dtype=wp.int64, device=device), view, out], device=device)
    found = out.numpy()
    np.testing.assert_array_equal(found[: len(keys)], rows)
    assert (found[len(keys):] == -1).all()
    np.testing.assert_array_equal(found, ref.lookup_keys(probe, table, slot_rows))


def test_forced_collisions_in_a_tiny_table():
    # 16 slots, 12 distinct keys: long probe chains and wrap-around at the table end.
    keys = ref.pack_key(np.array([[i, 0, 0] for i in range(12)]))
    table, slot_rows, count, rows = _insert(keys, 16, 16, "cpu")
    assert count == 12
    np.testing.assert_array_equal(rows, np.arange(12))
    homes = [ref.hash_slot(k, 15) for k in keys]
    assert len(set(homes)) < 12, "the test wants at least one collision of home slots"
    slots = [int(np.flatnonzero(table == k)[0]) for k in keys]
    assert (np.array(slots) != np.array(homes)).any()
    np.testing.assert_array_equal(slot_rows[slots], rows + 1)


def test_full_table_refuses_instead_of_overwriting():
    keys = ref.pack_key(np.array([[i, i, 0] for i in range(20)]))
    table, slot_rows, count, rows = _insert(keys, 16, 10, "cpu")
    assert count == 10
    assert (rows[:10] >= 0).all() and (rows[10:] == -1).all()
    np.testing.assert_array_equal(_key_of_row(table, slot_rows)[rows[:10]], keys[:10])  # nothing inserted was overwritten


def test_lookup_points_uses_floor_of_the_grid(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    vm.insert_voxels(np.array([[0, 0, 0], [-1, -1, -1], [1, 0, 0]]))
    pts = np.array([[0.0, 0.0, 0.0], [0.49, 0.49, 0.49], [-0.01, -0.2, -0.5], [0.5, 0.0, 0.0], [0.5, 0.5, 0.0]])
    rows = vm.lookup_points(pts)
    key_of_row = _key_of_row(vm.keys.numpy(), vm.slot_rows.numpy())
    got = [tuple(unpack_voxel_keys(key_of_row[[r]])[0]) if r >= 0 else None for r in rows]
    assert got == [(0, 0, 0), (0, 0, 0), (-1, -1, -1), (1, 0, 0), None]
    np.testing.assert_array_equal(rows, ref.lookup_points(pts.astype(np.float32), 0.5, 0.0, vm.keys.numpy(), vm.slot_rows.numpy()))


def test_growth_keeps_every_key_and_value(device):
    vm = VoxelMap(4, 0.1, device=device, initial_capacity=16)
    rng = np.random.default_rng(3)
    index = np.unique(rng.integers(-30, 30, size=(2000, 3)), axis=0)
    rows = vm.insert_voxels(index)
    assert vm.grow_count >= 1 and vm.voxel_count == len(index)
    np.testing.assert_array_equal(rows, np.arange(len(index)))  # serial CPU order; any permutation on a GPU
    values = rng.random((len(index), 4))
    hits = rng.integers(0, 1000, len(index))
    data = vm.data.numpy().copy()
    data[rows, :4] = values
    data[rows, 4 + sc.COL_HITS] = hits
    vm.data = wp.array(data, dtype=wp.float64, device=device)
    old_keys, old_slot_rows = vm.keys.numpy().copy(), vm.slot_rows.numpy().copy()
    vm.grow(vm.capacity * 4)
    ref_keys, ref_slot_rows = ref.rehash(old_keys, old_slot_rows, vm.capacity)
    if device == "cpu":
        np.testing.assert_array_equal(vm.keys.numpy(), ref_keys)
        np.testing.assert_array_equal(vm.slot_rows.numpy(), ref_slot_rows)
    np.testing.assert_array_equal(vm.lookup_points((index + 0.5) * 0.1), rows)  # voxels keep their rows
    arrays = vm.arrays()
    order = np.lexsort(index.T[::-1])
    np.testing.assert_array_equal(arrays.index, index[order])
    np.testing.assert_array_equal(arrays.evidence, values[order])
    np.testing.assert_array_equal(arrays.hits, hits[order])
    # rows past the stored voxels were never written: a grown CPU table maps them only when used
    assert not vm.data.numpy()[len(index):].any()


def test_lookup_points_outside_the_key_range_find_nothing_like_the_twin(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    vm.insert_voxels(np.array([[0, 0, 0], [ht.INDEX_LIMIT - 1, 0, 0], [-ht.INDEX_LIMIT, 0, 0]]))
    limit = ht.INDEX_LIMIT * 0.5
    pts = np.array([[0.1, 0.1, 0.1], [limit - 0.1, 0.1, 0.1], [-limit + 0.1, 0.1, 0.1], [limit + 0.1, 0.1, 0.1],
                    [2 * limit + 0.1, 0.1, 0.1], [0.1, -3 * limit, 0.1], [1e300, 0, 0], [-1e300, 0, 0]])
    rows = vm.lookup_points(pts)
    np.testing.assert_array_equal(rows, ref.lookup_points(pts, 0.5, 0.0, vm.keys.numpy(), vm.slot_rows.numpy()))
    assert (rows[:3] >= 0).all() and (rows[3:] == -1).all()


def test_gather_rows_matches_the_twin(device):
    rng = np.random.default_rng(9)
    src = rng.random((50, 7))
    for rows in (np.array([3], np.int32), np.array([0, 49, 0], np.int32), rng.integers(0, 50, 200).astype(np.int32)):
        dst = wp.empty((len(rows), 7), dtype=wp.float64, device=device)
        wp.launch(ht.gather_rows, dim=len(rows), inputs=[wp.array(src, dtype=wp.float64, device=device), wp.array(rows, dtype=int, device=device), dst], device=device)
        np.testing.assert_array_equal(dst.numpy(), ref.gather_rows(src, rows))


def test_rows_at_returns_zero_rows_for_missing_voxels(device):
    vm = VoxelMap(3, 0.5, device=device, initial_capacity=64)
    rows = vm.insert_voxels(np.array([[0, 0, 0], [1, 0, 0]]))
    data = vm.data.numpy().copy()
    data[rows, 0] = [5.0, 7.0]
    vm.data = wp.array(data, dtype=wp.float64, device=device)
    picked = vm.rows_at(np.array([rows[1], -1, rows[0]]))
    np.testing.assert_array_equal(picked[:, 0], [7.0, 0.0, 5.0])
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
    table, slot_rows, count, rows = _insert(keys, 64, 64, "cpu")
    ref_table, ref_slot_rows = np.full(64, ref.EMPTY_KEY, dtype=np.int64), np.zeros(64, np.int64)
    np.testing.assert_array_equal(rows, ref.insert_keys(keys, ref_table, ref_slot_rows, [0], 64))
    np.testing.assert_array_equal(table, ref_table)
    np.testing.assert_array_equal(slot_rows, ref_slot_rows)


@pytest.mark.parametrize("reserved", [True, False])
def test_cpu_rows_stay_in_place_when_reserved_and_are_copied_otherwise(reserved, monkeypatch):
    from evsemmap_warp.core import host_memory

    if reserved and not host_memory.reservation_allowed():
        pytest.skip("this process may not reserve address space (not Linux, ulimit -v or strict overcommit)")
    if not reserved:  # a platform, limit or overcommit policy that refuses the reservation
        monkeypatch.setattr(host_memory, "reserved_zeros", lambda rows, columns: None)
    vm = VoxelMap(3, 0.5, initial_capacity=16)
    rng = np.random.default_rng(4)
    index = np.unique(rng.integers(-20, 20, size=(300, 3)), axis=0)
    rows = vm.insert_voxels(index)
    vm.data.numpy()[rows, 0] = np.arange(len(index), dtype=np.float64)
    before = vm.data.ptr
    vm.grow(vm.capacity * 8)
    assert (vm.data.ptr == before) == reserved
    np.testing.assert_array_equal(vm.data.numpy()[vm.lookup_points((index + 0.5) * 0.5), 0], np.arange(len(index)))


def test_no_row_reservation_under_an_address_space_limit():
    # Under ulimit -v a reservation counts against the limit, and so against the tables' memory budget
    # (limits.available_memory): each shard's 16 GiB left a 20 GiB limit's map about 3 GiB to grow in.
    import subprocess
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("ulimit -v and the reservation are Linux's")
    script = """
import resource
resource.setrlimit(resource.RLIMIT_AS, (20 << 30, resource.getrlimit(resource.RLIMIT_AS)[1]))
from evsemmap_warp.core.voxel_map import VoxelMap
from evsemmap_warp.limits import available_memory
before = available_memory()
maps = [VoxelMap(9, 0.2, initial_capacity=1024) for _ in range(2)]
print(before - available_memory())
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout.split()[-1]) < 1 << 30, "the tables took the address space of a reservation"


@pytest.mark.parametrize("rows", [1, 255, 256, 257, 5000])
@pytest.mark.parametrize("dtype", [np.float32, np.int64])
def test_column_bounds_are_the_columns_min_and_max(rows, dtype):
    from evsemmap_warp.voxel_keys import column_bounds

    values = (np.random.default_rng(rows).normal(size=(rows, 3)) * 1e4).astype(dtype)
    values[-1] = values.max() + 1  # the extremes in the rows left over after the folds
    values[0, 1] = values.min() - 1
    lo, hi = column_bounds(values)
    np.testing.assert_array_equal(lo, values.min(axis=0))
    np.testing.assert_array_equal(hi, values.max(axis=0))
    assert lo.dtype == hi.dtype == dtype
    if dtype == np.float32 and rows > 256:
        values[100, 2] = np.nan
        assert np.isnan(column_bounds(values)[0][2]) and np.isnan(column_bounds(values)[1][2])
