"""Stage B (docs/algorithm.md §2): per-pixel values (network alpha, or 2D labels) onto the LiDAR points that
fall inside the camera image, into the world frame with the poses, grouped into bins of frames.

Per frame: zero returns are dropped; points go into camera coordinates; a FOV pre-filter keeps
points strictly inside the image's angle of view widened by ``fov_margin_deg`` (which also rejects
points behind the camera); the rest are projected with the full pinhole + distortion model and kept
inside the image; each reads the value at its pixel. The value map may be smaller than the image
(the network's output): ``nearest`` reads the map pixel that covers the point's image pixel (the
default), ``bilinear`` reproduces the release (bilinear upsampling to full size, then the
truncated pixel). An optional z-buffer drops points hidden behind nearer points of the same scan.

The 3D ground truth of the evaluation comes from the same code with the 2D label images.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
from PIL import Image

from .camera import PinholeCamera, transform_points
from ..config import ConfigError


@dataclass(frozen=True)
class ProjectionConfig:
    """How LiDAR points read per-pixel values from an image (docs/algorithm.md §2): the lookup, the
    field-of-view pre-filter, the optional z-buffer and the bins of frames."""

    lookup: str = "nearest"  # or "bilinear" (the release: upsample the map bilinearly, then truncate)
    fov_margin_deg: float = 10.0  # points up to this far outside the camera's field of view pass the pre-filter
    zbuffer: bool = False  # drop points hidden behind nearer ones
    zbuffer_cell_px: int = 4  # image pixels per z-buffer cell (LiDAR points are sparse in the image)
    zbuffer_tolerance_m: float = 0.5  # a point is hidden when this much farther than the cell's nearest
    bin_frames: int = 1  # consecutive frames integrated as one insertion (30 for RELLIS-3D)

    def __post_init__(self):
        if self.lookup not in ("nearest", "bilinear"):
            raise ConfigError(f"projection.lookup must be 'nearest' or 'bilinear', got {self.lookup!r}")
        if not 0 <= self.fov_margin_deg < 90:
            raise ConfigError(f"projection.fov_margin_deg must lie in [0, 90), got {self.fov_margin_deg!r}")
        if self.bin_frames < 1 or self.zbuffer_cell_px < 1 or self.zbuffer_tolerance_m < 0:
            raise ConfigError(f"projection: bin_frames and zbuffer_cell_px must be >= 1 and zbuffer_tolerance_m >= 0, got {self}")


@dataclass
class Projected:
    """The points of a scan that land in the image: their rows in the scan, their pixel coordinates (u right,
    v down, px) and their depth (m, camera z)."""

    index: np.ndarray  # [M] rows of the scan that landed in the image
    pixel: np.ndarray  # [M, 2] float image coordinates (u right, v down)
    depth: np.ndarray  # [M] camera z, m


def project_scan(points_lidar: np.ndarray, camera: PinholeCamera, lidar_to_camera: np.ndarray, config: ProjectionConfig = ProjectionConfig()) -> Projected:
    """Project a scan's points [N, 3] (m, LiDAR frame; zero returns skipped) through ``lidar_to_camera`` [4,
    4] and ``camera``: the points inside the field of view and the image, with their pixels and depths
    (and only the nearest ones with the z-buffer). Raises ValueError for NaN or inf points."""
    points_lidar = np.asarray(points_lidar, np.float64)[:, :3]
    if not np.isfinite(points_lidar).all():
        bad = int(np.flatnonzero(~np.isfinite(points_lidar).all(1))[0])
        raise ValueError(f"scan: points have NaN or inf coordinates (first at row {bad})")
    candidates = np.flatnonzero(np.any(points_lidar != 0, axis=1))  # zero returns
    p = transform_points(lidar_to_camera, points_lidar[candidates])
    fov_x, fov_y = camera.field_of_view_deg()
    half_x, half_y = np.radians(fov_x + config.fov_margin_deg) / 2, np.radians(fov_y + config.fov_margin_deg) / 2
    inside = (np.abs(np.arctan2(p[:, 0], p[:, 2])) < half_x) & (np.abs(np.arctan2(p[:, 1], p[:, 2])) < half_y) & (p[:, 2] > 0)
    candidates, p = candidates[inside], p[inside]
    uv = camera.project(p)
    in_image = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    out = Projected(candidates[in_image], uv[in_image], p[in_image, 2])
    if config.zbuffer and len(out.index):
        out = _zbuffer(out, config)
    return out


def _zbuffer(projected: Projected, config: ProjectionConfig) -> Projected:
    cell = (projected.pixel // config.zbuffer_cell_px).astype(np.int64)
    key = cell[:, 0] * 1_000_003 + cell[:, 1]
    _, group = np.unique(key, return_inverse=True)
    nearest = np.full(group.max() + 1, np.inf)
    np.minimum.at(nearest, group, projected.depth)
    visible = projected.depth <= nearest[group] + config.zbuffer_tolerance_m
    return Projected(projected.index[visible], projected.pixel[visible], projected.depth[visible])


def sample_map(values: np.ndarray, pixel: np.ndarray, image_size: tuple[int, int], lookup: str = "nearest") -> np.ndarray:
    """Read ``values`` ([C, h, w] channels-first or [h, w]) at image ``pixel`` [M, 2] of an image of
    ``image_size`` (width, height): [M, C] or [M]."""
    width, height = image_size
    channels_first = values.ndim == 3
    h, w = values.shape[-2:]
    iu = np.floor(pixel[:, 0]).astype(np.int64)  # truncation to the image pixel, as the release does
    iv = np.floor(pixel[:, 1]).astype(np.int64)
    if lookup == "nearest" or (h, w) == (height, width):
        mu = np.minimum(iu * w // width, w - 1)
        mv = np.minimum(iv * h // height, h - 1)
        out = values[:, mv, mu] if channels_first else values[mv, mu]
        return out.T if channels_first else out
    if not channels_first:
        raise ValueError("bilinear lookup interpolates channels; pass a [C, h, w] map (labels use nearest)")
    # Bilinear upsampling to (height, width) with align_corners=False, evaluated only at the pixels needed.
    su = np.maximum((iu + 0.5) * (w / width) - 0.5, 0.0)
    sv = np.maximum((iv + 0.5) * (h / height) - 0.5, 0.0)
    u0, v0 = np.minimum(np.floor(su).astype(np.int64), w - 1), np.minimum(np.floor(sv).astype(np.int64), h - 1)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    fu, fv = (su - u0).astype(np.float32), (sv - v0).astype(np.float32)
    v = values.astype(np.float32)
    top = v[:, v0, u0] * (1 - fu) + v[:, v0, u1] * fu
    bottom = v[:, v1, u0] * (1 - fu) + v[:, v1, u1] * fu
    return (top * (1 - fv) + bottom * fv).T


def overlay_image(image: np.ndarray, pixel: np.ndarray, colors: np.ndarray, radius: int = 1) -> np.ndarray:
    """The camera image dimmed, with projected points drawn as small squares in ``colors`` [M, 3]."""
    out = (np.asarray(image, np.float32) * 0.6).astype(np.uint8)
    h, w = out.shape[:2]
    iu, iv = np.floor(pixel[:, 0]).astype(int), np.floor(pixel[:, 1]).astype(int)
    for du in range(-radius, radius + 1):
        for dv in range(-radius, radius + 1):
            u, v = np.clip(iu + du, 0, w - 1), np.clip(iv + dv, 0, h - 1)
            out[v, u] = colors
    return out


def depth_colors(depth: np.ndarray) -> np.ndarray:
    """A color per point [M, 3] uint8 from its ``depth`` [M] (turbo, nearest to farthest), for overlays."""
    import matplotlib

    scaled = np.clip((depth - depth.min()) / max(np.ptp(depth), 1e-6), 0, 1) if len(depth) else depth
    return (matplotlib.colormaps["turbo"](scaled)[:, :3] * 255).astype(np.uint8)


def save_overlay(path, image: np.ndarray, pixel: np.ndarray, colors: np.ndarray) -> None:
    """Debug image: the projected points over the camera image (``depth_colors`` for depth)."""
    Image.fromarray(overlay_image(image, pixel, colors, radius=max(1, image.shape[1] // 640))).save(path)


# Sequences ---------------------------------------------------------------------------------------
@dataclass
class ProjectedFrame:
    """One frame's projected points: points [M, 3] (m, the sequence's world frame), their values ([M, C] or
    [M] labels), the sensor origin [3] (m, world frame), their rows in the scan file and their pixels."""

    frame_index: int
    points: np.ndarray  # [M, 3] world frame, m
    values: np.ndarray  # [M, C] or [M]
    sensor_origin: np.ndarray  # [3] world frame
    scan_rows: np.ndarray  # [M] rows of the scan file
    pixel: np.ndarray  # [M, 2] image coordinates


@dataclass
class Bin:
    """Consecutive projected frames joined as one map insertion: their indices, points [M, 3] and values (m,
    world frame), and the sensor origin of the bin's last frame."""

    frames: list[int]
    points: np.ndarray
    values: np.ndarray
    sensor_origin: np.ndarray  # of the bin's last frame
    scan_rows: list[np.ndarray] = field(default_factory=list)


