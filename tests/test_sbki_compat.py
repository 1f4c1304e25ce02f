"""The sbki compatibility mode, rule by rule on hand-built cases, against the block-centric brute
force, and against the original C++'s published results on the S-BKI toy scans."""

import warnings

import numpy as np
import pytest

from evsemmap_warp.methods import sbki_compat as sb
from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings, load_config
from evsemmap_warp.data.datasets import open_dataset
from evsemmap_warp.core.mapper import Mapper, VoxelState
from evsemmap_warp.data.pcd import read_pcd
from evsemmap_warp.reference.sbki import sbki_insert
from evsemmap_warp.voxel_keys import pack_voxel_keys, unpack_voxel_keys

from conftest import REPO, TOY_DIR, shared_path


def test_voxel_grid_majority_label_ties_and_centroid():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.01], [0.05, 0.02, 0.09],  # leaf (0,0,0)
                    [0.15, 0.0, 0.0], [0.11, 0.0, 0.0]], dtype=np.float32)           # leaf (1,0,0)
    labels = np.array([2, 1, 2, 3, 1])
    out, out_labels = sb.voxel_grid_downsample(pts, labels, 0.1)
    np.testing.assert_allclose(out, [[0.03, 0.08 / 3, 0.11 / 3], [0.13, 0, 0]], rtol=1e-6)
    assert out_labels.tolist() == [2, 1]  # majority 2; tie 3 vs 1 -> smallest label


def test_voxel_grid_with_one_label_equals_the_majority_path():
    rng = np.random.default_rng(8)
    pts = rng.uniform(-3, 3, (20000, 3)).astype(np.float32)
    one, one_labels = sb.voxel_grid_downsample(pts, np.full(len(pts), 4), 0.1)
    mixed_labels = np.full(len(pts), 4)
    mixed_labels[0] = 5  # forces the general path; leaf 0's majority is still 4 unless it holds one point
    mixed, general_labels = sb.voxel_grid_downsample(pts, mixed_labels, 0.1)
    np.testing.assert_array_equal(one, mixed)
    assert (one_labels == 4).all() and one_labels.dtype == general_labels.dtype
    assert (general_labels == 4).sum() >= len(general_labels) - 1


@pytest.mark.parametrize("offset", [0.0, -3.3, 1.5e5])
def test_leaf_index_kernel_matches_its_twin(offset):
    # Random points, points on leaf faces (multiples of the leaf) and their float32 neighbours, far
    # from zero; one point, and none.
    import warp as wp

    from evsemmap_warp.kernels import voxel_grid
    from evsemmap_warp.reference.voxel_grid import leaf_indices

    rng = np.random.default_rng(int(abs(offset)) + 1)
    inverse_leaf = np.float32(1.0) / np.float32(0.1)
    faces = (rng.integers(-50, 50, (300, 3)) * np.float32(0.1) + np.float32(offset)).astype(np.float32)
    points = np.concatenate([(rng.uniform(-5, 5, (2000, 3)) + offset).astype(np.float32), faces, np.nextafter(faces, np.float32(-np.inf))])
    for cloud in (points, points[:1], points[:0]):
        lowest = np.floor(cloud.min(axis=0) * inverse_leaf).astype(np.int64) if len(cloud) else np.zeros(3, np.int64)
        leaves = np.floor(cloud.max(axis=0) * inverse_leaf).astype(np.int64) - lowest + 1 if len(cloud) else np.ones(3, np.int64)
        out = wp.empty(len(cloud), dtype=wp.int64, device="cpu")
        wp.launch(voxel_grid.leaf_indices, dim=len(cloud), device="cpu", inputs=[
            wp.array(cloud, dtype=wp.vec3, device="cpu"), wp.array([len(cloud)], dtype=int, device="cpu"), float(inverse_leaf), *[int(x) for x in lowest],
            int(leaves[0]), int(leaves[1]), out])
        want = leaf_indices(cloud, inverse_leaf, lowest, int(leaves[0]), int(leaves[1]))
        np.testing.assert_array_equal(out.numpy(), want)
        assert len(cloud) == 0 or (want.min() >= 0 and want.max() < np.prod(leaves))


@pytest.mark.parametrize("offset", [0.0, 1.5e5])
def test_leaf_centroid_kernel_sums_as_pcl_in_order_from_zero(offset):
    # Bit for bit against its twin on leaves of every length up to 300, long leaves (the sensor origin's
    # leaf gathers one sample per hit), zeros of both signs, far coordinates; one leaf of one point, and
    # no leaves. The order matters: numpy's pairwise sums differ on many long leaves.
    import warp as wp

    from evsemmap_warp.kernels import voxel_grid
    from evsemmap_warp.reference.voxel_grid import leaf_centroids

    rng = np.random.default_rng(7)
    lengths = np.r_[np.arange(1, 301), [129, 136, 137, 1025, 1031, 4097, 28_000], rng.integers(1, 20, 3000)]
    rng.shuffle(lengths)
    n = int(lengths.sum())
    points = (rng.standard_normal((n, 3)) * 30 + offset).astype(np.float32)
    points[rng.random((n, 3)) < 0.02] = 0.0
    points[rng.random((n, 3)) < 0.02] = -0.0
    order = rng.permutation(n).astype(np.int64)
    starts = np.r_[0, np.cumsum(lengths)[:-1]].astype(np.int64)
    for case in ((points, order, starts, lengths), (points[:1], order[:1] * 0, starts[:1], lengths[:1] * 0 + 1),
                 (points[:0], order[:0], starts[:0], lengths[:0])):
        cloud, leaf_order, leaf_starts, leaf_counts = case
        out = wp.empty(len(leaf_starts), dtype=wp.vec3, device="cpu")
        wp.launch(voxel_grid.leaf_centroids, dim=1, device="cpu", inputs=[
            wp.array(cloud, dtype=wp.vec3, device="cpu"), wp.array(leaf_order, dtype=wp.int64, device="cpu"),
            wp.array(leaf_starts, dtype=wp.int64, device="cpu"), wp.array(leaf_counts.astype(np.int64), dtype=wp.int64, device="cpu"), out])
        want = leaf_centroids(cloud, leaf_order, leaf_starts, leaf_counts)
        np.testing.assert_array_equal(out.numpy().view(np.int32), want.view(np.int32))
    full = leaf_centroids(points, order, starts, lengths)
    long_leaves = np.flatnonzero(lengths > 8)
    pairwise = np.add.reduceat(points[order], starts, axis=0, dtype=np.float32)[long_leaves] / lengths[long_leaves, None].astype(np.float32)
    assert (pairwise != full[long_leaves]).any(axis=1).sum() > len(long_leaves) // 4


