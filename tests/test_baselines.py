"""ConvBKI, SEE-CSOM and the Dempster-Shafer variant: kernels against their numpy twins, hand-checked
rules, a dense conv3d, the sequential Dempster reference, and the map file / viewer round trip."""

import dataclasses

import numpy as np
import pytest
import torch

from evsemmap_warp.methods import convbki, see_csom
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.core.mapper import load_map, save_map
from evsemmap_warp.core.mapper import Mapper, VoxelState
from evsemmap_warp.reference import dempster as dempster_ref
from evsemmap_warp.reference import scatter as ref
from evsemmap_warp.core.integrators.convbki import scatter_stencil
from evsemmap_warp.core.integrators.see_csom import scatter_block_targets
from evsemmap_warp.core.voxel_map import VoxelMap
from test_scatter import _compare


def offroad(method, **changes):
    config = load_config(["configs/presets/offroad.yaml"], method=method).mapping
    return dataclasses.replace(config, **changes)


# --- ConvBKI --------------------------------------------------------------------------------------
def test_compound_stencil_weights_by_hand():
    lengths = convbki.ConvBkiLengths(np.array([0.5, 1.0]), np.array([0.5, 0.25]))
    w = convbki.stencil_weights(lengths, 0.2, 2)
    offsets = convbki.stencil_offsets(2)
    row = {tuple(o): i for i, o in enumerate(offsets)}

    def k(d, l):
        r = d / l
        return 0.0 if r >= 1 else (2 + np.cos(2 * np.pi * r)) * (1 - r) / 3 + np.sin(2 * np.pi * r) / (2 * np.pi)

    assert w[row[(0, 0, 0)]].tolist() == [1.0, 1.0]
    np.testing.assert_allclose(w[row[(1, 1, 0)]], [k(0.2 * np.sqrt(2), 0.5), k(0.2 * np.sqrt(2), 1.0)])
    np.testing.assert_allclose(w[row[(0, 0, 2)]], [k(0.4, 0.5), k(0.4, 0.25)])  # class 1: 0.4 m is beyond 0.25 m
    assert w[row[(0, 0, 2)]][1] == 0.0 and w.shape == (125, 2)


def test_stencil_kernel_matches_twin(device):
    rng = np.random.default_rng(3)
    k = 5
    points = rng.uniform(-1.5, 1.5, (300, 3))
    points[:20] = np.round(points[:20] / 0.2) * 0.2  # on voxel faces
    weights = rng.dirichlet(np.ones(k), len(points))
    table = convbki.stencil_weights(convbki.ConvBkiLengths(rng.uniform(0.1, 0.6, k), rng.uniform(0.1, 0.6, k)), 0.2, 2)
    unc = rng.uniform(0, 1, len(points))
    vm = VoxelMap(k, 0.2, device=device, initial_capacity=64)  # grows during the launch
    updates = scatter_stencil(vm, points, np.full(len(points), 0.2), unc, weights, table)
    _compare(vm, updates, ref.scatter_points(points, None, weights, np.full(len(points), 0.2), unc, None, ref.MODE_STENCIL, 0.2, 0.0, 1.0, 1, k,
                                             stencil_weights=table))
    empty = VoxelMap(k, 0.2, device=device)
    assert scatter_stencil(empty, np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros((0, k)), table) == 0


def test_convbki_map_equals_a_dense_depthwise_conv3d():
    """docs/compatibility.md §2.2: the scatter equals its authors' dense conv3d of the voxelised evidence."""
    rng = np.random.default_rng(0)
    k, res = 4, 0.25
    lengths = convbki.ConvBkiLengths(rng.uniform(0.2, 0.7, k), rng.uniform(0.2, 0.7, k))
    path_config = dataclasses.replace(offroad("convbki"), resolution_m=res, prior=1e-3)
    mapper = Mapper(path_config, k, workers=1)
    mapper.integrator.lengths = lengths
    mapper.integrator.weights = convbki.stencil_weights(lengths, res, 2)
    points = rng.uniform(0.0, 2.0, (400, 3))
    probs = rng.dirichlet(np.ones(k), len(points))
    mapper.integrate(points, probs, payload_type="prob")
    grid = np.zeros((k, 12, 12, 12))
    voxels, summed = convbki.voxelise(points, probs, res)
    grid[:, voxels[:, 0] + 2, voxels[:, 1] + 2, voxels[:, 2] + 2] = summed.T  # 2 voxels of margin
    filters = torch.as_tensor(convbki.stencil_weights(lengths, res, 2).T.reshape(k, 1, 5, 5, 5))
    dense = torch.nn.functional.conv3d(torch.as_tensor(grid)[None], filters, padding=2, groups=k)[0].numpy()
    arrays, _ = mapper.voxels()
    np.testing.assert_allclose(arrays.evidence, dense[:, arrays.index[:, 0] + 2, arrays.index[:, 1] + 2, arrays.index[:, 2] + 2].T, rtol=1e-4, atol=1e-5)
    assert (dense.sum(axis=0) > 0).sum() == len(arrays.index)  # exactly the voxels that receive evidence


