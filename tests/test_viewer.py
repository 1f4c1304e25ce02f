"""The map viewer in-process: filters, colorings, several maps, picking, exports, the CLI."""

import html

import numpy as np
import pytest
import trimesh

from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import load_config
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.apps.viewer import MapViewer, free_port, load_points, load_trajectory
from evsemmap_warp.apps.viewer.colors import CLASS_COLORS, colormap
from evsemmap_warp.frames import WorldFrame
from evsemmap_warp.terrain import LayerSettings
from evsemmap_warp.terrain.layers import VoxelColumns

from conftest import REPO, wait_until

CLASSES = ["void", "sky", "water", "object", "paved", "unpaved", "dirt", "grass", "vegetation"]


def make_map(path, seed=0, offset=(0.0, 0.0, 0.0), frame=None, dirt_below_x=None):
    """Grass ground, an object box, and a patch of void (free) evidence, 100 m from the origin (plus
    ``offset``), recorded in world frame ``frame`` (None: as a file written before frames were recorded).
    ``dirt_below_x``: ground points less than this far along x (from the ground's edge) are dirt."""
    rng = np.random.default_rng(seed)
    cfg = load_config([REPO / "configs/presets/rellis3d.yaml"], method="s-bki").mapping
    mapper = Mapper(cfg, 9, class_names=CLASSES)
    ground = np.c_[rng.uniform(0, 6, (6000, 2)), rng.normal(0, 0.02, 6000)]
    box = np.c_[rng.uniform(2, 3, (2000, 2)), rng.uniform(0.2, 1.2, 2000)]
    air = np.c_[rng.uniform(4, 5, (500, 2)), rng.uniform(1.5, 2, 500)]
    points = np.concatenate([ground, box, air]) + np.array([100.0, 100.0, 0.0]) + offset
    labels = np.r_[np.full(6000, 7), np.full(2000, 3), np.zeros(500, int)]
    if dirt_below_x is not None:
        labels[:6000][ground[:, 0] < dirt_below_x] = 6
    alpha = 1.0 + rng.uniform(0, 0.5, (len(labels), 9))
    alpha[np.arange(len(labels)), labels] += rng.uniform(1, 60, len(labels))
    mapper.integrate(points, alpha, payload_type="alpha")
    mapper.frame = frame
    mapper.save(path)
    return mapper


@pytest.fixture
def maps(tmp_path):
    make_map(tmp_path / "a.npz")
    make_map(tmp_path / "b.npz", seed=1, offset=(0.3, 0, 0))
    return [tmp_path / "a.npz", tmp_path / "b.npz"]


@pytest.fixture
def viewer(maps):
    v = MapViewer(maps, port=free_port(), max_voxels=100_000)
    yield v
    v.server.stop()


def test_defaults_hide_free_and_unknown_and_toggles_show_them(viewer):
    layer = viewer.layers[0]
    assert viewer.url.startswith("http://127.0.0.1:")
    assert set(layer.state[viewer.visible_rows[0]]) == {2}  # OCCUPIED only
    assert len(viewer.visible_rows[1]) == 0  # one map at a time by default
    viewer.gui_show_free.value = True
    assert set(layer.state[viewer.visible_rows[0]]) == {1, 2} and (layer.state == 1).sum() > 0


def test_voxels_below_the_evidence_threshold_are_hidden_by_default_counted_and_shown_on_request(viewer):
    layer = viewer.layers[0]
    assert viewer.min_evidence == LayerSettings().min_evidence  # the layers' threshold: one definition of known
    below = (layer.state == 2) & (layer.evidence_sum < viewer.min_evidence)  # kernel tails beside the surfaces
    assert below.sum() > 100
    shown = viewer.visible_rows[0]
    assert not below[shown].any() and (layer.evidence_sum[shown] >= viewer.min_evidence).all()
    assert f"{int(below.sum()):,} below the evidence threshold (min_evidence 0.2) hidden" in viewer.gui_status.content
    viewer.gui_show_below.value = True
    assert below[viewer.visible_rows[0]].sum() == below.sum() and "below the evidence threshold" not in viewer.gui_status.content
    # the Selected panel says what such a voxel is, instead of a class its evidence does not tell
    row = int(np.flatnonzero(below)[0])
    text = viewer.picking.describe(0, row)
    assert "**below the evidence threshold**" in text and "label: **" not in text
    assert f"evidence: {layer.evidence_sum[row]:.3g} (min_evidence 0.2)" in text
    known_row = int(viewer.visible_rows[0][~below[viewer.visible_rows[0]]][0])
    assert "below the evidence threshold" not in viewer.picking.describe(0, known_row)


