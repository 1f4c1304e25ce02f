"""Sensor sequences on disk: RELLIS-3D (real, and the synthetic world's output) and SemanticKITTI.

A sequence gives frames (scan, optional camera image and labels, pose) and its calibration; files
are read on demand so long sequences stream. ``check_sequence`` lists what is missing or
inconsistent before a long run fails halfway.

RELLIS-3D (docs/algorithm.md §5.3) is read from a sequence folder in its layout, or from loose files in one folder
(``NNNNNN.bin``, ``NNNNNN.label``, ``frameNNNNNN-*.jpg`` and a ``.png`` label of the same stem, as in
RELLIS-3D's ``utils/example``). Distortion comes from ``camera_distortion.txt`` when present (the
synthetic world writes one), else RELLIS-3D's hard-coded coefficients.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from ..geometry.camera import RELLIS3D_DISTORTION, PinholeCamera, quaternion_to_matrix, rigid
from ..classes import decode_color_labels, original_to_v3_table, palette
from ..frames import FrameError, WorldFrame
from .point_files import read_kitti_bin

EXTRINSIC_KEY = "os1_cloud_node-pylon_camera_node"
FRAME_FILE = "frame.yaml"  # a folder's poses frame: name (and crs), docs/algorithm.md §6.6
RIGID_TOLERANCE = 1e-4  # largest |R R^T - I| entry of a pose read from text
_FRAME_NUMBER = re.compile(r"^frame(\d{6})")


class DataError(ValueError):
    """A dataset file is missing, unreadable or inconsistent; the message names the file."""


@dataclass
class Frame:
    """One frame of a sequence: its index (scan number = pose line), the scan file, and the files beside it
    when it has them: per-point labels, camera image, 2D label image (colors or ids, as
    ``label_is_color`` says)."""

    index: int  # frame number = scan index = pose line
    scan: Path
    point_labels: Path | None = None
    image: Path | None = None
    label_image: Path | None = None
    label_is_color: bool = True


def read_text(path: Path) -> str:
    """A small text file (calibration, transforms), or a DataError naming it when it is binary."""
    try:
        return Path(path).read_text()
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a text file") from None


def remap_point_labels(raw: np.ndarray, table: np.ndarray, path) -> np.ndarray:
    """Raw per-point label ids through a class table; ids outside it are an error naming the file."""
    raw = np.asarray(raw, np.int64)
    labels = table[np.clip(raw, 0, len(table) - 1)]
    outside = (raw < 0) | (raw >= len(table)) | (labels < 0)
    if outside.any():
        raise DataError(f"{path}: label ids outside the class table: {np.unique(raw[outside])[:10].tolist()}")
    return labels


def read_poses(path: Path) -> np.ndarray:
    """KITTI/RELLIS poses.txt: [N, 4, 4] from 12 row-major numbers per line."""
    try:
        data = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DataError(f"{path}: not a table of numbers ({exc})") from None
    if data.shape[1] != 12:
        raise DataError(f"{path}: a pose line needs 12 numbers (3x4 row-major), got {data.shape[1]}")
    if not np.isfinite(data).all():
        raise DataError(f"{path}: pose line {int(np.flatnonzero(~np.isfinite(data).all(1))[0]) + 1} has NaN or inf")
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    poses[:, :3, :] = data.reshape(-1, 3, 4)
    rotations = poses[:, :3, :3]
    # A pose is a rotation and a translation: anything else (a scale, a shear, a mirror, a typo) would
    # bend the map without a word. Text poses carry ~6-9 digits, hence the tolerance.
    off = np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((off > RIGID_TOLERANCE) | (np.linalg.det(rotations) <= 0))
    if len(bad):
        line = int(bad[0])
        det = np.linalg.det(rotations[line])
        what = ("is singular (zero or degenerate)" if abs(det) < 1e-9 else "mirrors" if det < 0
                else f"is not orthonormal (|R R^T - I| = {off[line]:.3g})")
        raise DataError(f"{path}: pose line {line + 1} is not a rigid transform: its rotation {what}"
                        + (f" ({len(bad)} such lines)" if len(bad) > 1 else ""))
    return poses


def read_frame_file(folder: Path) -> WorldFrame | None:
    """A sequence folder's ``frame.yaml`` (the name and CRS of its poses' frame), None without one."""
    path = Path(folder) / FRAME_FILE
    if not path.is_file():
        return None
    try:
        data = yaml.safe_load(read_text(path))
    except yaml.YAMLError as exc:
        raise DataError(f"{path}: not valid YAML ({exc})") from None
    try:
        return WorldFrame.from_dict(data, str(path))
    except FrameError as exc:
        raise DataError(str(exc)) from None


def read_point_labels(path: Path, expected: int) -> np.ndarray:
    """SemanticKITTI-style .label -> [N] semantic ids (lower 16 bits)."""
    raw = np.fromfile(path, dtype=np.uint32)
    if len(raw) != expected:
        raise DataError(f"{path}: {len(raw)} labels for a scan of {expected} points")
    return (raw & 0xFFFF).astype(np.int64)


class _ScanSequence:
    """What RELLIS-3D and SemanticKITTI sequences share: frames with scans, optional poses, labels."""

    root: Path
    frames: list[Frame]

    def __len__(self) -> int:
        return len(self.frames)

    def _pose_line(self, poses: np.ndarray | None, frame: Frame) -> np.ndarray:
        if poses is None:
            return np.eye(4)
        if frame.index >= len(poses):
            raise DataError(f"{self.root / 'poses.txt'}: {len(poses)} poses, but scan {frame.index} needs line {frame.index + 1}")
        return poses[frame.index]

    def read_scan(self, frame: Frame) -> np.ndarray:
        return read_kitti_bin(frame.scan)

    def read_point_labels(self, frame: Frame) -> np.ndarray:
        """Raw label ids per point (including zero returns)."""
        if frame.point_labels is None:
            raise DataError(f"{frame.scan}: no per-point label file for this scan")
        return read_point_labels(frame.point_labels, frame.scan.stat().st_size // 16)  # 16 bytes per scan point


class Rellis3DSequence(_ScanSequence):
    """A RELLIS-3D-layout sequence folder (``os1_cloud_node_kitti_bin/``, labels, ``pylon_camera_node/``
    images and label images, ``poses.txt``, ``camera_info.txt``, ``transforms.yaml``; what ``evsemmap
    synth`` writes), or RELLIS-3D's loose example files (NNNNNN.bin beside their images). Raises DataError
    naming the folder when it does not exist or holds no scans."""

    def __init__(self, root):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(f"{self.root}: no such sequence folder")
        layout = (self.root / "os1_cloud_node_kitti_bin").is_dir()
        scans = sorted((self.root / "os1_cloud_node_kitti_bin").glob("*.bin")) if layout else sorted(self.root.glob("[0-9]*.bin"))
        if not scans:
            recording = sorted(p.name for p in self.root.glob("*") if p.suffix in (".db3", ".mcap"))
            if recording:  # a ROS 2 bag folder gets its metadata.yaml when the recorder closes it
                raise DataError(f"{self.root}: a ROS 2 bag folder without metadata.yaml (still being recorded, or cut short): name its "
                                f"file {recording[0]} to read what it holds so far")
            raise DataError(f"{self.root}: no scans (expected os1_cloud_node_kitti_bin/NNNNNN.bin or NNNNNN.bin)")
        image_dir = self.root / "pylon_camera_node" if layout else self.root
        images = {}
        for path in sorted(image_dir.glob("frame*.jpg")) + sorted(image_dir.glob("frame*.png")):
            match = _FRAME_NUMBER.match(path.stem)
            if match and not (not layout and path.suffix == ".png"):
                images.setdefault(int(match.group(1)), path)
        self.frames: list[Frame] = []
        for scan in scans:
            if not scan.stem.isdigit():
                continue
            index = int(scan.stem)
            frame = Frame(index, scan)
            labels = (self.root / "os1_cloud_node_semantickitti_label_id" / f"{scan.stem}.label") if layout else scan.with_suffix(".label")
            frame.point_labels = labels if labels.exists() else None
            frame.image = images.get(index)
            if frame.image is not None:
                frame.label_image, frame.label_is_color = self._label_image(frame.image, layout)
            self.frames.append(frame)
        self._camera = None
        self._poses = None

    def _label_image(self, image: Path, layout: bool):
        if not layout:
            candidate = image.with_suffix(".png")
            if candidate.exists():
                with Image.open(candidate) as img:
                    return candidate, img.mode in ("RGB", "RGBA", "P")
            return None, True
        color = self.root / "pylon_camera_node_label_color" / f"{image.stem}.png"
        ids = self.root / "pylon_camera_node_label_id" / f"{image.stem}.png"
        if color.exists():
            return color, True
        return (ids, False) if ids.exists() else (None, True)

    # Calibration ---------------------------------------------------------------------------------
    @property
    def camera(self) -> PinholeCamera:
        """The camera's intrinsics and distortion (``camera_info.txt``, ``camera_distortion.txt`` or
        RELLIS-3D's fixed distortion), read on first use; raises DataError when a file is missing or
        malformed."""
        if self._camera is None:
            self._camera = self._read_camera()
        return self._camera

    def _read_camera(self) -> PinholeCamera:
        info = self.root / "camera_info.txt"
        if not info.exists():
            raise DataError(f"{info}: missing (RELLIS-3D ships it in the 'camera intrinsic' archive: fx fy cx cy)")
        values = read_text(info).split()
        try:
            fx, fy, cx, cy = (float(v) for v in values)
        except ValueError:
            raise DataError(f"{info}: expected four numbers fx fy cx cy, got {values[:8]}") from None
        if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
            raise DataError(f"{info}: fx fy cx cy = {values}: the focal lengths must be finite numbers > 0 and the principal point finite")
        distortion = RELLIS3D_DISTORTION
        distortion_file = self.root / "camera_distortion.txt"
        if distortion_file.exists():
            try:
                distortion = tuple(float(v) for v in read_text(distortion_file).split())
            except ValueError:
                raise DataError(f"{distortion_file}: expected five numbers k1 k2 p1 p2 k3") from None
            if len(distortion) != 5:
                raise DataError(f"{distortion_file}: expected five numbers k1 k2 p1 p2 k3, got {len(distortion)}")
        first = next((f.image for f in self.frames if f.image is not None), None)
        if first is None:
            raise DataError(f"{self.root}: no camera images, so the image size is unknown")
        with Image.open(first) as img:
            width, height = img.size
        if not (0 < cx < width and 0 < cy < height):
            raise DataError(f"{info}: principal point ({cx}, {cy}) lies outside the {width}x{height} camera images ({first.name}): "
                            f"camera_info.txt belongs to another camera or resolution")
        return PinholeCamera(fx, fy, cx, cy, width, height, distortion)

    def _check_image_size(self, path: Path, height: int, width: int) -> None:
        camera = self.camera
        if (height, width) != (camera.height, camera.width):
            raise DataError(f"{path}: {width}x{height} pixels, but the sequence's camera (camera_info.txt with "
                            f"{self.frames[0].image.name if self.frames[0].image else 'its first image'}) is {camera.width}x{camera.height}")

    @property
    def lidar_to_camera(self) -> np.ndarray:
        """4x4 transform of LiDAR coordinates into camera coordinates (the inverse of the stored T)."""
        q, t = self.camera_mount
        return np.linalg.inv(rigid(quaternion_to_matrix(q), t))

    @property
    def camera_mount(self) -> tuple[list[float], list[float]]:
        """The camera's pose in the LiDAR frame as transforms.yaml stores it: quaternion (x, y, z, w), translation."""
        path = self.root / "transforms.yaml"
        if not path.exists():
            raise DataError(f"{path}: missing (RELLIS-3D ships it in the 'camera to LiDAR' archive)")
        try:
            entry = yaml.safe_load(read_text(path))[EXTRINSIC_KEY]
            q = [entry["q"][k] for k in "xyzw"]
            t = [entry["t"][k] for k in "xyz"]
        except (yaml.YAMLError, KeyError, TypeError) as exc:
            raise DataError(f"{path}: expected {EXTRINSIC_KEY}: {{q: {{x, y, z, w}}, t: {{x, y, z}}}} ({type(exc).__name__}: {exc})") from None
        return q, t

    @property
    def poses(self) -> np.ndarray | None:
        """[N, 4, 4] LiDAR poses from poses.txt, or None when the folder has none (single frames)."""
        if self._poses is None and (self.root / "poses.txt").exists():
            self._poses = read_poses(self.root / "poses.txt")
        return self._poses

    def pose(self, frame: Frame) -> np.ndarray:
        """Frame ``frame``'s LiDAR pose [4, 4] float64 in the poses' frame (``poses.txt`` line
        ``frame.index``; identity without a poses file). Raises DataError when the poses run short."""
        return self._pose_line(self.poses, frame)

    # Per-frame data ------------------------------------------------------------------------------
    def read_image(self, frame: Frame) -> np.ndarray:
        """Frame ``frame``'s camera image, [H, W, 3] uint8 RGB; raises DataError when its size is not the
        camera's."""
        with Image.open(frame.image) as img:
            image = np.asarray(img.convert("RGB"))
        self._check_image_size(frame.image, *image.shape[:2])
        return image

    def read_label_ids(self, frame: Frame) -> np.ndarray:
        """[H, W] raw ontology ids of the frame's 2D labels (color PNGs decoded with the palette)."""
        if frame.label_image is None:
            raise DataError(f"{frame.image}: no label image for this frame")
        with Image.open(frame.label_image) as img:
            raw = np.asarray(img.convert("RGB") if frame.label_is_color else img)
        if frame.label_is_color:
            self._check_image_size(frame.label_image, *raw.shape[:2])
            return decode_color_labels(raw, palette("rellis3d_colors"), str(frame.label_image))
        if raw.ndim != 2:
            raise DataError(f"{frame.label_image}: an id label image must have one channel, got shape {list(raw.shape)}")
        self._check_image_size(frame.label_image, *raw.shape[:2])
        return raw.astype(np.int64)