def test_the_sensor_origins_free_sample_drifts_as_pcls_does():
    # PCL's VoxelGrid adds a leaf's points one by one in float32: the 30,000 copies of a sensor origin
    # far from zero (one free sample per hit) sum to a centroid that is not the origin (here up to 9 mm
    # off), and the C++ trains on that point. A pairwise sum stays within a few ulp of the origin.
    origin = np.array([24.31, 40.73, 1.52], np.float32)
    copies = np.tile(origin, (30000, 1))
    centroid, _ = sb.voxel_grid_downsample(copies, np.zeros(len(copies), np.int64), 0.1)
    pcl = np.add.accumulate(copies, axis=0, dtype=np.float32)[-1] / np.float32(len(copies))
    np.testing.assert_array_equal(centroid[0], pcl)
    assert np.abs(centroid[0] - origin).max() > 5e-3


def test_voxel_grid_orders_leaves_x_fastest():
    pts = np.array([[0.0, 0.15, 0.0], [0.15, 0.0, 0.0], [0.0, 0.0, 0.15], [0.0, 0.0, 0.0]], dtype=np.float32)
    out, _ = sb.voxel_grid_downsample(pts, np.zeros(4, int), 0.1)
    np.testing.assert_array_equal(out, pts[[3, 1, 0, 2]])
    empty, lab = sb.voxel_grid_downsample(np.zeros((0, 3)), np.zeros(0, int), 0.1)
    assert empty.shape == (0, 3) and lab.shape == (0,)


def test_free_space_samples_follow_beam_sample():
    origin = np.array([1.0, 2.0, 0.5])
    hits = np.array([[2.2, 2.0, 0.5], [1.3, 2.0, 0.5], [1.0, 3.0, 0.5]])  # l = 1.2, 0.3, 1.0
    frees = sb.free_space_samples(hits, origin, 0.5)
    x = lambda d: [1.0 + d, 2.0, 0.5]  # noqa: E731
    y = lambda d: [1.0, 2.0 + d, 0.5]  # noqa: E731
    expected = [origin, x(0.5), x(1.0), x(0.7),  # samples at 0.5, 1.0 < 1.2, then l - f = 0.7
                origin,                         # l = 0.3 < f: the origin only
                origin, y(0.5), y(0.5)]         # d = 1.0 is not < l = 1.0; l - f = 0.5 once more
    np.testing.assert_allclose(frees, expected, atol=1e-6)


def _free_space_samples_numpy(hits, origin, f):
    """The vectorised numpy form the ray kernel replaced (repeat and fancy-index passes)."""
    hits, origin, f = np.asarray(hits, np.float32), np.asarray(origin, np.float32), np.float32(f)
    diff = hits - origin
    ray_length = np.sqrt(np.sum(diff * diff, axis=1, dtype=np.float32), dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = diff / ray_length[:, None]
    steps = [f]
    while steps[-1] < ray_length.max():
        steps.append(np.float32(steps[-1] + f))
    steps = np.array(steps, dtype=np.float32)
    per_hit = np.searchsorted(steps, ray_length, side="left")
    extra = ray_length > f
    starts = np.r_[0, np.cumsum(1 + per_hit + extra)[:-1]]
    out = np.empty((int((1 + per_hit + extra).sum()), 3), dtype=np.float32)
    out[starts] = origin
    hit_of_sample = np.repeat(np.arange(len(hits)), per_hit)
    step_of_sample = np.arange(len(hit_of_sample)) - np.repeat(np.r_[0, np.cumsum(per_hit)[:-1]], per_hit)
    out[starts[hit_of_sample] + 1 + step_of_sample] = origin + direction[hit_of_sample] * steps[step_of_sample][:, None]
    extra_hits = np.flatnonzero(extra)
    out[starts[extra_hits] + 1 + per_hit[extra_hits]] = origin + direction[extra_hits] * (ray_length[extra_hits] - f)[:, None]
    return out, (direction, ray_length, steps, per_hit, starts)


@pytest.mark.parametrize("f", [0.5, 4.0, 0.37])
def test_free_space_ray_kernel_matches_numpy_bit_for_bit(f):
    # Hits at the origin, closer than f, at exact multiples of f and just past them, far away.
    from evsemmap_warp.reference.free_space import ray_samples

    rng = np.random.default_rng(int(f * 100))
    origin = np.array([3.25, -1.5, 1.2], np.float32)
    hits = (origin + rng.normal(size=(3000, 3)) * rng.uniform(0, 25, (3000, 1))).astype(np.float32)
    hits[0] = origin
    hits[1] = origin + np.float32(f / 3)
    hits[2:5] = origin + np.float32(f) * np.array([[1, 0, 0], [0, 2, 0], [0, 0, 3]], np.float32)
    hits[5] = np.nextafter(hits[2], np.float32(np.inf))
    got = sb.free_space_samples(hits, origin, f)
    want, (direction, ray_length, steps, per_hit, starts) = _free_space_samples_numpy(hits, origin, f)
    np.testing.assert_array_equal(got, want)
    few = slice(0, 40)
    rows = int(starts[40]) if len(starts) > 40 else len(want)
    twin = ray_samples(direction[few], ray_length[few], origin, f, steps, per_hit[few], starts[few], rows)
    np.testing.assert_array_equal(twin, want[:rows])
    assert sb.free_space_samples(hits[:0], origin, f).shape == (0, 3)
    np.testing.assert_array_equal(sb.free_space_samples(hits[:1], origin, f), [origin])


def test_training_data_range_filter_and_free_label():
    pts = np.array([[1.0, 0, 0], [9.0, 0, 0]], dtype=np.float32)
    train, labels, info = sb.training_data(pts, np.array([2, 3]), np.zeros(3), ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=8.0)
    assert info["hits"] == 1 and labels[0] == 2 and (labels[1:] == 0).all()
    assert np.abs(train[1:, 0]).max() <= 1.0  # no samples towards the dropped 9 m hit


@pytest.mark.parametrize(
    "point, blocks",
    [
        ([0.1, 0.1, 0.1], [(0, 0, 0)]),
        ([0.2, 0.1, 0.1], [(0, 0, 0), (1, 0, 0)]),                    # on a face: both blocks
        ([0.2, 0.2, 0.1], [(0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 1, 0)]),  # on an edge: four
        ([-0.2, -0.2, -0.2], [(i, j, k) for i in (-1, 0) for j in (-1, 0) for k in (-1, 0)]),  # corner: eight
        ([-0.5, 0.0, 0.61], [(-1, 0, 2)]),
    ],
)
def test_block_membership_is_inclusive(point, blocks):
    ids, owners = sb.block_memberships(np.array([point], dtype=np.float32), sb.block_size_m(0.2, 2))
    assert sorted(map(tuple, owners)) == sorted(blocks) and (ids == 0).all()


def test_test_blocks_are_the_extended_blocks():
    tb = sb.test_blocks(np.array([[0, 0, 0], [0, 0, 0]]))
    assert len(tb) == 7 and {tuple(b) for b in tb} == {(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)}
    assert sb.test_blocks(np.zeros((0, 3), int)).shape == (0, 3)
    np.testing.assert_array_equal(sb.unique_rows(np.array([[2, -1, 5], [0, 0, 0], [2, -1, 5]])), [[0, 0, 0], [2, -1, 5]])


def _compat_config(counting: bool, **kw) -> MappingConfig:
    return MappingConfig(method="s-csm" if counting else "s-bki", kernel=Kernel.COUNT if counting else Kernel.SPARSE,
                         media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False, compat=Compat.SBKI, **kw)


@pytest.mark.parametrize("counting", [False, True])
def test_compat_insertion_matches_block_centric_brute_force(device, counting):
    rng = np.random.default_rng(int(counting))
    cfg = _compat_config(counting, resolution_m=0.1, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=3, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=8.0))
    pts = rng.uniform(0, 1.6, (300, 3)).astype(np.float32)
    pts[:5, 0] = np.float32(0.4)  # on block faces (and S-BKI's inclusive-box double counting)
    pts[5:10, 1] = np.float32(0.25) if counting else np.float32(0.8)
    labels = rng.integers(1, 4, 300)
    origin = np.array([0.8, 0.8, 0.1])
    mapper = Mapper(cfg, 4, device=device)
    mapper.integrate(pts, labels, payload_type="label", sensor_origin=origin)
    train, train_labels, _ = sb.training_data(pts, labels, origin, ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=8.0)
    expected = sbki_insert(train, train_labels, resolution_m=0.1, block_depth=1 if counting else 3, ell=0.3, sf2=10.0, counting=counting, num_classes=4)
    arrays, _ = mapper.voxels()
    assert {tuple(v) for v in arrays.index} == set(expected)
    want = np.array([expected[tuple(v)][0] for v in arrays.index])
    np.testing.assert_allclose(arrays.evidence, want, rtol=1e-4, atol=2e-5)
    np.testing.assert_array_equal(arrays.touched, [expected[tuple(v)][1] for v in arrays.index])