def test_the_threshold_is_the_cost_tables_layers_min_evidence(maps, tmp_path):
    costs = tmp_path / "costs.yaml"
    costs.write_text("layers: {min_evidence: 0.0}\n")
    v = MapViewer(maps, port=free_port(), costs=costs)
    try:
        layer = v.layers[0]
        assert v.min_evidence == 0.0 and "below the evidence threshold" not in v.gui_status.content
        assert len(v.visible_rows[0]) == (layer.state == 2).sum()
    finally:
        v.server.stop()


def test_the_viewer_and_the_layers_know_the_same_voxels(maps):
    mapper = Mapper.load(maps[0])
    columns = VoxelColumns.of([mapper], min_evidence=0.2)
    v = MapViewer(maps, port=free_port())
    try:
        layer = v.layers[0]
        np.testing.assert_array_equal(layer.voxel_index, columns.index)
        np.testing.assert_array_equal(columns.occupied, (layer.state == 2) & v.voxels.known(0))
    finally:
        v.server.stop()


def test_class_toggle_and_variance_slider(viewer):
    layer = viewer.layers[0]
    before = viewer.visible_rows[0]
    viewer.gui_classes["object"].value = False
    assert 3 not in layer.label[viewer.visible_rows[0]] and 3 in layer.label[before]
    viewer.gui_classes["object"].value = True
    threshold = float(np.median(layer.variance[before]))
    viewer.gui_max_variance.value = threshold / viewer.variance_unit  # the slider counts in units of 10^e
    assert viewer.max_variance == pytest.approx(threshold)
    shown = viewer.visible_rows[0]
    assert 0 < len(shown) < len(before) and layer.variance[shown].max() <= threshold + 1e-9


def test_colorings(viewer):
    rows = viewer.visible_rows[0]
    semantic = viewer.voxels.colors(0, rows)
    labels = viewer.layers[0].label[rows]
    assert (semantic[labels == 3] == CLASS_COLORS["object"]).all() and (semantic[labels == 7] == CLASS_COLORS["grass"]).all()
    for mode in ("variance", "mean uncertainty", "observations"):
        viewer.gui_color_by.value = mode
        colors = viewer.voxels.colors(0, rows)
        assert len(np.unique(colors, axis=0)) > 5, mode
        assert viewer.gui_legend.image.shape[0] == 46  # a color bar instead of the class legend
    np.testing.assert_array_equal(colormap(np.array([0.0, 1.0, np.nan]), 0, 1), [[68, 1, 84], [253, 231, 37], [128, 128, 128]])


def test_color_by_variance_spreads_over_the_range_the_map_holds(viewer):
    # variances spanning decades, a few large: on a linear ramp from the minimum to the maximum nearly every
    # voxel would take the ramp's first color
    layer = viewer.layers[0]
    layer.variance = 10.0 ** np.random.default_rng(0).normal(-3.0, 0.7, len(layer.variance))
    layer.variance[:5] = 0.25
    viewer.gui_color_by.value = "variance"
    colors = viewer.voxels.colors(0, viewer.visible_rows[0]).astype(int)
    at_low_end = np.abs(colors - colormap(np.zeros(1), 0, 1)[0]).sum(axis=1) <= 12
    assert at_low_end.mean() < 0.1, at_low_end.mean()
    assert "log10 variance, p1-p99" in viewer.voxels.legend_label("variance")
    lo, hi = viewer.voxels.color_ranges["variance"]
    assert -4.8 < lo < -4.2 and -2.0 < hi < -1.2  # about the 1st and 99th percentiles of log10 variance


def test_several_maps_switchable_and_side_by_side(viewer):
    viewer.gui_map.value = viewer.gui_map.options[1]
    assert len(viewer.visible_rows[0]) == 0 and len(viewer.visible_rows[1]) > 0
    viewer.gui_side_by_side.value = True
    assert len(viewer.visible_rows[0]) > 0 and len(viewer.visible_rows[1]) > 0
    assert viewer.comparison.shift(1)[0] > 6.0  # the second map sits beside the first, not on top


def test_positions_are_float32_relative_to_a_local_origin(viewer):
    np.testing.assert_array_equal(viewer.origin, np.round(viewer.origin))
    assert np.abs(viewer.origin[:2] - 103).max() < 1.0
    points = viewer.voxels.handles[0].points
    assert points.dtype == np.float32 and np.abs(points).max() < 10


def test_decimation_and_full_map(maps):
    v = MapViewer(maps, port=free_port(), max_voxels=500)
    try:
        assert len(v.visible_rows[0]) == 500 and "decimated" in v.gui_status.content
        v.gui_full_map.value = True
        assert len(v.visible_rows[0]) > 500 and "decimated" not in v.gui_status.content
    finally:
        v.server.stop()


