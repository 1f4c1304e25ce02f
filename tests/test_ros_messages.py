"""Robot-log building blocks held against plain constructions: the TF tree (interpolation, chains,
refusals), PointCloud2 decoding (every field type, padding, byte order, organised clouds), images,
camera info and header stamps read from raw bytes."""

import io
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from evsemmap_warp.data.ros_messages import (POINTFIELD_DTYPES, MessageError, camera_from_info, decode_cloud, decode_image,
                                             encode_cloud, header_stamp_ns)
from evsemmap_warp.geometry.camera import matrix_to_quaternion, quaternion_to_matrix, rigid
from evsemmap_warp.geometry.transform_tree import TransformError, TransformTree, slerp


def yaw(degrees: float) -> np.ndarray:
    half = np.radians(degrees) / 2
    return np.array([0.0, 0.0, np.sin(half), np.cos(half)])


# TF tree -------------------------------------------------------------------------------------------
def test_interpolation_is_linear_in_translation_and_slerp_in_rotation():
    tree = TransformTree()
    tree.add_timed("odom", "base", 1_000, [0, 0, 0], yaw(0))
    tree.add_timed("odom", "base", 2_000, [4, 2, 0], yaw(90))
    pose = tree.lookup("odom", "base", 1_250)
    np.testing.assert_allclose(pose[:3, 3], [1.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], quaternion_to_matrix(yaw(22.5)), atol=1e-12)
    # at a sample's own stamp the sample itself, bit for bit
    q = yaw(90)
    assert np.array_equal(tree.lookup("odom", "base", 2_000), rigid(quaternion_to_matrix(q / np.linalg.norm(q)), [4, 2, 0]))


def test_slerp_takes_the_shorter_arc_and_keeps_unit_length():
    a, b = yaw(170), -yaw(-170)  # 20 degrees apart the short way, b given with the opposite sign
    mid = slerp(a, b, 0.5)
    assert abs(np.linalg.norm(mid) - 1) < 1e-12
    np.testing.assert_allclose(quaternion_to_matrix(mid), quaternion_to_matrix(yaw(180)), atol=1e-12)
    assert np.allclose(slerp(a, a, 0.3), a)


def test_a_chain_of_frames_composes_and_inverts():
    rng = np.random.default_rng(3)
    parts = {}
    tree = TransformTree()
    for parent, child in (("odom", "base_link"), ("base_link", "sensor"), ("sensor", "lidar"), ("base_link", "camera")):
        q = rng.normal(size=4)
        t = rng.normal(size=3)
        parts[child] = rigid(quaternion_to_matrix(q), t)
        if child == "base_link":
            tree.add_timed(parent, child, 0, t, q)
            tree.add_timed(parent, child, 10, t, q)
        else:
            tree.add_static(parent, child, t, q)
    odom_lidar = parts["base_link"] @ parts["sensor"] @ parts["lidar"]
    np.testing.assert_allclose(tree.lookup("odom", "lidar", 5), odom_lidar, atol=1e-12)
    camera_lidar = np.linalg.inv(parts["camera"]) @ parts["sensor"] @ parts["lidar"]
    np.testing.assert_allclose(tree.lookup("camera", "lidar", 5), camera_lidar, atol=1e-12)
    assert tree.is_static_between("camera", "lidar") and not tree.is_static_between("odom", "lidar")
    assert tree.root("lidar") == "odom"


def test_times_outside_the_record_and_broken_chains_are_refused_with_names():
    tree = TransformTree()
    tree.add_timed("odom", "base", 1_000_000_000, [0, 0, 0], yaw(0))
    tree.add_timed("odom", "base", 2_000_000_000, [1, 0, 0], yaw(0))
    tree.add_static("base", "lidar", [0, 0, 1], yaw(0))
    tree.add_static("map", "gps", [0, 0, 0], yaw(0))
    with pytest.raises(TransformError, match=r"odom -> base at t = 2\.500000 s.*recorded from t = 1\.000000 s"):
        tree.lookup("odom", "lidar", 2_500_000_000)
    with pytest.raises(TransformError, match=r"'gps' and 'lidar' are not connected"):
        tree.lookup("gps", "lidar", 1_500_000_000)
    with pytest.raises(TransformError, match="two parents"):
        tree.add_static("map", "lidar", [0, 0, 0], yaw(0))


def test_matrix_to_quaternion_round_trips_to_rounding():
    rng = np.random.default_rng(0)
    for i in range(2000):
        q = rng.normal(size=4)
        if i % 3 == 0:  # nearly the identity and nearly half turns: where a naive formula cancels digits
            q[:3] *= 1e-6 if i % 2 else 1.0
            q[3] *= 1.0 if i % 2 else 1e-6
        rotation = quaternion_to_matrix(q)
        back = quaternion_to_matrix(matrix_to_quaternion(rotation))
        assert np.abs(back - rotation).max() < 1e-14
        assert matrix_to_quaternion(rotation)[3] >= 0


# PointCloud2 ---------------------------------------------------------------------------------------
def _fields(layout):
    return [SimpleNamespace(name=n, offset=o, datatype=d, count=c) for n, o, d, c in layout]


def _message(columns: dict, *, point_step=None, offsets=None, height=1, big_endian=False, row_padding=0):
    attrs = encode_cloud(columns, point_step=point_step, offsets=offsets, height=height, big_endian=big_endian)
    data = attrs["data"]
    if row_padding:  # rows longer than their points, as some drivers align them
        rows = data.reshape(height, -1)
        data = np.concatenate([rows, np.full((height, row_padding), 0xAB, np.uint8)], axis=1).reshape(-1)
        attrs["row_step"] += row_padding
    attrs["data"] = data
    attrs["fields"] = _fields(attrs["fields"])
    return SimpleNamespace(**attrs)


