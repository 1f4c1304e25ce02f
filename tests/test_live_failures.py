"""What a robot does to a live mapper, without a network: the tiny drive's messages (CDR, from a ROS 2 bag)
handed to the subscriber callback as Zenoh samples, in the order and at the times a test chooses. Each
case is said in one line and counted, never mapped silently wrong. Also the wire format's pieces."""

import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")

from evsemmap_warp.config import ConfigError, load_config  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402
from evsemmap_warp.data.log_writer import write_log  # noqa: E402
from evsemmap_warp.data.logs import open_reader  # noqa: E402
from evsemmap_warp.live.feed import RobotFeed  # noqa: E402
from evsemmap_warp.live.mapping import LiveMapping, LiveSettings  # noqa: E402
from evsemmap_warp.live.ros2_wire import (WireError, decode_attachment, encode_attachment, node_token, parse_key, parse_token,  # noqa: E402
                                          publisher_token, topic_key, typestore)
from evsemmap_warp.live.scan_queue import ReceivedScan, ScanQueue  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402

PRESETS = ["rellis3d", "rellis3d-bag"]
CLOUD, ODOMETRY, TF_STATIC = "/os1_cloud_node/points", "/odometry/filtered", "/tf_static"
STORE = typestore()


@pytest.fixture(scope="module")
def messages(tmp_path_factory):
    """(topic, msgtype, CDR) of the tiny LiDAR-only drive's ROS 2 bag, in log order, and the bag."""
    root = tmp_path_factory.mktemp("live_failures")
    generate_sequence(load_preset("tiny"), root / "folder", progress=False, camera=False)
    write_log(root / "folder", root / "bag", "rosbag2")
    reader = open_reader([root / "bag"])
    try:
        return [(c.topic, c.msgtype, bytes(raw)) for c, _, raw in reader.messages()], root / "bag"
    finally:
        reader.close()


class Bytes:
    def __init__(self, data: bytes):
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class Sample:
    """What a Zenoh subscriber callback is handed: key, payload, attachment."""

    def __init__(self, key: str, payload: bytes, attachment: bytes | None = None):
        self.key_expr, self.payload = key, Bytes(payload)
        self.attachment = None if attachment is None else Bytes(attachment)


class NoNetwork:
    """A session that subscribes to nothing: the test hands the callback its samples."""

    def declare_subscriber(self, key, callback):
        return type("Subscriber", (), {"undeclare": lambda self: None})()


def rig(tmp_path, *, queue: int = 8, key_format: str = "rmw_zenoh", max_cloud_bytes: int = 256 << 20, **settings):
    run = load_config(PRESETS, method="ebs")
    scans = ScanQueue(queue)
    feed = RobotFeed(NoNetwork(), run.dataset.bag, scans, STORE, key_format=key_format, max_cloud_bytes=max_cloud_bytes)
    mapping = LiveMapping(run, feed, scans, LiveSettings(**settings), out=tmp_path / "live.npz")
    return feed, mapping, scans


def send(feed, topic, msgtype, cdr, *, key_format="rmw_zenoh", sequence=1):
    if key_format == "rmw_zenoh":
        key = topic_key(topic, key_format="rmw_zenoh", msgtype=msgtype, type_hash=STORE.hash_rihs01(msgtype))
        feed.on_sample(topic, Sample(key, cdr, encode_attachment(sequence, time.time_ns(), b"g" * 16)))
    else:
        feed.on_sample(topic, Sample(topic.strip("/"), cdr))


def map_queued(mapping, scans) -> None:
    while (item := scans.get(timeout=0.0)) is not None:
        mapping.map_scan(item)


def frames(messages):
    """The messages grouped per cloud: the cloud and the odometry stamped with it (the static transforms apart)."""
    static = [m for m in messages if m[0] == TF_STATIC]
    odometry = [m for m in messages if m[0] == ODOMETRY]
    clouds = [m for m in messages if m[0] == CLOUD]
    return static, list(zip(clouds, odometry))