def test_clicking_a_voxel_describes_it(viewer):
    layer = viewer.layers[0]
    rows = viewer.visible_rows[0]
    top = rows[np.argmax(layer.centers[rows, 2])]  # the highest visible voxel: nothing above it
    origin = layer.centers[top] - viewer.origin + np.array([0.0, 0.0, 10.0])

    viewer.picking.click(origin, (0.0, 0.0, -1.0))
    text = viewer.gui_selection.content
    assert f"voxel {tuple(int(v) for v in layer.voxel_index[top])}" in text and "| object |" in text
    assert f"label: **{CLASSES[layer.label[top]]}**" in text
    assert viewer.picking.pick(origin + np.array([500.0, 0, 0]), (0, 0, -1)) is None


def test_exports(viewer, tmp_path):
    html = viewer.export_html(tmp_path / "scene.html").read_text()
    assert html.startswith("<!") and len(html) > 100_000
    ply = viewer.export_ply(tmp_path / "voxels.ply")
    cloud = trimesh.load(ply)
    rows = viewer.visible_rows[0]
    assert len(cloud.vertices) == len(rows)
    np.testing.assert_allclose(np.sort(cloud.vertices[:, 2]), np.sort(viewer.layers[0].centers[rows, 2]), atol=1e-4)
    props = cloud.metadata["_ply_raw"]["vertex"]["data"]
    assert set(np.unique(props["label"])) <= {2.0, 3.0, 7.0} and (props["state"] == 2).all()
    assert (props["evidence"] >= viewer.min_evidence).all()  # what the viewer shows: no voxel below the threshold
    viewer.gui_show_below.value = True
    props = trimesh.load(viewer.export_ply(tmp_path / "all.ply")).metadata["_ply_raw"]["vertex"]["data"]
    assert (props["evidence"] < viewer.min_evidence).sum() > 100


def test_trajectory_scan_and_file_errors(maps, tmp_path):
    poses = np.zeros((5, 12))
    poses[:, [0, 5, 10]] = 1
    poses[:, 3] = np.arange(5) + 100
    np.savetxt(tmp_path / "poses.txt", poses)
    np.testing.assert_array_equal(load_trajectory(tmp_path / "poses.txt")[:, 0], np.arange(5) + 100)
    scan = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    scan.tofile(tmp_path / "scan.bin")
    np.testing.assert_allclose(load_points(tmp_path / "scan.bin"), scan[:, :3])
    v = MapViewer(maps[:1], port=free_port(), trajectory=tmp_path / "poses.txt", scan=tmp_path / "scan.bin", style="boxes")
    v.server.stop()
    np.savetxt(tmp_path / "bad.txt", np.zeros((3, 5)))
    with pytest.raises(ValueError, match="3 \\(x y z\\) or 12"):
        load_trajectory(tmp_path / "bad.txt")
    with pytest.raises(ValueError, match="unknown point file type"):
        load_points(tmp_path / "x.xyz")


def test_view_command_exports_without_serving(maps, tmp_path, capsys):
    assert main(["view", *map(str, maps), "--port", str(free_port()), "--no-serve",
                 "--export-html", str(tmp_path / "v.html"), "--export-ply", str(tmp_path / "v.ply")]) == 0
    assert (tmp_path / "v.html").exists() and (tmp_path / "v.ply").exists()
    assert main(["view", str(tmp_path / "missing.npz"), "--no-serve"]) == 2
    assert "no such map file" in capsys.readouterr().err


# --- maps anchored in a world frame (UTM, far from the origin) ----------------------------------
UTM = WorldFrame("map", "EPSG:32617")
FAR = (500_000.0 - 100.0, 4_000_000.0 - 100.0, 100.0)  # make_map's points sit near (500 km, 4000 km, 100 m)


