"""The terrain kernels (kernels/terrain.py) against their numpy twins (evsemmap_warp/reference/terrain.py),
on random inputs and edge cases: no voxel, one voxel, cells larger than a voxel, voxels far from
(0, 0, 0), the grid's edges, a z range; NaN-riddled grids, one known cell, cells on one line.

Tagged boundary band (style recommendation 3): a voxel center exactly on a cell face (cells that are
not a multiple of the voxel size) may fall either side in the kernel's arithmetic and the twin's; only
cells holding such voxels may differ, and the test counts them.
"""

import numpy as np
import pytest

from evsemmap_warp.reference import terrain as ref
from evsemmap_warp.terrain.layers import LayerGrid, VoxelColumns, column_reduction, grid_covering
from evsemmap_warp.kernels import terrain as tk


def _voxels(index, label, occupied, hits) -> VoxelColumns:
    n = len(index)
    k = 4
    return VoxelColumns(index=np.asarray(index, np.int64).reshape(-1, 3), label=np.asarray(label, np.int32),
                        occupied=np.asarray(occupied, bool), hits=np.asarray(hits, np.float64), probabilities=np.zeros((n, k)),
                        variance=np.zeros(n), weight_sum=np.zeros(n), weighted_uncertainty_sum=np.zeros(n), evidence=np.zeros((n, k)),
                        height_offset=np.zeros(n))


def _random_voxels(rng, n, spread, origin=(0, 0, 0), columns=None):
    if columns is None:
        index = rng.integers(-spread, spread, (n, 3))
    else:  # several voxels per column: pick columns, then z
        xy = rng.integers(-spread, spread, (columns, 2))[rng.integers(0, columns, n)]
        index = np.column_stack([xy, rng.integers(-8, 8, n)])
    index = np.unique(index, axis=0) + np.asarray(origin, np.int64)
    n = len(index)
    return _voxels(index, rng.integers(0, 4, n), rng.random(n) < 0.7, rng.integers(0, 50, n))


def _twin(voxels, grid, voxel_m, offset_m, surface, clearance_m, z_range=(-np.inf, np.inf)):
    """The twin's keys, decoded as column_reduction decodes the kernels'."""
    reference = voxels.index.min(axis=0)
    local = voxels.index - reference
    shift_x = (reference[0] * voxel_m + offset_m) - grid.x0_m
    shift_y = (reference[1] * voxel_m + offset_m) - grid.y0_m
    limit = tk.Z_OFFSET - 1
    low = -limit if not np.isfinite(z_range[0]) else int(np.ceil((z_range[0] - offset_m) / voxel_m - 0.5)) - int(reference[2])
    high = limit if not np.isfinite(z_range[1]) else int(np.floor((z_range[1] - offset_m) / voxel_m - 0.5)) - int(reference[2])
    args = (voxel_m, shift_x, shift_y, grid.cell_m, grid.width, grid.height, low, high)
    top, support, low_z, observations = ref.column_extremes(local, voxels.label, voxels.occupied, surface, voxels.hits, *args)
    cover = ref.column_cover(local, voxels.occupied, *args, int(np.floor(clearance_m / voxel_m + 1e-9)), support, low_z)
    out = {"observations": observations}
    for name, key in (("top", top), ("support", support), ("cover", cover)):
        out[f"{name}_row"] = np.where(key >= 0, key & 0xFFFFFFFF, -1)
        out[f"{name}_z"] = np.where(key >= 0, (key >> 32) - tk.Z_OFFSET + reference[2], 0)
    return out


def _compare(got, expected, skip_cells=None):
    keep = np.ones(len(got["observations"]), bool) if skip_cells is None else ~skip_cells
    for name in expected:
        np.testing.assert_array_equal(got[name][keep], expected[name][keep], err_msg=name)


SURFACE = np.array([0, 1, 1, 0], np.int32)


