"""Robot logs straight in: the synthetic drive written as a ROS 1 bag, a ROS 2 sqlite3 bag and a bare
MCAP file maps to the same map as the same drive from its folder; a hand-made log with NaN points,
an organised cloud and a TF tree at its own rate is read as ROS would; check-data explains logs that
cannot be mapped; configs and missing packages fail with one line."""

import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from evsemmap_warp.apps.cli import main  # noqa: E402
from evsemmap_warp.config import ConfigError, load_config  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402
from evsemmap_warp.data.datasets import open_dataset, open_sequence  # noqa: E402
from evsemmap_warp.data.log_writer import _LogOut, write_log  # noqa: E402
from evsemmap_warp.data.logs import LogSequence, check_log  # noqa: E402
from evsemmap_warp.data.ros_messages import encode_cloud  # noqa: E402
from evsemmap_warp.data.sequences import DataError  # noqa: E402
from evsemmap_warp.geometry.camera import quaternion_to_matrix, rigid  # noqa: E402
from evsemmap_warp.geometry.projection import label_map_for, project_frames  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402

METHODS = ["ebs", "s-bki", "dempster", "see-csom"]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The tiny synthetic drive as a folder and as a log of each format (and in two halves)."""
    root = tmp_path_factory.mktemp("drive")
    folder = root / "folder"
    generate_sequence(load_preset("tiny"), folder, progress=False)
    logs = {"rosbag1": root / "drive.bag", "rosbag2": root / "drive_ros2", "mcap": root / "drive.mcap"}
    for fmt, path in logs.items():
        write_log(folder, path, fmt)
    halves = [root / "first.bag", root / "second.bag"]
    write_log(folder, halves[0], "rosbag1", frames=slice(0, 3))
    write_log(folder, halves[1], "rosbag1", frames=slice(3, None))
    return folder, logs, halves


def _map(sources, method):
    run = load_config([str(s) for s in sources], method=method)
    dataset = open_dataset(run.dataset)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names)
    for scan in dataset:
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
    return mapper


def _assert_same_map(a: Mapper, b: Mapper):
    (va, sa), (vb, sb) = a.voxels(), b.voxels()
    np.testing.assert_array_equal(va.index, vb.index)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(sa.state, sb.state)
    np.testing.assert_array_equal(va.hits, vb.hits)
    # the folder's poses are 3x3 matrices, a log's quaternions: the round trip costs float64 rounding
    np.testing.assert_allclose(va.evidence, vb.evidence, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_each_log_format_maps_to_the_folder_map(drive, method):
    folder, logs, _ = drive
    reference = _map([folder], method)
    assert reference.voxel_count > 1000
    for fmt, log in logs.items():
        _assert_same_map(reference, _map([log, "rellis3d-bag"], method))


def test_tf_poses_and_compressed_images_read_the_same_drive(drive, tmp_path):
    """pose_source tf (the /tf samples, with halfway ones between clouds) instead of odometry, and the
    JPEG-compressed image topic instead of the raw one."""
    folder, logs, _ = drive
    override = tmp_path / "tf.yaml"
    override.write_text("dataset:\n  bag:\n    pose_source: tf\n    image_topic: /pylon_camera_node/image_raw/compressed\n")
    _assert_same_map(_map([folder], "ebs"), _map([logs["rosbag2"], "rellis3d-bag", override], "ebs"))
    seq, seq_folder = open_sequence([logs["rosbag2"], "rellis3d-bag", override]), open_sequence(folder)
    assert np.array_equal(seq.read_image(seq.frames[1]), seq_folder.read_image(seq_folder.frames[1]))
    # halfway between two clouds the pose is interpolated (the log holds a sample there: the writer's slerp)
    halfway = (seq.frames[1].stamp_ns + seq.frames[2].stamp_ns) // 2
    pose = seq.tree.lookup(seq.fixed_frame, seq.lidar_frame, halfway)
    np.testing.assert_allclose(pose[:3, 3], (seq.pose(seq.frames[1])[:3, 3] + seq.pose(seq.frames[2])[:3, 3]) / 2, atol=0.05)


def test_a_drive_split_over_two_logs_maps_as_one(drive):
    _, logs, halves = drive
    _assert_same_map(_map([logs["rosbag1"], "rellis3d-bag"], "ebs"), _map([*halves, "rellis3d-bag"], "ebs"))


def test_a_bare_sqlite_file_reads_like_its_bag_folder(drive):
    _, logs, _ = drive
    (db3,) = logs["rosbag2"].glob("*.db3")
    a, b = open_sequence([logs["rosbag2"], "rellis3d-bag"]), open_sequence([db3, "rellis3d-bag"])
    assert len(a) == len(b) == 6
    assert np.array_equal(a.read_scan(a.frames[4]), b.read_scan(b.frames[4]))


def test_projection_from_a_log_equals_the_folder(drive):
    folder, logs, _ = drive
    seq_folder = open_sequence(folder)
    for log in logs.values():
        seq_log = open_sequence([log, "rellis3d-bag"])
        assert np.array_equal(seq_log.lidar_to_camera, seq_folder.lidar_to_camera)
        assert seq_log.camera == seq_folder.camera
        pairs = zip(project_frames(seq_folder, seq_folder.frames, label_map_for(seq_folder)),
                    project_frames(seq_log, seq_log.frames, label_map_for(seq_log)))
        for a, b in pairs:
            assert np.array_equal(a.scan_rows, b.scan_rows)
            np.testing.assert_allclose(a.points, b.points, atol=1e-9)
            np.testing.assert_array_equal(a.values, b.values)
        # raw and compressed images hold the same pixels (the compressed one is the folder's JPEG)
        image = seq_log.read_image(seq_log.frames[2])
        assert np.array_equal(image, seq_folder.read_image(seq_folder.frames[2]))


def test_reading_streams_forward_and_seeks_back(drive):
    _, logs, _ = drive
    seq = open_sequence([logs["rosbag1"], "rellis3d-bag"])
    scans = [seq.read_scan(f).copy() for f in seq.frames]
    assert np.array_equal(seq.read_scan(seq.frames[1]), scans[1])  # backwards: the cursor starts again
    assert np.array_equal(seq.read_scan(seq.frames[5]), scans[5])
    # the Ouster layout pads each 48-byte point; its label field gives the folder's labels
    folder_seq = open_sequence(drive[0])
    assert np.array_equal(seq.read_point_labels(seq.frames[3]), folder_seq.read_point_labels(folder_seq.frames[3]))


# A hand-made log: NaN points, organised cloud, TF at its own rate ---------------------------------
def _yaw(degrees):
    half = np.radians(degrees) / 2
    return np.array([0, 0, np.sin(half), np.cos(half)])


BASE_TO_LIDAR = rigid(quaternion_to_matrix(_yaw(90)), [0.5, 0, 1]) @ rigid(quaternion_to_matrix(_yaw(180)), [0, 0, 0.1])


def _hand_made_log(path: Path, fmt="rosbag1", *, lidar_frame="lidar", static=True, relocalised=False):
    log = _LogOut(path, fmt)
    s = 1_000_000_000
    t0 = 100 * s
    if relocalised:  # odometry over the whole drive, and a localiser's map -> odom from the second cloud on only
        log.write("/tf", log.tf([log.transform("odom", "base", rigid(quaternion_to_matrix(_yaw(60)), [3.0, 0, 0]), t0 + 2 * s)]), t0 + 2 * s)
        for k in (1, 2):
            log.write("/tf", log.tf([log.transform("map", "odom", rigid(np.eye(3), [10.0 * k, 0, 0]), t0 + k * s)]), t0 + k * s)
    if static:
        chain = [log.transform("base", "mast", rigid(quaternion_to_matrix(_yaw(90)), [0.5, 0, 1]), t0),
                 log.transform("mast", "lidar", rigid(quaternion_to_matrix(_yaw(180)), [0, 0, 0.1]), t0)]
        log.write("/tf_static", log.tf(chain), t0)
    for k, (x, angle) in enumerate(((0.0, 0.0), (2.0, 40.0))):  # TF at 1 Hz
        log.write("/tf", log.tf([log.transform("odom", "base", rigid(quaternion_to_matrix(_yaw(angle)), [x, 0, 0]), t0 + k * s)]), t0 + k * s)
    nan = np.float32("nan")
    xyz = np.array([[1, 0, 0], [nan, nan, nan], [0, 2, 0], [0, 0, 3], [nan, 0, 0], [4, 4, 4]], np.float32)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": np.arange(6, dtype=np.float32),
               "t": np.zeros(6, np.uint32), "reflectivity": np.zeros(6, np.uint16), "ring": np.array([0, 0, 0, 1, 1, 1], np.uint16),
               "label": np.array([1, 3, 4, 3, 1, 19], np.uint32), "range": np.zeros(6, np.uint32)}
    for k, stamp in enumerate((t0 + s // 4, t0 + 3 * s // 2)):  # the second cloud comes after the last transform
        msg = log.cloud(columns, stamp, lidar_frame, k, height=2)
        msg.is_dense = False
        log.write("/os1_cloud_node/points", msg, stamp)
    log.close()
    return path


def test_nan_points_go_and_poses_are_interpolated_through_a_chain_of_three_frames(tmp_path):
    seq = LogSequence([_hand_made_log(tmp_path / "hand.bag")])
    first, late = seq.frames
    scan = seq.read_scan(first)
    assert scan.shape == (4, 4)  # the two points with NaN dropped
    np.testing.assert_array_equal(scan[:, 3], [0, 2, 3, 5])
    np.testing.assert_array_equal(seq.read_point_labels(first), [1, 4, 3, 19])
    base = rigid(quaternion_to_matrix(_yaw(10)), [0.5, 0, 0])  # a quarter of the way from (0 m, 0 deg) to (2 m, 40 deg)
    np.testing.assert_allclose(seq.pose(first), base @ BASE_TO_LIDAR, atol=1e-12)
    assert seq.fixed_frame == "odom"
    with pytest.raises(DataError, match=r"message 1 .*no pose: no transform odom -> base at t = 101\.500000 s"):
        seq.pose(late)


def test_a_given_lidar_extrinsic_stands_in_for_missing_static_transforms(tmp_path):
    from evsemmap_warp.config import BagConfig
    from evsemmap_warp.geometry.camera import matrix_to_quaternion

    path = _hand_made_log(tmp_path / "no_static.bag", static=False)
    alone = LogSequence([path])
    with pytest.raises(DataError, match="LiDAR frame 'lidar' is in no TF tree .frames known: base, odom."):
        alone.pose(alone.frames[0])  # not the identity: that would map a moving robot as standing still
    extrinsic = tuple(BASE_TO_LIDAR[:3, 3]) + tuple(matrix_to_quaternion(BASE_TO_LIDAR[:3, :3]))
    seq = LogSequence([path], BagConfig(lidar_extrinsic=extrinsic))
    with_static = LogSequence([_hand_made_log(tmp_path / "static.bag")])
    np.testing.assert_allclose(seq.pose(seq.frames[0]), with_static.pose(with_static.frames[0]), atol=1e-12)


def test_a_lidar_extrinsic_on_a_log_holding_the_mount_is_refused_as_a_conflict(tmp_path):
    """The extrinsic stands in for a mount the log lacks; given beside the log's own it would either
    replace it silently (the same parent) or fail as a TF tree with two parents, naming no key."""
    from evsemmap_warp.config import BagConfig

    path = _hand_made_log(tmp_path / "static.bag")
    extrinsic = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    with pytest.raises(DataError, match=r"dataset.bag.lidar_extrinsic conflicts with the log's own transform 'mast' -> 'lidar'"):
        LogSequence([path], BagConfig(lidar_extrinsic=extrinsic))


def test_a_fixed_frame_that_moves_with_the_robot_is_refused_like_a_robot_standing_still(tmp_path, capsys):
    """--frame base (the robot's own frame): the LiDAR is fixed to it, so every scan would get one
    pose, the case refused when the log's own tree says so."""
    from evsemmap_warp.config import BagConfig

    path = _hand_made_log(tmp_path / "hand.bag")
    moving = LogSequence([path], BagConfig(fixed_frame="base"))
    with pytest.raises(DataError, match=r"fixed_frame \(--frame\) 'base' moves with the robot \(the transform 'odom' -> 'base' moves\)"):
        moving.check_pose_chain()
    assert main(["map", str(path), "rellis3d", "--frame", "base", "--method", "ebs", "--out", str(tmp_path / "m.npz"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--frame" in err and "'base'" in err and not (tmp_path / "m.npz").exists(), err


def test_a_logs_run_frames_and_run_id(tmp_path):
    """odom by name, a frame that moves in the TF tree, and the odometry's header frame are one run's;
    the run id comes from the log's first cloud: the same log gives the same id, another log another."""
    from evsemmap_warp.config import BagConfig

    path = _hand_made_log(tmp_path / "relocalised.bag", relocalised=True)
    seq = LogSequence([path])
    assert seq.is_run_frame("odom") and seq.is_run_frame("base") and seq.is_run_frame("mast") and not seq.is_run_frame("map")
    assert LogSequence([path]).run_id == seq.run_id and len(seq.run_id) == 16
    assert LogSequence([_hand_made_log(tmp_path / "vlp.bag", lidar_frame="velodyne")]).run_id != seq.run_id  # another first cloud


def test_check_data_explains_a_log_that_cannot_be_mapped(tmp_path, capsys):
    path = _hand_made_log(tmp_path / "broken.bag", lidar_frame="velodyne")  # the cloud's frame is in no TF tree
    report = check_log([path])
    assert not report.ok
    text = report.text()
    assert "/os1_cloud_node/points" in text and "sensor_msgs/msg/PointCloud2" in text and "2 msgs" in text
    assert "never connect" in text and "'base'" in text
    assert main(["check-data", str(path)]) == 1
    late = _hand_made_log(tmp_path / "late.bag")
    report = check_log([late])
    assert any("1 of 2 clouds have no pose" in p and "'odom' -> 'base'" in p and "changes mid-drive" in p for p in report.problems), report.problems


def test_a_tf_root_that_changes_mid_drive_and_a_missing_fixed_frame_are_refused_before_mapping(tmp_path, capsys):
    """A localiser's map -> odom that starts with the second cloud moves the TF root from odom to map
    mid-drive: map names the transform and its time range, the frame to use instead, and writes nothing."""
    path = _hand_made_log(tmp_path / "plain.bag")
    relocalised = _hand_made_log(tmp_path / "relocalised.bag", relocalised=True)
    override = tmp_path / "labels.yaml"
    override.write_text("dataset:\n  num_classes: 20\n  bag:\n    label_ontology: none\nmapping:\n  resolution_m: 0.5\n")
    out = tmp_path / "map.npz"
    assert main(["map", str(relocalised), override.as_posix(), "--method", "s-csm", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "changes mid-drive" in err and "'map' -> 'odom'" in err and "fixed_frame: odom" in err, err
    assert not out.exists()
    assert main(["map", str(path), override.as_posix(), "--method", "s-csm", "--frame", "world", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "dataset.bag.fixed_frame 'world' is not a frame of the log's TF tree" in err and "odom" in err, err


def test_check_data_on_the_synthetic_logs_is_clean(drive, capsys):
    _, logs, _ = drive
    assert main(["check-data", str(logs["mcap"]), "rellis3d-bag"]) == 0
    out = capsys.readouterr().out
    assert "6 clouds, 6 with a camera image, 6 with a 2D label image" in out
    assert "/pylon_camera_node/image_raw/compressed" in out and "OK" in out


def test_the_cli_maps_a_log_and_check_data_names_a_missing_topic(drive, tmp_path, capsys):
    _, logs, _ = drive
    out = tmp_path / "map.npz"
    assert main(["map", str(logs["rosbag1"]), "rellis3d", "rellis3d-bag", "--method", "ebs", "--out", str(out), "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["scans"] == 6
    config = tmp_path / "wrong.yaml"
    config.write_text("dataset:\n  bag:\n    image_topic: /camera/nope\n")
    assert main(["check-data", str(logs["rosbag1"]), "rellis3d-bag", str(config)]) == 1
    assert "'/camera/nope' (dataset.bag.image_topic) is not in the log" in capsys.readouterr().out


# Configs and refusals -------------------------------------------------------------------------------
def test_bag_configs_merge_key_by_key_and_name_wrong_keys(drive, tmp_path):
    _, logs, _ = drive
    run = load_config([str(logs["rosbag1"]), "rellis3d-bag"])
    assert run.dataset.kind == "bag" and run.dataset.bag.odometry_topic == "/odometry/filtered"
    override = tmp_path / "mine.yaml"
    override.write_text("dataset:\n  bag:\n    pose_source: tf\n")
    run = load_config([str(logs["rosbag1"]), "rellis3d-bag", str(override)])
    assert run.dataset.bag.pose_source == "tf" and run.dataset.bag.image_topic == "/pylon_camera_node/image_raw"
    override.write_text("dataset:\n  bag:\n    cloud_topc: /x\n")
    with pytest.raises(ConfigError, match=r"mine\.yaml: unknown key\(s\) dataset\.bag\.cloud_topc"):
        load_config([str(logs["rosbag1"]), str(override)])
    override.write_text("dataset:\n  bag:\n    pose_source: odometry\n")
    with pytest.raises(ConfigError, match="odometry_topic.*needs an odometry topic"):
        load_config([str(logs["rosbag1"]), str(override)])
    override.write_text("dataset:\n  kind: bag\n  bag:\n    camera_extrinsic: [1, 2, 3]\n")
    with pytest.raises(ConfigError, match="camera_extrinsic.*7 numbers"):
        load_config([str(logs["rosbag1"]), str(override)])
    with pytest.raises(ConfigError, match="needs at least one log"):
        open_dataset(load_config(["rellis3d-bag"]).dataset)


def test_ros1_and_ros2_logs_are_not_mixed_and_junk_is_named(drive, tmp_path):
    _, logs, _ = drive
    with pytest.raises(DataError, match="cannot be read as one sequence"):
        open_sequence([logs["rosbag1"], logs["mcap"], "rellis3d-bag"])
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(DataError, match=r"junk\.bag: not a readable robot log"):
        open_sequence([junk])
    assert main(["map", str(junk), "--method", "ebs", "--out", str(tmp_path / "x.npz"), "--quiet"]) == 2


def test_a_log_still_being_recorded_or_cut_short_is_one_line_naming_it(drive, tmp_path, monkeypatch, capsys):
    """Issue 31: a log copied while its recorder still writes it (a ROS 1 bag without its index, an MCAP
    without its summary and footer, a ROS 2 folder without metadata.yaml, a .db3 with nothing committed)
    or cut short (an interrupted copy) is never mapped in part: `map` says so in one line naming it (exit 2),
    `check-data` lists it as a problem (exit 1), no traceback, no map written."""
    folder, logs, _ = drive
    recording = {}
    original = _LogOut.close

    def snapshot_then_close(self):  # the files as they lie on disk while the recorder is still writing them
        storage = self.writer if self.fmt == "rosbag1" else self.writer.storage
        if self.fmt == "rosbag1":
            storage.bio.flush()
            recording["rosbag1"] = Path(shutil.copy(self.out, tmp_path / "recording.bag"))
        elif self.fmt == "mcap":
            storage.bio.flush()
            recording["mcap"] = Path(shutil.copy(storage.path, tmp_path / "recording.mcap"))
        else:  # nothing committed yet; the folder has no metadata.yaml until the recorder closes it
            recording["db3"] = Path(shutil.copy(storage.path, tmp_path / "recording.db3"))
            (tmp_path / "recording_ros2").mkdir()
            shutil.copy(storage.path, tmp_path / "recording_ros2" / storage.path.name)
            recording["ros2 folder"] = tmp_path / "recording_ros2"
        original(self)

    monkeypatch.setattr(_LogOut, "close", snapshot_then_close)
    for fmt in ("rosbag1", "mcap", "rosbag2"):
        write_log(folder, tmp_path / f"written_{fmt}", fmt)
    monkeypatch.setattr(_LogOut, "close", original)
    assert set(recording) == {"rosbag1", "mcap", "db3", "ros2 folder"}
    unreadable = "not a readable robot log .*a log still being recorded, or cut short"
    cases = {recording["rosbag1"]: "Bag is not indexed", recording["mcap"]: unreadable, recording["db3"]: "holds no topic and no message .yet.",
             recording["ros2 folder"]: "a ROS 2 bag folder without metadata.yaml.*still being recorded.*cut short"}
    for log in (logs["rosbag1"], logs["mcap"], next(logs["rosbag2"].glob("*.db3"))):
        for share in (0.3, 0.9, 0.999):
            data = log.read_bytes()
            cut = tmp_path / f"cut_{share}{log.suffix}"
            cut.write_bytes(data[: int(len(data) * share)])
            cases[cut] = unreadable if log.suffix != ".db3" else f"{unreadable}|the log is damaged .CorruptError"  # (its last pages)
    out = tmp_path / "map.npz"
    for log, pattern in cases.items():
        assert main(["map", str(log), "rellis3d-bag", "--method", "ebs", "--out", str(out), "--quiet"]) == 2, log
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(log) in err and re.search(pattern, err), (log, err)
        assert not out.exists()
        assert main(["check-data", str(log), "rellis3d-bag"]) == 1, log
        printed = capsys.readouterr()
        assert "Traceback" not in printed.err and re.search(f"problem: {re.escape(str(log))}: .*{pattern}", printed.out), (log, printed)


def test_without_rosbags_a_log_says_how_to_install_it(drive, monkeypatch):
    _, logs, _ = drive
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(ConfigError, match=r'pip install "evsemmap_warp\[ros\]"'):
        open_sequence([logs["rosbag1"]])


def test_camera_labelled_maps_from_a_log_equal_the_folder(drive, tmp_path, capsys):
    """map --checkpoint: inference on each frame's image, projection, bins: from the folder and from
    the log (raw images hold the folder JPEG's pixels) the same map."""
    import torch

    from evsemmap_warp.apps.scan_sources import CheckpointScans
    from evsemmap_warp.classes import class_set
    from evsemmap_warp.segmentation.config import ModelConfig
    from evsemmap_warp.segmentation.model import build_model
    from evsemmap_warp.segmentation.train import TrainConfig, save_checkpoint

    torch.manual_seed(0)
    names = class_set().names
    config = TrainConfig(model=ModelConfig(num_classes=len(names), width=8, aspp_channels=8), input_size=(32, 64))
    model = build_model(config.model)
    checkpoint = tmp_path / "net.pt"
    save_checkpoint(checkpoint, model, torch.optim.SGD(model.parameters(), lr=0.1), 1, config, names, [])
    folder, logs, _ = drive

    def camera_map(sources):
        run = load_config([str(s) for s in sources], method="prob")  # no uncertainty cut: an untrained net is unsure of everything
        scans = CheckpointScans(run, checkpoint, 2, 4)
        assert len(scans) == 3 and scans.num_classes == len(names)
        mapper = Mapper(run.mapping, scans.num_classes, class_names=scans.class_names)
        for scan in scans:
            mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
        return mapper

    reference = camera_map([folder])
    assert reference.voxel_count > 100
    _assert_same_map(reference, camera_map([logs["rosbag2"], "rellis3d-bag"]))
    out = tmp_path / "m.npz"
    assert main(["map", str(logs["mcap"]), "rellis3d", "rellis3d-bag", "--method", "prob", "--checkpoint", str(checkpoint),
                 "--out", str(out), "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["scans"] == 1  # the rellis3d preset bins 30 frames: the 6 frames make one bin


def test_batch_maps_a_log_in_worker_processes_as_the_folder(drive, tmp_path):
    """A log's index travels to the workers (pickled without its open reader); each reopens the log."""
    from evsemmap_warp.apps.batch import BatchOptions, run_batch
    from evsemmap_warp.core.map_store import MapStore

    folder, logs, _ = drive
    run_batch([str(logs["rosbag1"]), "rellis3d-bag"], BatchOptions(method="ebs", out=tmp_path / "store", workers=2, chunk_frames=2,
                                                                    progress=False), log=lambda m: None)
    _assert_same_map(_map([folder], "ebs"), MapStore(tmp_path / "store").to_mapper())


def test_dump_config_shows_the_bag_settings_and_the_preset_bins(drive, capsys):
    import yaml

    folder, logs, _ = drive
    assert main(["dump-config", str(logs["rosbag1"]), "rellis3d", "rellis3d-bag"]) == 0
    dumped = yaml.safe_load(capsys.readouterr().out)
    assert dumped["dataset"]["bag"]["odometry_topic"] == "/odometry/filtered" and dumped["pipeline"]["bin_frames"] == 30
    assert main(["dump-config", str(folder)]) == 0
    assert "bag" not in yaml.safe_load(capsys.readouterr().out)["dataset"]


def test_messages_sharing_a_log_time_are_found_in_any_order(tmp_path):
    log = _LogOut(tmp_path / "same_time.bag", "rosbag1")
    t0 = 50 * 1_000_000_000
    log.write("/tf_static", log.tf([log.transform("odom", "lidar", np.eye(4), t0)]), t0)
    for k in range(3):  # three clouds recorded at one instant, stamped 10 ms apart
        xyz = np.full((2, 3), k + 1, np.float32)
        columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
        msg = log.types["sensor_msgs/msg/PointCloud2"](header=log.header(t0 + k * 10_000_000, "lidar"), is_dense=True, fields=[
            log.types["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c)
            for n, o, d, c in encode_cloud(columns)["fields"]], **{k2: v for k2, v in encode_cloud(columns).items() if k2 != "fields"})
        log.write("/os1_cloud_node/points", msg, t0)
    log.close()
    seq = LogSequence([tmp_path / "same_time.bag"])
    for frame in (seq.frames[2], seq.frames[0], seq.frames[1], seq.frames[1], seq.frames[2]):
        assert seq.read_scan(frame)[0, 0] == frame.index + 1


def test_a_log_damaged_mid_read_is_one_line_naming_it(drive, tmp_path, monkeypatch, capsys):
    """What rosbags raises on a damaged chunk or message (its own error types) becomes one line."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    _, logs, _ = drive
    original = AnyReader.deserialize

    def damaged(self, raw, msgtype):
        if msgtype == "sensor_msgs/msg/PointCloud2":
            raise AnyReaderError("Could not deserialize message: buffer too short")
        return original(self, raw, msgtype)

    seq = open_sequence([logs["rosbag1"], "rellis3d-bag"])  # indexed intact; the clouds break afterwards
    monkeypatch.setattr(AnyReader, "deserialize", damaged)
    with pytest.raises(DataError, match=r"drive\.bag .*the log is damaged \(AnyReaderError: Could not deserialize"):
        seq.read_scan(seq.frames[3])
    assert main(["map", str(logs["rosbag1"]), "rellis3d-bag", "--method", "ebs", "--out", str(tmp_path / "m.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the log is damaged" in err and "Traceback" not in err


def test_a_pose_chain_without_a_moving_transform_is_refused_before_mapping(drive, tmp_path, monkeypatch, capsys):
    """Issue 31: a log whose /tf_static lacks base_link -> os1_sensor (with TF or odometry poses), or whose
    tf_topic is the cloud topic, used to be mapped in the broken subtree's root with one pose for every
    scan (rc 0). map, batch, project and experiment refuse it, naming the missing link and the time; check-data
    says the same."""
    folder, logs, _ = drive
    original = _LogOut.tf
    monkeypatch.setattr(_LogOut, "tf", lambda self, transforms: original(self, [t for t in transforms if t.child_frame_id != "os1_sensor"]))
    broken = tmp_path / "broken.bag"
    write_log(folder, broken, "rosbag1")
    monkeypatch.setattr(_LogOut, "tf", original)
    tf_on_clouds = tmp_path / "tf_on_clouds.yaml"
    tf_on_clouds.write_text("dataset:\n  bag:\n    tf_topic: /os1_cloud_node/points\n")
    no_tf = tmp_path / "no_tf.yaml"
    no_tf.write_text("dataset:\n  bag:\n    tf_topic: /nope\n")
    out = tmp_path / "map.npz"
    cases = [([broken], r"link from one of the moving frames \['base_link', 'odom'\] to 'os1_sensor' is missing at t = 1600000000\.0+ s"),
             ([broken, "rellis3d-bag"], "to 'os1_sensor' is missing"),  # pose_source: odometry
             ([logs["rosbag1"], tf_on_clouds], r"'/os1_cloud_node/points' \(dataset.bag.tf_topic\) carries sensor_msgs/msg/PointCloud2"),
             ([logs["rosbag1"], no_tf], r"no moving transform at all on '/nope'")]
    projected = tmp_path / "projected"
    for sources, pattern in cases:
        commands = [["map", *sources, "--method", "ebs", "--out", out, "--quiet"], ["project", *sources, "--out", projected]]
        if not str(sources[-1]).endswith(".yaml"):  # (batch takes a config with a dataset section for an input)
            commands.append(["batch", *sources, "--method", "ebs", "--out", tmp_path / "store", "--workers", "1", "--quiet"])
        for argv in commands:
            assert main([str(a) for a in argv]) == 2, argv
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and re.search(pattern, err), (argv, err)
        assert not out.exists() and not (tmp_path / "store" / "store.json").exists() and not projected.exists()
    # a study reading the log (its network trained on it, a condition mapped from it) stops before training
    study = tmp_path / "study.yaml"
    study.write_text(f"name: broken\nsequences:\n  d: {{path: '{broken}'}}\nnetworks:\n  n: {{train_on: [d], epochs: 1}}\n"
                     "conditions:\n  c: {network: n, sequence: d}\nmethods: [ebs]\n")
    assert main(["experiment", str(study), "--out", str(tmp_path / "study"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(cases[1][1], err) and "broken.bag" in err, err
    assert not (tmp_path / "study" / "results.md").exists()
    report = check_log([broken])
    assert any("to 'os1_sensor' is missing" in p for p in report.problems), report.problems
    fixed = tmp_path / "fixed.yaml"  # a sensor that never moves: mapped when the fixed frame is said
    fixed.write_text("dataset:\n  bag:\n    fixed_frame: os1_sensor\n")
    seq = open_sequence([broken, str(fixed)])
    np.testing.assert_array_equal(seq.pose(seq.frames[0]), seq.pose(seq.frames[-1]))
