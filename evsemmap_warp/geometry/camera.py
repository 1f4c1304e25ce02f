"""Camera and rigid-transform geometry shared by the projection stage and the synthetic sensors.

Pinhole camera with OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3; the semantics of
``cv2.projectPoints``), camera frame x right, y down, z forward. Poses are 4x4 matrices.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# RELLIS-3D's distortion, hard-coded by its tools and by EvSemMap for every sequence (docs/algorithm.md §2.1).
RELLIS3D_DISTORTION = (-0.134313, -0.025905, 0.002181, 0.00084, 0.0)


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera with OpenCV distortion: focal lengths and principal point (px), image size (px) and
    k1 k2 p1 p2 k3. Raises ValueError for non-positive focal lengths or size, or a distortion of other
    than five values."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self):
        if not (self.fx > 0 and self.fy > 0 and self.width > 0 and self.height > 0):
            raise ValueError(f"camera: fx, fy, width and height must be positive, got fx={self.fx} fy={self.fy} {self.width}x{self.height}")
        if len(self.distortion) != 5:
            raise ValueError(f"camera: distortion needs 5 coefficients (k1 k2 p1 p2 k3), got {self.distortion}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, distortion=(0.0,) * 5) -> "PinholeCamera":
        """A distortion-free camera (unless ``distortion`` says otherwise) of ``width`` x ``height`` px with
        horizontal field of view ``hfov_deg``, square pixels and the principal point at the center."""
        f = width / (2 * np.tan(np.radians(hfov_deg) / 2))
        return cls(f, f, width / 2, height / 2, width, height, tuple(float(d) for d in distortion))

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's distortion of normalised image coordinates (x, y) = (X / Z, Y / Z): the distorted (x, y)."""
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """[N, 3] camera-frame points (z > 0) -> [N, 2] pixel coordinates (u right, v down)."""
        p = np.asarray(points_camera, np.float64)
        x, y = self.distort(p[:, 0] / p[:, 2], p[:, 1] / p[:, 2])
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)

    def pixel_rays(self, iterations: int = 20) -> np.ndarray:
        """[H, W, 3] unit ray directions (camera frame) through pixel centers, distortion inverted by
        fixed-point iteration (as cv2.undistortPoints does)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        xd, yd = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        if any(self.distortion):
            k1, k2, p1, p2, k3 = self.distortion
            for _ in range(iterations):
                r2 = x * x + y * y
                radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
                x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
                y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def field_of_view_deg(self) -> tuple[float, float]:
        """Full horizontal and vertical angles of view of the undistorted pinhole."""
        return (float(np.degrees(2 * np.arctan(self.width / (2 * self.fx)))),
                float(np.degrees(2 * np.arctan(self.height / (2 * self.fy)))))


def quaternion_to_matrix(q) -> np.ndarray:
    """(x, y, z, w) -> 3x3 rotation; the quaternion is normalised first."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> (x, y, z, w) with w >= 0. Shepperd's method: the largest component comes from
    the diagonal, the others from sums and differences of off-diagonal pairs, so no component loses
    digits to cancellation (a rotation survives the round trip to float64 rounding)."""
    m = np.asarray(rotation, np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    largest = int(np.argmax([trace, m[0, 0], m[1, 1], m[2, 2]]))
    if largest == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4])
    elif largest == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif largest == 2:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
        q = np.array([(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rigid(rotation: np.ndarray, translation) -> np.ndarray:
    """The 4x4 transform of a 3x3 ``rotation`` and a ``translation`` [3]."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def relative_pose(reference: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """inv(reference) @ pose, and exactly the identity for the reference pose itself: the world frame
    is the first scan's own frame, so its points keep their coordinates bit for bit (a point on a
    voxel face stays on it however the poses were stored)."""
    if np.array_equal(reference, pose):
        return np.eye(4)
    return np.linalg.inv(reference) @ pose


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` [N, 3] mapped by the 4x4 ``transform`` (float64)."""
    points = np.asarray(points, np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]