def read_ply(path):
    """(header lines, structured vertex array) of a binary little-endian PLY, read with numpy alone."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4"}
    dtype = [(line.split()[2], types[line.split()[1]]) for line in header if line.startswith("property ")]
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    assert "format binary_little_endian 1.0" in header
    return header, np.frombuffer(data[end:], dtype=dtype, count=count)


@pytest.fixture
def far_viewer(tmp_path):
    make_map(tmp_path / "utm.npz", offset=FAR, frame=UTM)
    v = MapViewer([tmp_path / "utm.npz"], port=free_port(), max_voxels=100_000)
    yield v
    v.server.stop()


def test_far_map_shows_its_frame_and_the_local_origin_in_world_coordinates(far_viewer):
    v = far_viewer
    assert v.frame == UTM and v.layers[0].frame == UTM
    assert v.layers[0].centers.dtype == np.float64 and v.layers[0].centers[:, 0].min() > 499_990
    assert "frame: **map (EPSG:32617)**" in v.gui_frame.content
    x, y, z = v.origin
    assert 500_000 < x < 500_010 and 4_000_000 < y < 4_000_010
    label = f"map: x={x:.3f}, y={y:.3f}, z={z:.3f} m"
    assert label in v.gui_frame.content and v.orientation.origin_label.text == label
    points = v.voxels.handles[0].points  # still float32, small, relative to the local origin
    assert points.dtype == np.float32 and np.abs(points).max() < 10


def test_clicked_voxel_is_described_in_world_coordinates_of_its_frame(far_viewer):
    v = far_viewer
    layer = v.layers[0]
    rows = v.visible_rows[0]
    top = rows[np.argmax(layer.centers[rows, 2])]
    start = layer.centers[top] - v.origin + np.array([0.0, 0.0, 10.0])
    assert v.picking.pick(start, (0.0, 0.0, -1.0)) == (0, top)
    v.picking.click(start, (0.0, 0.0, -1.0))
    cx, cy, cz = layer.centers[top]
    assert cx > 500_000 and cy > 4_000_000
    assert f"center in frame 'map' (EPSG:32617): x={cx:.3f}, y={cy:.3f}, z={cz:.3f} m" in v.gui_selection.content


def test_the_panel_follows_what_lies_under_the_screen_center_as_the_camera_moves(far_viewer):
    """In place of coordinates on hover (viser 1.1 sends the server no pointer moves): each camera move reports
    what lies under the screen's center, in world coordinates, and puts the crosshair at the orbit center."""
    from types import SimpleNamespace

    v = far_viewer
    layer = v.layers[0]
    rows = v.visible_rows[0]
    top = rows[np.argmax(layer.centers[rows, 2])]
    look_at = layer.centers[top] - v.origin

    def camera(at, height=10.0):
        return SimpleNamespace(position=at + np.array([0.0, -0.01, height]), look_at=at, fov=1.0, image_height=800)

    v.cameras.center_hit = None
    v.cameras.report(camera(look_at), client_id=1)
    assert wait_until(lambda: v.center_hit is not None and v.center_hit["kind"] == "voxel", 10.0)
    assert v.center_hit["row"] == top
    cx, cy = layer.centers[top][:2]
    assert f"(a voxel of utm, {layer.classes[layer.label[top]]}): x={cx:.3f}" in v.gui_view_center.content
    assert "in frame 'map' (EPSG:32617)" in v.gui_view_center.content and cy > 4_000_000
    assert np.allclose(v.cameras.crosshair.position, look_at) and v.cameras.crosshair.visible
    # beside the map, the ground grid's plane, 30 m further east in world coordinates
    beside = look_at + np.array([30.0, 0.0, 0.0])
    beside[2] = v.ground.z - v.origin[2] + 1.0
    v.cameras.report(camera(beside), client_id=1)
    assert wait_until(lambda: v.center_hit is not None and v.center_hit["kind"] == "ground", 10.0)
    assert v.center_hit["point"][0] == pytest.approx(beside[0] + v.origin[0], abs=0.05)
    assert "(the ground grid's plane)" in v.gui_view_center.content
    # the crosshair keeps a fixed size on screen: 8 pixels' worth of metres at the orbit center
    near = v.cameras.crosshair.scale
    v.cameras.center_hit = None
    v.cameras.report(camera(beside, height=100.0), client_id=1)
    assert v.cameras.crosshair.scale == pytest.approx(10 * near, rel=0.01)
    assert wait_until(lambda: v.center_hit is not None and v.center_hit["kind"] == "ground", 10.0)


def test_ply_export_holds_float64_world_coordinates_and_names_the_frame(far_viewer, tmp_path):
    v = far_viewer
    rows = v.visible_rows[0]
    header, vertex = read_ply(v.export_ply(tmp_path / "far.ply"))
    assert "comment frame map" in header and "comment crs EPSG:32617" in header
    assert {"property double x", "property double y", "property double z"} <= set(header)
    assert vertex["x"].dtype == np.float64 and len(vertex) == len(rows)
    np.testing.assert_array_equal(np.c_[vertex["x"], vertex["y"], vertex["z"]], v.layers[0].centers[rows])
    np.testing.assert_array_equal(vertex["label"], v.layers[0].label[rows])
    np.testing.assert_array_equal(vertex["observations"], v.layers[0].hits[rows])
    assert (vertex["state"] == 2).all() and vertex["variance"].dtype == np.float32
    cloud = trimesh.load(tmp_path / "far.ply")  # an ordinary reader gets the same world coordinates
    np.testing.assert_allclose(cloud.vertices, v.layers[0].centers[rows], rtol=0, atol=1e-6)
    assert "label" in cloud.metadata["_ply_raw"]["vertex"]["data"].dtype.names


