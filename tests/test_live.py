"""Live mapping over Zenoh, end to end: real Zenoh peers on 127.0.0.1 (peer mode, explicit endpoints, no
multicast, no other network). ``evsemmap replay`` publishes the tiny synthetic drive as a ROS 2 robot on
rmw_zenoh would; ``evsemmap live`` maps it; the live map equals ``evsemmap map`` of the same log, and what
it publishes back decodes with rosbags into the map and its terrain layers."""

import json
from pathlib import Path
import socket
import threading
import time

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from conftest import wait_until  # noqa: E402

from evsemmap_warp.apps.cli import main  # noqa: E402
from evsemmap_warp.config import load_config  # noqa: E402
from evsemmap_warp.core.mapper import Mapper, VoxelState  # noqa: E402
from evsemmap_warp.data.log_writer import write_log  # noqa: E402
from evsemmap_warp.live.publish import COSTMAP_TOPIC, GRID_MAP_TOPIC, MAP_TOPIC  # noqa: E402
from evsemmap_warp.live.ros2_wire import ADMIN_SPACE, decode_attachment, parse_token, topic_key, typestore  # noqa: E402
from evsemmap_warp.live.session import ZenohOptions, open_session  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402
from evsemmap_warp.terrain.api import compute_layers  # noqa: E402
from evsemmap_warp.terrain.outputs import band_from_grid_map  # noqa: E402