def test_length_files_load_and_bad_ones_name_the_problem(tmp_path):
    torch.save({"ell_h": torch.full((9,), 0.7), "ell_z": torch.full((9,), 0.4)}, tmp_path / "Epoch1.pt")
    loaded = convbki.load_lengths(tmp_path / "Epoch1.pt", 9)
    assert loaded.horizontal.tolist() == pytest.approx([0.7] * 9) and loaded.vertical.tolist() == pytest.approx([0.4] * 9)
    convbki.save_lengths(tmp_path / "l.json", loaded)
    assert convbki.load_lengths(tmp_path / "l.json", 9).vertical.tolist() == pytest.approx([0.4] * 9)
    with pytest.raises(ValueError, match="l.json: ell_h has 9 values, the map has 15 classes"):
        convbki.load_lengths(tmp_path / "l.json", 15)
    (tmp_path / "bad.yaml").write_text("ell_h: [1, 2]\n")
    with pytest.raises(ValueError, match="bad.yaml: expected the keys ell_h and ell_z"):
        convbki.load_lengths(tmp_path / "bad.yaml", 2)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        Mapper(offroad("convbki").replace(convbki={"lengths_file": str(tmp_path / "missing.pt")}), 9)


def test_training_moves_lengths_and_lowers_the_loss():
    """A world of two class slabs: smoothing within a slab helps, so the loss falls."""
    rng = np.random.default_rng(1)
    windows = []
    for _ in range(3):
        points = rng.uniform(0, 3, (1500, 3))
        labels = np.where(points[:, 2] > 1.5, 2, 1)
        probs = np.full((len(points), 3), 0.1)
        probs[np.arange(len(points)), labels] = 0.8
        probs[rng.random(len(points)) < 0.3] = [0.1, 0.45, 0.45]  # ambiguous points
        windows.append(convbki.TrainingWindow(points, probs, points[:300], labels[:300]))
    lengths, history = convbki.train_lengths(windows, 3, 0.2, epochs=6, progress=False)
    assert history[-1] < history[0]
    assert (lengths.horizontal >= 0.01).all() and (lengths.horizontal <= 1.0).all()
    # the differentiable evidence equals the map's at the query voxels
    mapper = Mapper(dataclasses.replace(offroad("convbki"), resolution_m=0.2, prior=1e-6), 3, workers=1)
    mapper.integrator.weights = convbki.stencil_weights(lengths, 0.2, 2)
    mapper.integrate(windows[0].points, windows[0].evidence, payload_type="prob")
    voxels, summed = convbki.voxelise(windows[0].points, windows[0].evidence, 0.2)
    query = np.floor(windows[0].query_points / 0.2).astype(np.int64)
    torch_evidence = convbki.stencil_evidence_at(torch.as_tensor(query), torch.as_tensor(voxels), torch.as_tensor(summed),
                                                 torch.as_tensor(lengths.horizontal), torch.as_tensor(lengths.vertical), 0.2, 2).numpy()
    probabilities = mapper.query(windows[0].query_points).probabilities
    np.testing.assert_allclose(probabilities, (torch_evidence + 1e-6) / (torch_evidence + 1e-6).sum(1, keepdims=True), rtol=1e-3, atol=1e-5)


# --- SEE-CSOM -------------------------------------------------------------------------------------
def test_block_entropy_matches_the_quoted_values():
    c = 21  # SemanticKITTI's class count in SEE-CSOM
    h = see_csom.block_entropy(np.array([[10] + [0] * 20, [8, 2] + [0] * 19, [7, 3] + [0] * 19, [5, 5] + [0] * 19]), c)
    np.testing.assert_allclose(h, [0.0, 0.21, 0.31, 0.51], atol=0.005)