# ---------------------------------------------------------------------- the S-BKI toy example
def _toy_config(method):
    return load_config([REPO / "configs/datasets/sbki_toy.yaml"], method=method)


def test_toy_training_sets_match_the_cpp_per_scan():
    # docs/compatibility.md §1.5: VoxelGrid hits and training points per scan, from the C++.
    hits = [802, 1037, 436, 1313, 1103, 1202, 1141, 1373, 1099, 1105, 661, 1091]
    train = [2371, 2818, 702, 3659, 3511, 2859, 2612, 4470, 3745, 3701, 1603, 2606]
    for i in range(12):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cloud = read_pcd(TOY_DIR / f"sim_unstructured_annotated_{i + 1}.pcd")
        pts, _, info = sb.training_data(cloud.points, cloud.fields["label"], cloud.sensor_origin,
                                        ds_resolution_m=0.1, free_resolution_m=0.5, max_range_m=8.0)
        assert (info["hits"], len(pts)) == (hits[i], train[i]), f"scan {i + 1}"


def _map_toy(method):
    run = _toy_config(method)
    mapper = Mapper(run.mapping, 4)
    for scan in open_dataset(run.dataset):
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
    return mapper


def test_toy_scsm_reproduces_the_cpp_map_up_to_one_leafs_summation_order():
    # One training point differs (docs/compatibility.md §1.5): PCL sums its three-point leaf in the order
    # its std::sort leaves them, ours in input order, and the centroids fall on the two sides of a cell
    # face; that cell's count ties at FREE here and is OCCUPIED in the C++ map.
    mapper = _map_toy("s-csm")
    assert mapper.voxel_count == 64130
    assert mapper.state_counts() == {"UNKNOWN": 41329, "FREE": 15813 + 1, "OCCUPIED": 6988 - 1}
    arrays, summary = mapper.voxels()
    # S-CSM cells sit on the half-shifted grid: centers at multiples of 0.1 m.
    np.testing.assert_allclose(mapper.voxel_centers(arrays.index[:5]) / 0.1, np.round(mapper.voxel_centers(arrays.index[:5]) / 0.1), atol=1e-9)
    unknown = summary.state == VoxelState.UNKNOWN
    assert (arrays.evidence[unknown] == 0).all()  # created as test blocks, never updated


def test_toy_sbki_reproduces_the_cpp_map_up_to_near_ties():
    mapper = _map_toy("s-bki")
    assert mapper.voxel_count == 215936
    counts = mapper.state_counts()
    # docs/compatibility.md §1.3, §1.5: 163,872 FREE / 52,064 OCCUPIED; the authors' own float32
    # re-implementation flipped 10 near-tie cells, so a small band is allowed, nothing more.
    assert counts["UNKNOWN"] == 0
    assert abs(counts["FREE"] - 163872) <= 25 and abs(counts["OCCUPIED"] - 52064) <= 25
    arrays, summary = mapper.voxels()
    occupied = summary.label[summary.state == VoxelState.OCCUPIED]
    for cls, golden in ((1, 13353), (2, 24162), (3, 14549)):
        assert abs((occupied == cls).sum() - golden) <= 25
    prior_only = (arrays.evidence == 0).all(axis=1)
    assert prior_only.sum() >= 93000 and (summary.state[prior_only] == VoxelState.FREE).all()


def test_vendored_toy_scans_are_byte_identical_to_shared():
    shared = shared_path("data", "sbki_toy")
    for f in sorted(shared.glob("*.pcd")):
        assert (TOY_DIR / f.name).read_bytes() == f.read_bytes(), f.name


@pytest.mark.parametrize("counting", [False, True])
def test_compat_two_workers_give_the_single_worker_map(counting):
    rng = np.random.default_rng(8)
    cfg = _compat_config(counting, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.05, free_resolution_m=4.0))
    pts = rng.uniform(0, 8, (30000, 3)).astype(np.float32)  # >= 8192 training points: split in two
    labels = rng.integers(1, 6, len(pts))
    maps = []
    for workers in (1, 2):
        m = Mapper(cfg, 6, workers=workers)
        m.integrate(pts, labels, payload_type="label", sensor_origin=np.array([4.0, 4.0, 0.5]))
        maps.append(m)
    assert maps[1].shards[1].voxel_count > 0
    (a, sa), (b, sb) = maps[0].voxels(), maps[1].voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.touched, b.touched)
    assert (sa.state != sb.state).sum() <= 5  # near-ties only