PRESETS = ["rellis3d", "rellis3d-bag"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The tiny synthetic drive (LiDAR only: no camera) as a ROS 2 bag, and as its two halves."""
    root = tmp_path_factory.mktemp("live_drive")
    folder = root / "folder"
    generate_sequence(load_preset("tiny"), folder, progress=False, camera=False)
    logs = {"whole": root / "whole", "first": root / "first", "second": root / "second", "ros1": root / "whole.bag",
            "mcap": root / "whole.mcap"}
    write_log(folder, logs["whole"], "rosbag2")
    write_log(folder, logs["ros1"], "rosbag1")
    write_log(folder, logs["mcap"], "mcap")
    write_log(folder, logs["first"], "rosbag2", frames=slice(0, 3))
    write_log(folder, logs["second"], "rosbag2", frames=slice(3, None))
    return logs


class LiveRun:
    """``evsemmap live`` on a thread of this process, listening on a free port; ``result()`` joins it."""

    def __init__(self, tmp_path, *extra):
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.out, self.report = tmp_path / "live.npz", tmp_path / "live.json"
        argv = ["live", *PRESETS, "--method", "ebs", "--out", str(self.out), "--listen", self.endpoint, "--report", str(self.report),
                "--map-period", "0.2", "--grid-period", "0.5", *extra]
        self.code = None
        self.thread = threading.Thread(target=lambda: setattr(self, "code", main(argv)), daemon=True)
        self.thread.start()

    def result(self, timeout: float = 60.0) -> dict:
        self.thread.join(timeout)
        assert not self.thread.is_alive(), "evsemmap live did not end"
        return json.loads(self.report.read_text()) if self.report.exists() else {}


def replay(endpoint: str, log, *extra) -> int:
    return main(["replay", str(log), "--connect", endpoint, "--quiet", "--wait-subscribers", "10", *extra])


def batch_map(log, tmp_path) -> Mapper:
    out = tmp_path / "batch.npz"
    assert main(["map", str(log), *PRESETS, "--method", "ebs", "--out", str(out), "--quiet"]) == 0
    return Mapper.load(out)


def assert_same_map(live: Mapper, batch: Mapper) -> None:
    (va, sa), (vb, sb) = live.voxels(), batch.voxels()
    np.testing.assert_array_equal(va.index, vb.index)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(va.hits, vb.hits)
    np.testing.assert_allclose(va.evidence, vb.evidence, rtol=1e-5, atol=1e-6)  # float32 kernels, summed in another order
    assert live.frame == batch.frame


class Listener:
    """A third peer, connected to live's endpoint: keeps the last sample of the published topics."""

    def __init__(self, endpoint: str):
        self.session = open_session(ZenohOptions(connect=[endpoint]))
        self.last: dict[str, tuple[bytes, bytes | None]] = {}
        self.subscribers = [self.session.declare_subscriber(topic_key(t, key_format="rmw_zenoh"), self._keep(t))
                            for t in (MAP_TOPIC, GRID_MAP_TOPIC, COSTMAP_TOPIC)]

    def _keep(self, topic):
        def keep(sample):
            attachment = None if sample.attachment is None else sample.attachment.to_bytes()
            self.last[topic] = (sample.payload.to_bytes(), attachment)
        return keep

    def publishers(self) -> dict[str, str]:
        tokens = {}
        for reply in self.session.liveliness().get(f"{ADMIN_SPACE}/0/**", timeout=5.0):
            token = parse_token(str(reply.ok.key_expr)) if reply.ok is not None else None
            if token is not None and token["kind"] == "MP":
                tokens[token["topic"]] = token["msgtype"]
        return tokens

    def close(self):
        for s in self.subscribers:
            s.undeclare()
        self.session.close()


def test_replayed_drive_maps_live_as_the_log_maps_and_the_published_map_decodes_back(drive, tmp_path):
    batch = batch_map(drive["whole"], tmp_path)
    live = LiveRun(tmp_path, "--idle-exit", "4", "--window", "12")  # a window inside the map: the layers of its columns only
    listener = Listener(live.endpoint)
    try:
        assert replay(live.endpoint, drive["whole"]) == 0
        # ros2 topic list on an rmw_zenoh robot reads the publishers' liveliness tokens
        assert wait_until(lambda: {MAP_TOPIC, GRID_MAP_TOPIC, COSTMAP_TOPIC} <= set(listener.publishers()), 10)
        assert listener.publishers()[MAP_TOPIC] == "sensor_msgs/msg/PointCloud2"
        report = live.result()
        assert live.code == 0, report
        assert wait_until(lambda: len(listener.last) == 3, 5)
    finally:
        listener.close()
    assert report["scans_mapped"] == 6 and report["scans_dropped"] == 0 and report["key_format"] == "rmw_zenoh"
    mapped = Mapper.load(live.out)
    assert_same_map(mapped, batch)

    store = typestore()
    # the map cloud published last holds every scan: the occupied voxels' centers, labels, probabilities, variances
    payload, attachment = listener.last[MAP_TOPIC]
    assert decode_attachment(attachment)[0] >= 1
    cloud = store.deserialize_cdr(payload, "sensor_msgs/msg/PointCloud2")
    from evsemmap_warp.data.ros_messages import decode_cloud

    points = decode_cloud(cloud)
    arrays, summary = batch.voxels()
    occupied = summary.state == VoxelState.OCCUPIED
    assert len(points) == occupied.sum() and cloud.header.frame_id == batch.frame.name
    np.testing.assert_allclose(np.stack([points[n] for n in "xyz"], axis=1), batch.voxel_centers(arrays.index[occupied]), atol=1e-4)
    np.testing.assert_array_equal(points["label"], summary.label[occupied])
    labels = summary.label[occupied]
    np.testing.assert_allclose(points["probability"], summary.probabilities[occupied][np.arange(len(labels)), labels], rtol=1e-5)
    np.testing.assert_allclose(points["variance"], summary.variance[occupied], rtol=1e-4, atol=1e-9)

    # the GridMap: every band of the terrain layers over the window it covers
    grid_map = store.deserialize_cdr(listener.last[GRID_MAP_TOPIC][0], "grid_map_msgs/msg/GridMap")
    info = grid_map.info
    size_x, size_y = round(info.length_x / info.resolution), round(info.length_y / info.resolution)
    cx, cy, inset = info.pose.position.x, info.pose.position.y, 1e-6
    layers = compute_layers(batch, bounds=[cx - info.length_x / 2 + inset, cy - info.length_y / 2 + inset,
                                           cx + info.length_x / 2 - inset, cy + info.length_y / 2 - inset])
    assert (layers.grid.width, layers.grid.height) == (size_x, size_y) and list(grid_map.layers) == layers.band_names
    for name, data in zip(grid_map.layers, grid_map.data):
        np.testing.assert_allclose(band_from_grid_map(data.data, size_x, size_y), layers.bands[name], rtol=1e-4, atol=1e-5,
                                   equal_nan=True, err_msg=name)
    costmap = store.deserialize_cdr(listener.last[COSTMAP_TOPIC][0], "nav_msgs/msg/OccupancyGrid")
    assert (costmap.info.width, costmap.info.height) == (size_x, size_y)
    assert set(np.unique(costmap.data)) <= set(range(-1, 101))


def test_the_mapper_starts_before_the_robot_which_stops_and_comes_back(drive, tmp_path):
    """The robot's publisher session ends after the first half of the drive and a new one brings the second:
    the live map is the map of the whole log."""
    batch = batch_map(drive["whole"], tmp_path)
    # the run ends with the drive's sixth scan; --idle-exit only ends a run that lost scans, however busy the machine
    live = LiveRun(tmp_path, "--max-scans", "6", "--idle-exit", "60", "--no-publish")
    time.sleep(1.0)  # nobody publishes yet: live waits
    assert replay(live.endpoint, drive["first"]) == 0
    time.sleep(1.0)  # the robot is gone
    assert replay(live.endpoint, drive["second"]) == 0
    report = live.result()
    assert live.code == 0 and report["scans_mapped"] == 6 and report["scans_dropped"] == 0, report
    assert_same_map(Mapper.load(live.out), batch)


def test_a_run_stopped_by_an_error_still_writes_the_map_it_made(drive, tmp_path, monkeypatch, capsys):
    """A memory budget that stops holding (other processes on the robot grew) ends the run in one line, exit 2,
    and the scans mapped before it are written, not lost."""
    from evsemmap_warp.limits import MemoryBudgetError
    from evsemmap_warp.live.mapping import LiveMapping

    real = LiveMapping.map_scan

    def map_scan(self, item):
        if self.stats.mapped == 2:
            raise MemoryBudgetError("the voxel table would need 9.0 GB, over the memory budget of 1.0 GB (--max-memory)")
        return real(self, item)

    monkeypatch.setattr(LiveMapping, "map_scan", map_scan)
    live = LiveRun(tmp_path, "--idle-exit", "30", "--no-publish")
    assert replay(live.endpoint, drive["whole"]) == 0
    live.result()
    assert live.code == 2
    err = capsys.readouterr().err
    assert "stopped: the voxel table would need 9.0 GB" in err and "evsemmap: error: the voxel table would need" in err, err
    assert Mapper.load(live.out).scans_integrated == 2


def test_ctrl_c_ends_a_replay_within_a_long_gap_of_the_log(drive):
    """At 1e-4 of the recorded rate messages milliseconds apart are tens of seconds apart: a stop (Ctrl-C) ends the replay
    then, not after the gap, and no later loop starts."""
    from evsemmap_warp.live.replay import replay_log

    session = open_session(ZenohOptions(listen=[f"tcp/127.0.0.1:{free_port()}"]))
    stop = threading.Event()
    threading.Timer(1.0, stop.set).start()
    started = time.monotonic()
    try:
        replay_log(session, [drive["whole"]], rate=1e-4, loops=3, stop=stop, linger_s=0.0)
    finally:
        session.close()
    assert time.monotonic() - started < 10


def test_a_store_written_as_it_goes_is_resumed_by_the_next_run(drive, tmp_path):
    """--store: the first half of the drive mapped by one live run, the second by another resuming the store:
    the store holds the map of the whole log."""
    from evsemmap_warp.core.map_store import MapStore

    batch = batch_map(drive["whole"], tmp_path)
    store = tmp_path / "store"
    for half in ("first", "second"):
        (tmp_path / half).mkdir()
        live = LiveRun(tmp_path / half, "--idle-exit", "3", "--no-publish", "--store", str(store), "--store-every", "0.2")
        assert replay(live.endpoint, drive[half]) == 0
        report = live.result()
        assert live.code == 0 and report["scans_mapped"] == 3, report
        assert MapStore(store).to_mapper().scans_integrated == (3 if half == "first" else 6)
    assert not store.with_name("store.next").exists() and not store.with_name("store.prev").exists()
    assert_same_map(MapStore(store).to_mapper(), batch)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_ros1_bag_and_an_mcap_file_replay_as_ros2_and_map_the_same(drive, tmp_path, fmt):
    """A ROS 1 bag's messages are rewritten as their ROS 2 types (the header's seq dropped, ...); an MCAP file's go
    out as they are; as fast as the replay can (--rate 0)."""
    batch = batch_map(drive["whole"], tmp_path)
    live = LiveRun(tmp_path, "--idle-exit", "3", "--no-publish")
    assert replay(live.endpoint, drive[fmt], "--rate", "0") == 0
    report = live.result()
    assert live.code == 0 and report["scans_mapped"] == 6 and report["scans_dropped"] == 0, report
    assert_same_map(Mapper.load(live.out), batch)


def test_replay_publishes_the_log_time_on_clock(drive):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listener = open_session(ZenohOptions(listen=[endpoint]))
    clock = []
    subscriber = listener.declare_subscriber(topic_key("/clock", key_format="rmw_zenoh"), lambda sample: clock.append(sample.payload.to_bytes()))
    try:
        assert replay(endpoint, drive["whole"], "--rate", "0", "--topics", "/tf_static") == 0
        assert wait_until(lambda: clock, 5)
    finally:
        subscriber.undeclare()
        listener.close()
    assert typestore().deserialize_cdr(clock[-1], "rosgraph_msgs/msg/Clock").clock.sec == 1_600_000_000


def test_tf_static_published_before_the_mapper_subscribed_still_reaches_it():
    """/tf_static is TRANSIENT_LOCAL: a robot published it long before the mapper started; the feed's subscriber asks
    the publisher's cache for it (Zenoh's advanced publisher and subscriber, as rmw_zenoh keeps latched topics)."""
    from evsemmap_warp.live.feed import RobotFeed
    from evsemmap_warp.live.node import Ros2Node
    from evsemmap_warp.live.scan_queue import ScanQueue

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = open_session(ZenohOptions(listen=[endpoint]))
    mapper = feed = None
    store = typestore()
    T = store.types
    try:
        node = Ros2Node(robot, "robot", store=store)
        node.advertise("/tf_static", "tf2_msgs/msg/TFMessage", latched=True)
        stamp = T["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
        transform = T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="base_link"), child_frame_id="lidar",
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](0.0, 0.0, 1.0),
                                                       rotation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0)))
        node.publish_message("/tf_static", T["tf2_msgs/msg/TFMessage"](transforms=[transform]))
        mapper = open_session(ZenohOptions(connect=[endpoint]))
        feed = RobotFeed(mapper, load_config(PRESETS, method="ebs").dataset.bag, ScanQueue(2), store, key_format="rmw_zenoh")
        assert wait_until(lambda: feed.topics["/tf_static"].received == 1, 10)
        assert feed.tree.parent("lidar") == "base_link"
        node.close()
    finally:
        if feed is not None:
            feed.close()
        if mapper is not None:
            mapper.close()
        robot.close()