@pytest.mark.parametrize("cell_factor", [1, 2, 5])
@pytest.mark.parametrize("origin", [(0, 0, 0), (2_500_000, -1_800_000, 3_000)], ids=["near", "far"])
def test_column_reduction_matches_twin(device, cell_factor, origin):
    rng = np.random.default_rng(cell_factor)
    voxels = _random_voxels(rng, 3000, 12, origin=origin, columns=150)
    voxel_m, offset_m = 0.2, 0.0
    from evsemmap_warp.terrain.layers import voxel_extent

    extent = voxel_extent(voxels.index, voxel_m, offset_m)
    grid = grid_covering(extent[:, 0], extent[:, 1], voxel_m * cell_factor, offset_m)
    got = column_reduction(voxels, grid, voxel_m=voxel_m, offset_m=offset_m, surface_mask=SURFACE, clearance_m=0.6, device=device)
    _compare(got, _twin(voxels, grid, voxel_m, offset_m, SURFACE, 0.6))
    assert (got["support_row"] >= 0).any() and (got["cover_row"] != got["top_row"]).any(), "the case must exercise the clearance"


def test_grid_edges_z_range_and_grid_offset(device):
    """A grid smaller than the voxels' extent (voxels beyond its edges and beyond the z range are left
    out), on the S-CSM grid offset."""
    rng = np.random.default_rng(3)
    voxels = _random_voxels(rng, 2000, 10)
    grid = LayerGrid(0.2, -0.1, (-4, -3), 9, 7)
    got = column_reduction(voxels, grid, voxel_m=0.2, offset_m=-0.1, surface_mask=SURFACE, clearance_m=0.4, z_range_m=(-0.5, 0.9),
                           device=device)
    _compare(got, _twin(voxels, grid, 0.2, -0.1, SURFACE, 0.4, (-0.5, 0.9)))
    assert got["observations"].sum() < voxels.hits.sum()


def test_no_voxel_and_one_voxel(device):
    grid = LayerGrid(0.2, 0.0, (0, 0), 3, 2)
    empty = column_reduction(_voxels(np.zeros((0, 3)), [], [], []), grid, voxel_m=0.2, offset_m=0.0, surface_mask=SURFACE, clearance_m=1.0,
                             device=device)
    assert (empty["top_row"] == -1).all() and not empty["observations"].any()
    one = _voxels([[1, 1, 5]], [1], [True], [7])
    got = column_reduction(one, grid, voxel_m=0.2, offset_m=0.0, surface_mask=SURFACE, clearance_m=1.0, device=device)
    _compare(got, _twin(one, grid, 0.2, 0.0, SURFACE, 1.0))
    cell = 1 * 3 + 1
    assert got["support_row"][cell] == 0 and got["support_z"][cell] == 5 and got["observations"][cell] == 7


def test_cells_that_are_not_a_voxel_multiple_differ_only_on_cell_faces(device):
    rng = np.random.default_rng(9)
    voxels = _random_voxels(rng, 3000, 15, columns=200)
    grid = grid_covering((-3.2, 3.2), (-3.2, 3.2), 0.3, 0.0)
    got = column_reduction(voxels, grid, voxel_m=0.2, offset_m=0.0, surface_mask=SURFACE, clearance_m=0.6, device=device)
    expected = _twin(voxels, grid, 0.2, 0.0, SURFACE, 0.6)
    # cells holding a voxel whose center lies on a cell face (x or y center a multiple of 0.3 m), and their neighbours
    centers = (voxels.index[:, :2] + 0.5) * 0.2
    on_face = np.any(np.abs(centers / 0.3 - np.round(centers / 0.3)) < 1e-9, axis=1)
    band = np.zeros((grid.height, grid.width), bool)
    for c in centers[on_face]:
        i, j = int(np.floor((c[0] - grid.x0_m) / 0.3)), int(np.floor((c[1] - grid.y0_m) / 0.3))
        band[max(j - 1, 0):j + 2, max(i - 1, 0):i + 2] = True
    band = band.reshape(-1)
    assert on_face.any() and band.mean() < 0.9
    _compare(got, expected, skip_cells=band)
    differing = sum((got[n] != expected[n]) for n in ("top_row", "support_row", "cover_row")).astype(bool)
    assert differing.sum() <= band.sum()