@pytest.mark.parametrize("big_endian", [False, True])
def test_every_field_type_decodes_with_padding_and_byte_order(big_endian):
    rng = np.random.default_rng(1)
    n = 24
    columns = {}
    for code, kind in POINTFIELD_DTYPES.items():
        info = np.iinfo(kind) if kind[0] in "iu" else None
        values = rng.integers(info.min, info.max, n, endpoint=True) if info else rng.normal(0, 1e3, n)
        columns[f"f{code}"] = np.asarray(values).astype(kind)
    offsets, at = {}, 0
    for name, col in columns.items():  # 3 bytes of padding before every field
        offsets[name] = at + 3
        at = offsets[name] + col.dtype.itemsize
    msg = _message(columns, point_step=at + 5, offsets=offsets, height=4, big_endian=big_endian, row_padding=7)
    cloud = decode_cloud(msg)
    assert len(cloud) == n
    for name, col in columns.items():
        assert np.array_equal(cloud[name].astype(col.dtype), col), name


def test_organised_clouds_flatten_row_by_row_and_count_fields_are_vectors():
    xyz = np.arange(2 * 3 * 3, dtype=np.float32).reshape(6, 3)
    msg = SimpleNamespace(height=2, width=3, point_step=16, row_step=48, is_bigendian=False,
                          fields=_fields([("xyz", 0, 7, 3), ("i", 12, 2, 1)]))
    raw = np.zeros((6, 16), np.uint8)
    raw[:, :12] = xyz.view(np.uint8).reshape(6, 12)
    raw[:, 12] = np.arange(6)
    msg.data = raw.reshape(-1)
    cloud = decode_cloud(msg)
    assert np.array_equal(cloud["xyz"], xyz) and np.array_equal(cloud["i"], np.arange(6))


def test_truncated_and_inconsistent_clouds_say_what_is_wrong():
    msg = _message({"x": np.zeros(10, np.float32), "y": np.zeros(10, np.float32), "z": np.zeros(10, np.float32)})
    msg.data = msg.data[:-4]
    with pytest.raises(MessageError, match="truncated"):
        decode_cloud(msg)
    msg = _message({"x": np.zeros(4, np.float32)})
    msg.fields[0].offset = 2
    with pytest.raises(MessageError, match="past point_step"):
        decode_cloud(msg)
    msg = _message({"x": np.zeros(4, np.float32)})
    msg.fields[0].datatype = 9
    with pytest.raises(MessageError, match="unknown datatype 9"):
        decode_cloud(msg)
    empty = _message({"x": np.zeros(0, np.float32)})
    assert len(decode_cloud(empty)) == 0


# Images, camera info, stamps ---------------------------------------------------------------------
def test_raw_and_compressed_images_decode_to_rgb_or_ids():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    padded = np.zeros((5, 7 * 3 + 3), np.uint8)
    padded[:, :21] = rgb.reshape(5, 21)
    msg = SimpleNamespace(encoding="bgr8", height=5, width=7, step=24, is_bigendian=0, data=padded.reshape(-1))
    assert np.array_equal(decode_image(msg, "x"), rgb[..., ::-1])
    ids = rng.integers(0, 60000, (5, 7)).astype(">u2")
    msg = SimpleNamespace(encoding="mono16", height=5, width=7, step=14, is_bigendian=1, data=ids.view(np.uint8).reshape(-1))
    assert np.array_equal(decode_image(msg, "x"), ids.astype(np.uint16))
    png = io.BytesIO()
    Image.fromarray(rgb).save(png, format="png")
    assert np.array_equal(decode_image(SimpleNamespace(format="png", data=np.frombuffer(png.getvalue(), np.uint8)), "x"), rgb)
    with pytest.raises(MessageError, match="cannot be decoded"):
        decode_image(SimpleNamespace(format="jpeg", data=np.zeros(10, np.uint8)), "x")
    with pytest.raises(MessageError, match="'bayer_rggb8' is not supported"):
        decode_image(SimpleNamespace(encoding="bayer_rggb8", height=1, width=1, step=1, is_bigendian=0, data=np.zeros(1, np.uint8)), "x")


def test_camera_info_gives_the_pinhole_camera_and_refuses_models_it_cannot_apply():
    header = SimpleNamespace(frame_id="cam")
    info = SimpleNamespace(header=header, width=640, height=480, distortion_model="plumb_bob", d=[0.1, -0.2, 0.001, 0.002, 0.05],
                           k=[500, 0, 320, 0, 510, 240, 0, 0, 1])
    camera = camera_from_info(info, "x").camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height) == (500, 510, 320, 240, 640, 480)
    assert camera.distortion == (0.1, -0.2, 0.001, 0.002, 0.05)
    info.distortion_model = "equidistant"
    with pytest.raises(MessageError, match="'equidistant' is not supported"):
        camera_from_info(info, "x")


def test_header_stamps_read_from_raw_bytes_match_the_deserialised_header():
    pytest.importorskip("rosbags")
    from rosbags.typesys import Stores, get_typestore

    for store, ros2 in ((Stores.ROS1_NOETIC, False), (Stores.ROS2_HUMBLE, True)):
        types = get_typestore(store)
        t = types.types
        time = t["builtin_interfaces/msg/Time"](sec=1_600_000_123, nanosec=987_654_321)
        header = t["std_msgs/msg/Header"](**({"seq": 7} if not ros2 else {}), stamp=time, frame_id="os1_lidar")
        msg = t["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=np.zeros(3, np.uint8))
        raw = types.serialize_cdr(msg, msg.__msgtype__) if ros2 else types.serialize_ros1(msg, msg.__msgtype__)
        assert header_stamp_ns(raw, ros2) == 1_600_000_123_987_654_321
