"""Stores in the viewer at scale (issue 30 item 6): a first frame before the store is read, the overview filling in,
tiles in full near the camera or where a click lands, and memory bounded by what is shown."""

import re
import shutil
import time
from types import SimpleNamespace

import numpy as np
import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp.apps.viewer import MapViewer, StoreOverview, free_port
from evsemmap_warp.core.map_store import TILE_SUFFIX

from conftest import run_cli, wait_until
from test_viewer import make_map


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    folder = tmp_path_factory.mktemp("store")
    make_map(folder / "a.npz")
    make_map(folder / "b.npz", seed=1, offset=(0.3, 0, 0))
    assert main(["merge", str(folder / "a.npz"), str(folder / "b.npz"), "--out", str(folder / "store"), "--tile-voxels", "8"]) == 0
    return folder / "store"


def _wait(predicate, timeout=30.0):
    return wait_until(predicate, timeout)  # this module's default wait


def test_first_frame_from_the_first_tiles_then_the_overview_fills_in(store):
    viewer = MapViewer([store], port=free_port(), max_voxels=600, store_first_voxels=1)
    overview = viewer.stores[0]
    try:
        tiles = len(overview.store.tiles)
        assert tiles > 10
        origin = viewer.origin.copy()
        lo, hi = overview.bounds
        np.testing.assert_array_equal(origin, np.round((lo + hi) / 2))  # the whole store's middle, before it is read
        assert _wait(lambda: overview.complete)
        assert _wait(lambda: len(viewer.layers[0].state) == overview.held_rows)
        np.testing.assert_array_equal(viewer.origin, origin)  # the origin does not move as tiles arrive
        assert overview.held_rows <= 600 + tiles  # each tile its share of max_voxels (at least one row)
        assert round(viewer.layers[0].weight.sum()) == overview.total_voxels
        assert set(viewer.present_classes) == {"object", "grass"}
        # the counter is rewritten by the redraw that follows the last tile's rows, on the viewer's thread
        assert _wait(lambda: "reading its tiles" not in viewer.gui_status.content), viewer.gui_status.content
    finally:
        viewer.close()


def test_the_first_tiles_are_the_middle_ones_within_the_budget(store):
    overview = StoreOverview(store, 600)
    sizes = [overview.store.tiles[name]["voxels"] for name in overview.unread]
    center = (overview.bounds[0] + overview.bounds[1]) / 2
    distances = [np.linalg.norm(np.mean(overview.store.tiles[n]["bounds_m"], axis=0)[:2] - center[:2]) for n in overview.unread]
    assert distances == sorted(distances)
    overview.read_first(sizes[0] + sizes[1])
    assert len(overview.parts) == 2 and len(overview.unread) == len(sizes) - 2
    overview.read_first(1)  # at least one tile, whatever the budget
    assert len(overview.parts) == 3


