"""Watching maps being made (issue 30 item 5) in-process: map --view, its segments, a slow viewer, batch tiles."""

import time

import numpy as np
import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp import Mapper
from evsemmap_warp.apps.scan_sources import map_scans, open_scan_source
from evsemmap_warp.apps.viewer import MapLayer, MapViewer, free_port
from evsemmap_warp.apps.viewer.live import LiveMap, LiveTiles, map_live, reading_template
from evsemmap_warp.config import load_config
from evsemmap_warp.core.mapper import read_map_arrays
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence

LAYER_ARRAYS = ("voxel_index", "centers", "alpha", "label", "state", "variance", "hits")


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live") / "seq"
    generate_sequence(load_preset("tiny", trajectory__frames=8), folder, progress=False)
    return folder


def _source_and_mapper(sequence):
    run = load_config([str(sequence), "rellis3d"], method="ebs")
    source = open_scan_source(run)
    return source, Mapper.for_dataset(source, run.mapping)


def _empty_viewer(mapper, path):
    return MapViewer([MapLayer.from_mapper(path.stem, path, mapper)], port=free_port())


def test_map_view_serves_while_mapping_and_ends_with_the_map_as_written(sequence, tmp_path, monkeypatch, capsys):
    seen = {}

    def instead_of_serving(viewer):  # the command would serve until Ctrl-C
        seen["layer"] = viewer.layers[0]
        viewer.server.stop()

    monkeypatch.setattr(MapViewer, "serve_forever", instead_of_serving)
    out = tmp_path / "live.npz"
    assert main(["map", str(sequence), "rellis3d", "--method", "ebs", "--out", str(out), "--view", "--view-every", "3",
                 "--port", str(free_port()), "--quiet"]) == 0
    assert "shows the map as written to" in capsys.readouterr().err
    arrays, _ = read_map_arrays(out)
    shown = seen["layer"]
    for key in LAYER_ARRAYS:  # bit for bit what the file holds
        np.testing.assert_array_equal(getattr(shown, key), arrays[key], err_msg=key)
    assert shown.name == "live" and len(shown.state) > 1000


def test_segments_map_the_same_map_and_the_viewer_follows(sequence, tmp_path):
    source, mapper = _source_and_mapper(sequence)
    viewer = _empty_viewer(mapper, tmp_path / "m.npz")
    live = LiveMap(viewer, mapper, name="m", path=tmp_path / "m.npz", scan_total=len(source))
    try:
        stats = map_live(mapper, source, live, every=3)
        assert len(stats) == len(source) == 8
        _, direct = _source_and_mapper(sequence)
        map_scans(direct, source)
        (a, sa), (b, sb) = mapper.voxels(), direct.voxels()
        np.testing.assert_array_equal(a.index, b.index)
        np.testing.assert_array_equal(a.evidence, b.evidence)  # segments change nothing, not even summation order
        np.testing.assert_array_equal(sa.label, sb.label)
        assert live.wait_idle() and live.updates >= 1 and not live.errors
        final = live.show_final()
        assert viewer.layers[0] is final and len(final.state) == len(a.index)
        assert "**done**" in live.gui_status.content and "8 of 8 scans" in live.gui_status.content
        assert len(live.sensor_path) == 3  # one sensor position per update: after scans 3, 6 and 8
        np.testing.assert_allclose(live.sensor_path[-1], list(source.scans(7, 8))[0].sensor_origin)
        assert viewer._origin_from_data and np.all(np.abs(final.centers - viewer.origin).max(axis=0) < 100)
    finally:
        live.close()
        viewer.server.stop()


def test_a_slow_viewer_never_holds_mapping_back(sequence, tmp_path, monkeypatch):
    source, mapper = _source_and_mapper(sequence)
    viewer = _empty_viewer(mapper, tmp_path / "m.npz")
    drawn = viewer.replace_layer

    def slow(i, layer):
        time.sleep(3.0)
        drawn(i, layer)

    monkeypatch.setattr(viewer, "replace_layer", slow)
    live = LiveMap(viewer, mapper, name="m", path=tmp_path / "m.npz")
    try:
        map_live(mapper, source, live, every=1)  # warm: kernels compiled, files cached
        live.wait_idle(30)
        source, mapper = _source_and_mapper(sequence)
        live.mapper = mapper
        started = time.perf_counter()
        map_live(mapper, source, live, every=1)
        mapping = time.perf_counter() - started
        assert live.busy, "the viewer was done before mapping: not slow enough to tell"
        assert mapping < 3.0, f"mapping took {mapping:.1f} s beside a viewer that takes 3 s an update"
        assert live.offers_skipped >= 5  # copies are not made while the viewer is busy
        assert live.copy_seconds < 1.0
    finally:
        live.close()
        viewer.server.stop()