class SemanticKittiSequence(_ScanSequence):
    """``sequences/XX``: velodyne/NNNNNN.bin, labels/NNNNNN.label, poses.txt (cam0 frame), calib.txt (Tr).
    LiDAR poses are inv(Tr) * pose * Tr (docs/algorithm.md §5.4)."""

    def __init__(self, root):
        self.root = Path(root)
        scans = sorted((self.root / "velodyne").glob("*.bin"))
        if not scans:
            raise DataError(f"{self.root}: no velodyne/NNNNNN.bin scans")
        self.frames = [Frame(int(s.stem), s, self.root / "labels" / f"{s.stem}.label") for s in scans if s.stem.isdigit()]
        for frame in self.frames:
            if not frame.point_labels.exists():
                frame.point_labels = None
        self.tr = self._read_tr()
        poses_path = self.root / "poses.txt"
        cam_poses = read_poses(poses_path) if poses_path.exists() else None
        self.poses = None if cam_poses is None else np.linalg.inv(self.tr) @ cam_poses @ self.tr

    def _read_tr(self) -> np.ndarray:
        path = self.root / "calib.txt"
        if not path.exists():
            return np.eye(4)
        for line in read_text(path).splitlines():
            if line.startswith("Tr:"):
                try:
                    values = [float(v) for v in line.split()[1:]]
                except ValueError:
                    raise DataError(f"{path}: Tr needs 12 numbers, got {line.split()[1:][:12]}") from None
                if len(values) != 12:
                    raise DataError(f"{path}: Tr needs 12 numbers, got {len(values)}")
                tr = np.eye(4)
                tr[:3, :] = np.reshape(values, (3, 4))
                rotation = tr[:3, :3]
                if (not np.isfinite(tr).all() or np.abs(rotation @ rotation.T - np.eye(3)).max() > RIGID_TOLERANCE
                        or np.linalg.det(rotation) <= 0):
                    raise DataError(f"{path}: Tr is not a rigid transform (a rotation and a translation, finite): {values}")
                return tr
        raise DataError(f"{path}: no 'Tr:' line")

    def pose(self, frame: Frame) -> np.ndarray:
        """Frame ``frame``'s LiDAR pose [4, 4] float64, inv(Tr) * P * Tr (docs/algorithm.md §5.4); raises
        DataError when the poses run short."""
        return self._pose_line(self.poses, frame)


