"""Robot logs as sequences, without a ROS install: ROS 1 ``.bag`` files, ROS 2 bag folders (sqlite3
or MCAP) and bare ``.mcap`` / ``.db3`` files, read with the pure-Python ``rosbags`` package.

``LogSequence`` offers what a sequence folder offers (frames, camera, LiDAR-to-camera transform,
poses, scans, images, labels), so projection, mapping and the experiments read logs and folders
alike. Opening a log indexes it once: each cloud's and image's header stamp (read from the raw
bytes, nothing decoded), the transforms (``/tf``, ``/tf_static``, odometry) and the camera info. Scans
and images are then decoded one at a time as they are asked for, by a cursor that moves forward
through the log, so a log larger than memory streams and a sequential pass reads each message once.
Maps are made in the log's fixed frame (``data/world_frame.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import BagConfig, ConfigError
from ..frames import is_run_frame_name, run_id
from ..geometry.camera import PinholeCamera
from ..geometry.transform_tree import TransformError, TransformTree, format_stamp
from .ros_messages import MessageError, camera_from_info, cloud_xyz, decode_cloud, decode_image, header_stamp_ns
from .sequences import CheckReport, DataError

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
INSTALL_HINT = 'reading robot logs needs the rosbags package: pip install "evsemmap_warp[ros]"'


def open_reader(logs: list[Path]):
    """An opened ``rosbags`` AnyReader over the logs (several ROS 1 bags, or ROS 2 bags / files)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    kinds = {p.suffix == ".bag" for p in logs}
    if len(kinds) > 1:
        raise DataError(f"{logs[0]} and {logs[-1]}: ROS 1 bags and ROS 2 logs cannot be read as one sequence; map them separately and merge the maps")
    reader = AnyReader(logs, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own error types per format; all mean "not a readable log"
        raise DataError(f"{', '.join(map(str, logs))}: not a readable robot log ({type(exc).__name__}: {exc}); a log still being "
                        f"recorded, or cut short, has no index or end yet") from None
    if not reader.connections:  # e.g. a .db3 whose recorder has not committed its first messages yet
        reader.close()
        raise DataError(f"{', '.join(map(str, logs))}: the log holds no topic and no message (yet): a log still being recorded "
                        f"holds none until its recorder writes them; map it once it is recorded")
    return reader


class _ReadingErrors:
    """Turns what a damaged log makes rosbags raise mid-read (its reader, deserialiser and
    decompression errors: no common base class) into one DataError naming the log; the project's
    own errors pass through."""

    def __init__(self, where: str):
        self.where = where

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, traceback):
        if exc is None or isinstance(exc, (ValueError, KeyboardInterrupt, MemoryError, GeneratorExit)):
            return False
        raise DataError(f"{self.where}: the log is damaged ({type(exc).__name__}: {exc})") from None


@dataclass
class LogFrame:
    """One cloud of the log; ``image`` / ``label_image``: (log time, header stamp) of the paired
    messages, None without one. ``scan`` and ``point_labels`` name the message in errors."""

    index: int
    stamp_ns: int
    log_time_ns: int
    scan: str
    image: tuple[int, int] | None = None
    label_image: tuple[int, int] | None = None
    point_labels: str | None = None


class _Cursor:
    """Reads the messages of some connections forward in log time; asking for an earlier message
    starts again from there (random access costs a seek, a sequential pass reads each message once)."""

    def __init__(self, reader, connections):
        self.reader, self.connections = reader, connections
        self._messages = None
        self._last = -1

    def get(self, log_time_ns: int, stamp_ns: int, ros2: bool, where: str):
        # at or before the last message read: start again there (messages may share a log time)
        if self._messages is None or log_time_ns <= self._last:
            self._messages = self.reader.messages(connections=self.connections, start=log_time_ns)
        with _ReadingErrors(where):
            for connection, time_ns, raw in self._messages:
                self._last = time_ns
                if time_ns > log_time_ns:
                    break
                if time_ns == log_time_ns and header_stamp_ns(raw, ros2) == stamp_ns:
                    return self.reader.deserialize(raw, connection.msgtype)
        self._messages = None
        raise DataError(f"{where}: the message is no longer where the index found it (was the log changed while reading?)")