@pytest.mark.parametrize("n", [1, 3, 400])
def test_sbki_gather_kernel_matches_its_table_twin(device, n):
    rng = np.random.default_rng(20 + n)
    pts = rng.uniform(0, 1.6, (n, 3)).astype(np.float32)
    pts[: max(1, n // 8), 0] = np.float32(0.2)  # on a block face: in two blocks
    labels = rng.integers(0, 4, n)
    cfg = _compat_config(False, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=100.0))
    mapper = Mapper(cfg, 4, device=device, origin=np.zeros(3))
    origin = np.array([0.8, 0.8, 1.5])
    mapper.integrate(pts, labels, payload_type="label", sensor_origin=origin)
    _assert_map_is_the_twins(mapper, _sbki_gather_twin(pts, labels, origin - mapper.origin)[1])


def _sbki_gather_twin(pts, labels, origin):
    """The gather tables of one scan (resolution 0.2, block depth 2, ell 0.3, sigma0 10, free_res 100)
    and the S-BKI gather twin's cells: index -> [K evidence, weight sum, hits]."""
    from evsemmap_warp.reference.block_gather import gather_sbki_blocks

    train, train_labels, _ = sb.training_data(pts, labels, origin, ds_resolution_m=0.1, free_resolution_m=100.0, max_range_m=None)
    ids, owners = sb.block_memberships(train, sb.block_size_m(0.2, 2))
    tables = sb.gather_tables(owners)
    order = ids[tables.pair_order]
    return tables, gather_sbki_blocks(tables.test_blocks, tables.sources, tables.point_start, train[order].astype(np.float64), train_labels[order],
                                      length=0.3, sigma0=10.0, resolution_m=0.2, cells_per_block=2, num_classes=4)


def _assert_map_is_the_twins(mapper, expected, scans: int = 1):
    """The mapper holds the twin's cells with ``scans`` times its sums (4 classes)."""
    arrays, _ = mapper.voxels()
    assert {tuple(v) for v in arrays.index} == set(expected)
    want = np.array([expected[tuple(v)] for v in arrays.index])
    np.testing.assert_allclose(arrays.evidence, scans * want[:, :4], rtol=1e-6, atol=1e-6)  # float32 trig: numpy vs C
    np.testing.assert_array_equal(arrays.hits, scans * want[:, 5])


def test_the_brick_cache_holds_blocks_with_consecutive_rows_only(device):
    # The gather kernels find a block through the brick cache when its cells' rows are consecutive in
    # cell order. Cells inserted before, one by one and out of order (as a loaded map's are), must be
    # found cell by cell instead: a cached first row would send their sums to other voxels. Two scans
    # of the same points (the second one finds every block it can in the cache) give twice the twin's
    # sums, and every cached block's cells have the rows the cache claims.
    rng = np.random.default_rng(31)
    pts = rng.uniform(0, 3.2, (3000, 3)).astype(np.float32)  # ~1500 test blocks: the cache grows from 16 slots
    labels = rng.integers(0, 4, len(pts))
    cfg = _compat_config(False, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=100.0))
    mapper = Mapper(cfg, 4, device=device, origin=np.zeros(3), workers=1)
    origin = np.array([1.6, 1.6, 3.5])
    tables, expected = _sbki_gather_twin(pts, labels, origin)
    cell_offsets = np.array([[j // 4, (j // 2) % 2, j % 2] for j in range(8)])
    scrambled = tables.test_blocks[::7]
    shard = mapper.shards[0]
    for block in scrambled:  # each block's cells in reverse order: consecutive rows, but not in cell order
        shard.insert_voxels(block * 2 - 1 + cell_offsets[::-1])
    for _ in range(2):
        mapper.integrate(pts, labels, payload_type="label", sensor_origin=origin)
    _assert_map_is_the_twins(mapper, expected, scans=2)

    brick_keys = shard.brick_keys.numpy()
    cached = np.flatnonzero(brick_keys != -1)
    first_cells = unpack_voxel_keys(brick_keys[cached])
    first_rows = shard.brick_rows.numpy()[cached].astype(np.int64) - 1
    for j, offset in enumerate(cell_offsets):
        np.testing.assert_array_equal(shard.insert_voxels(first_cells + offset), first_rows + j)
    assert not {tuple(b) for b in scrambled * 2 - 1} & {tuple(c) for c in first_cells}
    if device == "cpu":  # one thread inserts every other block's cells in order
        assert len(cached) == len(tables.test_blocks) - len(scrambled)
        assert shard.brick_capacity > 16


def test_a_maps_first_gather_is_sized_for_its_blocks_and_launched_once(monkeypatch):
    # Every cell is new in a map's first scan: the table is grown for all of its blocks' cells before
    # the launch, instead of relaunching the blocks that did not fit after each doubling.
    from evsemmap_warp.core.voxel_map import VoxelMap

    launches = []
    original = VoxelMap.launch_until_done

    def counted(self, n, launch, **kw):
        def counting(ids, failed):
            launches.append((kw["kind"], len(ids)))
            launch(ids, failed)
        return original(self, n, counting, **kw)

    monkeypatch.setattr(VoxelMap, "launch_until_done", counted)
    rng = np.random.default_rng(33)
    pts = rng.uniform(0, 12.0, (20000, 3)).astype(np.float32)  # ~20 k test blocks, 160 k cells: 2^16 slots would not do
    cfg = _compat_config(False, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=100.0))
    mapper = Mapper(cfg, 4, origin=np.zeros(3), workers=1)
    mapper.integrate(pts, rng.integers(0, 4, len(pts)), payload_type="label", sensor_origin=np.array([6.0, 6.0, 13.0]))
    gathers = [n for kind, n in launches if kind == "sbki_gather"]
    assert len(gathers) == 1 and mapper.voxel_count == 8 * gathers[0] > 65536 * 0.75


def test_the_float32_sbki_kernel_is_zero_where_the_gather_skips_points():
    # The gather kernel has no reach test of its own: it adds where the kernel is positive and skips
    # points at SBKI_ZERO_BEYOND ell or more from a block's cells. So the float32 kernel must not be
    # positive there: every float32 distance from 0.95 to 8 ell (beyond, (d - 1) / 3 alone outweighs
    # sin / (2 pi)). Its last positive value lies just below.
    import warp as wp

    from evsemmap_warp.kernels.block_gather import SBKI_ZERO_BEYOND
    from evsemmap_warp.kernels.scatter import sbki_sparse_kernel_scaled

    @wp.kernel(enable_backward=False)
    def kernel_at(distance: wp.array(dtype=float), value: wp.array(dtype=float)):
        i = wp.tid()
        value[i] = sbki_sparse_kernel_scaled(wp.vec3(distance[i], 0.0, 0.0), wp.vec3(0.0, 0.0, 0.0), 10.0)

    bits = np.arange(np.float32(0.95).view(np.int32), np.float32(8.0).view(np.int32), dtype=np.int32)
    last_positive = 0.0
    for chunk in np.array_split(bits, 8):
        distance = chunk.view(np.float32)
        value = wp.empty(len(distance), dtype=float, device="cpu")
        wp.launch(kernel_at, dim=len(distance), inputs=[wp.array(distance, dtype=float, device="cpu"), value], device="cpu")
        positive = distance[value.numpy() > 0]
        if len(positive):
            last_positive = max(last_positive, float(positive.max()))
    assert 0.98 < last_positive < SBKI_ZERO_BEYOND


def _random_sbki_scan(seed: int, n: int, extent: float, free_resolution_m: float):
    """A bench-like S-BKI config (0.2 m cells, 0.4 m blocks) and n random labelled points in an extent^3 cube."""
    rng = np.random.default_rng(seed)
    cfg = _compat_config(False, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
                         sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.05, free_resolution_m=free_resolution_m))
    pts = rng.uniform(0, extent, (n, 3)).astype(np.float32)
    return cfg, pts, rng.integers(1, 6, n)


def test_sbki_maps_are_bit_identical_for_one_and_two_workers():
    cfg, pts, labels = _random_sbki_scan(21, 30000, 8.0, free_resolution_m=4.0)
    rows = []
    for workers in (1, 2):
        m = Mapper(cfg, 6, workers=workers)
        m.integrate(pts, labels, payload_type="label", sensor_origin=np.array([4.0, 4.0, 0.5]))
        rows.append(m.voxels()[0])
    np.testing.assert_array_equal(rows[0].index, rows[1].index)
    np.testing.assert_array_equal(rows[0].rows(), rows[1].rows())
    assert rows[0].hits.sum() > 0 and not rows[0].weighted_height_sum.any()  # the original's rows: no heights kept


def test_every_form_of_the_sbki_gather_kernel_gives_the_same_map_bit_for_bit():
    # Branch-free or per-cell branches, with or without the prefetch: the forms the study times.
    import functools

    from evsemmap_warp.kernels import block_gather

    cfg, pts, labels = _random_sbki_scan(22, 20000, 6.0, free_resolution_m=2.0)
    maps = []
    for branch_free in (True, False):
        for prefetch in (True, False):
            m = Mapper(cfg, 6, workers=1)
            m.integrator.gather_kernel = functools.partial(block_gather.gather_sbki_kernel, branch_free=branch_free, prefetch=prefetch)
            m.integrate(pts, labels, payload_type="label", sensor_origin=np.array([3.0, 3.0, 0.5]))
            m.integrate(pts[::-1] + np.float32(0.07), labels[::-1], payload_type="label", sensor_origin=np.array([3.0, 3.0, 0.5]))
            maps.append(m.voxels()[0])
    assert maps[0].hits.sum() > 0
    for other in maps[1:]:
        np.testing.assert_array_equal(other.index, maps[0].index)
        np.testing.assert_array_equal(other.rows(), maps[0].rows())


@pytest.mark.parametrize("n, limit", [(0, 10), (1, 10), (5000, 7), (5000, 1 << 40), (3000, 1 << 62),
                                      (sb.MIN_RADIX_SORT_KEYS, 1), (sb.MIN_RADIX_SORT_KEYS, 2), (sb.MIN_RADIX_SORT_KEYS, 1000),
                                      (sb.MIN_RADIX_SORT_KEYS + 1, 1 << 26), (70_000, 1 << 45)])
def test_stable_sort_is_a_stable_argsort(n, limit):
    # numpy's sort for few keys, the radix kernels from MIN_RADIX_SORT_KEYS on (one to four passes, a
    # single key value, digits that skip passes), numpy's stable argsort where keys and positions do not fit.
    rng = np.random.default_rng(n + limit)
    keys = rng.integers(0, limit, n, dtype=np.int64)
    if n:
        keys[:: 7] = limit - 1  # the widest key, many ties
    got_keys, got_order = sb.stable_sort(keys, limit)
    want = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(got_order, want)
    np.testing.assert_array_equal(got_keys, keys[want])


def test_nonnegative_indices_are_the_indices_themselves():
    # The host loops index through kernels.indexing.nonnegative: every int from 0 to the largest is itself.
    import warp as wp

    from evsemmap_warp.kernels.indexing import nonnegative

    @wp.kernel(module="unique")
    def through_nonnegative(values: wp.array(dtype=int), out: wp.array(dtype=int)):
        i = wp.tid()
        out[i] = nonnegative(values[i])

    values = np.array([0, 1, 2, 255, 1 << 16, (1 << 30) + 7, np.iinfo(np.int32).max], np.int32)
    out = wp.empty(len(values), dtype=int, device="cpu")
    wp.launch(through_nonnegative, dim=len(values), device="cpu", inputs=[wp.array(values, dtype=int, device="cpu"), out])
    np.testing.assert_array_equal(out.numpy(), values)


@pytest.mark.parametrize("n, digit_bits", [(0, 4), (1, 4), (1000, 1), (3000, 7), (3000, 10)])
def test_radix_kernels_match_their_twins(n, digit_bits):
    import warp as wp

    from evsemmap_warp.kernels import radix_sort as kernels
    from evsemmap_warp.reference import radix_sort as twin

    rng = np.random.default_rng(n + digit_bits)
    lowest_bit, passes = 12, 3
    values = (rng.integers(0, 1 << (digit_bits * passes), n, dtype=np.int64) << lowest_bit) | rng.integers(0, 1 << lowest_bit, n)
    if n > 2:
        values[:2] = [0, ((1 << (digit_bits * passes)) - 1) << lowest_bit]  # the lowest and highest digits
    counts = wp.zeros((passes, 1 << digit_bits), dtype=int, device="cpu")
    wp.launch(kernels.digit_histograms, dim=1, device="cpu", inputs=[wp.array(values, dtype=wp.int64, device="cpu"), lowest_bit, digit_bits, passes,
                                                                     counts[0], counts[1], counts[2]])
    np.testing.assert_array_equal(counts.numpy(), twin.digit_histograms(values, lowest_bit, digit_bits, passes))
    for fewer in (1, 2):  # the arrays of passes not counted stay as they were
        partial = wp.zeros((3, 1 << digit_bits), dtype=int, device="cpu")
        wp.launch(kernels.digit_histograms, dim=1, device="cpu", inputs=[wp.array(values, dtype=wp.int64, device="cpu"), lowest_bit, digit_bits, fewer,
                                                                         partial[0], partial[1], partial[2]])
        np.testing.assert_array_equal(partial.numpy()[:fewer], twin.digit_histograms(values, lowest_bit, digit_bits, fewer))
        assert not partial.numpy()[fewer:].any()
    shift = lowest_bit + digit_bits
    next_slot = np.r_[0, np.cumsum(counts.numpy()[1][:-1])].astype(np.int32)
    out = wp.empty(n, dtype=wp.int64, device="cpu")
    wp.launch(kernels.radix_scatter, dim=1, device="cpu", inputs=[
        wp.array(values, dtype=wp.int64, device="cpu"), shift, digit_bits, wp.array(next_slot, dtype=int, device="cpu"), out])
    np.testing.assert_array_equal(out.numpy(), twin.radix_scatter(values, shift, digit_bits, next_slot))
    # The twin's sort is numpy's stable sort by the same bits.
    by_bits = (values >> lowest_bit) & ((1 << (digit_bits * passes)) - 1)
    np.testing.assert_array_equal(twin.radix_sort(values, lowest_bit, digit_bits, passes), values[np.argsort(by_bits, kind="stable")])


@pytest.mark.parametrize("n, limit", [(0, 10), (1, 10), (7, 1), (5000, 7), (sb.MIN_RADIX_SORT_KEYS + 1, 1 << 26)])
def test_sorted_runs_match_a_stable_argsort_and_their_twin(n, limit):
    # The host path's sort into runs (sbki_compat.sorted_runs: numpy's sort or the radix kernels, then one
    # pass for the order and the runs' starts): no values, one, one key for all, many ties, a wide key.
    import warp as wp

    from evsemmap_warp.kernels import radix_sort as kernels
    from evsemmap_warp.reference import radix_sort as twin

    rng = np.random.default_rng(n + limit)
    keys = rng.integers(0, limit, n, dtype=np.int64)
    position_bits, key_bits = sb._packing_bits(n, limit)
    packed = (keys << position_bits) | np.arange(n, dtype=np.int64)
    order, starts = sb.sorted_runs(packed, position_bits, key_bits)
    want = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(order, want)
    sorted_keys = keys[want]
    np.testing.assert_array_equal(starts, np.r_[np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])[:n], n])
    out_order, out_starts, runs = wp.empty(n, dtype=wp.int64, device="cpu"), wp.empty(n + 1, dtype=wp.int64, device="cpu"), wp.zeros(1, dtype=int, device="cpu")
    sorted_packed = np.sort(packed)
    wp.launch(kernels.sorted_runs, dim=1, device="cpu", inputs=[wp.array(sorted_packed, dtype=wp.int64, device="cpu"), position_bits, out_order, out_starts, runs])
    want_order, want_starts = twin.sorted_runs(sorted_packed, position_bits)
    np.testing.assert_array_equal(out_order.numpy(), want_order)
    np.testing.assert_array_equal(out_starts.numpy()[:runs.numpy()[0] + 1], want_starts)