def project_frames(sequence, frames, values_for_frame: Callable, config: ProjectionConfig = ProjectionConfig(),
                   world=None) -> Iterator[ProjectedFrame]:
    """Project each frame's scan with ``values_for_frame(frame)`` ([C, h, w] or [h, w], None to skip
    the frame) into the world frame: ``world.to_world(pose)`` places a LiDAR pose (a ``Placement`` of
    ``data/world_frame.py``, or anything with that method); without one, poses are used as given."""
    camera, lidar_to_camera = sequence.camera, sequence.lidar_to_camera
    for frame in frames:
        values = values_for_frame(frame)
        if values is None:
            continue
        pose = sequence.pose(frame)
        scan = sequence.read_scan(frame)
        projected = project_scan(scan[:, :3], camera, lidar_to_camera, config)
        sampled = sample_map(np.asarray(values), projected.pixel, (camera.width, camera.height), config.lookup)
        to_world = pose if world is None else world.to_world(pose)
        yield ProjectedFrame(frame.index, transform_points(to_world, scan[projected.index, :3]), sampled, to_world[:3, 3], projected.index, projected.pixel)


def bin_frames(projected: Iterator[ProjectedFrame], frames_per_bin: int) -> Iterator[Bin]:
    """Group consecutive projected frames into bins of ``frames_per_bin`` (the last one may be short)."""
    pending: list[ProjectedFrame] = []
    for item in projected:
        pending.append(item)
        if len(pending) == frames_per_bin:
            yield _merge(pending)
            pending = []
    if pending:
        yield _merge(pending)


def _merge(items: list[ProjectedFrame]) -> Bin:
    return Bin([i.frame_index for i in items], np.concatenate([i.points for i in items]),
               np.concatenate([i.values for i in items]), items[-1].sensor_origin, [i.scan_rows for i in items])


def label_map_for(sequence) -> Callable:
    """values_for_frame that gives each frame's 2D ground truth as v3 ids (frames without labels skipped)."""
    from ..classes import remap_ids

    def values(frame):
        if frame.label_image is None:
            return None
        return remap_ids(sequence.read_label_ids(frame), str(frame.label_image))

    return values
