"""Terrain layers (evsemmap_warp/terrain, docs/terrain.md): what the layers say about scenes whose answer
is known, the cost model against sampling its Dirichlet, stores tile by tile equal to the whole map,
and every output read back by the library people use for it (rasterio, numpy, Pillow, rosbags)."""

import json
import shutil

import numpy as np
import pytest
from conftest import run_cli

from evsemmap_warp.apps.batch import write_store_from_mapper
from evsemmap_warp.apps.cli import main
from evsemmap_warp.classes import class_set
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core.map_store import MapStore, StoreError
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.core.voxel_map import VoxelArrays
from evsemmap_warp.frames import WorldFrame
from evsemmap_warp.terrain import TerrainConfig, compute_layers, load_terrain_config
from evsemmap_warp.terrain.layers import band_units, class_cost
from evsemmap_warp.terrain.outputs import band_from_grid_map, grid_map_typestore
from evsemmap_warp.terrain.pipeline import write_layers

CLASSES = class_set().names
C = {name: i for i, name in enumerate(CLASSES)}
VOXEL_M = 0.2
# x0, y0 of the far scene: UTM-like coordinates, where float32 positions would be centimetres off
FAR = (512_000.0, 4_100_000.0)


def _mapper(voxels: dict, *, frame=None, origin_cells=(0, 0)) -> Mapper:
    """A map holding ``voxels``: {(i, j, k): (class name, evidence)} at the given cells (global voxel
    indices offset by ``origin_cells``)."""
    keys = sorted(voxels)
    index = np.array(keys, np.int64) + np.array([*origin_cells, 0], np.int64)
    evidence = np.zeros((len(keys), len(CLASSES)))
    for row, key in enumerate(keys):
        name, amount = voxels[key]
        evidence[row, C[name]] = amount
    n = len(keys)
    mapper = Mapper(load_config([], method="ebs").mapping, len(CLASSES), class_names=CLASSES, frame=frame, workers=1)
    mapper.load_voxels(VoxelArrays(index=index, evidence=evidence, weight_sum=np.full(n, 2.0), weighted_uncertainty_sum=np.full(n, 0.2),
                                   hits=np.full(n, 3, np.int64), touched=np.ones(n, bool), weighted_height_sum=np.zeros(n)))
    return mapper


def _scene() -> dict:
    """20 x 20 cells of paved ground at z index 0; a 0.6 m box (object) on 2 x 2 cells; a tree canopy
    (vegetation) 2.1-2.5 m up over 4 x 4 cells; one cell of the ground barely observed; one column empty."""
    voxels = {(i, j, 0): ("paved", 50.0) for i in range(20) for j in range(20)}
    voxels.update({(i, j, k): ("object", 50.0) for i in (8, 9) for j in (8, 9) for k in (1, 2, 3)})
    voxels.update({(i, j, k): ("vegetation", 50.0) for i in range(14, 18) for j in range(2, 6) for k in (10, 11, 12)})
    voxels[(2, 15, 0)] = ("paved", 2.0)
    del voxels[(19, 19, 0)]
    return voxels


def _at(layers, name, i, j, origin_cells=(0, 0)):
    """Band value of global cell (i, j) (north-up bands)."""
    grid = layers.grid
    column = i + origin_cells[0] - grid.first_cell[0]
    row = grid.first_cell[1] + grid.height - 1 - (j + origin_cells[1])
    return float(layers.bands[name][row, column])


@pytest.fixture(scope="module")
def scene_layers():
    return compute_layers(_mapper(_scene()))


def test_elevation_cover_and_overhangs(scene_layers):
    L = scene_layers
    assert L.grid.width == L.grid.height == 20 and L.grid.cell_m == VOXEL_M
    assert _at(L, "elevation", 3, 3) == pytest.approx(0.1)  # the ground voxel's center
    assert _at(L, "surface_class", 3, 3) == C["paved"] and _at(L, "cover_class", 3, 3) == C["paved"]
    # the box: the ground below supports, the box top is what a robot meets
    assert _at(L, "elevation", 8, 8) == pytest.approx(0.1)
    assert _at(L, "cover_height", 8, 8) == pytest.approx(0.7) and _at(L, "cover_class", 8, 8) == C["object"]
    # the canopy is above the clearance: the ground is what a robot meets there, the canopy is the top
    assert _at(L, "elevation_top", 15, 3) == pytest.approx(2.5)
    assert _at(L, "cover_class", 15, 3) == C["paved"] and _at(L, "lethal", 15, 3) == 0
    assert _at(L, "observations", 8, 8) == 3 * 4  # ground + 3 box voxels, 3 contributions each
    assert _at(L, "input_uncertainty", 3, 3) == pytest.approx(0.1)
    np.testing.assert_allclose(L.bands["slope"][np.isfinite(L.bands["slope"])], 0.0, atol=1e-9)


