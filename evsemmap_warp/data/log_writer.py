"""Write a sequence folder (RELLIS-3D layout: what ``evsemmap synth`` renders) as a robot log, with
``rosbags``' writers: a ROS 1 bag, a ROS 2 bag folder (sqlite3) or a bare MCAP file.

Topics are RELLIS-3D's (the ``rellis3d-bag`` preset reads them): Ouster-like organised clouds with
padded points and a ``label`` field, raw and JPEG-compressed images, camera info, 2D label ids,
odometry, and ``/tf`` + ``/tf_static`` with the chain odom -> base_link -> os1_sensor -> os1_lidar ->
pylon_camera. Poses are written at each cloud's stamp and halfway between, so a cloud's pose is read
back exactly and the halfway samples exercise interpolation.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import yaml

from ..config import ConfigError
from ..geometry.camera import matrix_to_quaternion, quaternion_to_matrix, rigid
from ..geometry.transform_tree import slerp
from .ros_messages import encode_cloud
from .sequences import Rellis3DSequence, read_frame_file

LOG_ROOT_FRAME = "odom"  # the TF root of a log written from a folder whose frame.yaml names none

LOG_FORMATS = ("rosbag1", "rosbag2", "mcap")
FIRST_STAMP_NS = 1_600_000_000 * 1_000_000_000  # the synthetic frames' first stamp (synthetic.writer.frame_stem)
FRAME_PERIOD_NS = 100_000_000
IMAGE_DELAY_NS = 10_000_000  # the camera fires 10 ms after the LiDAR, as an unsynchronised camera would
RECEIVE_DELAY_NS = 2_000_000  # messages reach the recorder 2 ms after their stamp
TOPICS = {
    "cloud": "/os1_cloud_node/points",
    "image": "/pylon_camera_node/image_raw",
    "compressed": "/pylon_camera_node/image_raw/compressed",
    "camera_info": "/pylon_camera_node/camera_info",
    "label_image": "/pylon_camera_node/label_id",
    "odometry": "/odometry/filtered",
    "tf": "/tf",
    "tf_static": "/tf_static",
}
# The LiDAR on its robot: base_link -> os1_sensor (a mast, turned 90 degrees) -> os1_lidar (Ouster's
# sensor-to-lidar frame turn of 180 degrees): a TF chain of three frames below odom.
BASE_TO_SENSOR = rigid(quaternion_to_matrix([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]), [0.2, 0.0, 1.2])
SENSOR_TO_LIDAR = rigid(quaternion_to_matrix([0.0, 0.0, 1.0, 0.0]), [0.0, 0.0, 0.03618])
# Ouster OS1 point layout: x y z, 4 bytes of padding, intensity, t, reflectivity, ring, ..., 48 bytes a point
OUSTER_OFFSETS = {"x": 0, "y": 4, "z": 8, "intensity": 16, "t": 20, "reflectivity": 24, "ring": 26, "label": 28, "range": 32}
OUSTER_POINT_STEP = 48

TF_MESSAGE_DEFINITION = "geometry_msgs/TransformStamped[] transforms\n"


def _typestore(ros2: bool):
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg(TF_MESSAGE_DEFINITION, "tf2_msgs/msg/TFMessage"))
    return store


class _LogOut:
    """One writer interface over the three formats: connections by topic, messages serialised."""

    def __init__(self, out: Path, fmt: str):
        try:
            from rosbags.rosbag1 import Writer as Writer1
            from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
        except ImportError:
            raise ConfigError('writing robot logs needs the rosbags package: pip install "evsemmap_warp[ros]"') from None
        self.out, self.fmt, self.ros2 = out, fmt, fmt != "rosbag1"
        self.store = _typestore(self.ros2)
        self.types = self.store.types
        self._staging = None
        if fmt == "rosbag1":
            self.writer = Writer1(out)
        else:
            target = out
            if fmt == "mcap":  # rosbag2 writes a bag folder; the bare .mcap inside it is moved out at the end
                self._staging = Path(tempfile.mkdtemp(prefix=".mcap-", dir=out.parent))
                target = self._staging / "bag"
            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(target, version=9, storage_plugin=plugin)
        self.writer.open()
        self.connections = {}

    def header(self, stamp_ns: int, frame_id: str, seq: int = 0):
        time = self.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        if self.ros2:
            return self.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](seq=seq, stamp=time, frame_id=frame_id)

    def write(self, topic: str, msg, log_time_ns: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = self.store.serialize_cdr(msg, msgtype) if self.ros2 else self.store.serialize_ros1(msg, msgtype)
        self.writer.write(self.connections[topic], log_time_ns, data)

    def close(self) -> None:
        self.writer.close()
        if self._staging is not None:
            (mcap,) = (self._staging / "bag").glob("*.mcap")
            mcap.replace(self.out)
            shutil.rmtree(self._staging)

    def abort(self) -> None:
        try:
            self.writer.close()
        finally:
            if self._staging is not None:
                shutil.rmtree(self._staging, ignore_errors=True)

    # Messages ------------------------------------------------------------------------------------
    def transform(self, parent: str, child: str, matrix: np.ndarray, stamp_ns: int, quaternion=None):
        T = self.types
        q = matrix_to_quaternion(matrix[:3, :3]) if quaternion is None else quaternion
        return T["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*map(float, matrix[:3, 3])),
                                                       rotation=T["geometry_msgs/msg/Quaternion"](*map(float, q))))

    def tf(self, transforms):
        return self.types["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(self, parent: str, child: str, matrix: np.ndarray, stamp_ns: int, seq: int):
        T = self.types
        q = matrix_to_quaternion(matrix[:3, :3])
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*map(float, matrix[:3, 3])), orientation=T["geometry_msgs/msg/Quaternion"](*map(float, q)))
        zero = T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, parent, seq), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))

    def cloud(self, columns: dict, stamp_ns: int, frame_id: str, seq: int, height: int):
        T = self.types
        attrs = encode_cloud(columns, point_step=OUSTER_POINT_STEP, offsets=OUSTER_OFFSETS, height=height)
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c) for n, o, d, c in attrs.pop("fields")]
        return T["sensor_msgs/msg/PointCloud2"](header=self.header(stamp_ns, frame_id, seq), fields=fields, is_dense=True, **attrs)

    def image(self, pixels: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, seq: int):
        pixels = np.ascontiguousarray(pixels)
        return self.types["sensor_msgs/msg/Image"](header=self.header(stamp_ns, frame_id, seq), height=pixels.shape[0], width=pixels.shape[1],
                                                   encoding=encoding, is_bigendian=0, step=pixels.strides[0], data=pixels.reshape(-1).view(np.uint8))

    def compressed(self, data: bytes, fmt: str, stamp_ns: int, frame_id: str, seq: int):
        return self.types["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, frame_id, seq), format=fmt, data=np.frombuffer(data, np.uint8))

    def camera_info(self, camera, stamp_ns: int, frame_id: str, seq: int):
        T = self.types
        k = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], np.float64)
        p = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], np.float64)
        matrices = {"D": np.array(camera.distortion, np.float64), "K": k, "R": np.eye(3).reshape(-1), "P": p}
        if self.ros2:
            matrices = {name.lower(): value for name, value in matrices.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](header=self.header(stamp_ns, frame_id, seq), height=camera.height, width=camera.width,
                                               distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **matrices)


def _beams(folder: Path) -> int:
    """Rows of the organised clouds: the synthetic LiDAR's beams when synth.yaml says, else 1."""
    record = folder / "synth.yaml"
    return int(yaml.safe_load(record.read_text())["preset"]["lidar"]["beams"]) if record.exists() else 1