def test_html_export_states_the_frame_and_the_local_origin(far_viewer, tmp_path):
    v = far_viewer
    page = v.export_html(tmp_path / "far.html").read_text(encoding="utf-8")
    x, y, z = v.origin
    assert '<meta name="evsemmap-frame" content="map" />' in page
    assert '<meta name="evsemmap-crs" content="EPSG:32617" />' in page
    assert f'<meta name="evsemmap-local-origin" content="{x:.3f} {y:.3f} {z:.3f}" />' in page
    note = f"positions are relative to the local origin at x={x:.3f} y={y:.3f} z={z:.3f} m in frame 'map' (EPSG:32617)"
    assert f"<!-- evsemmap_warp map viewer export: {note}" in page
    assert '<div id="evsemmap-frame-note"' in page and page.index("evsemmap-frame-note") < page.rindex("</body>")
    assert html.unescape(page).count(note) >= 3  # the meta element, the comment, the visible note
    assert page.startswith("<!") and len(page) > 100_000


def test_maps_of_different_frames_are_refused_naming_both(tmp_path, capsys):
    make_map(tmp_path / "utm.npz", offset=FAR, frame=UTM)
    make_map(tmp_path / "odom.npz", frame=WorldFrame("odom"))
    make_map(tmp_path / "old.npz")
    make_map(tmp_path / "old2.npz", seed=1)
    with pytest.raises(ValueError) as refused:
        MapViewer([tmp_path / "utm.npz", tmp_path / "odom.npz"], port=free_port())
    text = str(refused.value)
    assert "utm.npz" in text and "odom.npz" in text and "frame 'map' (EPSG:32617)" in text and "frame 'odom'" in text
    with pytest.raises(ValueError, match="old.npz.*no recorded frame"):  # an old file and a framed one: refused too
        MapViewer([tmp_path / "utm.npz", tmp_path / "old.npz"], port=free_port())
    assert main(["view", str(tmp_path / "odom.npz"), str(tmp_path / "utm.npz"), "--no-serve", "--port", str(free_port())]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "odom.npz" in err and "utm.npz" in err and "'odom'" in err and "EPSG:32617" in err
    v = MapViewer([tmp_path / "old.npz", tmp_path / "old2.npz"], port=free_port())  # two old files: still together
    try:
        assert v.frame is None and "frame: **not recorded** (all 2 maps)" in v.gui_frame.content
        header, _ = read_ply(v.export_ply(tmp_path / "old.ply"))
        assert "comment frame none" in header and "comment crs none" in header
    finally:
        v.server.stop()


def test_a_store_shows_its_frame_and_is_refused_beside_another(tmp_path):
    make_map(tmp_path / "a.npz", offset=FAR, frame=UTM)
    make_map(tmp_path / "b.npz", seed=1, offset=FAR, frame=UTM)
    make_map(tmp_path / "odom.npz", frame=WorldFrame("odom"))
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "store"), "--tile-voxels", "16"]) == 0
    v = MapViewer([tmp_path / "store", tmp_path / "a.npz"], port=free_port())  # a store and a map of its frame
    try:
        assert v.layers[0].frame == UTM and "frame: **map (EPSG:32617)** (all 2 maps)" in v.gui_frame.content
        v.gui_side_by_side.value = True
        assert "side by side" in v.gui_frame.content and "shifted" in offset_note(v)
    finally:
        v.server.stop()
    with pytest.raises(ValueError, match="store is in frame 'map' \\(EPSG:32617\\) but .*odom.npz in frame 'odom'"):
        MapViewer([tmp_path / "store", tmp_path / "odom.npz"], port=free_port())


# --- issue 30 (defects, orientation, diff) and issue 26 item 5 (terrain layers), in-process ------------------------
from evsemmap_warp.apps.viewer import comparison, lighting, orientation
from evsemmap_warp.apps.viewer.exports import offset_note
from evsemmap_warp.apps.viewer.terrain import TERRAIN_MODES


def test_lit_mesh_colors_render_as_the_palette():
    """The forward model (tone map of lit reflectance, fitted against Chromium: tests/test_viewer_browser.py) maps
    the compensated colors back onto the palette, within what ACES can render (saturated yellow the furthest)."""
    names = ["grass", "object", "dirt", "vegetation", "unpaved", "water", "sky", "paved"]
    palette = np.array([CLASS_COLORS[n] for n in names], np.uint8)
    shown = lighting.rendered_top_color(lighting.mesh_colors(palette)).astype(int)
    error = np.abs(shown - palette).max(axis=1)
    assert (error[:-1] <= 30).all() and error[-1] <= 60, dict(zip(names, error))
    # viser's defaults (the instance color itself, as the boxes were drawn) wash them out far more
    assert (np.abs(lighting.rendered_top_color(palette).astype(int) - palette).max(axis=1)[:5] > 60).all()
    np.testing.assert_allclose(lighting.aces(lighting.aces_inverse(np.array([[0.2, 0.3, 0.1]]))), [[0.2, 0.3, 0.1]], atol=1e-6)