def test_steps_and_lethal(scene_layers):
    L = scene_layers
    assert _at(L, "step", 8, 8) == pytest.approx(0.6) and _at(L, "step", 7, 8) == pytest.approx(0.6)
    assert _at(L, "step", 5, 5) == 0
    assert _at(L, "lethal", 8, 8) == 1 and _at(L, "traversability_cost", 8, 8) == 1.0
    assert _at(L, "lethal", 7, 8) == 1  # the cell beside a 0.6 m step cannot be driven either
    assert _at(L, "lethal", 5, 5) == 0 and 0 < _at(L, "traversability_cost", 5, 5) < 0.5


def test_an_unsure_cell_costs_its_class_and_is_marked_unsure(scene_layers):
    L = scene_layers
    assert _at(L, "surface_class", 2, 15) == _at(L, "surface_class", 2, 14) == C["paved"]
    assert _at(L, "semantic_variance", 2, 15) > 3 * _at(L, "semantic_variance", 2, 14)
    assert _at(L, "class_cost_std", 2, 15) > 3 * _at(L, "class_cost_std", 2, 14)
    assert _at(L, "surface_uncommitted", 2, 15) == pytest.approx(9 / 11) and _at(L, "surface_uncommitted", 2, 14) == pytest.approx(9 / 59)
    assert _at(L, "traversability_cost", 2, 15) == _at(L, "traversability_cost", 2, 14)  # the evidential rule: its class's cost
    from dataclasses import replace

    config = load_terrain_config()
    expected = compute_layers(_mapper(_scene()), config=replace(config, costs=replace(config.costs, rule="expected")))
    assert _at(expected, "traversability_cost", 2, 15) > _at(expected, "traversability_cost", 2, 14) + 0.1


def test_unknown_cells(scene_layers):
    L = scene_layers
    assert _at(L, "known", 19, 19) == 0 and _at(L, "lethal", 19, 19) == 0 and _at(L, "observations", 19, 19) == 0
    for name in ("elevation", "traversability_cost", "surface_class", "probability_paved"):
        assert np.isnan(_at(L, name, 19, 19)), name
    assert _at(L, "known", 18, 19) == 1


def test_a_ramp_gives_its_slope_and_a_steep_one_is_lethal():
    # rises one voxel every 4 cells (14 deg) for x < 20, every 2 cells (26.6 deg, steeper than 25) beyond
    voxels = {}
    for i in range(40):
        k = i // 4 if i < 20 else 5 + (i - 20) // 2
        for j in range(12):
            voxels[(i, j, k)] = ("dirt", 30.0)
    L = compute_layers(_mapper(voxels), config=_config(plane_window_cells=9, min_plane_cells=20))
    gentle = [_at(L, "slope", i, 6) for i in range(5, 15)]
    steep = [_at(L, "slope", i, 6) for i in range(25, 35)]
    assert np.median(gentle) == pytest.approx(np.degrees(np.arctan(0.25 * VOXEL_M / VOXEL_M)), abs=1.5)
    assert np.median(steep) == pytest.approx(np.degrees(np.arctan(0.5)), abs=1.5)
    assert all(_at(L, "lethal", i, 6) == 0 for i in range(5, 15))
    assert np.mean([_at(L, "lethal", i, 6) for i in range(25, 35)]) > 0.5
    assert 0 < np.median([_at(L, "roughness", i, 6) for i in range(5, 15)]) < VOXEL_M / 2  # the staircase of voxels


def _lidar_drive_on_a_road(rng, grade_deg: float, road_z: float = 0.2):
    """Scans of a 16-ring LiDAR 1.8 m above a road z = road_z + x tan(grade), from 17 poses 1 m apart along x:
    the rings' points (within 5 m of the road's axis and 20 m of the sensor), with 2 cm of noise in z."""
    grade = np.tan(np.radians(grade_deg))
    elevation, azimuth = np.meshgrid(np.radians(np.linspace(-25, -5, 16)), np.radians(np.arange(0.0, 360.0, 1.0)), indexing="ij")
    rays = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1).reshape(-1, 3)
    scans = []
    for x0 in np.arange(-8.0, 8.5, 1.0):
        sensor = np.array([x0, 0.0, road_z + grade * x0 + 1.8])
        reach = -1.8 / (rays[:, 2] - grade * rays[:, 0])  # where each ray meets the road
        points = sensor + reach[:, None] * rays
        points = points[(reach > 0) & (reach < 20) & (np.abs(points[:, 1]) < 5)]
        points[:, 2] += rng.normal(0.0, 0.02, len(points))
        scans.append(points)
    return scans


