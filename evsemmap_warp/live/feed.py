"""What a robot sends, received: the subscriptions of ``evsemmap live`` on the topics a dataset config
names (``dataset.bag``: the cloud, ``/tf`` and ``/tf_static`` or the odometry), in either key format.

The subscriber callbacks run on Zenoh's threads and never block: a cloud goes into the ``ScanQueue``
undecoded, a transform or odometry message into the TF tree (under a lock); a message of another type,
or one that does not decode, is counted and said once per topic, never mapped."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import BagConfig
from ..data.logs import CAMERA_INFO_TYPE, CLOUD_TYPE, IMAGE_TYPES, ODOMETRY_TYPE, TF_TYPE
from ..data.sequences import DataError
from ..geometry.transform_tree import TransformError, TransformTree
from .ros2_wire import LATCHED_DEPTH, WireError, decode_attachment, is_latched, parse_key, topic_key
from .scan_queue import ReceivedScan, ScanQueue


def say(text: str) -> None:
    """One line on stderr, prefixed as every line of ``evsemmap live``."""
    print(f"evsemmap live: {text}", file=sys.stderr, flush=True)


@dataclass
class TopicState:
    """One subscribed topic: its role, expected type, the messages that arrived, those refused and why."""

    role: str
    topic: str
    msgtype: str
    received: int = 0
    refused: int = 0
    first_ns: int | None = None
    key_format: str = ""
    problems: list[str] = field(default_factory=list)


class RobotFeed:
    """Subscriptions for ``config``'s topics on ``session``. ``key_format``: rmw_zenoh, bridge or auto (both
    subscribed; the first sample says which the robot uses). ``max_cloud_bytes``: a larger cloud is dropped,
    counted, before it is queued."""

    def __init__(self, session, config: BagConfig, queue: ScanQueue, store, *, key_format: str = "auto", domain_id: int = 0,
                 max_cloud_bytes: int = 256 << 20, labeller=None):
        if not config.cloud_topic:
            from ..config import ConfigError

            raise ConfigError("dataset.bag.cloud_topic: live mapping subscribes to one named PointCloud2 topic; set it (the "
                              "rellis3d-bag preset names RELLIS-3D's)")
        self.session, self.config, self.queue, self.store = session, config, queue, store
        self.domain_id, self.max_cloud_bytes = domain_id, max_cloud_bytes
        self.detected_format = None if key_format == "auto" else key_format
        self.tree = TransformTree()
        self.tree_lock = threading.Lock()
        self.odometry_frames: set[str] = set()
        self.too_large = 0
        self.topics: dict[str, TopicState] = {}
        roles = [("cloud", config.cloud_topic, CLOUD_TYPE), ("tf_static", config.tf_static_topic, TF_TYPE)]
        roles.append(("odometry", config.odometry_topic, ODOMETRY_TYPE) if config.pose_source == "odometry" else ("tf", config.tf_topic, TF_TYPE))
        self.labeller = labeller  # camera.CameraLabeller with --checkpoint: the camera's images and info go to it
        if labeller is not None:
            # a bridge's key names no type: an image topic named .../compressed carries CompressedImage, by ROS convention
            image_type = IMAGE_TYPES[1] if config.image_topic.rstrip("/").endswith("compressed") else IMAGE_TYPES[0]
            roles += [("image", config.image_topic, image_type), ("info", config.camera_info_topic, CAMERA_INFO_TYPE)]
        self._subscribers = []
        formats = ("rmw_zenoh", "bridge") if key_format == "auto" else (key_format,)
        for role, topic, msgtype in roles:
            if not topic:
                continue
            self.topics[topic] = TopicState(role, topic, msgtype)
            for fmt in formats:
                key = topic_key(topic, key_format=fmt, domain_id=domain_id)
                self._subscribers.append(self._subscribe(session, key, topic))

    def _subscribe(self, session, key: str, topic: str):
        """A subscriber of ``key`` handing samples to ``on_sample``; for a latched topic (/tf_static) one that also asks
        the publishers that joined before it for what they keep (Zenoh's advanced subscriber with history)."""
        callback = lambda sample: self.on_sample(topic, sample)  # noqa: E731 - one line, named by its use
        from .session import zenoh_module

        zenoh = zenoh_module()
        if is_latched(topic) and isinstance(session, zenoh.Session):
            return zenoh.ext.declare_advanced_subscriber(session, key, callback,
                                                         history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=LATCHED_DEPTH))
        return session.declare_subscriber(key, callback)

    def close(self) -> None:
        """Undeclare the subscriptions."""
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()

    # Receiving ---------------------------------------------------------------------------------
    def _refuse(self, state: TopicState, text: str, kind: str | None = None) -> None:
        state.refused += 1
        if (kind or text) not in state.problems:  # each kind of problem said once per topic, then counted
            state.problems.append(kind or text)
            say(f"{state.topic}: {text}; not mapped (counted in the diagnostics)")

    def on_sample(self, topic: str, sample) -> None:
        """The subscriber callback of ``topic`` (public: tests hand it samples without a network)."""
        state = self.topics[topic]
        try:
            key = parse_key(str(sample.key_expr), self.domain_id)
            if self.detected_format is None:
                self.detected_format = key.key_format
                say(f"the robot speaks {key.key_format} (first sample on {str(sample.key_expr)!r})")
            accepted = IMAGE_TYPES if state.role == "image" else (state.msgtype,)
            if key.msgtype and key.msgtype not in accepted:
                return self._refuse(state, f"a message of type {key.msgtype}, expected {' or '.join(accepted)}")
            attachment = decode_attachment(None if sample.attachment is None else sample.attachment.to_bytes())
            payload = sample.payload.to_bytes()
        except WireError as exc:
            return self._refuse(state, str(exc))
        state.received += 1
        state.key_format = key.key_format
        now = time.time_ns()
        state.first_ns = state.first_ns or now
        if state.role == "cloud":
            if len(payload) > self.max_cloud_bytes:
                self.too_large += 1
                return self._refuse(state, f"a cloud of {len(payload) / 2**20:.1f} MiB, over --max-cloud-mb "
                                           f"{self.max_cloud_bytes / 2**20:.0f}", kind="too_large")
            sequence, sent = (attachment[0], attachment[1]) if attachment else (None, None)
            return self.queue.put(ReceivedScan(payload, now, sent, sequence))
        if state.role == "image":
            if len(payload) < 12:  # not even a header stamp
                return self._refuse(state, f"a message of {len(payload)} bytes, no image", kind="short")
            return self.labeller.images.add_image(key.msgtype or state.msgtype, payload)
        try:
            msg = self.store.deserialize_cdr(payload, state.msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors for bytes that are no such message
            return self._refuse(state, f"a message that is no {state.msgtype} ({type(exc).__name__}: {exc})", kind=type(exc).__name__)
        try:
            if state.role == "info":
                self.labeller.add_camera_info(msg, state.topic)
            else:
                self._add_transforms(state.role, msg)
        except (TransformError, DataError) as exc:
            self._refuse(state, str(exc))

    def _add_transforms(self, role: str, msg) -> None:
        with self.tree_lock:
            if role == "odometry":
                self.odometry_frames.add(msg.header.frame_id)
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                self.tree.add_timed(msg.header.frame_id, msg.child_frame_id, stamp_of(msg.header), [p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
                return
            for t in msg.transforms:
                v, q = t.transform.translation, t.transform.rotation
                translation, rotation = np.array([v.x, v.y, v.z]), np.array([q.x, q.y, q.z, q.w])
                if role == "tf_static":
                    self.tree.add_static(t.header.frame_id, t.child_frame_id, translation, rotation)
                else:
                    self.tree.add_timed(t.header.frame_id, t.child_frame_id, stamp_of(t.header), translation, rotation)

    def trim(self, *, before_ns: int | None = None, after_ns: int | None = None) -> None:
        """``TransformTree.trim`` under the lock: forget moving transforms no scan to come needs (before the last
        scan mapped: the tree stays bounded over a drive of any length), or another timeline's (after time jumped back)."""
        with self.tree_lock:
            self.tree.trim(before_ns=before_ns, after_ns=after_ns)

    def silent_topics(self) -> list[str]:
        """Subscribed topics nothing has arrived on yet."""
        return [t for t, s in self.topics.items() if s.received == 0]


def stamp_of(header) -> int:
    """A std_msgs/Header's stamp in ns."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