def test_store_overview_counter_and_present_classes(tmp_path):
    make_map(tmp_path / "a.npz")
    make_map(tmp_path / "b.npz", seed=1, offset=(0.3, 0, 0))
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "store"), "--tile-voxels", "16"]) == 0
    v = MapViewer([tmp_path / "store"], port=free_port(), max_voxels=300)
    try:
        total = v.stores[0].total_voxels
        assert total > len(v.layers[0].state)  # the overview is a share of the store
        assert f"of its {total:,} voxels" in v.gui_status.content and "decimated" in v.gui_status.content
        assert abs(v.layers[0].weight.sum() - total) < 1e-6 * total  # each overview row stands for its share of a tile
        # the overview keeps each voxel's evidence summed, and hides those below the threshold, counted for the store
        below = (v.layers[0].state == 2) & (v.layers[0].evidence_sum < v.min_evidence)
        assert below.any() and not below[v.visible_rows[0]].any()
        assert f"about {round(v.layers[0].weight[below].sum()):,} below the evidence threshold" in v.gui_status.content
        # void labels the free-space evidence only (FREE voxels): no occupied voxel has it, so it is not offered
        assert v.present_classes == ["object", "grass"] and set(v.gui_classes) == {"object", "grass"}
    finally:
        v.server.stop()
    v = MapViewer([tmp_path / "store"], port=free_port(), max_voxels=10 * total)  # the whole store fits: nothing is left out
    try:
        assert "decimated" not in v.gui_status.content and len(v.layers[0].state) == total
    finally:
        v.server.stop()


def test_variance_slider_counts_in_a_power_of_ten(viewer):
    top = float(max(layer.variance.max() for layer in viewer.layers))
    assert 1.0 <= top / viewer.variance_unit < 10.0
    assert viewer.gui_max_variance.max * viewer.variance_unit >= top and len(f"{viewer.gui_max_variance.max:g}") <= 5
    assert viewer.max_variance >= top  # everything is shown at first