def test_a_lidar_road_reads_its_grade_and_height_not_the_voxel_staircase():
    # A road rising 0.8 deg (flat to a planner), its surface near a voxel face (z 0.2 m at x = 0), swept by a
    # LiDAR's rings and mapped with ebs. Measured on the cells the layers know (evidence at least min_evidence,
    # with a slope): the slope's 90th percentile and median, and the elevation's median error against the road.
    # Heights at the voxel centers read this road as 0.2 m steps (slope p90 4.5 deg, elevation +0.1 m).
    grade_deg = 0.8
    mapper = Mapper(load_config([], method="ebs").mapping, len(CLASSES), class_names=CLASSES, workers=1, origin=np.zeros(3))
    for points in _lidar_drive_on_a_road(np.random.default_rng(0), grade_deg):
        mapper.integrate(points, np.full(len(points), C["paved"]), payload_type="label")
    L = compute_layers(mapper)
    known = (L.bands["known"] > 0) & np.isfinite(L.bands["slope"])
    assert known.sum() > 5000
    slope = L.bands["slope"][known]
    assert np.percentile(slope, 90) < 3.0
    assert np.median(slope) == pytest.approx(grade_deg, abs=0.3)
    x, _ = L.grid.cell_centers()
    road = np.broadcast_to(0.2 + np.tan(np.radians(grade_deg)) * x, known.shape)
    assert np.median(np.abs(L.bands["elevation"][known] - road[known])) < 0.02


def _config(**layers) -> TerrainConfig:
    from dataclasses import replace

    base = load_terrain_config()
    return replace(base, layers=replace(base.layers, **layers))


def test_class_cost_is_the_mean_and_deviation_under_the_dirichlet():
    from dataclasses import replace

    config = load_terrain_config()
    config = replace(config, costs=replace(config.costs, rule="expected"))
    rng = np.random.default_rng(4)
    costs = np.array([config.costs.classes[n] for n in CLASSES])
    for alpha in (np.ones(9), rng.uniform(0.5, 20, 9), np.array([1, 1, 1, 1, 80, 3, 1, 1, 1.0])):
        mean, std, lethal = class_cost(alpha[None], config, CLASSES)
        samples = rng.dirichlet(alpha, 400_000) @ costs
        assert mean[0] == pytest.approx(samples.mean(), abs=2e-3)
        assert std[0] == pytest.approx(samples.std(), rel=2e-2)
        assert lethal[0] == pytest.approx((alpha[C["object"]] + alpha[C["vegetation"]]) / alpha.sum())


def test_layers_are_the_same_run_to_run(scene_layers):
    again = compute_layers(_mapper(_scene()))
    for name, values in scene_layers.bands.items():
        np.testing.assert_array_equal(values, again.bands[name], err_msg=name)


def test_far_from_the_origin_and_coarser_cells():
    origin_cells = (int(FAR[0] / VOXEL_M), int(FAR[1] / VOXEL_M))
    near = compute_layers(_mapper(_scene()))
    far = compute_layers(_mapper(_scene(), origin_cells=origin_cells))
    assert far.grid.x0_m == pytest.approx(FAR[0], abs=1e-6) and far.grid.y0_m == pytest.approx(FAR[1], abs=1e-6)
    for name, values in near.bands.items():
        np.testing.assert_array_equal(values, far.bands[name], err_msg=name)
    coarse = compute_layers(_mapper(_scene()), resolution_m=0.4)
    assert (coarse.grid.width, coarse.grid.height) == (10, 10)
    # a 0.4 m cell holds 2 x 2 voxel columns (rows north-up): the box's cell meets the box, the canopy's is topped by it
    assert coarse.bands["cover_class"][5, 4] == C["object"] and coarse.bands["elevation_top"][8, 7] == pytest.approx(2.5)


# Stores ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drive_map(tmp_path_factory):
    from evsemmap_warp.data.datasets import open_dataset
    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence

    folder = tmp_path_factory.mktemp("terrain") / "drive"
    generate_sequence(load_preset("tiny"), folder, progress=False, camera=False)
    run = load_config([str(folder)], method="ebs")
    dataset = open_dataset(run.dataset)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names or None, frame=dataset.frame)
    mapper.integrate_many(dataset)
    return mapper


@pytest.fixture(scope="module")
def drive_store(drive_map, tmp_path_factory):
    return write_store_from_mapper(drive_map, tmp_path_factory.mktemp("terrain") / "store", 32, ["drive"])


@pytest.mark.parametrize("region", [{}, {"bounds": [-6.1, -3.3, 7.7, 9.0]}, {"bounds": [-6, -3, -0.5, 7, 9, 1.5]}, {"resolution_m": 0.4}],
                         ids=["whole", "bounds", "z-bounds", "0.4m"])