def test_bad_live_input_is_one_line(sequence, tmp_path, capsys):
    base = ["map", str(sequence), "rellis3d", "--method", "ebs", "--quiet"]
    assert main(base + ["--out", str(tmp_path / "a.npz"), "--view-every", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--view" in err
    assert main(base + ["--out", str(tmp_path / "b.npz"), "--view", "--host", "192.0.2.1", "--port", str(free_port())]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "192.0.2.1" in err
    assert not (tmp_path / "a.npz").exists() and not (tmp_path / "b.npz").exists()  # refused before mapping


def _store_tiles(tmp_path):
    """Tiles of a small store (run_batch's on_tile gets the same: a tile's voxels, global indices) and its template."""
    from test_viewer import make_map

    from evsemmap_warp.core.map_store import MapStore

    make_map(tmp_path / "a.npz")
    make_map(tmp_path / "b.npz", seed=1, offset=(0.3, 0, 0))
    assert main(["merge", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "store"), "--tile-voxels", "16"]) == 0
    store = MapStore(tmp_path / "store")
    tiles = {name: store.tile_arrays(name) for name in sorted(store.tiles)}
    return store, tiles


def test_live_tiles_overview_of_running_sums(tmp_path):
    store, tiles = _store_tiles(tmp_path)
    template = reading_template(store.tile(next(iter(tiles))))
    viewer = MapViewer([MapLayer.from_mapper("store", tmp_path / "store", template)], port=free_port())
    live = LiveTiles(viewer, template, name="store", path=tmp_path / "store", max_voxels=800)
    try:
        names = list(tiles)
        assert len(names) > 2
        first = tiles[names[0]]
        half = len(first.index) // 2
        from evsemmap_warp.apps.viewer.live import _decimated

        live(names[0], _decimated(first, half))  # the tile's sum after its first chunk: some of its voxels
        assert live.wait_idle()
        assert live.voxel_counts[names[0]] == half
        for name in names:  # then every tile's final sum
            live(name, tiles[name])
        assert live.wait_idle() and not live.errors
        layer = viewer.layers[0]
        total = sum(len(t.index) for t in tiles.values())
        assert round(layer.weight.sum()) == total and len(layer.state) <= 1.5 * 800
        assert f"{len(names)} tiles so far, {total:,} voxels" in live.gui_status.content
        assert "decimated: the overview holds" in viewer.gui_status.content and f"tiles' {total:,} voxels" in viewer.gui_status.content
        # every voxel shown is the store's, with its label
        whole = store.to_mapper()
        result = whole.query(layer.centers)
        np.testing.assert_array_equal(result.label, layer.label)
        assert set(viewer.present_classes) == {"object", "grass"}  # toggles appeared with the tiles
    finally:
        live.close()
        viewer.server.stop()


def test_batch_view_shows_the_tiles_as_they_are_folded(sequence, tmp_path, monkeypatch, capsys):
    from evsemmap_warp.core.map_store import MapStore

    seen = {}

    def instead_of_serving(viewer):
        seen["layer"], seen["status"] = viewer.layers[0], viewer.gui_status.content
        viewer.server.stop()

    monkeypatch.setattr(MapViewer, "serve_forever", instead_of_serving)
    calls = []
    received = LiveTiles.__call__

    def counted(self, name, voxels):
        calls.append((name, len(voxels.index)))
        received(self, name, voxels)

    monkeypatch.setattr(LiveTiles, "__call__", counted)
    out = tmp_path / "store"
    assert main(["batch", str(sequence), "rellis3d", "--method", "ebs", "--out", str(out), "--workers", "1", "--chunk-frames", "2",
                 "--tile-voxels", "64", "--view", "--port", str(free_port()), "--quiet"]) == 0
    assert "watch the store's tiles fill in" in capsys.readouterr().err
    store = MapStore(out)
    layer = seen["layer"]
    assert round(layer.weight.sum()) == store.voxel_count and len(store.tiles) > 1
    np.testing.assert_array_equal(store.query(layer.centers).label, layer.label)
    assert {name for name, _ in calls} == set(store.tiles)
    assert len(calls) > len(store.tiles)  # a tile's running sum comes again as later chunks reach it


def test_batch_view_flags_need_view(sequence, tmp_path, capsys):
    assert main(["batch", str(sequence), "rellis3d", "--method", "ebs", "--out", str(tmp_path / "s"), "--port", "8123", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--view" in err and not (tmp_path / "s").exists()


class _Camera:
    def __init__(self, position, look_at):
        self.position, self.look_at = np.asarray(position, float), np.asarray(look_at, float)


class _Client:
    def __init__(self, camera):
        self.camera = camera


def test_cameras_follow_the_growing_map_despite_late_reports_and_stop_once_moved(sequence, tmp_path, monkeypatch):
    """A browser reports its camera a move or two late (sent before the move arrived): it has still not been moved
    by its user and keeps following; a camera the user moved stays where the user put it. (A browser test failed
    in CI when only the last move counted: the tiles grew the map past a camera that reported late.)"""
    source, mapper = _source_and_mapper(sequence)
    viewer = _empty_viewer(mapper, tmp_path / "live.npz")
    try:
        first = viewer.cameras.auto_camera
        lagging = _Camera(*first)  # reports the first placement while the viewer moves on twice
        moved = _Camera(first[0] + np.array([5.0, 0.0, 0.0]), first[1])
        monkeypatch.setattr(viewer.server, "get_clients", lambda: {1: _Client(lagging), 2: _Client(moved)})
        viewer.cameras.frame(np.zeros(3), np.full(3, 10.0))
        second = viewer.cameras.auto_camera
        lagging.position, lagging.look_at = first[0].copy(), first[1].copy()  # its report of the first placement arrives late
        viewer.cameras.frame(np.zeros(3), np.full(3, 40.0))
        third = viewer.cameras.auto_camera
        assert not np.allclose(second[0], third[0])
        np.testing.assert_allclose(lagging.position, third[0])
        np.testing.assert_allclose(lagging.look_at, third[1])
        np.testing.assert_allclose(moved.position, first[0] + np.array([5.0, 0.0, 0.0]))
    finally:
        viewer.server.stop()