def test_wire_keys_attachments_and_tokens():
    key = topic_key("/os1_cloud_node/points", key_format="rmw_zenoh", domain_id=3, msgtype="sensor_msgs/msg/PointCloud2",
                    type_hash=STORE.hash_rihs01("sensor_msgs/msg/PointCloud2"))
    # the hash ROS 2 Humble / Jazzy give PointCloud2 (ros2 topic info -v prints it)
    assert key == "3/os1_cloud_node/points/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
    assert parse_key(key, 3).topic == "/os1_cloud_node/points" and parse_key(key, 3).msgtype == "sensor_msgs/msg/PointCloud2"
    assert parse_key("os1_cloud_node/points", 3) == parse_key("os1_cloud_node/points", 0)
    assert parse_key("os1_cloud_node/points", 3).key_format == "bridge"
    assert topic_key("/tf", key_format="bridge") == "tf"
    assert decode_attachment(encode_attachment(7, 123, b"x" * 16)) == (7, 123, b"x" * 16)
    assert decode_attachment(None) is None
    with pytest.raises(WireError, match="33"):
        decode_attachment(b"\0" * 32)
    token = publisher_token(0, "abc", 1, 2, "evsemmap_live", "/evsemmap/map", "sensor_msgs/msg/PointCloud2", "RIHS01_x")
    assert token.startswith("@ros2_lv/0/abc/1/2/MP/%/%/evsemmap_live/%evsemmap%map/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_x/")
    assert parse_token(token)["topic"] == "/evsemmap/map" and parse_token(node_token(0, "abc", 1, "n")) is None


def test_a_full_queue_drops_the_oldest_scans_counted_and_never_blocks():
    dropped = []
    scans = ScanQueue(2, on_drop=lambda scan, total: dropped.append((scan.sequence, total)))
    started = time.perf_counter()
    for i in range(5):
        scans.put(ReceivedScan(b"", 0, None, i))
    assert time.perf_counter() - started < 0.5
    assert dropped == [(0, 1), (1, 2), (2, 3)] and scans.dropped == 3 and scans.received == 5
    assert [scans.get(0).sequence, scans.get(0).sequence, scans.get(0.01)] == [3, 4, None]


def test_mapping_behind_is_reported_in_the_diagnostics(messages, tmp_path, capsys):
    feed, mapping, scans = rig(tmp_path, queue=2)
    static, pairs = frames(messages[0])
    send(feed, *static[0])
    for cloud, odometry in pairs:  # every scan arrives before any is mapped
        send(feed, *odometry)
        send(feed, *cloud)
    map_queued(mapping, scans)
    values = mapping.diagnostics()
    assert values["dropped_queue_full"] == 4 and values["scans_mapped"] == 2 and values["scans_received"] == 6
    assert "the oldest scan was dropped" in capsys.readouterr().err


def test_a_late_transform_is_waited_for_and_one_that_never_comes_drops_the_scan(messages, tmp_path, capsys):
    static, pairs = frames(messages[0])
    feed, mapping, scans = rig(tmp_path, tf_wait_s=2.0)
    send(feed, *static[0])
    send(feed, *pairs[0][1])
    send(feed, *pairs[0][0])
    map_queued(mapping, scans)
    (cloud, odometry), (cloud2, odometry2) = pairs[1], pairs[2]
    send(feed, *cloud)  # its pose arrives 0.3 s later
    threading.Timer(0.3, lambda: send(feed, *odometry)).start()
    assert mapping.map_scan(scans.get(1.0))
    send(feed, *cloud2)  # its pose never comes
    mapping.settings.tf_wait_s = 0.2
    started = time.perf_counter()
    assert not mapping.map_scan(scans.get(1.0))
    assert time.perf_counter() - started < 1.5
    assert mapping.stats.mapped == 2 and mapping.diagnostics()["dropped_no_pose"] == 1
    err = capsys.readouterr().err
    assert "no pose in the fixed frame after waiting 0.2 s (--tf-wait)" in err and "is known up to" in err