def _halfway(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return rigid(quaternion_to_matrix(slerp(matrix_to_quaternion(a[:3, :3]), matrix_to_quaternion(b[:3, :3]), 0.5)), (a[:3, 3] + b[:3, 3]) / 2)


def write_log(folder, out, fmt: str, *, frames: slice = slice(None), progress: bool = False) -> dict:
    """Write the sequence folder ``folder`` (its ``frames``, all by default) as a log ``out`` in format
    ``fmt`` (rosbag1: a .bag file; rosbag2: a bag folder; mcap: a bare .mcap file). Returns counts of
    what was written."""
    if fmt not in LOG_FORMATS:
        raise ConfigError(f"log format {fmt!r} is unknown; known: {', '.join(LOG_FORMATS)}")
    from tqdm import tqdm

    folder, out = Path(folder), Path(out)
    if out.exists():
        raise ConfigError(f"{out} exists already; a log is written to a new path")
    out.parent.mkdir(parents=True, exist_ok=True)
    seq = Rellis3DSequence(folder)
    seq.frames = seq.frames[frames]
    if not seq.frames:
        raise ConfigError(f"{folder}: no frames in {frames}")
    has_images = any(f.image is not None for f in seq.frames)
    camera = seq.camera if has_images else None  # a LiDAR-only folder (synth --no-camera) has no image size
    mount_q, mount_t = seq.camera_mount
    base_to_lidar = BASE_TO_SENSOR @ SENSOR_TO_LIDAR
    lidar_to_base = np.linalg.inv(base_to_lidar)
    base_poses = [seq.pose(f) @ lidar_to_base for f in seq.frames]
    lidar_beams = _beams(folder)  # read once, not per frame
    own = read_frame_file(folder)
    root = own.name if own is not None else LOG_ROOT_FRAME  # the folder's poses frame is the log's fixed frame
    log = _LogOut(out, fmt)
    counts = {"clouds": 0, "images": 0, "transforms": 0}
    try:
        first = FIRST_STAMP_NS + seq.frames[0].index * FRAME_PERIOD_NS
        # the camera's quaternion as the folder stores it, so both give the very same LiDAR-to-camera matrix
        static = [log.transform("base_link", "os1_sensor", BASE_TO_SENSOR, first), log.transform("os1_sensor", "os1_lidar", SENSOR_TO_LIDAR, first),
                  log.transform("os1_lidar", "pylon_camera", rigid(np.eye(3), mount_t), first, quaternion=mount_q)]
        log.write(TOPICS["tf_static"], log.tf(static), first)
        for n, frame in enumerate(tqdm(seq.frames, desc=f"write {fmt}", unit="frame", disable=not progress)):
            stamp = FIRST_STAMP_NS + frame.index * FRAME_PERIOD_NS
            log.write(TOPICS["tf"], log.tf([log.transform(root, "base_link", base_poses[n], stamp)]), stamp + RECEIVE_DELAY_NS)
            log.write(TOPICS["odometry"], log.odometry(root, "base_link", base_poses[n], stamp, n), stamp + RECEIVE_DELAY_NS)
            if n + 1 < len(seq.frames):
                halfway = stamp + (seq.frames[n + 1].index - frame.index) * FRAME_PERIOD_NS // 2
                log.write(TOPICS["tf"], log.tf([log.transform(root, "base_link", _halfway(base_poses[n], base_poses[n + 1]), halfway)]),
                          halfway + RECEIVE_DELAY_NS)
            counts["transforms"] += 2
            scan = seq.read_scan(frame)
            labels = seq.read_point_labels(frame).astype(np.uint32) if frame.point_labels is not None else np.zeros(len(scan), np.uint32)
            beams = lidar_beams if len(scan) % lidar_beams == 0 else 1
            columns = {"x": scan[:, 0], "y": scan[:, 1], "z": scan[:, 2], "intensity": scan[:, 3],
                       "t": np.zeros(len(scan), np.uint32), "reflectivity": np.zeros(len(scan), np.uint16),
                       "ring": np.repeat(np.arange(beams, dtype=np.uint16), len(scan) // beams), "label": labels,
                       "range": (np.linalg.norm(scan[:, :3], axis=1) * 1000).astype(np.uint32)}
            log.write(TOPICS["cloud"], log.cloud(columns, stamp, "os1_lidar", n, beams), stamp + RECEIVE_DELAY_NS)
            counts["clouds"] += 1
            if frame.image is None:
                continue
            image_stamp = stamp + IMAGE_DELAY_NS
            received = image_stamp + RECEIVE_DELAY_NS
            log.write(TOPICS["image"], log.image(seq.read_image(frame), "rgb8", image_stamp, "pylon_camera", n), received)
            log.write(TOPICS["compressed"], log.compressed(frame.image.read_bytes(), "jpeg" if frame.image.suffix == ".jpg" else "png",
                                                           image_stamp, "pylon_camera", n), received)
            log.write(TOPICS["camera_info"], log.camera_info(camera, image_stamp, "pylon_camera", n), received)
            if frame.label_image is not None:
                ids = seq.read_label_ids(frame)
                log.write(TOPICS["label_image"], log.image(ids.astype(np.uint8) if ids.max(initial=0) < 256 else ids.astype(np.uint16),
                                                           "mono8" if ids.max(initial=0) < 256 else "mono16", image_stamp, "pylon_camera", n), received)
            counts["images"] += 1
    except BaseException:
        log.abort()
        if out.is_dir():
            shutil.rmtree(out, ignore_errors=True)
        elif out.exists():
            out.unlink()
        raise
    log.close()
    return {"log": str(out), "format": fmt, **counts}
