"""The ``dataset`` section: where scans come from (``DatasetConfig``) and how a robot log is read
(``BagConfig``, its ``dataset.bag`` section)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from .enums import PayloadType
from .errors import ConfigError


@dataclass(frozen=True)
class BagConfig:
    """How to read a robot log (``dataset.kind: bag``): topics, frames and the pose source. Empty
    topics are not read; an empty frame is taken from the messages' headers. The built-in preset
    ``rellis3d-bag`` holds RELLIS-3D's topic names."""

    cloud_topic: str = ""  # sensor_msgs/PointCloud2; "": the log's only PointCloud2 topic
    label_field: str = "label"  # per-point labels in this cloud field (as S-BKI's /labeled_pointcloud)
    label_ontology: str = "rellis3d"  # rellis3d (ids remapped to the 9 v3 classes), semantickitti, or none (class ids)
    image_topic: str = ""  # sensor_msgs/Image or CompressedImage
    camera_info_topic: str = ""  # sensor_msgs/CameraInfo of image_topic
    label_image_topic: str = ""  # 2D label ids (mono8/mono16 Image, or a PNG CompressedImage), for ground truth
    image_tolerance_s: float = 0.05  # a cloud pairs with the nearest image at most this far apart in time
    pose_source: str = "tf"  # tf: the TF tree from fixed_frame to the LiDAR; odometry: odometry_topic + extrinsic
    fixed_frame: str = ""  # "": the root of the LiDAR's TF tree (tf) or the odometry's header frame (odometry)
    lidar_frame: str = ""  # "": the clouds' header frame
    camera_frame: str = ""  # "": the images' header frame
    odometry_topic: str = ""  # nav_msgs/Odometry, when pose_source is odometry
    tf_topic: str = "/tf"  # tf2_msgs/TFMessage with the moving transforms
    tf_static_topic: str = "/tf_static"  # tf2_msgs/TFMessage with the fixed transforms
    # x y z qx qy qz qw; empty: from the TF tree. lidar: the LiDAR's pose in the odometry's child frame;
    # camera: the camera's pose in the LiDAR frame (what RELLIS-3D's transforms.yaml stores).
    lidar_extrinsic: tuple[float, ...] = ()
    camera_extrinsic: tuple[float, ...] = ()  # x y z qx qy qz qw, see lidar_extrinsic

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, text: str) -> None:
            if not ok:
                raise ConfigError(f"dataset.bag.{name} = {getattr(self, name)!r}: {text}")

        need(self.pose_source in ("tf", "odometry"), "pose_source", "must be tf or odometry")
        need(self.pose_source != "odometry" or bool(self.odometry_topic), "odometry_topic", "pose_source odometry needs an odometry topic")
        need(self.label_ontology in ("rellis3d", "semantickitti", "none"), "label_ontology", "must be rellis3d, semantickitti or none")
        need(math.isfinite(self.image_tolerance_s) and self.image_tolerance_s >= 0, "image_tolerance_s", "must be a finite number >= 0")
        for name in ("lidar_extrinsic", "camera_extrinsic"):
            value = getattr(self, name)
            need(len(value) in (0, 7), name, "must be empty or 7 numbers x y z qx qy qz qw")
            need(all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value), name, "must be finite numbers")
            need(not value or any(value[3:]), name, "has a zero quaternion")
        need(not self.label_image_topic or bool(self.image_topic), "label_image_topic", "label images pair with camera images: set image_topic too")


@dataclass(frozen=True)
class DatasetConfig:
    """Where scans come from. ``paths`` are candidates, the first existing one is used; a ``bag``
    dataset reads every one of its ``logs`` in order instead (ROS 1 .bag files, ROS 2 bag folders,
    .db3 or .mcap files), as ``bag`` says."""

    kind: str = ""  # rellis3d, semantickitti, bag (robot logs), pcd_sequence (numbered PCD files) or bench_npz (an .npz workload)
    paths: tuple[str, ...] = ()  # candidate locations of the data, relative to the config file; the first that exists is read
    logs: tuple[str, ...] = ()  # a bag dataset's robot logs, read in order as one drive
    bag: BagConfig = field(default_factory=BagConfig)  # how to read the logs (the dataset.bag section)
    pattern: str = ""  # pcd_sequence: the scans' file names, with {index} for the number (e.g. "scan_{index}.pcd")
    first_index: int = 1  # pcd_sequence: the first scan's number
    last_index: int = 1  # pcd_sequence: the last scan's number (inclusive)
    payload: PayloadType = PayloadType.LABEL  # what each point carries
    num_classes: int = 0  # classes of the payload; 0: the sequence's class set (a pcd_sequence must give it)
    class_names: tuple[str, ...] = ()  # names of the classes; empty: the sequence's class set
    # The world frame the map lives in (docs/algorithm.md §6.6). "": the data's own frame (a log's fixed
    # frame; a folder's poses.txt frame, named by its frame.yaml or after the folder; a point file's
    # frame); a name: the name of a folder's or point files' frame (a log's must equal its fixed frame);
    # "first-scan": the paper's convention, coordinates relative to the first scan's LiDAR pose.
    frame: str = ""
    crs: str = ""  # EPSG code of georeferenced coordinates (e.g. EPSG:32617, UTM zone 17N); "": none or the folder's frame.yaml
    config_dir: str = "."  # folder of the file that named the paths (they are relative to it)

    def __post_init__(self) -> None:
        from ..frames import FIRST_SCAN, FrameError, check_crs

        try:
            object.__setattr__(self, "crs", check_crs(self.crs, "dataset.crs") or "")
        except FrameError as exc:
            raise ConfigError(str(exc)) from None
        if self.frame.strip() != self.frame:
            raise ConfigError(f"dataset.frame = {self.frame!r}: a frame name has no leading or trailing spaces")
        if self.kind == "bag" and self.frame not in ("", FIRST_SCAN):
            # a log's world frame is its fixed frame: naming the frame chooses it
            if self.bag.fixed_frame and self.bag.fixed_frame != self.frame:
                raise ConfigError(f"dataset.frame = {self.frame!r} but dataset.bag.fixed_frame = {self.bag.fixed_frame!r}: a log is mapped "
                                  f"in its fixed frame; give one of them")
            object.__setattr__(self, "bag", dataclasses.replace(self.bag, fixed_frame=self.frame))

    def resolve_path(self) -> Path:
        """The first of ``paths`` that exists (relative ones are relative to the config file that named
        them); raises ConfigError listing every path tried when none does."""
        tried = []
        for candidate in self.paths:
            path = Path(candidate).expanduser()
            if not path.is_absolute():
                path = (Path(self.config_dir) / path).resolve()
            tried.append(str(path))
            if path.exists():
                return path
        raise ConfigError(f"dataset.paths: none of these exists: {tried}")

    def resolve_logs(self) -> list[Path]:
        """The robot logs of a bag dataset as paths, in order; raises ConfigError when there are none, one
        does not exist or one is named twice."""
        if not self.logs:
            raise ConfigError("dataset.logs: a bag dataset needs at least one log (a .bag, .mcap or .db3 file or a ROS 2 bag folder): "
                              "name them on the command line or in dataset.logs")
        resolved = []
        for candidate in self.logs:
            path = Path(candidate).expanduser()
            path = path if path.is_absolute() else (Path(self.config_dir) / path).resolve()
            if not path.exists():
                raise ConfigError(f"dataset.logs: {path} does not exist")
            if path.resolve() in [p.resolve() for p in resolved]:  # read twice, every cloud would be integrated twice
                raise ConfigError(f"dataset.logs: {candidate} is given twice; name each log once")
            resolved.append(path)
        return resolved