def test_a_store_tile_by_tile_equals_the_whole_map(drive_map, drive_store, region):
    whole = compute_layers(drive_map, **region)
    store = MapStore(drive_store, cache_tiles=2)
    tiled = compute_layers(store, **region)
    assert tiled.grid == whole.grid and tiled.frame == drive_map.frame
    for name, values in whole.bands.items():
        np.testing.assert_array_equal(tiled.bands[name], values, err_msg=name)
    if "bounds" in region:  # only the tiles meeting the region are read
        assert store.tiles_loaded == len(store.tiles_in(_box(region["bounds"])))
        assert store.tiles_loaded < len(store.tiles)


def _box(bounds):
    values = np.asarray(bounds, float)
    if len(values) == 4:
        return np.array([[values[0], values[1], -np.inf], [values[2], values[3], np.inf]])
    return values.reshape(2, 3)


def test_a_store_holds_a_few_tile_columns_at_a_time(drive_store, monkeypatch):
    """The sweep computes each tile column's own bands once and keeps three lines of them."""
    from evsemmap_warp.terrain import stores

    import weakref

    class Bands(dict):  # a dict that can be watched
        __hash__ = object.__hash__

    computed, alive, held = [], weakref.WeakSet(), []
    real = stores.own_bands

    def counting(voxels, grid, **kwargs):
        computed.append(grid.first_cell)
        bands = Bands(real(voxels, grid, **kwargs))
        alive.add(bands)
        return bands

    monkeypatch.setattr(stores, "own_bands", counting)
    store = MapStore(drive_store, cache_tiles=2)
    plan = stores.plan_store_layers(store, config=load_terrain_config())
    columns = set(plan.columns)
    span = min(len({c[0] for c in columns}), len({c[1] for c in columns}))
    for _ in stores.iterate_store_layers(plan, config=load_terrain_config()):
        held.append(len(alive))
    assert len(computed) == len(set(computed)) == len(columns)  # each column's own bands once
    assert max(held) <= 3 * span < len(columns)  # three lines of columns across the shorter side, not the store


# Outputs ----------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def written(tmp_path_factory):
    far = _mapper(_scene(), frame=WorldFrame("utm17", "EPSG:32617"), origin_cells=(int(FAR[0] / VOXEL_M), int(FAR[1] / VOXEL_M)))
    out = tmp_path_factory.mktemp("terrain") / "layers"
    summary = write_layers(far, out)
    return out, compute_layers(far), summary


def test_geotiff_reads_back_with_rasterio(written):
    rasterio = pytest.importorskip("rasterio")
    out, layers, _ = written
    with rasterio.open(out / "layers.tif") as tif:
        assert tif.count == len(layers.band_names) and list(tif.descriptions) == layers.band_names
        assert tif.crs.to_epsg() == 32617 and tif.tags()["FRAME"] == "utm17"
        assert np.isnan(tif.nodata) and tif.dtypes[0] == "float32"
        assert tif.transform.a == VOXEL_M and tif.transform.e == -VOXEL_M
        assert tif.transform.c == pytest.approx(FAR[0]) and tif.transform.f == pytest.approx(FAR[1] + 20 * VOXEL_M)
        # the world position of a cell center comes back through the transform
        x, y = tif.xy(0, 0)
        assert (x, y) == (pytest.approx(FAR[0] + 0.1), pytest.approx(FAR[1] + 20 * VOXEL_M - 0.1))
        assert tif.tags(tif.descriptions.index("elevation") + 1)["UNITS"] == "m"
        assert list(tif.units) == [band_units(name) for name in layers.band_names]  # GDAL's own per-band unit
        assert tif.units[tif.descriptions.index("elevation")] == "m" and tif.units[tif.descriptions.index("slope")] == "deg"
        assert json.loads(tif.tags()["CLASSES"]) == list(CLASSES)
        for b, name in enumerate(layers.band_names, start=1):
            np.testing.assert_array_equal(tif.read(b), layers.bands[name], err_msg=name)