def test_packed_key_kernels_match_their_twins():
    import warp as wp

    from evsemmap_warp.kernels import block_gather, voxel_grid
    from evsemmap_warp.reference import block_gather as gather_twin
    from evsemmap_warp.reference import voxel_grid as grid_twin

    rng = np.random.default_rng(12)
    for n in (1, 3000):
        points = (rng.uniform(-5, 5, (n, 3)) + 150_000.0).astype(np.float32)  # far out: float32 leaves of 1.5 cm spacing
        inverse_leaf = np.float32(1) / np.float32(0.1)
        lowest = np.floor(points.min(axis=0) * inverse_leaf).astype(np.int64)
        dims = np.floor(points.max(axis=0) * inverse_leaf).astype(np.int64) - lowest + 1
        position_bits = max(1, int(n - 1).bit_length())
        packed = wp.empty(n, dtype=wp.int64, device="cpu")
        wp.launch(voxel_grid.packed_leaf_indices, dim=n, device="cpu", inputs=[
            wp.array(points, dtype=wp.vec3, device="cpu"), float(inverse_leaf), wp.vec3l(*lowest.tolist()), int(dims[0]), int(dims[1]), position_bits, packed])
        np.testing.assert_array_equal(packed.numpy(), grid_twin.packed_leaf_indices(points, inverse_leaf, lowest, dims[0], dims[1], position_bits))
        blocks = rng.integers(-300, 300, (n, 3)).astype(np.int64)
        lo, span = blocks.min(axis=0), blocks.max(axis=0) - blocks.min(axis=0) + 1
        wp.launch(block_gather.packed_box_positions, dim=n, device="cpu", inputs=[
            wp.array(blocks, dtype=wp.int64, device="cpu"), wp.vec3l(*lo.tolist()), int(span[1]), int(span[2]), position_bits, packed])
        np.testing.assert_array_equal(packed.numpy(), gather_twin.packed_box_positions(blocks, lo, int(span[1]), int(span[2]), position_bits))


