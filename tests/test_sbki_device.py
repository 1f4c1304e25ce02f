"""S-BKI's training data built by the parallel kernels (``methods.sbki_device``) is the host path's
(``methods.sbki_compat.training_data``) bit for bit, on Warp's CPU backend (and on CUDA where Warp sees
a GPU): random clouds and the edge cases, and each parallel kernel against its numpy twin."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.kernels import voxel_grid
from evsemmap_warp.methods import sbki_compat as sb
from evsemmap_warp.methods import sbki_device
from evsemmap_warp.methods.device_scratch import STATUS_FREE_ROWS, STATUS_OVERFLOW, DeviceScratch, Rows
from evsemmap_warp.reference import voxel_grid as twin


def _rows(values, dtype, device) -> Rows:
    """Rows over all of ``values``."""
    return Rows(wp.array(values, dtype=dtype, device=device), wp.array([len(values)], dtype=int, device=device))


def _on_device(points, labels, origin, device, scratch=None, **kw):
    # As the launch runs it (core.integrators.counted_gather_launch): redone with room for what a run that
    # ran out of room counted.
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int64), {"hits": 0, "free_samples": 0}
    scratch = scratch or DeviceScratch(device).begin()
    while True:
        hits, hit_labels, frees = sbki_device.training_arrays(points, labels, origin, device=device, scratch=scratch, **kw)
        status = scratch.status.numpy()
        if not status[STATUS_OVERFLOW]:
            break
        scratch.learn(status)
        scratch.begin()
    hits = hits.numpy()
    return sb.joined_training_set(hits, hit_labels.numpy()[:len(hits)], frees.numpy())


def _both(points, labels, origin, device, **kw):
    return sb.training_data(points, labels, origin, **kw), _on_device(points, labels, origin, device, **kw)


def _assert_same(host, on_device):
    (hp, hl, hi), (dp, dl, di) = host, on_device
    assert hp.dtype == dp.dtype == np.float32 and hl.dtype == dl.dtype == np.int64
    np.testing.assert_array_equal(dp, hp)
    np.testing.assert_array_equal(dl, hl)
    assert di == hi


def _cloud(rng, n, origin, spread=6.0, classes=5):
    points = (origin + rng.normal(size=(n, 3)) * rng.uniform(0.1, spread, (n, 1))).astype(np.float32)
    return points, rng.integers(0, classes, n)


@pytest.mark.parametrize("free_res, max_range", [(0.5, None), (0.5, 8.0), (4.0, 12.0), (100.0, None), (0.37, 30.0)])
def test_training_data_matches_the_host_path(device, free_res, max_range):
    rng = np.random.default_rng(int(free_res * 100))
    origin = np.array([3.25, -1.5, 1.2], np.float32)
    points, labels = _cloud(rng, 20_000, origin)
    # Points on leaf faces and block faces, several copies of one point (ties between labels), the origin.
    points[:50] = np.round(points[:50] * 10) / 10
    points[50:60] = points[60]
    labels[50:60] = [1, 2, 1, 2, 3, 3, 4, 4, 0, 0]
    points[70] = origin
    _assert_same(*_both(points, labels, origin, device, ds_resolution_m=0.1, free_resolution_m=free_res, max_range_m=max_range))


def test_training_data_edge_cases(device):
    origin = np.array([0.5, 0.25, -0.1], np.float32)
    kw = dict(ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=None)
    empty = np.zeros((0, 3), np.float32)
    _assert_same(*_both(empty, np.zeros(0, np.int64), origin, device, **kw))
    _assert_same(*_both(np.array([[2.0, 1.0, 0.5]], np.float32), np.array([3]), origin, device, **kw))
    # Every hit beyond the range: no hits, no free samples.
    _assert_same(*_both(np.array([[20.0, 1.0, 0.5], [30, 0, 0]], np.float32), np.array([3, 1]), origin, device,
                        ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=5.0))
    # One label everywhere; negative labels.
    rng = np.random.default_rng(3)
    points, _ = _cloud(rng, 3000, origin, spread=5.0)
    _assert_same(*_both(points, np.full(3000, 7), origin, device, **kw))
    _assert_same(*_both(points, rng.integers(-3, 2, 3000), origin, device, **kw))


def test_training_data_far_from_the_origin(device):
    # A cloud 80 km out (float32 spacing 8 mm): the leaf indices and the sums as the host forms them.
    rng = np.random.default_rng(5)
    origin = np.array([80_000.0, -40_000.0, 12.0], np.float32)
    points, labels = _cloud(rng, 5000, origin, spread=15.0)
    _assert_same(*_both(points, labels, origin, device, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=None))


def test_thousands_of_copies_in_one_leaf_drift_as_the_host_sums(device):
    # The sensor origin's leaf of the free samples: one copy per hit, summed in float32 one by one.
    origin = np.array([1234.567, -89.012, 3.3], np.float32)
    copies = np.repeat(origin[None], 20_000, axis=0)
    host = sb.voxel_grid_downsample(copies, np.zeros(len(copies), np.int64), 0.1)
    centroids, labels = sbki_device.voxel_grid_on_device(
        _rows(copies, wp.vec3, device), wp.array(np.zeros(len(copies), np.int64), dtype=wp.int64, device=device), (0, 0),
        (copies.min(axis=0), copies.max(axis=0)), 0.1)
    np.testing.assert_array_equal(centroids.numpy(), host[0])
    np.testing.assert_array_equal(labels.numpy()[:len(host[1])], host[1])


def test_a_grid_pcl_refuses_leaves_the_cloud_unchanged(device):
    points = np.array([[0, 0, 0], [1e6, 1e6, 1e3]], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        centroids, labels = sbki_device.voxel_grid_on_device(
            _rows(points, wp.vec3, device), wp.array(np.array([1, 2]), dtype=wp.int64, device=device), (1, 2),
            (points.min(axis=0), points.max(axis=0)), 0.01)
    np.testing.assert_array_equal(centroids.numpy(), points)
    np.testing.assert_array_equal(labels.numpy(), [1, 2])


def test_too_many_free_samples_are_refused_as_on_the_host(device):
    origin = np.zeros(3, np.float32)
    far = np.array([[3e6, 0, 0]], np.float32)  # 6 M steps of 0.5 m along one ray
    for build in (sb.training_data, lambda *a, **kw: _on_device(*a, device, **kw)):
        with pytest.raises(ValueError, match="free_resolution_m"):
            build(far, np.array([1]), origin, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=None)


def test_the_boxes_known_on_the_host_hold_what_they_stand_in_for():
    # training_box and member_block_box stand in for the bounds the device path would otherwise read back
    # (the free samples' leaf grid, the longest ray, the memberships' blocks); they must hold every training
    # point and block: an origin outside the cloud, points on leaf and block faces, a cloud far out, a range cut.
    rng = np.random.default_rng(21)
    block_size = sb.block_size_m(0.2, 2)
    for origin, spread, max_range in (([0.3, -0.2, 1.1], 6.0, None), ([40.0, 3.0, -2.0], 3.0, None), ([80_000.0, -40_000.0, 12.0], 15.0, None),
                                      ([1.0, 1.0, 0.0], 20.0, 5.0)):
        origin = np.array(origin, np.float32)
        points, labels = _cloud(rng, 4000, origin + np.float32(spread), spread=spread)
        points[:40] = (np.round(points[:40] / block_size) + np.float32(0.5)) * block_size
        train, _, _ = sb.training_data(points, labels, origin, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=max_range)
        lo, hi = sbki_device.training_box(points, origin, 0.1)
        assert (train >= lo).all() and (train <= hi).all()
        _, blocks = sb.block_memberships(train, block_size)
        block_lo, block_hi = sbki_device.member_block_box(lo, hi, block_size)
        assert (blocks >= block_lo).all() and (blocks <= block_hi).all()
        hits, _ = sb.voxel_grid_downsample(points, labels, 0.1)
        reach = np.linalg.norm(hits.astype(np.float64) - origin, axis=1).max()
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)
        assert np.linalg.norm(corners - origin.astype(np.float64), axis=1).max() >= reach


@pytest.mark.parametrize("case", ["leaf grid", "steps"])
def test_training_data_where_the_host_box_is_refused_reads_the_bounds(device, case, monkeypatch):
    # The box the host knows is wider than the free samples' bounds: its leaf grid (a cloud whose own grid is
    # 1290 leaves a side, just under PCL's limit, widened by a leaf) or its steps (the far hits are cut by
    # the range, at a fine free resolution) can be refused where the free samples' own are not. The device
    # path then reads the bounds back, and builds the host path's training set.
    rng = np.random.default_rng(22)
    if case == "leaf grid":
        origin = np.full(3, 64.0, np.float32)
        points = rng.uniform(0.0, 128.95, (3000, 3)).astype(np.float32)
        points[:2] = [[0.0, 0.0, 0.0], [128.95, 128.95, 128.95]]
        points[2:200] = origin + rng.normal(size=(198, 3)).astype(np.float32)
        free_res, max_range = 0.5, 8.0
    else:
        origin = np.array([0.5, -0.5, 0.2], np.float32)
        points = np.concatenate([origin + rng.uniform(-0.5, 0.5, (20, 3)), 60.0 + rng.uniform(0, 1, (50, 3))]).astype(np.float32)
        free_res, max_range = 1e-5, 1.0
    labels = rng.integers(0, 5, len(points))
    lo, hi = sbki_device.training_box(points, origin, 0.1)
    assert sb.leaf_grid(*sb.column_bounds(points), 0.1, warn=False) is not None
    if case == "leaf grid":
        assert sb.leaf_grid(lo, hi, 0.1, warn=False) is None
    else:
        with pytest.raises(ValueError, match="free_resolution_m"):
            sb.check_free_samples(0.0, float(np.linalg.norm(np.maximum(np.abs(lo - origin), np.abs(hi - origin)))), np.float32(free_res), origin)
    read = []
    for name in ("float_bounds_on_device", "_longest_ray"):
        monkeypatch.setattr(sbki_device, name, lambda *a, _f=getattr(sbki_device, name), _n=name: read.append(_n) or _f(*a))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no grid is refused on either path
        _assert_same(*_both(points, labels, origin, device, ds_resolution_m=0.1, free_resolution_m=free_res, max_range_m=max_range))
    assert set(read) == {"float_bounds_on_device" if case == "leaf grid" else "_longest_ray"}  # once per run (a scan out of room runs again)


def test_the_training_set_join_matches_its_twin(device):
    from evsemmap_warp.kernels import free_space
    from evsemmap_warp.reference.free_space import join_training_set

    rng = np.random.default_rng(23)
    for h, f in ((0, 0), (3, 0), (0, 4), (50, 70)):
        hits, frees = rng.normal(size=(h, 3)).astype(np.float32), rng.normal(size=(f, 3)).astype(np.float32)
        hit_labels = rng.integers(0, 9, h)
        # Each part with room for 5 more rows than it counts: the rows past the counts are not joined.
        hit_room = np.concatenate([hits, np.full((5, 3), np.nan, np.float32)])
        free_room = np.concatenate([frees, np.full((5, 3), np.nan, np.float32)])
        capacity = h + f + 10
        points = wp.empty(capacity, dtype=wp.vec3, device=device)
        labels = wp.empty(capacity, dtype=wp.int64, device=device)
        total = wp.empty(1, dtype=int, device=device)
        wp.launch(free_space.join_training_set, dim=capacity, device=device, inputs=[
            wp.array(hit_room, dtype=wp.vec3, device=device), wp.array(np.r_[hit_labels, np.full(5, -7)], dtype=wp.int64, device=device),
            wp.array([h], dtype=int, device=device), wp.array(free_room, dtype=wp.vec3, device=device), wp.array([f], dtype=int, device=device),
            sb.FREE_LABEL, points, labels, total])
        want_points, want_labels = join_training_set(hits, hit_labels, frees, sb.FREE_LABEL)
        assert total.numpy()[0] == h + f
        np.testing.assert_array_equal(points.numpy()[:h + f].reshape(-1, 3), want_points)
        np.testing.assert_array_equal(labels.numpy()[:h + f], want_labels)


def test_parallel_centroids_and_majority_labels_match_their_twins(device):
    rng = np.random.default_rng(11)
    n = 4000
    points = rng.normal(size=(n, 3)).astype(np.float32) * 3
    labels = rng.integers(0, 4, n)
    inverse_leaf, lowest, dims = sb.leaf_grid(points.min(axis=0), points.max(axis=0), 0.1)
    leaf = twin.leaf_indices(points, inverse_leaf, lowest, dims[0], dims[1])
    order = np.argsort(leaf, kind="stable")
    sorted_leaf = leaf[order]
    starts = np.flatnonzero(np.r_[True, sorted_leaf[1:] != sorted_leaf[:-1]])
    counts = np.diff(np.r_[starts, n])
    # Room for 100 more points than are counted: what lies past the count changes nothing.
    room = np.concatenate([points, rng.normal(size=(100, 3)).astype(np.float32)])
    centroids, majority = sbki_device.voxel_grid_on_device(
        Rows(wp.array(room, dtype=wp.vec3, device=device), wp.array([n], dtype=int, device=device)),
        wp.array(np.r_[labels, np.full(100, 3)], dtype=wp.int64, device=device), (0, 3), (room.min(axis=0), room.max(axis=0)), 0.1)
    np.testing.assert_array_equal(centroids.numpy(), twin.leaf_centroids(points, order, starts, counts))
    label_keys, _ = twin.leaf_label_keys(order, np.repeat(np.arange(1, len(starts) + 1), counts), labels, 0, 4)
    np.testing.assert_array_equal(majority.numpy()[:len(starts)], twin.leaf_majority_labels(np.sort(label_keys), np.r_[starts, n], len(starts), 0, 4))
    assert len(starts) < n  # leaves that hold several points, so the sums and the votes are tested


def test_leaf_runs_and_starts_on_one_point_and_on_one_leaf(device):
    # Over room for 3 more keys than are counted (keys past the count: the largest), and none counted.
    for sorted_leaf in ([5], [2, 2, 2], [0, 1, 1, 4, 4, 4, 9], []):
        room = np.r_[np.array(sorted_leaf, np.int64), np.full(3, np.iinfo(np.int64).max)]
        keys = wp.array(room, dtype=wp.int64, device=device)
        count = wp.array([len(sorted_leaf)], dtype=int, device=device)
        run_rank, starts, runs = sbki_device.runs_of_sorted(keys, len(room), count, DeviceScratch(device).begin())
        leaves = int(runs.numpy()[0])
        s = np.asarray(sorted_leaf)
        want = np.r_[np.flatnonzero(np.r_[True, s[1:] != s[:-1]]), len(s)] if len(s) else [0]
        np.testing.assert_array_equal(starts.numpy()[:leaves + 1], want)
        np.testing.assert_array_equal(run_rank.numpy()[len(s):], leaves)  # no run starts past the count


@pytest.mark.parametrize("free_res", [0.5, 4.0])
def test_training_data_of_bench_scans_matches_the_host_path(device, free_res):
    # Real scans of the shared benchmark workload (60 k points each; at free_res 0.5 ~0.7 M free samples).
    from conftest import shared_path

    data = np.load(shared_path("data", "bench", "rellis_like_30scans.npz"))
    offsets = data["scan_offsets"]
    for i in (0, 17):
        points = data["xyz_mm"][offsets[i]:offsets[i + 1]].astype(np.float32) / np.float32(1000)
        labels = data["label"][offsets[i]:offsets[i + 1]].astype(np.int64)
        origin = data["origins_mm"][i].astype(np.float32) / np.float32(1000)
        _assert_same(*_both(points, labels, origin, device, ds_resolution_m=0.1, free_resolution_m=free_res, max_range_m=None))


def _memberships_and_tables(points, block_size, length, device):
    labels = np.arange(len(points), dtype=np.int64) % 7
    ids, owners = sb.block_memberships(points, block_size)
    host = sb.gather_tables(owners)
    on_device = _rows(points, wp.vec3, device)
    device_ids, device_owners = sbki_device.block_memberships_on_device(on_device, block_size)
    owners_on_device = device_owners.numpy()
    np.testing.assert_array_equal(device_ids.numpy()[:len(owners_on_device)], ids)
    np.testing.assert_array_equal(owners_on_device, owners)
    tables = sbki_device.gather_tables_on_device(on_device, wp.array(labels, dtype=wp.int64, device=device), block_size, length)
    return ids, labels, host, tables


@pytest.mark.parametrize("block_depth", [1, 2, 3])
def test_memberships_and_gather_tables_match_the_host_path(device, block_depth):
    rng = np.random.default_rng(block_depth)
    block_size = sb.block_size_m(0.2, block_depth)
    points = (rng.normal(size=(5000, 3)) * 4).astype(np.float32)
    # On block faces and edges (members of 2, 4 and 8 blocks), and far from the origin.
    points[:30] = np.round(points[:30] / block_size) * block_size + block_size / np.float32(2)
    points[30:40, :2] = np.round(points[30:40, :2] / block_size) * block_size + block_size / np.float32(2)
    points[40:60] += np.float32(60_000.0)
    points = points[np.abs(points).max(axis=1) < 100] if block_depth == 1 else points  # a grid small enough for a dense lookup
    ids, labels, host, tables = _memberships_and_tables(points, block_size, 0.3, device)
    if tables is None:  # blocks 60 km apart: no dense grid, on the host as on the device
        assert sb.dense_block_grid(host.blocks)[0] is None
        points = points[np.abs(points).max(axis=1) < 100]
        ids, labels, host, tables = _memberships_and_tables(points, block_size, 0.3, device)
    tests, blocks, pairs = len(host.test_blocks), len(host.point_start) - 1, len(host.pair_order)
    np.testing.assert_array_equal(tables.test_blocks, host.test_blocks)
    np.testing.assert_array_equal(tables.tests.numpy()[:tests], host.test_blocks.astype(np.int32))
    np.testing.assert_array_equal(tables.sources.numpy()[:tests], host.sources)
    np.testing.assert_array_equal(tables.point_start.numpy()[:blocks + 1], host.point_start)
    sorted_points = ids[host.pair_order]
    from evsemmap_warp.kernels.block_gather import scale_points
    np.testing.assert_array_equal(tables.scaled_points.numpy()[:pairs], scale_points(points[sorted_points], 0.3))
    np.testing.assert_array_equal(tables.labels.numpy()[:pairs], labels[sorted_points])


def test_memberships_of_one_point_and_of_none(device):
    block_size = sb.block_size_m(0.2, 2)
    for points in (np.zeros((0, 3), np.float32), np.array([[0.2, 0.2, 0.2]], np.float32), np.array([[0.05, 1.0, -2.0]], np.float32)):
        ids, owners = sb.block_memberships(points, block_size)
        device_ids, device_owners = sbki_device.block_memberships_on_device(_rows(points, wp.vec3, device), block_size)
        np.testing.assert_array_equal(device_ids.numpy()[:len(ids)], ids)
        np.testing.assert_array_equal(device_owners.numpy().reshape(-1, 3), owners.reshape(-1, 3))


@pytest.mark.parametrize("workers, free_res, scans", [(1, 0.5, 3), (2, 4.0, 11)])
def test_a_map_from_the_device_preprocessing_is_the_host_paths_bit_for_bit(device, workers, free_res, scans):
    # The sbki mode of the benchmark (tools/bench_integrate.py) over bench scans, through the Mapper; 11
    # scans on 2 workers prepared ahead hold several scratch sets at once and reuse them.
    from conftest import shared_path

    from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings
    from evsemmap_warp.core.mapper import Mapper

    data = np.load(shared_path("data", "bench", "rellis_like_30scans.npz"))
    offsets = data["scan_offsets"]
    config = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                           compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                           sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=free_res, max_range_m=None))
    maps = []
    for on_device in (False, True):
        mapper = Mapper(config, 9, workers=workers, device=device)
        mapper.integrator.preprocess_on_device = on_device
        mapper.integrate_many([SimpleNamespace(points=(data["xyz_mm"][offsets[i]:offsets[i + 1]] / 1000.0).astype(np.float32),
                                               payload=data["label"][offsets[i]:offsets[i + 1]].astype(np.int64), payload_type="label",
                                               sensor_origin=data["origins_mm"][i] / 1000.0) for i in range(scans)])
        maps.append(mapper.voxels()[0])
    assert len(maps[0].index) > 10_000
    np.testing.assert_array_equal(maps[1].index, maps[0].index)
    np.testing.assert_array_equal(maps[1].rows(), maps[0].rows())


def test_blocks_whose_box_reaches_past_the_key_range_are_read_back_and_checked(device):
    # A far outlier that the range filter drops widens the box the host knows past the key range (+-209 km
    # at 0.2 m): the test blocks are then read back and checked themselves, and the map is the host path's.
    # A scan whose blocks do lie past it is refused on both paths, before anything is written.
    from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings
    from evsemmap_warp.core.mapper import Mapper

    rng = np.random.default_rng(31)
    origin = np.array([1.0, 2.0, 0.5])
    points = origin + rng.normal(size=(3000, 3)) * 4.0
    points[0] = [300_000.0, 5.0, 1.0]
    labels = rng.integers(0, 5, len(points))
    config = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                           compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                           sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=20.0))
    maps = []
    for on_device in (False, True):
        mapper = Mapper(config, 5, device=device, workers=1, origin=origin)
        mapper.integrator.preprocess_on_device = on_device
        read = []
        host = sbki_device.DeviceBlocks.host
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(sbki_device.DeviceBlocks, "host", lambda self: read.append(1) or host(self))
            with pytest.warns(UserWarning, match="returning it unchanged"):  # the hits' leaf grid spans 300 km: PCL leaves the cloud as it is
                mapper.integrate(points, labels, payload_type="label", sensor_origin=origin)
        assert read == ([1] if on_device else [])
        maps.append(mapper.voxels()[0])
        with pytest.raises(ValueError, match="outside the key range"), pytest.warns(UserWarning, match="returning it unchanged"):
            mapper.integrate(points + [250_000.0, 0.0, 0.0], labels, payload_type="label", sensor_origin=origin + [250_000.0, 0.0, 0.0])
        assert len(mapper.voxels()[0].index) == len(maps[-1].index)
    assert len(maps[0].index) > 1000
    np.testing.assert_array_equal(maps[1].index, maps[0].index)
    np.testing.assert_array_equal(maps[1].rows(), maps[0].rows())


def _bench_sbki(free_res):
    from conftest import shared_path

    from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings

    data = np.load(shared_path("data", "bench", "rellis_like_30scans.npz"))
    offsets = data["scan_offsets"]
    config = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                           compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                           sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=free_res, max_range_m=None))
    scans = [SimpleNamespace(points=(data["xyz_mm"][offsets[i]:offsets[i + 1]] / 1000.0).astype(np.float32),
                             payload=data["label"][offsets[i]:offsets[i + 1]].astype(np.int64), payload_type="label",
                             sensor_origin=data["origins_mm"][i] / 1000.0) for i in range(2)]
    return config, scans


@pytest.mark.parametrize("starved", [("FREE_ROWS_GUESS_PER_HIT",), ("PAIRS_GUESS_PER_POINT",), ("FREE_ROWS_GUESS_PER_HIT", "PAIRS_GUESS_PER_POINT")])
def test_a_scan_that_outgrows_its_reserved_room_is_redone_to_the_same_map(device, starved, monkeypatch):
    # Room for one free sample, or 16 pairs, or both: the first scan outgrows it, gathers nothing (its later
    # stages ran on what fitted), is built again (twice where the pairs of its cut training set fitted) and
    # gathered; the map is the host path's, and a later scan reads once.
    from test_host_reads import assert_outgrown_room_is_redone_to_the_host_map

    for name in starved:
        monkeypatch.setattr(sbki_device, name, 0)
    config, scans = _bench_sbki(4.0)
    assert_outgrown_room_is_redone_to_the_host_map(config, scans, device)


def test_a_scan_that_outgrows_its_room_and_takes_the_host_path_is_redone_first(device, monkeypatch):
    # Blocks too spread for the dense grid take the host path from the training set, read back: a training
    # set cut short by a stage that ran out of room is built again whole first.
    from evsemmap_warp.core.mapper import Mapper

    monkeypatch.setattr(sbki_device, "FREE_ROWS_GUESS_PER_HIT", 0)
    monkeypatch.setattr(sb, "MAX_DENSE_LOOKUP_CELLS", 10)
    config, scans = _bench_sbki(4.0)
    maps = []
    for on_device in (False, True):
        mapper = Mapper(config, 9, workers=1, device=device)
        mapper.integrator.preprocess_on_device = on_device
        kept = [stats.kept_points for stats in mapper.integrate_many(scans[:1])]
        maps.append((kept, mapper.voxels()[0]))
    assert maps[1][0] == maps[0][0]
    np.testing.assert_array_equal(maps[1][1].index, maps[0][1].index)
    np.testing.assert_array_equal(maps[1][1].rows(), maps[0][1].rows())


def test_a_scan_with_too_many_free_samples_is_refused_on_both_paths_and_writes_nothing(device, monkeypatch):
    # The limit lowered under the scan's free samples: the device path learns their count from its status
    # (the gather saw no block), and refuses the scan on its redo, as the host path refuses it up front.
    from evsemmap_warp.core.mapper import Mapper

    config, scans = _bench_sbki(4.0)
    for on_device in (False, True):
        mapper = Mapper(config, 9, workers=1, device=device)
        mapper.integrator.preprocess_on_device = on_device
        mapper.integrate_many(scans[1:])
        before = len(mapper.voxels()[0].index)
        monkeypatch.setattr(sb, "MAX_FREE_SAMPLES_PER_SCAN", 20_000)
        with pytest.raises(ValueError, match="free_resolution_m"):
            mapper.integrate_many(scans[:1])
        monkeypatch.undo()
        assert len(mapper.voxels()[0].index) == before


def test_free_samples_past_an_ints_range_are_counted_and_refused(device):
    # 600 hits 2,000 km out at free_res 0.5: 4 M samples each, 2.4 G in all, past an int's range (the
    # rows' prefix sum wraps); their total is summed in int64 too, so the scan is refused as on the host.
    from evsemmap_warp.core.mapper import Mapper

    config, _ = _bench_sbki(0.5)
    rng = np.random.default_rng(41)
    points = np.column_stack([2.0e6 + rng.uniform(0, 10, 600), rng.uniform(0, 10, (600, 2))]).astype(np.float32)
    labels = rng.integers(0, 5, 600)
    for on_device in (False, True):
        mapper = Mapper(config, 9, workers=1, device=device)
        mapper.integrator.preprocess_on_device = on_device
        with pytest.raises(ValueError, match="free_resolution_m"):
            mapper.integrate(points, labels, payload_type="label", sensor_origin=np.zeros(3))
        assert len(mapper.voxels()[0].index) == 0