def test_time_running_back_is_refused_or_starts_a_new_map(messages, tmp_path, capsys):
    static, pairs = frames(messages[0])
    for policy in ("refuse", "reset"):
        feed, mapping, scans = rig(tmp_path / policy, on_time_jump=policy)
        (tmp_path / policy).mkdir()
        send(feed, *static[0])
        for cloud, odometry in pairs:
            send(feed, *odometry)
            send(feed, *cloud)
            map_queued(mapping, scans)
        first = mapping.mapper
        send(feed, *pairs[0][1])  # the log again from its start
        send(feed, *pairs[0][0])
        map_queued(mapping, scans)
        err = capsys.readouterr().err
        assert "time jumped back 0.500 s" in err
        if policy == "refuse":
            assert mapping.stats.mapped == 6 and mapping.diagnostics()["dropped_time_jump"] == 1 and mapping.mapper is first
            assert "--on-time-jump refuse" in err
        else:
            assert mapping.stats.mapped == 7 and mapping.mapper is not first and mapping.mapper.scans_integrated == 1
            assert Mapper.load(tmp_path / policy / "live.1.npz").scans_integrated == 6 and "a new map starts" in err


def test_another_type_a_malformed_message_and_a_huge_cloud_are_refused_counted(messages, tmp_path, capsys):
    static, pairs = frames(messages[0])
    feed, mapping, scans = rig(tmp_path, max_cloud_bytes=1 << 20)
    send(feed, *static[0])
    send(feed, CLOUD, "tf2_msgs/msg/TFMessage", static[0][2])  # another type on the cloud topic
    send(feed, CLOUD, "tf2_msgs/msg/TFMessage", static[0][2])
    send(feed, CLOUD, "sensor_msgs/msg/PointCloud2", b"\0\1\0\0 not a cloud")
    send(feed, ODOMETRY, "nav_msgs/msg/Odometry", b"\0\1\0\0 not odometry")
    send(feed, *pairs[0][1])
    send(feed, CLOUD, "sensor_msgs/msg/PointCloud2", pairs[0][0][2] + bytes(2 << 20))  # 2 MiB over the limit
    send(feed, CLOUD, "sensor_msgs/msg/PointCloud2", pairs[0][0][2] + bytes(3 << 20))
    map_queued(mapping, scans)
    values = mapping.diagnostics()
    assert values["dropped_malformed"] == 1 and values["dropped_too_large"] == 2 and values["scans_mapped"] == 0
    assert values["refused_messages"] == 3  # two of another type, the odometry that does not decode
    err = capsys.readouterr().err
    assert err.count("a message of type tf2_msgs/msg/TFMessage, expected sensor_msgs/msg/PointCloud2") == 1  # said once, counted
    assert "a message that is no PointCloud2" in err and err.count("over --max-cloud-mb 1") == 1 and "no nav_msgs/msg/Odometry" in err
    send(feed, *pairs[0][0])  # the robot's own clouds still map
    map_queued(mapping, scans)
    assert mapping.stats.mapped == 1


def test_an_image_that_does_not_decode_drops_its_scan_not_the_run(messages, tmp_path, capsys):
    from evsemmap_warp.data.sequences import DataError

    class BrokenCamera:  # what CameraLabeller.image_for raises for an image that does not decode
        def image_for(self, stamp, deadline):
            raise DataError("/camera/image (1.000 s): not an image (decoding failed)")

    static, pairs = frames(messages[0])
    feed, mapping, scans = rig(tmp_path)
    mapping.labeller = BrokenCamera()
    for message in static + [m for pair in pairs[:2] for m in pair[::-1]]:
        send(feed, *message)
    map_queued(mapping, scans)
    values = mapping.diagnostics()
    assert values["dropped_no_image"] == 2 and values["scans_mapped"] == 0
    assert "not an image (decoding failed); dropped (2 no image so far)" in capsys.readouterr().err