def test_terrain_surface_picking_and_cli(tmp_path, capsys):
    make_map(tmp_path / "m.npz")
    v = MapViewer([tmp_path / "m.npz"], port=free_port(), terrain=True)
    try:
        surface = v.terrain.surfaces[0]
        assert v.gui_terrain_band.options[0] == "traversability_cost" and "elevation" in v.gui_terrain_band.options
        assert len(v.terrain.handles[0].batched_positions) == len(surface.rows) > 500
        v.gui_terrain_mode.value = TERRAIN_MODES[1]
        assert all(len(rows) == 0 for rows in v.visible_rows) and "terrain surface is drawn instead" in v.gui_status.content
        # a ray straight down onto a known cell hits that cell, at its height
        row, col = surface.rows[len(surface.rows) // 2], surface.cols[len(surface.rows) // 2]
        x, y = surface.grid.cell_centers()[0][col], surface.grid.cell_centers()[1][row]
        hit = v.picking.pick_point(np.array([x, y, 20.0]) - v.origin, (0, 0, -1))
        assert hit["kind"] == "cell" and (hit["row"], hit["column"]) == (row, col)
        assert abs(hit["point"][2] - surface.height[row, col]) < 0.06
        text = surface.describe(row, col, v.layers[0].classes, "frame")
        assert f"| elevation | {surface.layers.bands['elevation'][row, col]:.4g} | m |" in text
        for band in ("surface_class", "lethal", "slope"):
            v.gui_terrain_band.value = band
            assert v.gui_terrain_legend.image.shape[1] == 220
    finally:
        v.server.stop()
    assert main(["view", str(tmp_path / "m.npz"), "--layers", "--layers-resolution-m", "0.4", "--no-serve", "--port", str(free_port()),
                 "--export-html", str(tmp_path / "t.html")]) == 0
    assert "terrain surface: traversability_cost" in (tmp_path / "t.html").read_text()
    assert main(["view", str(tmp_path / "m.npz"), "--layers", "--layers-resolution-m", "0.1", "--no-serve", "--port", str(free_port())]) == 2
    assert "finer than the map's voxels" in capsys.readouterr().err


def test_orientation_grid_and_measuring(viewer):
    g = viewer.ground
    assert g.section in (1.0, 2.0) and g.x0 <= 100.0 and g.x1 >= 106.0 and g.x0 % g.section == 0
    assert "x 100 m" in [t for t, _ in g.labels] and "y 106 m" in [t for t, _ in g.labels]
    # an even number of sections (viser draws a grid about its center), and every line labelled: the line added
    # to make the number even had none
    for lo, hi in ((np.array([0.0, 0.0, 0.0]), np.array([25.0, 31.0, 2.0])), (np.array([-3.0, 1.0, 0.0]), np.array([5.0, 2.5, 1.0]))):
        grid = orientation.ground_grid(lo, hi, 0.0)
        sections_x, sections_y = round((grid.x1 - grid.x0) / grid.section), round((grid.y1 - grid.y0) / grid.section)
        assert sections_x % 2 == 0 and sections_y % 2 == 0
        assert len(grid.labels) == sections_x + 1 + sections_y + 1
        assert f"y {orientation.format_metres(grid.y1, grid.section)}" in [t for t, _ in grid.labels]
    assert orientation.nice_length(7.3) == 5.0 and orientation.nice_length(0.034) == 0.02 and orientation.nice_length(1.0) == 1.0
    html_text, metres, pixels = orientation.scale_bar_html(0.05)
    assert metres == 5.0 and pixels == 100.0 and 'data-metres="5"' in html_text

    layer = viewer.layers[0]
    rows = viewer.visible_rows[0]
    top = rows[np.argmax(layer.centers[rows, 2])]
    near = rows[np.argmin(np.abs(layer.centers[rows, 0] - 105.5) + np.abs(layer.centers[rows, 1] - 105.5) + (layer.label[rows] != 7))]
    column = rows[np.all(layer.voxel_index[rows, :2] == layer.voxel_index[near, :2], axis=1)]
    ground = column[np.argmax(layer.centers[column, 2])]  # the highest voxel of that column: the one a ray from above meets
    viewer.gui_measure.value = True
    for row in (ground, top):
        viewer.picking.click(layer.centers[row] - viewer.origin + [0, 0, 10], (0, 0, -1))
    a, b = viewer.measure_points
    np.testing.assert_allclose(a[:2], layer.centers[ground, :2])
    assert abs(a[2] - (layer.centers[ground, 2] + layer.resolution / 2)) < 1e-6  # the top face the ray enters
    assert abs((b[2] - a[2]) - (layer.centers[top, 2] - layer.centers[ground, 2])) < 1e-6
    assert f"height difference **{b[2] - a[2]:+.3f} m**" in viewer.gui_measure_result.content
    assert "clicked point in" in viewer.gui_selection.content
    viewer.gui_measure.value = False
    assert viewer.measure_points == [] and viewer.gui_measure_result.content == ""


def test_a_long_map_framed_whole_is_inside_the_far_clipping_plane(viewer):
    """viser clips at 1 km by default: a 1.9 km store, framed whole, drew nothing (its camera 2.2 km away)."""
    viewer.cameras.frame(np.array([-50.0, -50.0, -4.0]), np.array([1837.0, 50.0, 12.0]))
    position, look_at = viewer.cameras.auto_camera
    farthest = np.linalg.norm(position - look_at) + 1887.0  # to the far end of the map, at most
    assert viewer.server.initial_camera.far >= 2 * farthest
    assert viewer.cameras.far_plane_m(10.0) == 1000.0  # small maps keep viser's default


def test_points_keep_a_visible_size_when_the_camera_is_far(viewer):
    """viser sizes points in world units with no screen minimum: a long store seen whole (0.2 m voxels over
    kilometres) drew nothing. Far away, a point is at least MIN_POINT_PX at the orbit center; near, a voxel."""

    class Camera:
        def __init__(self, distance):
            self.look_at, self.position = np.zeros(3), np.array([0.0, 0.0, distance])
            self.fov, self.image_height = 1.0, 800

    layer, handle = viewer.layers[0], viewer.voxels.handles[0]
    viewer.cameras.update_scale_bar(Camera(5.0))
    assert handle.point_size == pytest.approx(layer.resolution)
    viewer.cameras.update_scale_bar(Camera(2000.0))
    m_per_px = orientation.metres_per_pixel(np.array([0.0, 0.0, 2000.0]), np.zeros(3), 1.0, 800)
    assert handle.point_size == pytest.approx(viewer.voxels.MIN_POINT_PX * m_per_px) and handle.point_size > 10 * layer.resolution
    viewer.refresh()  # a layer drawn again (new tiles, a control) keeps the size
    assert viewer.voxels.handles[0].point_size == pytest.approx(viewer.voxels.MIN_POINT_PX * m_per_px)
    viewer.cameras.update_scale_bar(Camera(5.0))
    assert viewer.voxels.handles[0].point_size == pytest.approx(layer.resolution)


def _projection(path, dirt_below_x):
    import json

    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 6, (6000, 2)), rng.normal(0, 0.02, 6000)]
    labels = np.where(ground[:, 0] < dirt_below_x, 6, 7)
    np.savez_compressed(path, points=ground + [100.0, 100.0, 0.0], labels=labels, frame=np.array(json.dumps({"name": "odom"})))
    return path