def _transform_parts(transform) -> tuple[np.ndarray, np.ndarray]:
    t, q = transform.translation, transform.rotation
    return np.array([t.x, t.y, t.z], np.float64), np.array([q.x, q.y, q.z, q.w], np.float64)


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def cloud_points(msg, label_field: str | None, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A decoded PointCloud2 as [N, 4] float32 x y z intensity (points without a return, NaN, dropped) and
    the raw label ids of field ``label_field`` (None: no labels); raises DataError naming ``where``."""
    try:
        cloud = decode_cloud(msg)
        xyz = cloud_xyz(cloud, where)
    except MessageError as exc:
        raise DataError(f"{where}: {exc}") from None
    # organised clouds and is_dense: false mark missing returns with NaN: they are no points
    finite = np.isfinite(xyz).all(axis=1)
    scan = np.zeros((int(finite.sum()), 4), np.float32)
    scan[:, :3] = xyz[finite]
    if "intensity" in cloud.dtype.names:
        scan[:, 3] = cloud["intensity"][finite]
    if label_field is None:
        return scan, None
    if label_field not in cloud.dtype.names:
        raise DataError(f"{where}: the cloud has no {label_field!r} field (dataset.bag.label_field); its fields: {list(cloud.dtype.names)}")
    return scan, cloud[label_field][finite].astype(np.int64)


class LogSequence:
    """A robot log read as a sequence (see the module text). ``missing_topics`` lists configured
    camera topics the log lacks (for ``check-data``); using a missing or broken part raises a
    DataError naming it."""

    def __init__(self, logs, config: BagConfig = BagConfig()):
        self.logs = [Path(p) for p in logs]
        self.root = self.logs[0]
        self.config = config
        self._reader = open_reader(self.logs)
        self.ros2 = bool(self._reader.is2)
        self.missing_topics: dict[str, str] = {}  # dataset.bag key -> what is missing
        self.topics = {c.topic: c.msgtype for c in self.reader.connections}
        self.cloud_topic = self._cloud_topic()
        self.frames: list[LogFrame] = []
        self.tree = TransformTree()
        self._camera_info = None
        self._cloud_fields: tuple[str, ...] = ()
        self._odometry_frames: set[str] = set()  # the header frames of the odometry: frames of this run
        self.run_id = ""  # the run's id, from its first cloud (frames.run_id)
        self._index()
        self._poses: dict[int, np.ndarray] = {}
        self._cursors = {}
        self._decoded: tuple[int, np.ndarray, np.ndarray | None] | None = None

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def reader(self):
        """The open log reader, opened on first use (after unpickling in a batch worker only the index came
        along)."""
        if self._reader is None:  # unpickled in a batch worker: the index came along, the file is opened here
            self._reader = open_reader(self.logs)
        return self._reader

    def __getstate__(self):
        return self.__dict__ | {"_reader": None, "_cursors": {}, "_decoded": None}

    def close(self) -> None:
        """Close the log files (reopened on the next read)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def describe(self) -> str:
        """The logs' paths, for messages."""
        return ", ".join(str(p) for p in self.logs)

    # Index -----------------------------------------------------------------------------------------
    def _connections(self, topic: str, types: tuple[str, ...], key: str, required: bool = True):
        """The log's connections of a configured topic. A missing camera topic is noted, not fatal:
        mapping from point labels needs no camera, and reading an image then names the topic."""
        if not topic:
            return []
        found = [c for c in self.reader.connections if c.topic == topic]
        if not found:
            text = f"{self.describe()}: topic {topic!r} (dataset.bag.{key}) is not in the log; its topics: {sorted(self.topics)}"
            if required:
                raise DataError(text)
            self.missing_topics[key] = text
            return []
        wrong = [c.msgtype for c in found if c.msgtype not in types]
        if wrong:
            raise DataError(f"{self.describe()}: topic {topic!r} (dataset.bag.{key}) carries {wrong[0]}, expected {' or '.join(types)}")
        return found

    def _cloud_topic(self) -> str:
        if self.config.cloud_topic:
            return self.config.cloud_topic
        clouds = sorted(t for t, kind in self.topics.items() if kind == CLOUD_TYPE)
        if len(clouds) != 1:
            raise DataError(f"{self.describe()}: set dataset.bag.cloud_topic: the log has {len(clouds)} PointCloud2 topics {clouds} "
                            f"(the rellis3d-bag preset names RELLIS-3D's)")
        return clouds[0]

    def _index(self) -> None:
        c = self.config
        cloud = self._connections(self.cloud_topic, (CLOUD_TYPE,), "cloud_topic")
        image = self._connections(c.image_topic, IMAGE_TYPES, "image_topic", required=False)
        label_image = self._connections(c.label_image_topic, IMAGE_TYPES, "label_image_topic", required=False)
        info = self._connections(c.camera_info_topic, (CAMERA_INFO_TYPE,), "camera_info_topic", required=False)
        odometry = self._connections(c.odometry_topic, (ODOMETRY_TYPE,), "odometry_topic") if c.pose_source == "odometry" else []
        tf = [x for x in self.reader.connections if x.topic == c.tf_topic and x.msgtype == TF_TYPE] if c.pose_source == "tf" else []
        tf_static = [x for x in self.reader.connections if x.topic == c.tf_static_topic and x.msgtype == TF_TYPE]
        for key in ("tf_topic", "tf_static_topic"):  # a missing TF topic may be fine (the pose check decides); one of another type is not
            wrong = sorted({x.msgtype for x in self.reader.connections if x.topic == getattr(c, key) and x.msgtype != TF_TYPE})
            if wrong and (key != "tf_topic" or c.pose_source == "tf"):
                raise DataError(f"{self.describe()}: topic {getattr(c, key)!r} (dataset.bag.{key}) carries {wrong[0]}, expected {TF_TYPE}")
        # topics, not connections: a connection refers to its open reader, and the sequence pickles without one
        self._topics = {"cloud": self.cloud_topic, "image": c.image_topic if image else "", "label_image": c.label_image_topic if label_image else ""}
        kinds = {x.id: kind for kind, conns in (("cloud", cloud), ("image", image), ("label_image", label_image), ("info", info),
                                                 ("odometry", odometry), ("tf", tf), ("tf_static", tf_static)) for x in conns}
        wanted = [x for conns in (cloud, image, label_image, info, odometry, tf, tf_static) for x in conns]
        stamps = {"cloud": [], "image": [], "label_image": []}
        with _ReadingErrors(self.describe()):
            first_cloud = self._read_index(wanted, kinds, stamps)
        if first_cloud is None:
            raise DataError(f"{self.describe()}: no message on {self.cloud_topic!r}")
        cloud_stamps = np.array([s for _, s in stamps["cloud"]], np.int64)
        unique, counts = np.unique(cloud_stamps, return_counts=True)
        if (counts > 1).any():  # one sweep twice (a log given twice, a copy of it, a message recorded twice) would count twice
            raise DataError(f"{self.describe()}: {int((counts - 1).sum())} clouds on {self.cloud_topic!r} repeat a stamp of another (first at "
                            f"{format_stamp(int(unique[counts > 1][0]))}): a log given twice, or logs that overlap? Name each drive once")
        self.lidar_frame = c.lidar_frame or first_cloud.header.frame_id
        self._cloud_fields = tuple(f.name for f in first_cloud.fields)
        has_labels = bool(c.label_field) and c.label_field in self._cloud_fields
        self._add_extrinsics()
        images = sorted(stamps["image"], key=lambda s: s[1])
        labels = {s[1]: s for s in stamps["label_image"]}
        image_stamps = np.array([s[1] for s in images], np.int64)
        tolerance = int(round(c.image_tolerance_s * 1e9))
        for index, (time_ns, stamp) in enumerate(stamps["cloud"]):
            where = f"{self.describe()} {self.cloud_topic} message {index} ({format_stamp(stamp)})"
            frame = LogFrame(index, stamp, time_ns, where, point_labels=f"{where} field {c.label_field!r}" if has_labels else None)
            if len(image_stamps):
                at = int(np.searchsorted(image_stamps, stamp))
                nearest = min((i for i in (at - 1, at) if 0 <= i < len(images)), key=lambda i: abs(int(image_stamps[i]) - stamp))
                if abs(int(image_stamps[nearest]) - stamp) <= tolerance:
                    frame.image = images[nearest]
                    frame.label_image = labels.get(frame.image[1])
            self.frames.append(frame)

    def _read_index(self, wanted, kinds: dict, stamps: dict):
        """One pass over the log: stamps of clouds and images (from the raw bytes), transforms,
        odometry and the camera info; returns the first cloud, decoded (its frame and fields)."""
        first_cloud = None
        for connection, time_ns, raw in self.reader.messages(connections=wanted):
            kind = kinds[connection.id]
            if kind in stamps:
                stamps[kind].append((time_ns, header_stamp_ns(raw, self.ros2)))
                if kind == "cloud" and first_cloud is None:
                    first_cloud = self.reader.deserialize(raw, connection.msgtype)
                    self.run_id = run_id(str(stamps[kind][0][1]), raw)  # the drive's first sweep identifies its run
                continue
            msg = self.reader.deserialize(raw, connection.msgtype)
            try:
                if kind == "info":
                    if self._camera_info is None:
                        self._camera_info = camera_from_info(msg, f"{self.describe()} {connection.topic}")
                elif kind == "odometry":
                    self._odometry_frames.add(msg.header.frame_id)
                    pose = msg.pose.pose
                    self.tree.add_timed(msg.header.frame_id, msg.child_frame_id, _stamp(msg.header),
                                        [pose.position.x, pose.position.y, pose.position.z],
                                        [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
                else:
                    for t in msg.transforms:
                        translation, rotation = _transform_parts(t.transform)
                        if kind == "tf_static":
                            self.tree.add_static(t.header.frame_id, t.child_frame_id, translation, rotation)
                        else:
                            self.tree.add_timed(t.header.frame_id, t.child_frame_id, _stamp(t.header), translation, rotation)
            except (TransformError, MessageError) as exc:
                raise DataError(f"{self.describe()} {connection.topic} at {format_stamp(time_ns)}: {exc}") from None
        return first_cloud

    def _add_extrinsics(self) -> None:
        c = self.config
        try:
            if c.lidar_extrinsic:
                self._refuse_second_mount("lidar_extrinsic", self.lidar_frame)
                base = self._odometry_child()
                self.tree.add_static(base, self.lidar_frame, c.lidar_extrinsic[:3], c.lidar_extrinsic[3:])
            if c.camera_extrinsic:
                self._refuse_second_mount("camera_extrinsic", self.camera_frame)
                self.tree.add_static(self.lidar_frame, self.camera_frame, c.camera_extrinsic[:3], c.camera_extrinsic[3:])
        except TransformError as exc:
            raise DataError(f"dataset.bag extrinsics: {exc}") from None

    def _refuse_second_mount(self, key: str, frame: str) -> None:
        """An extrinsic stands in for a mount the log lacks; one the log holds would be replaced or
        contradicted, silently either way."""
        parent = self.tree.parent(frame)
        if parent is not None:
            raise DataError(f"{self.describe()}: dataset.bag.{key} conflicts with the log's own transform {parent!r} -> {frame!r} "
                            f"(on {self.config.tf_static_topic!r} or {self.config.tf_topic!r}); the extrinsic is for a log without "
                            f"one: drop dataset.bag.{key} to use the log's")

    def _odometry_child(self) -> str:
        children = [f for f in self.tree.frames if self.tree.is_timed(f)]
        if len(children) != 1:
            raise DataError(f"{self.describe()}: dataset.bag.lidar_extrinsic needs one odometry child frame, found {sorted(children)}")
        return children[0]

    # Calibration and poses ---------------------------------------------------------------------
    @property
    def camera_frame(self) -> str:
        """The camera's TF frame: ``dataset.bag.camera_frame``, else the camera info's header frame; raises
        DataError when neither names one."""
        if self.config.camera_frame:
            return self.config.camera_frame
        if self._camera_info is not None and self._camera_info.frame_id:
            return self._camera_info.frame_id
        raise DataError(f"{self.describe()}: set dataset.bag.camera_frame (no camera info names the camera's frame)")

    @property
    def camera(self) -> PinholeCamera:
        """The camera's intrinsics from the log's camera info; raises DataError when the log has none."""
        if self._camera_info is None and "camera_info_topic" in self.missing_topics:
            raise DataError(self.missing_topics["camera_info_topic"])
        if self._camera_info is None:
            what = repr(self.config.camera_info_topic) if self.config.camera_info_topic else "(dataset.bag.camera_info_topic is not set)"
            raise DataError(f"{self.describe()}: no camera info message on {what}; projection needs the camera's intrinsics")
        return self._camera_info.camera

    @property
    def fixed_frame(self) -> str:
        """The log's world frame: dataset.bag.fixed_frame, else the root of the LiDAR's TF tree."""
        if self.config.fixed_frame:
            if self.config.fixed_frame not in self.tree.frames:
                known = ", ".join(sorted(self.tree.frames)) or "none"
                raise DataError(f"{self.describe()}: dataset.bag.fixed_frame {self.config.fixed_frame!r} is not a frame of the log's "
                                f"TF tree (frames: {known})")
            return self.config.fixed_frame
        try:
            root = self.tree.root(self.lidar_frame)
        except TransformError as exc:
            raise DataError(f"{self.describe()}: {exc}") from None
        if root == self.lidar_frame:  # no parent: every pose would be the identity, a map of a robot standing still
            known = ", ".join(sorted(self.tree.frames)) or "none"
            raise DataError(f"{self.describe()}: the LiDAR frame {self.lidar_frame!r} is in no TF tree (frames known: {known}); check "
                            f"dataset.bag.lidar_frame, give dataset.bag.lidar_extrinsic, or set fixed_frame to it for a sensor that never moves")
        return root

    def is_run_frame(self, frame: str) -> bool:
        """Whether ``frame`` is one run's, not world-fixed: ``odom`` by name (REP 105), the header frame
        of the log's odometry, or a frame that moves in the log's TF tree (drifts against its root)."""
        if is_run_frame_name(frame) or frame in self._odometry_frames:
            return True
        try:
            return any(self.tree.is_timed(f) for f in self.tree.path_to_root(frame)[:-1])
        except TransformError:
            return False

    def check_pose_chain(self) -> None:
        """Refuse, before any mapping, a drive that is not posed in the fixed frame throughout: the
        LiDAR frame not connected to it, or a moving transform of the chain recorded for part of the
        drive only (the TF root changing mid-drive, e.g. a localiser's map -> odom starting late)."""
        fixed = self.fixed_frame
        if not self.frames:
            return
        try:
            up_lidar, up_fixed = self.tree.chain(fixed, self.lidar_frame)
        except TransformError as exc:
            raise DataError(f"{self.describe()}: no pose of the LiDAR in the fixed frame: {exc}") from None
        first, last = self.frames[0].stamp_ns, self.frames[-1].stamp_ns
        if not any(self.tree.is_timed(f) for f in up_lidar[:-1] + up_fixed[:-1]):
            if not self.config.fixed_frame:
                self._refuse_standing_still(fixed, up_lidar, first)
            self._refuse_moving_fixed_frame(fixed, up_lidar)
        for child in up_lidar[:-1] + up_fixed[:-1]:
            if not self.tree.is_timed(child):
                continue
            start, end = self.tree.time_range(child)
            if start <= first and end >= last:
                continue
            unposed = sum(not start <= f.stamp_ns <= end for f in self.frames)
            below = up_lidar[:up_lidar.index(child)] if child in up_lidar else []
            moving_below = any(self.tree.is_timed(f) and self.tree.time_range(f)[0] <= first and self.tree.time_range(f)[1] >= last
                               for f in below)
            # a frame below the gap that still moves with the robot over the whole drive is a fixed frame for all of it
            hint = (f"; set dataset.bag.fixed_frame: {child} to map the whole drive there, or cut the log to the part that is posed"
                    if moving_below else "; cut the log to the part that is posed")
            raise DataError(f"{self.describe()}: the LiDAR's chain to the fixed frame {fixed!r} changes mid-drive: the transform "
                            f"{self.tree.parent(child)!r} -> {child!r} is recorded from {format_stamp(start)} to {format_stamp(end)}, "
                            f"but the clouds run from {format_stamp(first)} to {format_stamp(last)} ({unposed} of {len(self.frames)} "
                            f"clouds have no pose in {fixed!r}){hint}")

    def _refuse_moving_fixed_frame(self, fixed: str, up_lidar: list[str]) -> None:
        """A fixed frame the user named, static to the LiDAR but moving in the log (a frame of the
        robot, e.g. base_link): every scan would get the same pose, as in ``_refuse_standing_still``."""
        moving = next((f for f in self.tree.path_to_root(fixed)[:-1] if self.tree.is_timed(f)), None)
        if moving is None:  # a sensor that never moves: its frame is world-fixed
            return
        chain = " -> ".join(reversed(up_lidar))
        raise DataError(f"{self.describe()}: dataset.bag.fixed_frame (--frame) {fixed!r} moves with the robot (the transform "
                        f"{self.tree.parent(moving)!r} -> {moving!r} moves) and the LiDAR is fixed to it ({chain}), so every scan would "
                        f"get the same pose (a moving robot mapped as standing still); name a frame the robot moves in, e.g. "
                        f"{self.tree.root(fixed)!r}, or none for the log's TF root")

    def _refuse_standing_still(self, root: str, up_lidar: list[str], first_ns: int) -> None:
        """The LiDAR's tree (its root picked as the fixed frame) holds no moving transform: every scan
        would get the same pose, a moving robot mapped as one standing still. Names the missing link:
        the root's parent among the moving frames of another tree, or the pose source that gave none."""
        chain = " -> ".join(reversed(up_lidar))
        moving = sorted({f for f in self.tree.frames if self.tree.is_timed(f)} | {self.tree.parent(f) for f in self.tree.frames if self.tree.is_timed(f)})
        if moving:
            link = (f"the link from one of the moving frames {moving} to {root!r} is missing at {format_stamp(first_ns)} (the first cloud) "
                    f"and at every later cloud; it belongs on {self.config.tf_static_topic!r} (dataset.bag.tf_static_topic)")
        else:
            source = (f"odometry topic {self.config.odometry_topic!r}" if self.config.pose_source == "odometry"
                      else f"{self.config.tf_topic!r} (dataset.bag.tf_topic)")
            link = f"the log has no moving transform at all on {source} at {format_stamp(first_ns)} (the first cloud) or later"
        raise DataError(f"{self.describe()}: no moving transform poses the LiDAR: its TF chain {chain} is static, so every scan would get "
                        f"the same pose (a moving robot mapped as standing still); {link}; give dataset.bag.lidar_extrinsic, or set "
                        f"dataset.bag.fixed_frame: {root} for a sensor that never moves")

    @property
    def lidar_to_camera(self) -> np.ndarray:
        """4x4 transform of LiDAR coordinates into camera coordinates."""
        try:
            if not self.tree.is_static_between(self.camera_frame, self.lidar_frame):
                raise DataError(f"{self.describe()}: the camera ({self.camera_frame!r}) and LiDAR ({self.lidar_frame!r}) frames are joined by a moving "
                                f"transform; give dataset.bag.camera_extrinsic")
            return self.tree.lookup(self.camera_frame, self.lidar_frame, self.frames[0].stamp_ns if self.frames else 0)
        except TransformError as exc:
            raise DataError(f"{self.describe()}: LiDAR to camera: {exc} (give dataset.bag.camera_extrinsic if the log has no such transform)") from None

    def pose(self, frame: LogFrame) -> np.ndarray:
        """4x4 pose of the LiDAR in the fixed frame at the cloud's stamp."""
        if frame.index not in self._poses:
            try:
                self._poses[frame.index] = self.tree.lookup(self.fixed_frame, self.lidar_frame, frame.stamp_ns)
            except TransformError as exc:
                raise DataError(f"{frame.scan}: no pose: {exc}") from None
        return self._poses[frame.index]

    # Per-frame data ------------------------------------------------------------------------------
    def _message(self, kind: str, log_time_ns: int, stamp_ns: int, where: str):
        if kind not in self._cursors:
            connections = [x for x in self.reader.connections if x.topic == self._topics[kind]]
            self._cursors[kind] = _Cursor(self.reader, connections)
        return self._cursors[kind].get(log_time_ns, stamp_ns, self.ros2, where)

    def _decode(self, frame: LogFrame) -> tuple[np.ndarray, np.ndarray | None]:
        if self._decoded is None or self._decoded[0] != frame.index:
            msg = self._message("cloud", frame.log_time_ns, frame.stamp_ns, frame.scan)
            label_field = self.config.label_field if frame.point_labels is not None else None
            self._decoded = (frame.index, *cloud_points(msg, label_field, frame.scan))
        return self._decoded[1], self._decoded[2]

    def read_scan(self, frame: LogFrame) -> np.ndarray:
        """[N, 4] float32 x y z intensity in the LiDAR frame; points without a return (NaN) dropped."""
        return self._decode(frame)[0]

    def read_point_labels(self, frame: LogFrame) -> np.ndarray:
        """Raw label ids of the points ``read_scan`` gives."""
        if frame.point_labels is None:
            raise DataError(f"{frame.scan}: the cloud has no {self.config.label_field!r} field (dataset.bag.label_field); its fields: "
                            f"{list(self._cloud_fields)}. Map it from camera images with a segmentation checkpoint instead")
        return self._decode(frame)[1]

    def _picture(self, kind: str, message: tuple[int, int], topic: str) -> tuple[np.ndarray, str]:
        """A camera or label image message decoded, checked against the camera info's size."""
        where = f"{self.describe()} {topic} ({format_stamp(message[1])})"
        try:
            pixels = decode_image(self._message(kind, *message, where), where)
        except MessageError as exc:
            raise DataError(str(exc)) from None
        if pixels.shape[:2] != (self.camera.height, self.camera.width):
            raise DataError(f"{where}: {pixels.shape[1]}x{pixels.shape[0]} pixels, but the camera info says {self.camera.width}x{self.camera.height}")
        return pixels, where

    def read_image(self, frame: LogFrame) -> np.ndarray:
        """Frame ``frame``'s camera image, [H, W, 3] uint8 RGB; raises DataError when the image topic is
        missing or no image lies within ``image_tolerance_s`` of the cloud."""
        if "image_topic" in self.missing_topics:
            raise DataError(self.missing_topics["image_topic"])
        if frame.image is None:
            raise DataError(f"{frame.scan}: no camera image within {self.config.image_tolerance_s} s")
        image, _ = self._picture("image", frame.image, self.config.image_topic)
        return np.repeat(image[..., None], 3, axis=2).astype(np.uint8) if image.ndim == 2 else image

    def read_label_ids(self, frame: LogFrame) -> np.ndarray:
        """[H, W] raw ontology ids of the frame's 2D labels (one-channel ids, or RELLIS-3D colors)."""
        if frame.label_image is None:
            raise DataError(self.missing_topics.get("label_image_topic", f"{frame.scan}: no label image paired with its camera image"))
        raw, where = self._picture("label_image", frame.label_image, self.config.label_image_topic)
        if raw.ndim == 3:
            from ..classes import decode_color_labels, palette

            return decode_color_labels(raw, palette("rellis3d_colors"), where)
        return raw.astype(np.int64)


def check_log(logs, config: BagConfig = BagConfig()) -> CheckReport:
    """What ``check-data`` says about a log: topics, types, counts, rates and time range; configured
    topics that are missing; clouds without an image or a pose; TF frames that never connect."""
    logs = [Path(p) for p in logs]
    report = CheckReport(logs[0], unit="clouds")
    try:
        reader = open_reader(logs)
    except DataError as exc:
        report.problems.append(str(exc))
        return report
    try:
        start, end = reader.start_time, reader.end_time
        span = max(end - start, 1) / 1e9
        report.details.append(f"time range {format_stamp(start)} .. {format_stamp(end)} ({span:.1f} s)")
        counts = {}
        for c in reader.connections:
            counts[(c.topic, c.msgtype)] = counts.get((c.topic, c.msgtype), 0) + c.msgcount
        width = max((len(t) for t, _ in counts), default=5)
        for (topic, msgtype), n in sorted(counts.items()):
            report.details.append(f"{topic:<{width}}  {msgtype:<32} {n:>7} msgs  {n / span:7.2f}/s")
    finally:
        reader.close()
    try:
        seq = LogSequence(logs, config)
    except DataError as exc:
        report.problems.append(str(exc))
        return report
    try:
        _check_sequence(seq, report)
    finally:
        seq.close()
    return report


def _check_sequence(seq: LogSequence, report: CheckReport) -> None:
    c = seq.config
    report.frames = len(seq)
    report.with_images = sum(f.image is not None for f in seq.frames)
    report.with_labels = sum(f.label_image is not None for f in seq.frames)
    report.problems += list(seq.missing_topics.values())
    for name in ("image_topic", "camera_info_topic", "label_image_topic", "odometry_topic"):
        if not getattr(c, name) and (name != "odometry_topic"):
            report.notes.append(f"dataset.bag.{name} is not set: {'no camera projection' if name != 'label_image_topic' else 'no 2D ground truth'}")
    if not seq.frames[0].point_labels:
        report.notes.append(f"the clouds have no {c.label_field!r} field: mapping needs camera images and a segmentation checkpoint")
    if c.image_topic:
        missing = [f for f in seq.frames if f.image is None]
        if missing:
            report.problems.append(f"{len(missing)} of {len(seq)} clouds have no image within {c.image_tolerance_s} s (first {missing[0].scan})")
        for what in ("camera", "lidar_to_camera"):
            try:
                getattr(seq, what)
            except DataError as exc:
                report.problems.append(str(exc))
    lidar_root = seq.tree.root(seq.lidar_frame)
    apart = sorted(f for f in seq.tree.frames if seq.tree.root(f) != lidar_root)
    if apart:
        report.problems.append(f"TF frames that never connect to the LiDAR's tree (rooted at {lidar_root!r}): {apart}")
    try:
        fixed = seq.fixed_frame
        report.details.append(f"poses: {c.pose_source}, LiDAR frame {seq.lidar_frame!r} in fixed frame {fixed!r}")
        report.details.append(f"world frame: maps are made in {fixed!r}, the log's fixed frame")
        seq.check_pose_chain()
    except DataError as exc:
        report.problems.append(str(exc))
        return
    unposed = []
    for frame in seq.frames:
        try:
            seq.pose(frame)
        except DataError as exc:
            unposed.append(str(exc))
    if unposed:
        report.problems.append(f"{len(unposed)} of {len(seq)} clouds have no pose; first: {unposed[0]}")