def test_geotiff_of_a_map_without_crs_names_its_frame(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    write_layers(_mapper(_scene(), frame=WorldFrame("odom")), tmp_path / "out", previews=False, bag=False)
    with rasterio.open(tmp_path / "out" / "layers.tif") as tif:
        assert tif.crs is None and tif.tags()["FRAME"] == "odom"


def test_npz_and_previews_read_back(written):
    from PIL import Image

    from evsemmap_warp.terrain.outputs import read_npz

    out, layers, summary = written
    bands, meta = read_npz(out / "layers.npz")
    assert meta["frame"] == {"name": "utm17", "crs": "EPSG:32617"} and meta["bands"] == layers.band_names
    for name in layers.band_names:
        np.testing.assert_array_equal(bands[name], layers.bands[name])
    previews = sorted((out / "previews").glob("*.png"))
    assert {p.stem for p in previews} >= {"elevation", "traversability_cost", "surface_conflict", "surface_class", "lethal", "class_probabilities"}
    for path in previews:
        with Image.open(path) as image:
            pixels = np.asarray(image.convert("RGB")).astype(np.uint32)
            colors = np.unique((pixels[..., 0] << 16) | (pixels[..., 1] << 8) | pixels[..., 2])
            assert image.width >= 600 and len(colors) > 20, path.name  # a plot, a bar, a legend
    assert json.loads((out / "layers.json").read_text())["known_cells"] == summary["known_cells"] == 399


def test_previews_show_each_band_with_its_own_color_bar_or_legend(written):
    """The previews share one figure: each must show its own colormap on the color bar, class colors in its
    legend, and nothing left over from the band drawn before it."""
    import matplotlib
    from PIL import Image

    from evsemmap_warp.terrain.outputs import PREVIEW_COLORMAPS
    from evsemmap_warp.terrain.pipeline import class_colors

    out, layers, _ = written

    def pixels(name):
        with Image.open(out / "previews" / f"{name}.png") as image:
            return np.asarray(image.convert("RGB")).astype(int)

    def shows(region, color, share=0.0):  # more than ``share`` of the region's pixels of ``color``
        return float((np.abs(region - np.asarray(color[:3])).max(axis=-1) <= 3).mean()) > share

    def bar(px):  # the color bar's middle column (figure fractions of its axes), top (maximum) to bottom (minimum)
        h, w, _ = px.shape
        return px[int(0.15 * h) + 3:int(0.85 * h) - 2, int(0.8125 * w)]

    def map_of(px):  # the map's axes
        h, w, _ = px.shape
        return px[int(0.1 * h):int(0.9 * h), int(0.08 * w):int(0.74 * w)]

    for name, cmap in PREVIEW_COLORMAPS.items():
        column = bar(pixels(name))
        colormap = matplotlib.colormaps[cmap]
        assert shows(column[:1], colormap(1.0, bytes=True)) and shows(column[-1:], colormap(0.0, bytes=True)), name
    cost = map_of(pixels("traversability_cost"))
    assert shows(cost, (26, 26, 26), 0.005) and shows(cost, (217, 217, 217), 0.001)  # the lethal box over the costs; the empty column
    colors = class_colors(layers.class_names)
    for name in ("surface_class", "cover_class", "known", "lethal"):
        px = pixels(name)
        column = bar(px)
        assert (column[:10] == 255).all() and (column[-10:] == 255).all(), name  # no color bar
        legend = px[:, int(0.745 * px.shape[1]):]
        present = np.unique(layers.bands[name][np.isfinite(layers.bands[name])]).astype(int)
        expected = [colors[c] for c in present] if name.endswith("_class") else [(38, 38, 38)]
        assert all(shows(legend, color) for color in expected), name
        assert shows(map_of(px), expected[0], 0.005), name


def test_bag_reads_back_with_rosbags(written):
    from rosbags.rosbag1 import Reader

    out, layers, _ = written
    store = grid_map_typestore()
    with Reader(out / "layers.bag") as reader:
        by_topic = {c.topic: c for c in reader.connections}
        # the MD5 sums ROS 1 tools check on subscribing (grid_map_msgs, nav_msgs as released)
        assert by_topic["/terrain/grid_map"].digest == "95681e052b1f73bf87b7eb984382b401"
        assert by_topic["/terrain/costmap"].digest == "3381f2d731d4076ec5c71b0759edbe4e"
        messages = {c.topic: store.deserialize_ros1(raw, c.msgtype) for c, _, raw in reader.messages()}
    grid_map = messages["/terrain/grid_map"]
    info = grid_map.info
    assert info.header.frame_id == "utm17" and info.resolution == VOXEL_M
    assert (info.length_x, info.length_y) == (pytest.approx(4.0), pytest.approx(4.0))
    assert (info.pose.position.x, info.pose.position.y) == (pytest.approx(FAR[0] + 2.0), pytest.approx(FAR[1] + 2.0))
    assert list(grid_map.layers) == layers.band_names and list(grid_map.basic_layers) == ["elevation"]
    size_x = grid_map.data[0].layout.dim[1].size
    size_y = grid_map.data[0].layout.dim[0].size
    assert (grid_map.data[0].layout.dim[0].label, size_x, size_y) == ("column_index", 20, 20)
    for name, array in zip(grid_map.layers, grid_map.data):
        np.testing.assert_array_equal(band_from_grid_map(array.data, size_x, size_y), layers.bands[name], err_msg=name)
    # grid_map's index (0, 0) is the +x +y corner: the north-east cell, the empty column (19, 19)
    assert np.isnan(grid_map.data[layers.band_names.index("elevation")].data[0])
    costmap = messages["/terrain/costmap"]
    assert (costmap.info.width, costmap.info.height) == (20, 20) and costmap.header.frame_id == "utm17"
    assert (costmap.info.origin.position.x, costmap.info.origin.position.y) == (pytest.approx(FAR[0]), pytest.approx(FAR[1]))
    values = np.asarray(costmap.data).reshape(20, 20)  # row 0 = south
    assert values[19, 19] == -1 and values[8, 8] == 100 and 0 < values[5, 5] < 50


def test_a_store_writes_tiles_and_the_mosaic(drive_map, drive_store, tmp_path):
    rasterio = pytest.importorskip("rasterio")
    summary = write_layers(drive_store, tmp_path / "out", bounds=[-6, -3, 7, 9], previews=False)
    whole = compute_layers(drive_map, bounds=[-6, -3, 7, 9])
    with rasterio.open(tmp_path / "out" / "layers.tif") as tif:
        for b, name in enumerate(whole.band_names, start=1):
            np.testing.assert_array_equal(tif.read(b), whole.bands[name], err_msg=name)
    tiles = sorted((tmp_path / "out" / "tiles").glob("*.npz"))
    assert len(tiles) == len(summary["tile_columns"]) > 1
    from rosbags.rosbag1 import Reader

    with Reader(tmp_path / "out" / "layers.bag") as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {"/terrain/grid_map": len(tiles), "/terrain/costmap": 1}


# The command line and bad input -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("terrain") / "scene.npz"
    _mapper(_scene(), frame=WorldFrame("odom")).save(path)
    return path


def test_the_command_writes_every_output(scene_file, tmp_path, capsys):
    assert main(["layers", str(scene_file), "--out", str(tmp_path / "out"), "--no-previews", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["known_cells"] == 399 and summary["frame"] == {"name": "odom", "crs": None}
    assert {p.name for p in (tmp_path / "out").iterdir()} == {"layers.tif", "layers.npz", "layers.bag", "layers.json"}


COSTS_CASES = {
    "unknown-class": ("costs:\n  classes: {gravel: 0.1}\n", r"costs.classes names classes the map does not have: \['gravel'\]"),
    "negative-cost": ("costs:\n  classes: {grass: -0.5}\n", r"costs.classes.grass = -0.5 must be a finite cost >= 0"),
    "nan-cost": ("costs:\n  classes: {grass: .nan}\n", r"costs.classes.grass = nan must be a finite cost >= 0"),
    "unknown-surface": ("layers:\n  surface_classes: [road]\n", r"layers.surface_classes names classes the map does not have: \['road'\]"),
    "even-window": ("layers:\n  plane_window_cells: 4\n", r"plane_window_cells = 4 must be an odd number"),
    "unknown-key": ("costs:\n  max_slope: 3\n", r"unknown key\(s\) \['max_slope'\]"),
}


@pytest.mark.parametrize("case", sorted(COSTS_CASES))
def test_a_bad_costs_file_is_one_line_naming_file_and_key(scene_file, tmp_path, capsys, case):
    text, pattern = COSTS_CASES[case]
    path = tmp_path / f"{case}.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=pattern):
        compute_layers(Mapper.load(scene_file), config=load_terrain_config(path))
    line = run_cli(capsys, "layers", scene_file, "--out", tmp_path / "out", "--costs", path)
    assert str(path) in line and not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, pattern", [
    (["--resolution-m", "0"], "resolution_m = 0.0 must be a finite number > 0"),
    (["--resolution-m", "-1"], "resolution_m = -1.0 must be a finite number > 0"),
    (["--resolution-m", "nan"], "resolution_m = nan must be a finite number > 0"),
    (["--resolution-m", "0.1"], "finer than the map's voxels"),
    (["--bounds", "50", "50", "60", "60"], r"lie outside the map \(voxel centers span x 0.10..3.90"),
    (["--bounds", "3", "0", "1", "4"], "the x minimum 3.0 is larger than its maximum 1.0"),
    (["--bounds", "0", "0", "5", "1", "4", "-5"], "the z minimum 5.0 is larger than its maximum -5.0"),
    (["--bounds", "0", "0", "nan", "4"], "x and y must be finite"),
    (["--bounds", "0", "0", "4"], "give 4 numbers .* got 3"),
], ids=["zero", "negative", "nan", "finer", "outside", "x-min-max", "z-min-max", "nan-bounds", "three"])
def test_bad_resolution_and_bounds_are_one_line(scene_file, tmp_path, capsys, argv, pattern):
    import re

    line = run_cli(capsys, "layers", scene_file, "--out", tmp_path / "out", *argv)
    assert re.search(pattern, line), line
    values = [float(v) for v in argv[1:]]
    with pytest.raises(ValueError, match=pattern):
        compute_layers(Mapper.load(scene_file), **({"resolution_m": values[0]} if argv[0] == "--resolution-m" else {"bounds": values}))


def test_an_empty_map_an_existing_file_and_a_store_missing_tiles(scene_file, drive_store, tmp_path, capsys):
    empty = tmp_path / "empty.npz"
    Mapper(load_config([], method="ebs").mapping, len(CLASSES), class_names=CLASSES).save(empty)
    assert "the map holds no voxels" in run_cli(capsys, "layers", empty, "--out", tmp_path / "o1")
    with pytest.raises(ValueError, match="the map holds no voxels"):
        compute_layers(Mapper.load(empty))
    taken = tmp_path / "taken"
    taken.write_text("")
    assert f"--out {taken}: exists and is a file" in run_cli(capsys, "layers", scene_file, "--out", taken)
    broken = shutil.copytree(drive_store, tmp_path / "broken")
    lost = sorted((broken / "tiles").glob("*.vox"))[3]
    lost.unlink()
    line = run_cli(capsys, "layers", broken, "--out", tmp_path / "o2")
    assert f"tiles/{lost.name}" in line and "1 of the" in line
    with pytest.raises(StoreError, match=lost.stem):
        compute_layers(MapStore(broken))
    assert "inside the input" in run_cli(capsys, "layers", broken, "--out", broken / "layers")


def test_a_store_refuses_cells_that_do_not_tile_it(drive_store, tmp_path, capsys):
    with pytest.raises(ValueError, match=r"resolution_m = 0.3: a store's cells must divide its 6.4 m tiles"):
        compute_layers(MapStore(drive_store), resolution_m=0.3)
    assert "must divide its 6.4 m tiles" in run_cli(capsys, "layers", drive_store, "--out", tmp_path / "o", "--resolution-m", "0.3")
    wide = tmp_path / "wide.yaml"
    from evsemmap_warp.terrain import default_costs_path

    wide.write_text(default_costs_path().read_text().replace("plane_window_cells: 9 ", "plane_window_cells: 99 "))
    with pytest.raises(ValueError, match="the filters reach 49 cells beyond a cell, more than a tile of the store"):
        compute_layers(MapStore(drive_store), config=load_terrain_config(wide))


def test_layers_replace_their_folder_whole_and_leave_the_last_whole_when_stopped(drive_store, tmp_path, monkeypatch, capsys):
    """A rerun with other bounds leaves none of the first run's tile columns (they stayed beside the new
    one, layers.json listing only the new); a run interrupted (Ctrl-C) or failing (a full disk) halfway
    leaves the last run's output byte for byte and no staging folder; a second run into a folder being
    written is refused; a folder of other files is not replaced."""
    import errno
    import fcntl
    import os

    from evsemmap_warp.terrain import pipeline

    out = tmp_path / "L"
    first = write_layers(drive_store, out, previews=False, bag=False)
    second = write_layers(drive_store, out, bounds=[0, 0, 3, 3], previews=False, bag=False)
    assert len(second["tile_columns"]) < len(first["tile_columns"])
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted(second["files"] + ["layers.json"])
    assert json.loads((out / "layers.json").read_text())["out"] == str(out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real_write_npz = pipeline.write_npz
    for failure in (KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")):
        calls = []

        def write_npz_then_fail(path, layers):
            calls.append(path)
            if len(calls) > 1:  # the first tile column written, then stopped
                raise failure
            return real_write_npz(path, layers)

        monkeypatch.setattr(pipeline, "write_npz", write_npz_then_fail)
        with pytest.raises(type(failure)) as raised:
            write_layers(drive_store, out, previews=False, bag=False)
        if isinstance(failure, OSError):  # named as the folder asked for, not the staging one
            assert raised.value.errno == errno.ENOSPC and raised.value.filename == str(out)
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
        assert sorted(p.name for p in tmp_path.iterdir()) == ["L"]
    monkeypatch.setattr(pipeline, "write_npz", real_write_npz)
    handle = os.open(out, os.O_RDONLY)
    fcntl.flock(handle, fcntl.LOCK_EX)  # what a run writing the folder holds
    try:
        assert "another layers run is writing this folder now" in run_cli(capsys, "layers", drive_store, "--out", out)
    finally:
        os.close(handle)
    (tmp_path / "notes.txt").write_text("mine")
    assert "exists and is not a layers folder" in run_cli(capsys, "layers", drive_store, "--out", tmp_path)
    assert (tmp_path / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("stride", [1, 3, 7])
def test_the_preview_mosaic_is_the_whole_grid_decimated_whatever_the_parts(stride):
    """A store's previews are drawn from a mosaic filled part by part (tile columns at any offset, on the grid's
    edges included): it must equal the whole grid's bands taken one cell in ``stride``, with counts and masks 0
    (not NaN) where no part reached."""
    from types import SimpleNamespace

    from evsemmap_warp.terrain.layers import LayerGrid
    from evsemmap_warp.terrain.pipeline import _PreviewMosaic

    grid = LayerGrid(0.2, 0.0, (-13, 40), 50, 23)
    rng = np.random.default_rng(stride)
    whole = {"elevation": rng.normal(size=(23, 50)).astype(np.float32), "known": (rng.random((23, 50)) < 0.5).astype(np.float32)}
    mosaic = _PreviewMosaic(grid, list(whole), stride)
    reached = np.zeros((23, 50), bool)
    # parts of 11 x 9 cells from the south-west corner, the last ones cut by the grid's edges; one part left out
    for k, (i, j) in enumerate((i, j) for i in range(0, 50, 11) for j in range(0, 23, 9)):
        if k == 4:
            continue
        width, height = min(11, 50 - i), min(9, 23 - j)
        part = LayerGrid(0.2, 0.0, (grid.first_cell[0] + i, grid.first_cell[1] + j), width, height)
        row, column = part.window_in(grid)
        mosaic.add(SimpleNamespace(grid=part, bands={n: b[row:row + height, column:column + width] for n, b in whole.items()}))
        reached[row:row + height, column:column + width] = True
    expected_elevation = np.where(reached, whole["elevation"], np.nan)[::stride, ::stride]
    np.testing.assert_array_equal(mosaic.bands["elevation"], expected_elevation)
    np.testing.assert_array_equal(mosaic.bands["known"], np.where(reached, whole["known"], 0.0)[::stride, ::stride])


def test_the_geotiff_holds_zero_counts_and_masks_where_no_part_reached():
    """Cells no part of a mosaic reaches: NaN layers, but 0 observations, known and lethal (written at close in one
    window per run of such cells and band of alike rows); reached cells keep what was written."""
    from types import SimpleNamespace

    rasterio = pytest.importorskip("rasterio")
    from evsemmap_warp.terrain.layers import LayerGrid, band_names
    from evsemmap_warp.terrain.outputs import GeoTiffWriter

    import tempfile
    from pathlib import Path

    classes = ["grass", "tree"]
    grid = LayerGrid(0.5, 0.0, (0, 0), 30, 20)
    names = band_names(classes)
    reached = np.zeros((20, 30), bool)
    with tempfile.TemporaryDirectory() as folder:
        writer = GeoTiffWriter(Path(folder) / "t.tif", grid, None, classes, costs_file="c.yaml")
        # an L of two parts: the south-west 10 x 12 cells and a strip along the north edge
        for first, width, height in (((0, 0), 10, 12), ((5, 17), 25, 3)):
            part = LayerGrid(0.5, 0.0, first, width, height)
            writer.write(SimpleNamespace(grid=part, bands={n: np.full((height, width), 2.0, np.float32) for n in names}))
            row, column = part.window_in(grid)
            reached[row:row + height, column:column + width] = True
        path = writer.close()
        with rasterio.open(path) as tif:
            bands = {n: tif.read(names.index(n) + 1) for n in ("elevation", "observations", "known", "lethal")}
    assert 0 < reached.sum() < reached.size
    assert np.all(np.isnan(bands["elevation"][~reached])) and np.all(bands["elevation"][reached] == 2.0)
    for name in ("observations", "known", "lethal"):
        assert np.all(bands[name][~reached] == 0.0) and np.all(bands[name][reached] == 2.0), name


def test_a_swap_that_fails_halfway_puts_the_last_output_back(tmp_path, monkeypatch):
    import errno
    import os

    from evsemmap_warp.terrain.outputs import staged_output_folder

    out = tmp_path / "L"
    with staged_output_folder(out, "layers.json") as staging:
        (staging / "layers.json").write_text("first\n")
    real = os.rename

    def rename(src, dst):  # the new output cannot take the folder's name (a full disk, a quota)
        if ".writing-" in str(src):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError, match="No space left"):
        with staged_output_folder(out, "layers.json") as staging:
            (staging / "layers.json").write_text("second\n")
    assert (out / "layers.json").read_text() == "first\n" and sorted(p.name for p in tmp_path.iterdir()) == ["L"]