def test_diff_counts_against_a_projection_and_a_map(tmp_path, capsys):
    make_map(tmp_path / "a.npz", frame=WorldFrame("odom"))
    make_map(tmp_path / "b.npz", frame=WorldFrame("odom"), dirt_below_x=1.5)
    truth = _projection(tmp_path / "ground_truth.npz", 0.75)
    v = MapViewer([tmp_path / "a.npz", tmp_path / "b.npz"], port=free_port(), truth=truth)
    try:
        v.gui_diff.value = "labels differ"
        diff = v.comparison.diff()
        a, b = v.layers
        x = a.centers[diff.a_rows, 0]
        category = diff.category()
        # the strip the second map calls dirt: left of 100.75 the truth agrees with it, right of it with the first
        judged = diff.differ & (diff.truth >= 0)  # voxels the truth's points fall in
        assert (category[judged & (x < 100.6)] == 1).mean() > 0.9 and (category[judged & (x > 100.9)] == 0).mean() > 0.9
        assert (category[diff.differ & (diff.truth < 0)] == 3).all()
        assert not diff.differ[x > 101.8].any()
        shown = v.visible_rows[0]
        drawn = diff.differ & (a.state[diff.a_rows] == 2) & v.voxels.known(0)[diff.a_rows]  # OCCUPIED and known voxels that differ
        assert set(np.unique(a.label[shown])) <= {6, 7} and len(shown) == drawn.sum()
        assert f"labels differ in **{int(drawn.sum()):,}**" in v.gui_diff_status.content  # the counts are the drawn voxels'
        assert drawn.sum() < diff.differ.sum()  # below the evidence threshold, labels that differ are not counted
        counts = diff.counts()
        assert counts["first map agrees with the truth"] + counts["second map agrees with the truth"] + counts["neither agrees with the truth"] \
            + counts["labels differ (no truth here)"] == counts["differ"]
        v.gui_diff.value = "variance difference"
        assert "variance of the first minus the second" in v.gui_diff_status.content
        np.testing.assert_allclose(diff.variance_difference, a.variance[diff.a_rows] - b.variance[diff.b_rows])
        # a map as the truth: its labels where it is occupied
        truth_map = comparison.load_truth(tmp_path / "b.npz", a, WorldFrame("odom"))
        occupied = b.state[diff.b_rows] == 2
        np.testing.assert_array_equal(truth_map[diff.a_rows][occupied], b.label[diff.b_rows][occupied])
    finally:
        v.server.stop()
    with pytest.raises(ValueError, match="compare with the truth.*'map'.*'odom'|'odom'.*'map'"):
        comparison.load_truth(_projection(tmp_path / "gt.npz", 0.75), a, WorldFrame("map"))
    np.savez(tmp_path / "junk.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not a ground truth"):
        comparison.load_truth(tmp_path / "junk.npz", a, WorldFrame("odom"))
    assert main(["view", str(tmp_path / "a.npz"), "--truth", str(tmp_path / "none.npz"), "--no-serve", "--port", str(free_port())]) == 2
    assert "no such ground-truth file" in capsys.readouterr().err


def test_html_export_holds_the_legend(viewer, tmp_path):
    page = viewer.export_html(tmp_path / "scene.html").read_text()
    legend = page[page.index('<div id="evsemmap-legend"'):]
    assert "grass" in legend and "object" in legend and "sky" not in legend and "color by semantic" in legend
    viewer.gui_color_by.value = "variance"
    page = viewer.export_html(tmp_path / "scene2.html").read_text()
    assert 'alt="color bar' in page and "data:image/png;base64," in page


def test_examples_and_the_viewer_tools_use_no_private_names():
    """Issue 47: examples drove the viewer's private handlers (``_approach``, ``_on_camera``, ``_on_click``); they use
    its public methods and handles (``tiles.approach``, ``cameras.report``, ``picking.click``), as a user's script would."""
    import ast

    files = sorted((REPO / "examples").glob("*.py")) + [REPO / "tools/viewer_screenshots.py", REPO / "tools/bench_viewer.py"]
    wrong = [f"{path.name}:{node.lineno} .{node.attr}" for path in files for node in ast.walk(ast.parse(path.read_text()))
             if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")]
    assert not wrong, f"private names used: {wrong}"
