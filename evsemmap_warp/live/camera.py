"""``evsemmap live --checkpoint``: scans labelled from the camera, as ``evsemmap map LOG --checkpoint`` labels a
log's (``apps.scan_sources.CheckpointScans``): each scan paired with the camera image nearest in time (within
``dataset.bag.image_tolerance_s``), the image through the segmentation network, the scan projected into it
(``geometry.projection``) and the frames integrated in bins of ``bin_frames``.

The feed keeps the last images (``IMAGE_BUFFER``) and the first camera info; a scan waits for the image
stamped after it (the nearest one may be the next), up to the pose's wait, then takes the nearest so far, or
none (the scan is dropped, counted: ``no_image``)."""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError, PayloadType
from ..data.datasets import Scan
from ..data.ros_messages import MessageError, camera_from_info, decode_image, header_stamp_ns
from ..data.sequences import DataError
from ..geometry.projection import ProjectionConfig, bin_frames, project_frames
from ..geometry.transform_tree import TransformError, format_stamp

IMAGE_BUFFER = 64  # images kept: several seconds of a camera at 10-30 Hz, so a scan's image is still there


class ImageBuffer:
    """The last images of the camera topic (stamp, type, CDR) and its first camera info, filled by the feed."""

    def __init__(self):
        self.images: collections.deque = collections.deque(maxlen=IMAGE_BUFFER)
        self.camera_info = None
        self.lock = threading.Lock()

    def add_image(self, msgtype: str, cdr: bytes) -> None:
        """Keep an image (its stamp read from the raw bytes)."""
        with self.lock:
            self.images.append((header_stamp_ns(cdr, True), msgtype, cdr))

    def nearest(self, stamp: int, tolerance_ns: int) -> tuple[bool, tuple | None]:
        """(whether an image stamped after ``stamp`` has arrived, the image nearest ``stamp`` within the tolerance or None)."""
        with self.lock:
            images = list(self.images)
        later = any(s > stamp for s, _, _ in images)
        near = [i for i in images if abs(i[0] - stamp) <= tolerance_ns]
        # the earlier of two equally near images, as the log's pairing (searchsorted, then min) picks it
        return later, min(near, key=lambda i: (abs(i[0] - stamp), i[0])) if near else None


@dataclass
class _Frame:
    index: int


class _OneScan:
    """What ``project_frames`` asks of a sequence, for one scan at a time."""

    def __init__(self, camera, lidar_to_camera, pose, scan):
        self.camera, self.lidar_to_camera, self._pose, self._scan = camera, lidar_to_camera, pose, scan

    def pose(self, frame):
        return self._pose

    def read_scan(self, frame):
        return self._scan


class CameraLabeller:
    """Labels scans from the camera with the segmentation ``checkpoint`` (see the module text)."""

    def __init__(self, checkpoint, bag, store, *, bin_frames_: int):
        from ..segmentation.train import load_checkpoint

        try:
            self.model, self.train_config, self.meta, _ = load_checkpoint(checkpoint)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--checkpoint {checkpoint}: {exc}") from None
        if not bag.image_topic or not bag.camera_info_topic:
            raise ConfigError("--checkpoint labels scans from the camera: set dataset.bag.image_topic and camera_info_topic")
        self.bag, self.store, self.bin_frames = bag, store, bin_frames_
        self.class_names = tuple(self.meta["classes"])
        self.num_classes = self.train_config.model.num_classes
        self.payload_type = PayloadType.ALPHA if self.train_config.head == "evidential" else PayloadType.PROB
        self.images = ImageBuffer()
        self.frames = 0
        self._pending: list = []  # projected frames of the bin being filled

    def image_for(self, stamp: int, deadline: float):
        """The decoded image paired with a scan at ``stamp`` ([H, W, 3] uint8) and its stamp, waiting until
        ``deadline`` (monotonic s) for the image after it; None when there is none within the tolerance."""
        tolerance = int(round(self.bag.image_tolerance_s * 1e9))
        while True:  # the camera info comes with the first images: wait for it too
            later, image = self.images.nearest(stamp, tolerance)
            if (later and self.images.camera_info is not None) or time.monotonic() >= deadline:
                break
            time.sleep(0.002)
        if image is None:
            return None
        image_stamp, msgtype, cdr = image
        where = f"{self.bag.image_topic} ({format_stamp(image_stamp)})"
        try:
            pixels = decode_image(self.store.deserialize_cdr(cdr, msgtype), where)
        except MessageError as exc:
            raise DataError(str(exc)) from None
        return (np.repeat(pixels[..., None], 3, axis=2).astype(np.uint8) if pixels.ndim == 2 else pixels), image_stamp

    def camera(self, tree, lidar_frame: str, stamp: int):
        """The camera's intrinsics and the LiDAR-to-camera transform, from the camera info and the TF tree."""
        info = self.images.camera_info
        if info is None:
            raise DataError(f"no camera info on {self.bag.camera_info_topic!r} yet; projection needs the camera's intrinsics")
        camera_frame = self.bag.camera_frame or info.frame_id
        try:
            if not tree.is_static_between(camera_frame, lidar_frame):
                raise DataError(f"the camera ({camera_frame!r}) and LiDAR ({lidar_frame!r}) frames are joined by a moving transform")
            return info.camera, tree.lookup(camera_frame, lidar_frame, stamp)
        except TransformError as exc:
            raise DataError(f"LiDAR to camera: {exc}") from None

    def add_camera_info(self, msg, where: str) -> None:
        """Keep the first camera info (decoded: intrinsics, distortion, frame)."""
        if self.images.camera_info is None:
            try:
                self.images.camera_info = camera_from_info(msg, where)
            except MessageError as exc:
                raise DataError(str(exc)) from None

    def add_frame(self, name: str, scan: np.ndarray, pose: np.ndarray, image: np.ndarray, camera, lidar_to_camera) -> Scan | None:
        """One scan with its image: inference, projection into the world; returns the bin's insertion when it is full."""
        from ..segmentation.train import infer_alpha

        values = next(infer_alpha(self.model, self.train_config, self.meta, [image], batch_size=1))[0].astype(np.float32)
        frame = _Frame(self.frames)
        self.frames += 1
        self._pending += list(project_frames(_OneScan(camera, lidar_to_camera, pose, scan), [frame], lambda f: values, ProjectionConfig()))
        if len(self._pending) < self.bin_frames:
            return None
        return self.flush(name)

    def flush(self, name: str = "the last frames") -> Scan | None:
        """The bin of the frames so far as one insertion (None when there are none)."""
        if not self._pending:
            return None
        (b,) = bin_frames(iter(self._pending), len(self._pending))
        self._pending = []
        return Scan(f"{name}: frames {b.frames[0]}..{b.frames[-1]}", b.points, b.values, self.payload_type, b.sensor_origin)