def test_a_dds_robot_behind_the_zenoh_bridge_is_detected_and_answered_in_its_format(drive, tmp_path):
    """The bridge's keys (the topic name alone, no attachment): live detects them and publishes the map back so."""
    live = LiveRun(tmp_path, "--idle-exit", "3")
    listener = open_session(ZenohOptions(connect=[live.endpoint]))
    maps = []
    subscriber = listener.declare_subscriber(topic_key(MAP_TOPIC, key_format="bridge"), lambda sample: maps.append(sample.payload.to_bytes()))
    try:
        assert replay(live.endpoint, drive["whole"], "--key-format", "bridge") == 0
        report = live.result()
        assert wait_until(lambda: maps, 5)
    finally:
        subscriber.undeclare()
        listener.close()
    assert live.code == 0 and report["key_format"] == "bridge" and report["scans_mapped"] == 6, report
    cloud = typestore().deserialize_cdr(maps[-1], "sensor_msgs/msg/PointCloud2")
    assert cloud.width == report["occupied"]


@pytest.fixture(scope="module")
def camera_drive(tmp_path_factory):
    """The tiny drive with its camera, as a ROS 2 bag, and an untrained tiny segmentation checkpoint."""
    import torch

    from evsemmap_warp.classes import class_set
    from evsemmap_warp.segmentation.config import ModelConfig
    from evsemmap_warp.segmentation.model import build_model
    from evsemmap_warp.segmentation.train import TrainConfig, save_checkpoint

    root = tmp_path_factory.mktemp("live_camera")
    generate_sequence(load_preset("tiny"), root / "folder", progress=False)
    write_log(root / "folder", root / "bag", "rosbag2")
    torch.manual_seed(0)
    names = class_set().names
    config = TrainConfig(model=ModelConfig(num_classes=len(names), width=8, aspp_channels=8), input_size=(32, 64))
    model = build_model(config.model)
    save_checkpoint(root / "net.pt", model, torch.optim.SGD(model.parameters(), lr=0.1), 1, config, names, [])
    return root / "bag", root / "net.pt"