def semantickitti_learning_map() -> np.ndarray:
    """[260] raw SemanticKITTI id -> 19-class learning id (0 = ignore), from configs/classes/semantickitti.yaml."""
    from ..classes import classes_dir

    table = np.zeros(260, np.int64)
    for raw, learned in yaml.safe_load((classes_dir() / "semantickitti.yaml").read_text())["learning_map"].items():
        table[int(raw)] = int(learned)
    return table


# Checking a folder before a long run -------------------------------------------------------------
@dataclass
class CheckReport:
    """What ``evsemmap check-data`` found in one folder or log: counts of frames, images and label images,
    the problems that would stop a run, notes, and what the source holds."""

    root: Path
    frames: int = 0
    with_images: int = 0
    with_labels: int = 0
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    details: list[str] = field(default_factory=list)  # what the source holds (a log's topics), before the verdict
    unit: str = "scans"

    @property
    def ok(self) -> bool:
        """True when nothing would stop a run."""
        return not self.problems

    def text(self) -> str:
        """The report as the lines ``check-data`` prints."""
        lines = [f"{self.root}: {self.frames} {self.unit}, {self.with_images} with a camera image, {self.with_labels} with a 2D label image"]
        lines += [f"  {d}" for d in self.details]
        lines += [f"  problem: {p}" for p in self.problems]
        lines += [f"  note: {n}" for n in self.notes]
        lines.append("  OK" if self.ok else f"  {len(self.problems)} problem(s)")
        return "\n".join(lines)