def test_a_dds_bridge_robot_is_detected_and_maps_as_rmw_zenoh_does(messages, tmp_path):
    static, pairs = frames(messages[0])
    maps = {}
    for key_format in ("rmw_zenoh", "bridge"):
        feed, mapping, scans = rig(tmp_path, key_format="auto")
        send(feed, *static[0], key_format=key_format)
        for cloud, odometry in pairs:
            send(feed, *odometry, key_format=key_format)
            send(feed, *cloud, key_format=key_format)
            map_queued(mapping, scans)
        assert feed.detected_format == key_format and mapping.stats.mapped == 6
        maps[key_format] = mapping.mapper.voxels().arrays
    np.testing.assert_array_equal(maps["rmw_zenoh"].index, maps["bridge"].index)
    np.testing.assert_array_equal(maps["rmw_zenoh"].evidence, maps["bridge"].evidence)


def test_a_silent_topic_is_named_within_seconds(tmp_path, capsys):
    feed, mapping, _ = rig(tmp_path, topic_timeout_s=0.3, duration_s=1.0)
    started = time.perf_counter()
    mapping.run_until_stopped(threading.Event())
    assert time.perf_counter() - started < 3
    err = capsys.readouterr().err
    assert f"nothing on ['{CLOUD}', '{TF_STATIC}', '{ODOMETRY}'] after 0.3 s (--topic-timeout)" in err
    assert mapping.finish() is None


def test_a_live_map_refuses_first_scan_frames(tmp_path):
    run = load_config(PRESETS, method="ebs", frame="first-scan")
    scans = ScanQueue(2)
    with pytest.raises(ConfigError, match="first-scan"):
        LiveMapping(run, RobotFeed(NoNetwork(), run.dataset.bag, scans, STORE), scans, LiveSettings())


def test_the_tf_tree_of_a_long_drive_stays_bounded_and_a_jump_forgets_the_old_timeline():
    from evsemmap_warp.geometry.transform_tree import TransformError, TransformTree

    tree = TransformTree()
    tree.add_static("base", "lidar", [0, 0, 1], [0, 0, 0, 1])
    for t in range(10):
        tree.add_timed("odom", "base", t * 100, [t, 0, 0], [0, 0, 0, 1])
    tree.trim(before_ns=450)  # the samples at 400 and later stay: 450 still interpolates
    assert tree.time_range("base") == (400, 900)
    np.testing.assert_allclose(tree.lookup("odom", "lidar", 450)[:3, 3], [4.5, 0, 1])
    tree.trim(after_ns=500)
    assert tree.time_range("base") == (400, 500)
    with pytest.raises(TransformError):
        tree.lookup("odom", "lidar", 600)
    tree.trim(before_ns=10_000, after_ns=0)
    assert not tree.is_timed("base") and tree.parent("lidar") == "base"


def test_without_eclipse_zenoh_live_says_how_to_install_it(monkeypatch, capsys):
    from evsemmap_warp.apps.cli import main

    monkeypatch.setitem(sys.modules, "zenoh", None)  # import zenoh raises ImportError, as without the package
    assert main(["live", *PRESETS, "--method", "ebs", "--out", "x.npz"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == 'evsemmap: error: live mapping over Zenoh needs the eclipse-zenoh package: pip install "evsemmap_warp[live]"'


@pytest.mark.parametrize("flags, says", [(["--connect", "192.168.1.10"], "--connect '192.168.1.10': a Zenoh endpoint is PROTOCOL/HOST:PORT"),
                                         (["--zenoh-config", "missing.json5"], "--zenoh-config missing.json5: no such file"),
                                         (["--mode", "client"], "--mode client needs --connect"),
                                         (["--domain-id", "-1"], "--domain-id -1: a ROS domain id is >= 0")])
def test_bad_connection_flags_are_one_line_naming_the_flag(flags, says, capsys):
    pytest.importorskip("zenoh")
    from evsemmap_warp.apps.cli import main

    assert main(["live", *PRESETS, "--method", "ebs", "--out", "x.npz", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evsemmap: error: ") and says in err[0], err