def test_camera_labelled_scans_map_live_as_map_checkpoint_maps_the_log(camera_drive, tmp_path):
    """--checkpoint: each scan's image through the network, the scan projected into it, bins of frames: the map
    of `evsemmap map LOG --checkpoint` (one image per inference batch in both: the same network outputs)."""
    log, checkpoint = camera_drive
    out = tmp_path / "batch.npz"
    assert main(["map", str(log), *PRESETS, "--method", "prob", "--checkpoint", str(checkpoint), "--bin-frames", "4", "--batch-size", "1",
                 "--out", str(out), "--quiet"]) == 0
    live = LiveRun(tmp_path, "--idle-exit", "3", "--no-publish", "--checkpoint", str(checkpoint), "--bin-frames", "4", "--method", "prob")
    assert replay(live.endpoint, log) == 0
    report = live.result()
    assert live.code == 0 and report["scans_mapped"] == 6 and report["scans_dropped"] == 0, report
    mapped = Mapper.load(live.out)
    assert mapped.scans_integrated == 2  # a bin of 4 frames and the last, short one of 2
    assert_same_map(mapped, Mapper.load(out))


def test_ctrl_c_writes_the_map_and_the_store(drive, tmp_path):
    """Nothing lost when the run ends: Ctrl-C (SIGINT) to a live run that was told no end writes --out and --store."""
    import shutil
    import signal
    import subprocess
    import sys

    from evsemmap_warp.core.map_store import MapStore

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    command = shutil.which("evsemmap", path=str(Path(sys.executable).parent))
    live = subprocess.Popen([command, "live", *PRESETS, "--method", "ebs", "--out", str(tmp_path / "live.npz"), "--listen", endpoint,
                             "--no-publish", "--store", str(tmp_path / "store"), "--store-every", "3600"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert replay(endpoint, drive["whole"]) == 0
        time.sleep(5.0)  # the six scans are in its queue once replay returns (it waited for the subscriber): mapped by now
        live.send_signal(signal.SIGINT)
        out, err = live.communicate(timeout=60)
    finally:
        if live.poll() is None:
            live.kill()
    assert live.returncode == 0 and "interrupted: writing the map" in err, err
    assert json.loads(out)["scans_mapped"] == 6
    assert Mapper.load(tmp_path / "live.npz").scans_integrated == 6 and MapStore(tmp_path / "store").to_mapper().scans_integrated == 6