def check_sequence(root, *, max_label_files: int = 50) -> CheckReport:
    """Look for what would make a run fail halfway: calibration, poses, frame pairing, file sizes and
    label ids outside the ontology (the first ``max_label_files`` label files are read)."""
    report = CheckReport(Path(root))
    try:
        seq = Rellis3DSequence(root)
    except DataError as exc:
        report.problems.append(str(exc))
        return report
    report.frames = len(seq)
    report.with_images = sum(f.image is not None for f in seq.frames)
    report.with_labels = sum(f.label_image is not None for f in seq.frames)
    lidar_only = report.with_images == 0 and all(f.point_labels is not None for f in seq.frames)
    for what in ("lidar_to_camera",) if lidar_only else ("camera", "lidar_to_camera"):
        try:
            getattr(seq, what)
        except DataError as exc:
            report.problems.append(str(exc))
    try:
        own = read_frame_file(seq.root)
        name = own.describe() if own else f"frame 'poses:{seq.root.name}' (no {FRAME_FILE} names it)"
        report.details.append(f"world frame: maps are made in {name}, poses.txt used as given")
        poses = seq.poses
        if poses is None:
            report.notes.append("no poses.txt: every scan is taken in its own LiDAR frame (fine for single frames only)")
        elif len(poses) <= max(f.index for f in seq.frames):
            report.problems.append(f"poses.txt has {len(poses)} lines but scan numbers reach {max(f.index for f in seq.frames)}")
    except DataError as exc:
        report.problems.append(str(exc))
    if lidar_only:
        report.notes.append("LiDAR only (no camera images): it maps from its per-point labels; projection and camera-labelled mapping need images")
    elif report.with_images == 0:
        report.problems.append("no camera image pairs with any scan (expected pylon_camera_node/frameNNNNNN-*.jpg)")
    elif report.with_images < report.frames:
        report.notes.append(f"{report.frames - report.with_images} scans have no camera image and will be skipped by projection")
    sizes = {f.scan.stat().st_size for f in seq.frames}
    if any(s % 16 for s in sizes):
        report.problems.append(f"scan files whose size is not a multiple of 16 bytes (truncated?): {sorted(s for s in sizes if s % 16)[:3]}")
    table = original_to_v3_table()
    checked = 0
    for frame in seq.frames:
        if checked >= max_label_files:
            break
        if frame.label_image is not None:
            checked += 1
            try:
                ids = seq.read_label_ids(frame)
            except ValueError as exc:
                if str(exc) not in report.problems:  # a broken camera_info.txt fails every frame alike: listed once
                    report.problems.append(str(exc))
                continue
            outside = np.unique(ids[(ids > 255) | (table[np.clip(ids, 0, 255)] < 0)])
            if len(outside):
                report.problems.append(f"{frame.label_image}: label ids outside the ontology: {outside.tolist()[:10]}")
            try:
                with Image.open(frame.image) as img:
                    image_size = img.size
                if image_size != ids.shape[::-1]:
                    report.problems.append(f"{frame.image} is {image_size[0]}x{image_size[1]} but {frame.label_image} is {ids.shape[1]}x{ids.shape[0]}")
            except OSError as exc:
                report.problems.append(f"{frame.image}: unreadable image ({exc})")
        if frame.point_labels is not None:
            if frame.point_labels.stat().st_size != frame.scan.stat().st_size // 4:
                report.problems.append(f"{frame.point_labels}: {frame.point_labels.stat().st_size // 4} labels for {frame.scan.stat().st_size // 16} points")
    return report