def test_tiles_in_full_near_the_camera_and_where_a_click_lands(store):
    viewer = MapViewer([store], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    try:
        assert overview.complete and overview.detail == ()
        layer = viewer.layers[0]
        # the camera comes near the box's tiles: their columns in full
        box = layer.centers[layer.label == 3].mean(axis=0)
        look_at = box - viewer.origin
        far = SimpleNamespace(position=look_at + [0, -20.0, 20.0], look_at=look_at)
        viewer.tiles.approach(far)  # 28 m away, further than 4 tile edges (6.4 m) from every tile: nothing happens
        time.sleep(0.5)
        assert overview.detail == ()
        near = SimpleNamespace(position=look_at + [0, -0.5, 0.8], look_at=look_at)
        viewer.tiles.approach(near)
        # the column it looks at (its tiles the overview thins out), and the tiles nearest it, up to the store's
        # limit; the nearest asked for last, to be kept longest
        column = [name for name in overview.tiles_at(box) if overview.decimated(name)]
        assert 0 < len(column) < overview.max_detail_tiles
        assert _wait(lambda: len(overview.detail) == overview.max_detail_tiles and set(overview.detail[-len(column):]) == set(column))
        assert _wait(lambda: "tile(s) in full" in viewer.gui_status.content)
        shown = viewer.layers[0]
        index = shown.voxel_index
        for name in column:  # every voxel of those tiles is held, each standing for one
            key = np.array([int(v) for v in name.split("_")])
            inside = np.all(np.floor_divide(index, overview.store.tile_voxels) == key, axis=1)
            assert inside.sum() == overview.store.tiles[name]["voxels"] and np.all(shown.weight[inside] == 1.0)
        # a click on a voxel of another tile: that tile's column in full as well
        drawn = viewer.voxels.visible_mask(0)  # a voxel below the evidence threshold is not drawn, nor clicked
        ground = shown.centers[drawn & (shown.label == 7) & np.all(np.abs(shown.centers[:, :2] - box[:2]) > 2.0, axis=1)][0]
        ray_origin = ground - viewer.origin + [0, 0, 5.0]
        viewer.picking.click(ray_origin, (0.0, 0.0, -1.0))
        assert "voxel" in viewer.gui_selection.content
        clicked = overview.tiles_at(ground)
        assert _wait(lambda: set(clicked) <= set(overview.detail) and set(column) <= set(overview.detail))
    finally:
        viewer.close()


def test_a_click_beside_an_overview_point_picks_it_and_its_tile(store):
    """Issue 45: a decimated overview's points stand apart, so a click ray passes between them; one passing within a
    few pixels of a point picks it (and brings its tile in full), not the ground grid's plane under it."""
    viewer = MapViewer([store], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    try:
        layer = viewer.layers[0]
        viewer.cameras.scale_bar = (1.0, 10.0, 0.1)  # 0.1 m a pixel at the orbit center: CLICK_RADIUS_PX is 0.6 m
        shown = layer.centers[viewer.visible_rows[0]]
        # a point whose column 0.4 m east holds no overview point: a ray straight down there met none before
        lonely = next(c for c in shown if not np.any(np.all(np.abs(shown[:, :2] - (c[:2] + [0.4, 0.0])) < 0.1, axis=1)))
        ray_origin = lonely + [0.4, 0.0, 30.0] - viewer.origin
        hit = viewer.picking.pick_point(ray_origin, (0.0, 0.0, -1.0))
        assert hit is not None and hit["kind"] == "voxel", hit
        picked = layer.centers[hit["row"]]
        assert np.linalg.norm(picked[:2] - lonely[:2] - [0.4, 0.0]) <= 0.6 and picked[2] >= lonely[2]
        viewer.picking.click(ray_origin, (0.0, 0.0, -1.0))
        assert "ground grid" not in viewer.gui_selection.content and "voxel" in viewer.gui_selection.content
        assert _wait(lambda: set(overview.tiles_at(picked)) & set(overview.detail))
    finally:
        viewer.close()


def test_tiles_are_listed_along_the_store_by_where_they_are_and_flown_to(store):
    """Issue 45: the *Store tile in full* list names tiles by their key and place ("tile (x, y, z) at E.. m N.. m"), in
    order along the store, and choosing one puts every browser's camera over it."""
    viewer = MapViewer([store], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    try:
        labels = list(viewer.tiles.choices)
        assert viewer.gui_tile.options[1:] == tuple(labels) and len(labels) == len(overview.store.tiles)
        assert all(re.fullmatch(r"tile \(-?\d+, -?\d+, -?\d+\) at E-?\d+ m N-?\d+ m, \d+ m along", label) for label in labels)
        along = [overview.along[viewer.tiles.choices[label][1]] for label in labels]
        assert along == sorted(along) and along[0] == 0.0 and along[-1] > 4.0
        middle = labels[len(labels) // 2]
        name = viewer.tiles.choices[middle][1]
        east, north, _ = overview.boxes[name].mean(axis=0)
        assert middle.startswith(f"tile {tuple(int(v) for v in name.split('_'))} at E{east:.0f} m N{north:.0f} m")
        viewer.tiles.show(middle)
        assert overview.detail == (name,)
    finally:
        viewer.close()


def test_the_tile_nearest_the_view_is_shown_before_the_others(store):
    """Tiles asked for together (a camera's approach, nearest last) are read and sent nearest first, then the rest
    with it: the tile a user looks at is not kept waiting for its neighbours' reads and the larger send."""
    viewer = MapViewer([store], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    shown = []
    replace_layer = viewer.replace_layer

    def recording(i, layer):
        shown.append(overview.detail)
        replace_layer(i, layer)

    viewer.replace_layer = recording
    try:
        names = sorted(overview.store.tiles)[:4]
        viewer.tiles.request(0, names)
        assert _wait(lambda: len(shown) == 2)
        assert shown == [(names[-1],), tuple(names[:-1]) + (names[-1],)]
    finally:
        viewer.close()


def test_memory_is_bounded_by_the_tiles_shown(store):
    viewer = MapViewer([store], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    overview.max_detail_tiles = 3
    try:
        sizes = sorted((info["voxels"] for info in overview.store.tiles.values()), reverse=True)
        overview_rows = sum(len(p["state"]) for p in overview.parts.values())
        for name in sorted(overview.store.tiles):  # a drive over the whole store, tile by tile
            viewer.tiles.request(0, [name])
            assert _wait(lambda: name in overview.detail)
            assert len(overview.detail) <= 3
            assert overview.held_rows <= overview_rows + sum(sizes[:3])
            assert len(viewer.layers[0].state) <= overview_rows + sum(sizes[:3])
        viewer.tiles.show("(overview only)")
        assert overview.detail == () and overview.held_rows == overview_rows
    finally:
        viewer.close()


def test_exports_wait_for_the_whole_overview(store, tmp_path, monkeypatch):
    read_next = StoreOverview.read_next

    def slowly(self):
        time.sleep(0.05)
        return read_next(self)

    monkeypatch.setattr(StoreOverview, "read_next", slowly)
    viewer = MapViewer([store], port=free_port(), max_voxels=600, store_first_voxels=1)
    overview = viewer.stores[0]
    try:
        assert not overview.complete and "reading its tiles" in viewer.gui_status.content
        assert viewer.wait_for_stores(60)
        assert overview.complete and len(viewer.layers[0].state) == sum(len(p["state"]) for p in overview.parts.values())
        from test_viewer import read_ply

        _, vertices = read_ply(viewer.export_ply(tmp_path / "all.ply"))
        assert len(vertices) == len(viewer.visible_rows[0]) > 0
    finally:
        viewer.close()


@pytest.mark.parametrize("which", ["a middle tile", "the last tile"])
def test_an_export_of_a_store_with_an_unreadable_tile_is_one_line_naming_it(store, tmp_path, monkeypatch, capsys, which):
    """view --export-ply --no-serve of a store whose tile cannot be read after the first frame (the loader's): the
    export left the tile out, said only in the status line, and exited 0; were it the last tile read, the export
    waited for ever. It is refused as `evsemmap export` refuses the store, in one line naming the tile."""
    copy = tmp_path / "store"
    shutil.copytree(store, copy)
    order = StoreOverview(copy, 600).unread  # the order the viewer reads the tiles in
    name = order[len(order) // 2] if which == "a middle tile" else order[-1]
    tile = copy / "tiles" / f"{name}{TILE_SUFFIX}"
    data = bytearray(tile.read_bytes())
    data[-9] ^= 0xFF
    tile.write_bytes(bytes(data))
    monkeypatch.setattr(MapViewer, "FIRST_FRAME_ROWS", 1)  # the first frame reads one tile: the loader the rest
    line = run_cli(capsys, "view", copy, "--export-ply", tmp_path / "all.ply", "--no-serve", "--port", free_port())
    assert str(tile) in line and "payload checksum mismatch" in line, line
    assert not (tmp_path / "all.ply").exists()


def test_an_export_past_a_tile_failing_otherwise_is_still_one_line(store, tmp_path, monkeypatch, capsys):
    """A tile whose read fails with something other than the store's refusals (here a RuntimeError) is named in
    the same one line, not shown as a traceback."""
    order = StoreOverview(store, 600).unread
    real = StoreOverview._read

    def failing(self, name, rows):
        if name == order[-1]:
            raise RuntimeError("the disk went away")
        return real(self, name, rows)

    monkeypatch.setattr(StoreOverview, "_read", failing)
    monkeypatch.setattr(MapViewer, "FIRST_FRAME_ROWS", 1)
    line = run_cli(capsys, "view", store, "--export-ply", tmp_path / "all.ply", "--no-serve", "--port", free_port())
    assert f"tile {order[-1]} could not be read (RuntimeError: the disk went away)" in line and str(store) in line, line


def test_a_small_store_is_read_whole_before_the_first_frame(store):
    """A store whose tiles fit the first frame's budget is complete when the viewer is built (its overview
    rows are its voxels, not its shares of a max_voxels larger than the store)."""
    viewer = MapViewer([store], port=free_port())  # max_voxels 500k: far more than the store holds
    try:
        assert viewer.stores[0].complete and len(viewer.layers[0].state) == viewer.stores[0].total_voxels
    finally:
        viewer.close()


def test_a_browsers_first_default_camera_is_not_an_approach(store, tmp_path):
    """A browser first reports viser's default camera, 5 m from the scene's origin, before the viewer's own:
    that is not a user coming near a tile (it put the origin's tiles in full on every page load)."""
    folder = store.parent  # the maps the store was merged from, into tiles of 6.4 m: the default camera is within one
    assert main(["merge", str(folder / "a.npz"), str(folder / "b.npz"), "--out", str(tmp_path / "store"), "--tile-voxels", "32"]) == 0
    viewer = MapViewer([tmp_path / "store"], port=free_port(), max_voxels=300)
    overview = viewer.stores[0]
    try:
        viewer.cameras.report(SimpleNamespace(position=np.array([3.0, 3.0, 3.0]), look_at=np.zeros(3), fov=1.0, image_height=800), client_id=7)
        time.sleep(0.5)
        assert overview.detail == ()
        position, look_at = viewer.cameras.auto_camera  # then the viewer's camera arrives; from there on, the user moves
        viewer.cameras.report(SimpleNamespace(position=position, look_at=look_at, fov=1.0, image_height=800), client_id=7)
        viewer.cameras.report(SimpleNamespace(position=np.array([0.0, -0.5, 1.0]), look_at=np.zeros(3), fov=1.0, image_height=800), client_id=7)
        assert _wait(lambda: overview.detail != ())
    finally:
        viewer.close()