@pytest.mark.parametrize("n", [0, 1, 3000])
def test_centroids_of_sorted_packed_leaves_match_their_twin(n):
    # Long leaves (one point many times, far out: float32 drift as PCL sums), one-point leaves, none.
    import warp as wp

    from evsemmap_warp.kernels import voxel_grid
    from evsemmap_warp.reference import voxel_grid as twin

    rng = np.random.default_rng(n + 3)
    points = (rng.normal(size=(n, 3)) * 3 + 80_000.0).astype(np.float32)
    points[: n // 3] = points[0] if n else points[: n // 3]
    leaf = rng.integers(0, max(1, n // 5), n).astype(np.int64)
    leaf[: n // 3] = 7
    position_bits = max(1, int(n - 1).bit_length())
    packed = np.sort((leaf << position_bits) | np.arange(n, dtype=np.int64))
    centroids, leaves = wp.empty(n, dtype=wp.vec3, device="cpu"), wp.zeros(1, dtype=int, device="cpu")
    wp.launch(voxel_grid.leaf_centroids_of_sorted, dim=1, device="cpu", inputs=[
        wp.array(points, dtype=wp.vec3, device="cpu"), wp.array(packed, dtype=wp.int64, device="cpu"), position_bits, centroids, leaves])
    want = twin.leaf_centroids_of_sorted(points, packed, position_bits)
    assert leaves.numpy()[0] == len(want) == len(np.unique(leaf))
    np.testing.assert_array_equal(centroids.numpy()[:len(want)], want)


def test_group_by_block_matches_the_unique_form_near_and_across_the_key_range():
    rng = np.random.default_rng(4)
    near = rng.integers(-5, 5, (3000, 3))
    spread = np.concatenate([near, [[2**20 - 1, -2**20, 7], [-2**20, 2**20 - 1, -7]]])  # a box of ~2^63 cells
    for members in (near, spread, near[:1], np.zeros((0, 3), np.int64)):
        blocks, keys, order, start = sb.group_by_block(members)
        want_keys, inverse = np.unique(pack_voxel_keys(members), return_inverse=True)
        np.testing.assert_array_equal(keys, want_keys)
        np.testing.assert_array_equal(blocks, unpack_voxel_keys(want_keys).reshape(-1, 3))
        np.testing.assert_array_equal(order, np.argsort(inverse.reshape(-1), kind="stable"))
        np.testing.assert_array_equal(start, np.r_[0, np.cumsum(np.bincount(inverse.reshape(-1), minlength=len(want_keys)))])


def test_gather_tables_hold_every_test_block_and_its_sources():
    # Blocks spread over the whole key range (no dense grid could hold them) and clustered ones.
    rng = np.random.default_rng(5)
    for members in (rng.integers(-9, 9, (2000, 3)), rng.integers(-(1 << 19), 1 << 19, (300, 3))):
        tables = sb.gather_tables(members)
        np.testing.assert_array_equal(tables.test_blocks, sb.test_blocks(members))
        index_of = {tuple(b): i for i, b in enumerate(tables.blocks.tolist())}
        want = [[index_of.get(tuple(t + o), -1) for o in sb.EXTENDED_BLOCK_OFFSETS.tolist()] for t in tables.test_blocks]
        np.testing.assert_array_equal(tables.sources, want)
        assert tables.sources.dtype == np.int32


@pytest.mark.parametrize("offset", [0.0, -7.3, 2.5e4])
def test_block_membership_kernel_matches_its_twin(offset):
    # Random points, points on block faces, edges and corners and their float32 neighbours on both
    # sides, far from zero; one point, and none.
    import warp as wp

    from evsemmap_warp.kernels import block_membership
    from evsemmap_warp.reference.block_membership import block_membership_masks

    rng = np.random.default_rng(int(abs(offset)) + 3)
    size = sb.block_size_m(0.2, 2)
    faces = ((rng.integers(-30, 30, (500, 3)) + round(offset / size) + np.float32(0.5)) * size).astype(np.float32)
    points = np.concatenate([(rng.uniform(-6, 6, (3000, 3)) + offset).astype(np.float32), faces,
                             np.nextafter(faces, np.float32(np.inf)), np.nextafter(faces, np.float32(-np.inf))])
    for cloud in (points, points[:1], points[:0]):
        nearest = wp.empty((len(cloud), 3), dtype=wp.int64, device="cpu")
        masks = wp.empty(len(cloud), dtype=int, device="cpu")
        wp.launch(block_membership.block_membership_masks, dim=1, device="cpu", inputs=[
            wp.array(cloud, dtype=wp.vec3, device="cpu"), float(size), nearest, masks])
        want_nearest, want_masks = block_membership_masks(cloud, size)
        np.testing.assert_array_equal(nearest.numpy(), want_nearest)
        np.testing.assert_array_equal(masks.numpy(), want_masks)
    _, all_masks = block_membership_masks(points, size)
    assert (all_masks != 1 << block_membership.NEAREST_BIT).sum() >= 200  # many face points lie in several blocks


@pytest.mark.parametrize("offset", [0.0, 2.5e4])
def test_membership_pair_kernels_match_their_twin(offset):
    # The pairs of every mask, in the twin's order (shift by shift, points ascending): mostly single
    # memberships, with face, edge and corner points in 2, 4 and 8 blocks; one point, and none.
    import warp as wp

    from evsemmap_warp.kernels import block_membership
    from evsemmap_warp.reference.block_membership import block_membership_masks, membership_counts, membership_pairs

    rng = np.random.default_rng(int(offset) + 5)
    size = sb.block_size_m(0.2, 2)
    corners = ((rng.integers(-30, 30, (200, 3)) + round(offset / size) + np.float32(0.5)) * size).astype(np.float32)
    edges, faces = corners.copy(), corners.copy()
    edges[:, 2] += np.float32(0.05)
    faces[:, 1:] += np.float32(0.05)
    points = np.concatenate([(rng.uniform(-6, 6, (3000, 3)) + offset).astype(np.float32), corners, edges, faces])
    points = points[rng.permutation(len(points))]
    for cloud in (points, points[:1], points[:0]):
        nearest, masks = block_membership_masks(cloud, size)
        counts = wp.zeros(27, dtype=int, device="cpu")
        masks_wp = wp.array(masks.astype(np.int32), dtype=int, device="cpu")
        wp.launch(block_membership.membership_counts, dim=1, device="cpu", inputs=[masks_wp, counts])
        counts = counts.numpy()
        np.testing.assert_array_equal(counts, membership_counts(masks))
        ids = wp.empty(int(counts.sum()), dtype=wp.int64, device="cpu")
        blocks = wp.empty((int(counts.sum()), 3), dtype=wp.int64, device="cpu")
        wp.launch(block_membership.membership_pairs, dim=1, device="cpu", inputs=[
            masks_wp, wp.array(nearest, dtype=wp.int64, device="cpu"), wp.array(np.r_[0, np.cumsum(counts[:-1])].astype(np.int32), dtype=int, device="cpu"),
            ids, blocks])
        want_ids, want_blocks = membership_pairs(nearest, masks)
        np.testing.assert_array_equal(ids.numpy(), want_ids)
        np.testing.assert_array_equal(blocks.numpy(), want_blocks)
    memberships = np.bincount(np.bitwise_count(block_membership_masks(points, size)[1]))
    assert memberships[2] and memberships[4] and memberships[8]  # faces, edges and corners all occur


@pytest.mark.parametrize("case", ["none", "one", "two", "random", "neighbours", "key range", "far"])
def test_extended_block_table_kernels_match_their_twins(case):
    # The merge of the shifted runs against the twins' block-by-block lookups: no block, one, two,
    # random blocks, a dense cluster whose test blocks are shared by many blocks, blocks at the key
    # range's far corners (their box packs in 62 bits at block depth 2) and blocks beyond it, whose box
    # does not pack (the host takes the wide kernel); no grid over the box in either.
    import warp as wp

    from evsemmap_warp.kernels import block_gather
    from evsemmap_warp.reference.block_gather import extended_block_tables, extended_block_tables_wide

    assert block_gather.EXTENDED_BLOCK_COUNT == len(sb.EXTENDED_BLOCK_OFFSETS)
    rng = np.random.default_rng(len(case))
    edge = 1 << 19
    blocks = {
        "none": np.zeros((0, 3)), "one": np.array([[3, -2, 7]]), "two": np.array([[0, 0, 0], [0, 0, 2]]),
        "random": rng.integers(-40, 40, (500, 3)), "neighbours": rng.integers(-3, 3, (300, 3)),
        "key range": np.array([[-edge, -edge, -edge], [edge - 1, 5, -edge], [edge - 1, edge - 1, edge - 1]]),
        "far": np.array([[-edge, -edge, -edge], [1 << 40, -(1 << 40), 3]]),
    }[case].astype(np.int64)
    blocks = np.unique(blocks, axis=0).reshape(-1, 3)  # distinct, in key order
    offsets = sb.EXTENDED_BLOCK_OFFSETS
    most = max(1, len(blocks) * len(offsets))
    want_tests, want_sources = extended_block_tables_wide(blocks, offsets)
    assert len(blocks) == 0 or len(want_tests) > len(blocks)

    tests = wp.empty(most, dtype=wp.vec3l, device="cpu")
    sources = wp.empty((most, len(offsets)), dtype=int, device="cpu")
    n = wp.zeros(1, dtype=int, device="cpu")
    wp.launch(block_gather.extended_block_tables_wide, dim=1, device="cpu", inputs=[
        wp.array(blocks, dtype=wp.vec3l, device="cpu"), wp.array(offsets, dtype=wp.vec3l, device="cpu"),
        wp.zeros(len(offsets), dtype=int, device="cpu"), tests, sources, n])
    got = int(n.numpy()[0])
    np.testing.assert_array_equal(tests.numpy()[:got].reshape(-1, 3), want_tests)
    np.testing.assert_array_equal(sources.numpy()[:got], want_sources)

    if case != "far" and len(blocks):  # packed in the box widened by one
        lo = blocks.min(axis=0) - 1
        span = blocks.max(axis=0) + 2 - lo
        keys = ((blocks[:, 0] - lo[0]) * span[1] + blocks[:, 1] - lo[1]) * span[2] + blocks[:, 2] - lo[2]
        shifts = (offsets[:, 0] * span[1] + offsets[:, 1]) * span[2] + offsets[:, 2]
        last = int(keys[-1] + np.abs(shifts).max())
        packed = wp.empty(most, dtype=wp.int64, device="cpu")
        n.zero_()
        wp.launch(block_gather.extended_block_tables, dim=1, device="cpu", inputs=[
            wp.array(np.append(keys, last + 2 * np.abs(shifts).max() + 1), dtype=wp.int64, device="cpu"),
            wp.array(shifts, dtype=wp.int64, device="cpu"), last, packed, sources, n])
        got = int(n.numpy()[0])
        want_keys, want_packed_sources = extended_block_tables(keys, shifts)
        np.testing.assert_array_equal(packed.numpy()[:got], want_keys)
        np.testing.assert_array_equal(sources.numpy()[:got], want_packed_sources)
        np.testing.assert_array_equal(want_packed_sources, want_sources)

    host_tests, host_sources = sb._extended_block_tables(blocks)  # the host picks its kernel by the box
    np.testing.assert_array_equal(host_tests, want_tests)
    np.testing.assert_array_equal(host_sources, want_sources)
    assert host_sources.dtype == np.int32


def test_block_memberships_match_the_27_box_tests():
    # Points on faces, edges and corners (and rounding near them) take the slow path; the order of
    # the pairs (shift by shift, points ascending) decides the kernel's summation order.
    rng = np.random.default_rng(6)
    size = sb.block_size_m(0.2, 2)
    on_grid = ((rng.integers(-20, 20, (400, 3)) + np.float32(0.5)) * size).astype(np.float32)  # block faces
    nudged = np.nextafter(on_grid, np.float32(np.inf))
    mixed = np.where(rng.random((400, 3)) < 0.5, on_grid, rng.uniform(-8, 8, (400, 3))).astype(np.float32)
    points = np.concatenate([rng.uniform(-8, 8, (3000, 3)).astype(np.float32), on_grid, nudged, mixed])
    rng.shuffle(points)
    ids, blocks = sb.block_memberships(points, size)
    half = np.float32(size / np.float32(2.0))
    nearest = np.floor(points.astype(np.float64) / np.float64(size) + 0.5).astype(np.int64)
    want_ids, want_blocks = [], []
    for shift in [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)]:
        k = nearest + np.array(shift)
        center = (k.astype(np.float32) * size).astype(np.float32)
        inside = ((center - half <= points) & (points <= center + half)).all(axis=1)
        want_ids.append(np.flatnonzero(inside))
        want_blocks.append(k[inside])
    np.testing.assert_array_equal(ids, np.concatenate(want_ids))
    np.testing.assert_array_equal(blocks, np.concatenate(want_blocks))
    assert len(ids) > len(points) + 400  # the face points were counted in several blocks


def test_majority_labels_dense_table_and_sorted_pairs_agree(monkeypatch):
    rng = np.random.default_rng(9)
    cells = np.sort(rng.integers(0, 400, 5000))
    labels = rng.integers(3, 9, 5000)
    labels[cells == 7] = 5  # a cell with one label only
    dense = sb._majority_labels(cells, labels, 400)
    monkeypatch.setattr(sb, "MAX_DENSE_LABEL_COUNTS", 0)
    pairs = sb._majority_labels(cells, labels, 400)
    np.testing.assert_array_equal(dense, pairs)
    for c in rng.choice(np.unique(cells), 50):
        values, counts = np.unique(labels[cells == c], return_counts=True)
        assert dense[c] == values[np.argmax(counts)]  # most frequent, smallest on ties


def test_the_benchmark_workload_maps_as_the_original_cpp_does():
    # The bench's like-for-like claim on the real workload: the sbki mode at free_res 100, fed the
    # workload's S-BKI labels, makes the C++ S-BKI's cells, and its states differ from the C++ map's in a
    # few dozen of 608 k cells: prior-level near-ties, where float32 noise in tiny kernel values at the
    # edge of the support decides the argmax (Eigen's vectorised sin/cos in the C++, correctly rounded
    # ones here). The release mode makes the released EvSemMap's counts exactly.
    import json
    import sys

    shared_path("data", "bench", "rellis_like_30scans.npz")
    sys.path.insert(0, str(REPO / "tools"))
    import bench_integrate

    cpp = json.loads((REPO / "docs" / "cpp_side_by_side.json").read_text())
    dataset, scans = bench_integrate.load_scans()
    labels = bench_integrate.sbki_labels(dataset)
    mapper = Mapper(bench_integrate.compat_config(100.0), 9, workers=1)
    for scan, label in zip(scans, labels):
        mapper.integrate(scan.points, label, payload_type="label", sensor_origin=scan.sensor_origin)
    want = cpp["sbki_original"]["results"]["fr100_t1"]
    states = mapper.state_counts()
    assert mapper.voxel_count == want["cells"] == 608_176
    assert abs(states["FREE"] - want["free"]) <= 60 and abs(states["OCCUPIED"] - want["occupied"]) <= 60 and states["UNKNOWN"] == 0

    release = load_config([REPO / "configs/presets/release.yaml"], method="ebs").mapping
    mapper = Mapper(release, 9, workers=1)
    kept = 0
    for scan in scans:
        kept += mapper.integrate(scan.points, scan.payload, payload_type="alpha", sensor_origin=scan.sensor_origin).kept_points
    want = cpp["evsemmap"]["results"]["ebs_t1"]
    assert (kept, mapper.voxel_count, mapper.state_counts()["OCCUPIED"]) == (want["after_ds"], want["cells"], want["occupied"])


def test_boxes_whose_cell_count_passes_int64_are_refused_not_wrapped():
    # 9e6 leaves per axis: 7.3e20 cells, which numpy's int64 product wrapped to a count small enough to
    # pass; a leaf grid that large is refused (PCL leaves the cloud unchanged), and so is a dense lookup
    # grid over blocks spread over the whole key range.
    with pytest.warns(UserWarning, match="too small"):
        assert sb.leaf_grid(np.full(3, -10.0, np.float32), np.full(3, 9e5, np.float32), 0.1) is None
    spread = np.array([[-(1 << 20), -(1 << 20), -(1 << 20)], [(1 << 20) - 1, (1 << 20) - 1, (1 << 20) - 1]])
    grid, lo = sb.dense_block_grid(spread)
    assert grid is None and lo.tolist() == [-(1 << 20) - 3] * 3
