"""Drive playback (issue 30 item 3) in-process: the replay's maps, the scan, pose and camera drawn, bad input."""

import numpy as np
import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp import Mapper
from evsemmap_warp.apps.scan_sources import open_scan_source
from evsemmap_warp.apps.viewer import MapViewer, free_port
from evsemmap_warp.apps.viewer.colors import colormap
from evsemmap_warp.apps.viewer.drive import DrivePlayback, at_image_size, open_drive, pixel_values
from evsemmap_warp.config import PayloadType, load_config
from evsemmap_warp.core.mapper import read_map_arrays
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence, write_stand_in_alpha

from conftest import REPO, wait_until


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A tiny synthetic drive, its map from point labels, alpha files and the map from them."""
    root = tmp_path_factory.mktemp("drive")
    generate_sequence(load_preset("tiny"), root / "seq", progress=False)
    assert main(["map", str(root / "seq"), "rellis3d", "--method", "ebs", "--out", str(root / "labels.npz"), "--quiet"]) == 0
    write_stand_in_alpha(root / "seq", root / "alpha")
    assert main(["map", str(root / "seq"), "rellis3d", "--method", "ebs", "--alpha-dir", str(root / "alpha"), "--bin-frames", "2",
                 "--out", str(root / "alpha.npz"), "--quiet"]) == 0
    return root


def _mapped(root, scans, **source_options):
    """A Mapper of the drive's first ``scans`` insertions, mapped directly (what the replay must give)."""
    run = load_config([str(root / "seq"), "rellis3d"], method="ebs")
    source = open_scan_source(run, **source_options)
    mapper = Mapper.for_dataset(source, run.mapping)
    mapper.integrate_many(source.scans(0, scans))
    return mapper


def test_replay_gives_the_map_after_each_scan_in_any_order(drive, capsys):
    capsys.readouterr()
    drive_, replay = open_drive(drive / "labels.npz", [drive / "seq", "rellis3d"], snapshot_every=2)
    assert len(drive_) == 6 and replay.snapshot_every == 2
    for scans in (5, 1, 6, 3, 4, 2):  # forward, back to a snapshot, on from the map built last
        mapper = replay.map_after(scans)
        (got, got_summary), (want, want_summary) = mapper.voxels(), _mapped(drive, scans).voxels()
        np.testing.assert_array_equal(got.index, want.index)
        np.testing.assert_array_equal(got_summary.label, want_summary.label)
        np.testing.assert_allclose(got.evidence, want.evidence, rtol=1e-12, atol=1e-12)
    assert sorted(replay.snapshots) == [0, 2, 4, 6]
    assert replay.map_after(3, cancelled=lambda: True) is None  # a newer wish stops the replay between scans


def test_playback_draws_the_scan_the_pose_and_the_map_as_it_stood(drive):
    file_arrays, _ = read_map_arrays(drive / "labels.npz")
    drive_, replay = open_drive(drive / "labels.npz", [drive / "seq", "rellis3d"], snapshot_every=2)
    viewer = MapViewer([drive / "labels.npz"], port=free_port())
    playback = DrivePlayback(viewer, drive_, replay)
    try:
        assert playback.wait_until_drawn(5), playback.errors
        assert len(viewer.layers[0].state) == len(file_arrays["state"])  # the last scan: the map file itself
        assert playback.gui_scan.max == 6 and playback.gui_scan.value == 6  # counted from 1, as the status line counts
        playback.show(1)
        assert playback.wait_until_drawn(1), playback.errors
        want = _mapped(drive, 2)
        np.testing.assert_array_equal(viewer.layers[0].voxel_index, want.voxels()[0].index)
        assert "scan **2** of 6" in playback.gui_status.content and "as it stood after scan 2" in playback.gui_status.content
        scan = drive_.scan(1)
        np.testing.assert_allclose(playback.scan_handle.points, (scan.points - viewer.origin).astype(np.float32))
        pose = drive_.poses[1]
        np.testing.assert_allclose(playback.pose_handle.position, pose[:3, 3] - viewer.origin, atol=1e-5)
        assert np.allclose(scan.sensor_origin, pose[:3, 3])  # the pose drawn is the scan's sensor
        # without "map as of", the map file again
        playback.gui_map_as_of.value = False
        assert playback.wait_until_drawn(1)
        assert len(viewer.layers[0].state) == len(file_arrays["state"])
        # idle: the snapshots fill in to the end, and the replay gives the map file back
        assert wait_until(lambda: "give the map file back" in playback.replay_check, 60), playback.replay_check
    finally:
        playback.close()
        viewer.server.stop()