def test_block_targets_by_hand():
    res, c = 0.5, 4
    # block b covers voxels 2b - 1, 2b: with res 0.5 block (0,0,0) spans [-0.5, 0.5) on each axis
    pure = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1]])  # block (0,0,0), both class 1
    mixed = np.array([[1.1, 0.1, 0.1], [1.2, 0.1, 0.1]])  # block (1,0,0), classes 1 and 2
    far = np.array([[0.1, 2.1, 0.1]])  # block (0,2,0): makes block (0,1,0) sandwiched
    points = np.concatenate([pure, mixed, far])
    labels = np.array([1, 1, 1, 2, 3])
    owners, lengths = see_csom.block_targets(points, labels, c, res)
    assert owners.tolist() == [[0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 2, 0]]
    h_mixed = 1 - 1 / 2 + np.log(2) / (c * np.log(c))
    np.testing.assert_allclose(lengths[0, 0], res * 3)  # pure: own points, length 3 res
    np.testing.assert_allclose(lengths[2, 0], res * (3 + 2 * h_mixed))
    assert lengths[2, 1] == 0.0  # block (0,0,0) is pure: it does not use its neighbour's points
    np.testing.assert_allclose(lengths[0, 2], res * (3 + 2 * h_mixed))  # the mixed block does use block (0,0,0)'s points
    assert lengths[0, 4] == pytest.approx(5 * res) and lengths[4, 3] == pytest.approx(5 * res)  # (0,1,0) is sandwiched
    assert lengths[2, 4] == 0.0  # (1,1,0) has one occupied neighbour only


def test_block_target_kernel_matches_twin(device):
    rng = np.random.default_rng(5)
    points = np.round(rng.uniform(-2, 2, (400, 3)) / 0.25) * 0.25  # many points on block and voxel faces
    points[200:] += rng.uniform(-0.1, 0.1, (200, 3))
    labels = np.where(points[:, 2] > 0, 1, 2)
    labels[rng.random(len(labels)) < 0.2] = 3
    owners, lengths = see_csom.block_targets(points, labels, 4, 0.25)
    unc = rng.uniform(0, 1, len(points))
    vm = VoxelMap(4, 0.25, device=device, initial_capacity=32)
    updates = scatter_block_targets(vm, points, labels, unc, owners, lengths, see_csom.CELLS_PER_BLOCK)
    _compare(vm, updates, ref.scatter_block_targets(points, labels, unc, owners, lengths, 0.25, 0.0, see_csom.CELLS_PER_BLOCK, 4))
    assert scatter_block_targets(VoxelMap(4, 0.25, device=device), np.zeros((0, 3)), np.zeros(0, int), np.zeros(0), np.zeros((0, 3), int), np.zeros((0, 7)), 2) == 0


def test_block_target_points_stopped_in_their_adding_pass_resume_where_they_stopped(device, overfill_next_launch):
    # As the scatter's (tests/test_scatter.py): a second, wider scan whose points stop part way through
    # their target blocks once every slot is taken; the relaunch lands each (point, cell) once.
    rng = np.random.default_rng(6)
    points = np.concatenate([rng.uniform(-1.0, 1.0, (100, 3)), rng.uniform(-3.0, 3.0, (3000, 3))])
    labels = rng.integers(1, 4, len(points))
    unc = rng.uniform(0, 1, len(points))
    owners, lengths = see_csom.block_targets(points, labels, 4, 0.25)
    vm = VoxelMap(4, 0.25, device=device, initial_capacity=32)
    first, second = slice(0, 100), slice(100, None)
    updates = scatter_block_targets(vm, points[first], labels[first], unc[first], owners[first], lengths[first], see_csom.CELLS_PER_BLOCK)
    resumed_after, launches = overfill_next_launch()
    updates += scatter_block_targets(vm, points[second], labels[second], unc[second], owners[second], lengths[second], see_csom.CELLS_PER_BLOCK)
    assert len(launches) >= 2 and np.count_nonzero(np.array(resumed_after) > 0) >= 20, "points must stop part way and be relaunched"
    _compare(vm, updates, ref.scatter_block_targets(points, labels, unc, owners, lengths, 0.25, 0.0, see_csom.CELLS_PER_BLOCK, 4))


def test_see_csom_is_dense_but_not_thick():
    """A flat floor of one class: SEE-CSOM keeps it one block thick; S-BKI-like smoothing would not
    fill a gap, SEE-CSOM fills a sandwiched empty block."""
    x, y = np.meshgrid(np.arange(-1, 1, 0.05), np.arange(-1, 1, 0.05))
    floor = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.1)], 1)
    floor = floor[~((np.abs(floor[:, 0] - 0.05) < 0.25) & (np.abs(floor[:, 1] - 0.05) < 0.25))]  # a hole of about one block
    mapper = Mapper(offroad("see-csom").replace(resolution_m=0.2, sbki={"ds_resolution_m": 0.05}), 3, workers=1)
    mapper.integrate(floor, np.full(len(floor), 2), payload_type="label", sensor_origin=[0, 0, 5.0])
    arrays, summary = mapper.voxels()
    occupied = arrays.index[summary.state == VoxelState.OCCUPIED]
    assert set(np.unique(occupied[:, 2]).tolist()) <= {-1, 0}  # the slab of blocks holding the floor
    hole = mapper.query(np.array([[0.05, 0.05, 0.1]]))
    assert hole.label[0] == 2  # the gap between occupied neighbours was filled