def _random_heights(rng, rows, columns, unknown):
    x, y = np.meshgrid(np.arange(columns), np.arange(rows))
    height = 0.05 * x - 0.02 * y + rng.normal(0, 0.05, (rows, columns)) + 300.0
    height[rng.random((rows, columns)) < unknown] = np.nan
    return height


@pytest.mark.parametrize("unknown", [0.0, 0.3, 0.8])
@pytest.mark.parametrize("radius", [1, 2])
def test_filters_match_twin(device, unknown, radius):
    from evsemmap_warp.terrain.config import LayerSettings, TerrainConfig
    from evsemmap_warp.terrain.layers import neighbourhood_filters

    rng = np.random.default_rng(int(unknown * 10) + radius)
    height = _random_heights(rng, 23, 31, unknown)
    config = TerrainConfig(LayerSettings(plane_window_cells=2 * radius + 1, step_window_cells=2 * radius + 1, min_plane_cells=4))
    got = neighbourhood_filters(height, height, cell_m=0.25, config=config, device=device)
    slope, rough = ref.plane_fit(height, radius, 0.25, 4)
    np.testing.assert_array_equal(np.isnan(got["slope"]), np.isnan(slope))
    np.testing.assert_allclose(got["slope"], slope, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got["roughness"], rough, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(got["step"], ref.max_step(height, radius))


def test_filter_edge_cases(device):
    from evsemmap_warp.terrain.config import LayerSettings, TerrainConfig
    from evsemmap_warp.terrain.layers import neighbourhood_filters

    config = TerrainConfig(LayerSettings(plane_window_cells=5, step_window_cells=3, min_plane_cells=6))
    unknown = np.full((4, 5), np.nan)
    got = neighbourhood_filters(unknown, unknown, cell_m=0.2, config=config, device=device)
    assert all(np.isnan(v).all() for v in got.values())
    one = unknown.copy()
    one[2, 2] = 1.0
    got = neighbourhood_filters(one, one, cell_m=0.2, config=config, device=device)
    assert np.isnan(got["step"]).all() and np.isnan(got["slope"]).all()
    line = np.full((7, 7), np.nan)
    line[3, :] = np.arange(7) * 0.1  # a ramp one cell wide: its plane is undetermined across it
    got = neighbourhood_filters(line, line, cell_m=0.2, config=config, device=device)
    assert np.isnan(got["slope"]).all() and np.isnan(ref.plane_fit(line, 2, 0.2, 6)[0]).all()
    np.testing.assert_allclose(got["step"][3, 1:-1], 0.1)
    empty = np.zeros((0, 0))
    assert neighbourhood_filters(empty, empty, cell_m=0.2, config=config, device=device)["slope"].shape == (0, 0)


def test_a_plane_gives_its_slope_and_no_roughness(device):
    from evsemmap_warp.terrain.config import TerrainConfig
    from evsemmap_warp.terrain.layers import neighbourhood_filters

    x, y = np.meshgrid(np.arange(12) * 0.2, np.arange(9) * 0.2)
    plane = 0.5 * x + 0.2 * y + 1000.0
    got = neighbourhood_filters(plane, plane, cell_m=0.2, config=TerrainConfig(), device=device)
    np.testing.assert_allclose(got["slope"], np.degrees(np.arctan(np.hypot(0.5, 0.2))), atol=1e-9)
    # the residual sum of squares is a difference of sums of squares: ~1e-17 m^2 of rounding left, 3e-9 m RMS
    np.testing.assert_allclose(got["roughness"], 0.0, atol=1e-8)
    # the (x, y) diagonal neighbour, which every cell but two corners has
    np.testing.assert_allclose(got["step"][1:-1, 1:-1], 0.5 * 0.2 + 0.2 * 0.2, atol=1e-9)
    np.testing.assert_array_equal(got["step"], ref.max_step(plane, 1))