def test_playback_of_an_alpha_labelled_map_shows_the_camera_labels_and_uncertainty(drive):
    drive_, replay = open_drive(drive / "alpha.npz", [drive / "seq", "rellis3d"], alpha_dir=drive / "alpha", bin_frames=2)
    assert len(drive_) == 3 and [f.index for f in drive_.insertions[1]] == [2, 3]  # bins of two frames, as mapped
    viewer = MapViewer([drive / "alpha.npz"], port=free_port())
    playback = DrivePlayback(viewer, drive_, replay, precompute=False)
    try:
        playback.show(1)
        assert playback.wait_until_drawn(1), playback.errors
        assert "frames 2..3" in playback.gui_status.content and "as it stood after scan 2" in playback.gui_status.content
        assert playback.gui_camera.visible and playback.gui_labels.visible and playback.gui_uncertainty.visible
        frame = drive_.insertions[1][-1]
        alpha = np.load(drive / "alpha" / f"{frame.image.stem}.npy").astype(np.float64)
        labels, uncertainty = pixel_values(alpha, PayloadType.ALPHA)
        image = drive_.sequence.read_image(frame)
        assert alpha.shape[1:] != image.shape[:2]  # alpha files at half the image's size: shown at the image's, nearest pixel
        np.testing.assert_array_equal(playback.gui_labels.image, playback.palette[at_image_size(labels, *image.shape[:2])])
        assert playback.gui_labels.image.shape == playback.gui_uncertainty.image.shape == image.shape
        assert uncertainty[:, : alpha.shape[2] // 2].mean() > 2 * uncertainty[:, alpha.shape[2] // 2:].mean()  # weaker evidence: less sure
        np.testing.assert_array_equal(playback.gui_camera.image, drive_.sequence.read_image(frame))
        # the scan by input uncertainty: K/S of each point's alpha
        assert playback.gui_scan_color.options == ("label", "input uncertainty")
        playback.gui_scan_color.value = "input uncertainty"
        assert wait_until(lambda: playback._drawn_scan == (1, "input uncertainty"), 30)
        scan = drive_.scan(1)
        want = colormap(9.0 / scan.payload.sum(axis=1), 0.0, 1.0)
        np.testing.assert_array_equal(playback.scan_handle.colors, want)
    finally:
        playback.close()
        viewer.server.stop()


def test_labels_only_drive_offers_no_input_uncertainty(drive):
    drive_, replay = open_drive(drive / "labels.npz", [drive / "seq", "rellis3d"])
    viewer = MapViewer([drive / "labels.npz"], port=free_port())
    playback = DrivePlayback(viewer, drive_, replay, precompute=False)
    try:
        assert playback.gui_scan_color.options == ("label",)
        assert playback.wait_until_drawn(5)
        assert playback.gui_camera.visible and not playback.gui_labels.visible  # the camera, and nothing labels it
    finally:
        playback.close()
        viewer.server.stop()


def _one_line_error(capsys, argv, *needles):
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse's own refusals
        code = exit_.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, err
    return err


def test_bad_drive_input_is_one_line(drive, tmp_path, capsys):
    port = ["--port", str(free_port())]
    labels = str(drive / "labels.npz")
    # a source without poses: the toy dataset's point files
    toy = str(REPO / "configs/datasets/sbki_toy.yaml")
    assert main(["map", toy, "--method", "s-csm", "--out", str(tmp_path / "toy.npz"), "--quiet"]) == 0
    capsys.readouterr()
    _one_line_error(capsys, ["view", str(tmp_path / "toy.npz"), "--drive", toy, *port], "has no poses")
    # a folder without poses.txt
    import shutil

    shutil.copytree(drive / "seq", tmp_path / "noposes")
    (tmp_path / "noposes" / "poses.txt").unlink()
    _one_line_error(capsys, ["view", labels, "--drive", str(tmp_path / "noposes"), "rellis3d", *port], "noposes")
    # another drive than the map's: its odom is another run's (before runs were recorded, its scans were not the map's)
    generate_sequence(load_preset("tiny", seed=11), tmp_path / "other", progress=False)
    _one_line_error(capsys, ["view", labels, "--drive", str(tmp_path / "other"), "rellis3d", *port], "play back", "of run", "labels.npz")
    # the map's drive labelled otherwise than when mapping
    _one_line_error(capsys, ["view", labels, "--drive", str(drive / "seq"), "rellis3d", "--alpha-dir", str(drive / "alpha"), *port],
                    "not one of the scans")
    _one_line_error(capsys, ["view", labels, str(drive / "alpha.npz"), "--drive", str(drive / "seq"), *port], "one map file")
    _one_line_error(capsys, ["view", labels, "--alpha-dir", str(drive / "alpha"), *port], "--alpha-dir", "--drive")
    _one_line_error(capsys, ["view", labels, "--drive", str(drive / "seq"), "--snapshot-every", "0", *port], "--snapshot-every")
    meta = read_map_arrays(drive / "labels.npz")[1]
    assert meta["scan_ids"], "the check needs the map's scan ids"