# --- Dempster-Shafer ------------------------------------------------------------------------------
def test_dempster_equals_the_sequential_rule_in_any_order():
    rng = np.random.default_rng(2)
    k = 4
    points = rng.uniform(0, 1.2, (60, 3))
    alpha = 1 + rng.gamma(0.7, 4, (len(points), k))
    config = dataclasses.replace(offroad("dempster"), uncertainty_threshold=False, adaptive_length=False, resolution_m=0.3, length_m=0.45)
    mapper = Mapper(config, k, workers=1)
    mapper.integrate(points, alpha, payload_type="alpha")
    arrays, summary = mapper.voxels()
    beliefs = (alpha - 1) / alpha.sum(axis=1, keepdims=True)
    expected = dempster_ref.dempster_map(points, beliefs, np.full(len(points), 0.45), arrays.index, 0.3, config.sigma0)
    masses = mapper.concentrations(arrays.evidence)
    np.testing.assert_allclose(masses, expected, rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(summary.variance, 1 - expected.sum(axis=1), atol=3e-5)  # the uncommitted mass
    shuffled = Mapper(config, k, workers=1)
    order = rng.permutation(len(points))
    shuffled.integrate(points[order[:30]], alpha[order[:30]], payload_type="alpha")
    shuffled.integrate(points[order[30:]], alpha[order[30:]], payload_type="alpha")
    np.testing.assert_allclose(shuffled.concentrations(shuffled.voxels()[0].evidence), masses, rtol=1e-4, atol=1e-6)


def test_dempster_vacuous_voxels_are_free_with_full_uncommitted_mass():
    config = dataclasses.replace(offroad("dempster"), uncertainty_threshold=False, adaptive_length=False, resolution_m=0.2, length_m=0.3)
    mapper = Mapper(config, 3, workers=1)
    mapper.integrate(np.array([[0.1, 0.1, 0.1]]), np.array([[1.0, 1.0, 1.0]]), payload_type="alpha")  # no evidence at all
    _, summary = mapper.voxels()
    assert (summary.label == 0).all() and (summary.state == VoxelState.FREE).all()
    np.testing.assert_allclose(summary.variance, 1.0)


def test_mass_readout_survives_huge_evidence():
    from evsemmap_warp.core.mapper import belief_masses

    masses = belief_masses(np.array([[400.0, 0.0, 0.0], [400.0, 400.0, 0.0], [0.0, 0.0, 0.0]]))
    assert np.isfinite(masses).all()
    np.testing.assert_allclose(masses, [[1, 0, 0], [0.5, 0.5, 0], [0, 0, 0]], atol=1e-6)


# --- every method through query, save / load and the viewer -------------------------------------
@pytest.mark.parametrize("method", ["convbki", "see-csom", "dempster"])
def test_methods_round_trip_through_files_and_viewer(method, tmp_path):
    from evsemmap_warp.apps.viewer import MapViewer, free_port

    rng = np.random.default_rng(0)
    points = rng.uniform(0, 2, (500, 3))
    alpha = 1 + rng.gamma(1, 3, (500, 9))
    mapper = Mapper(offroad(method), 9)
    mapper.integrate(points, alpha, payload_type="alpha", sensor_origin=[0, 0, 0])
    save_map(tmp_path / "m.npz", mapper)
    loaded = load_map(tmp_path / "m.npz")
    assert loaded.config == mapper.config
    np.testing.assert_array_equal(loaded.query(points).label, mapper.query(points).label)
    viewer = MapViewer([tmp_path / "m.npz"], port=free_port())
    viewer.server.stop()


def test_method_config_errors():
    with pytest.raises(ConfigError, match="mapping.media.*SEE-CSOM takes hard labels"):
        dataclasses.replace(offroad("see-csom"), media=offroad("ebs").media)
    with pytest.raises(ConfigError, match="Dempster-Shafer variant discounts beliefs with the sparse kernel"):
        dataclasses.replace(offroad("dempster"), kernel=offroad("s-csm").kernel)
