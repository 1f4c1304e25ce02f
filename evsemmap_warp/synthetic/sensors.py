"""Sensors of the synthetic world, by ray casting with Warp: a spinning LiDAR and a pinhole camera
rigidly mounted on it. Arrays in, arrays out; files are the writer's business."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.warp_runtime import init_warp, resolve_device
from ..geometry.camera import PinholeCamera, rigid, transform_points
from .appearance import add_sensor_noise, shade, sky_color, sun_direction
from .preset import CameraParams, LidarParams
from .scene import MATERIAL_INDEX, MATERIALS, World

SHADOW_BIAS_M = 0.02  # start shadow rays this far off the surface so they do not hit it again


class RayCaster:
    """A world mesh in a Warp BVH; ``cast`` returns distance, face and normal per ray (-1 on a miss)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, device: str | None = "cpu"):
        self.wp = init_warp()
        from ..kernels.raycast import cast_rays

        self._kernel = cast_rays
        self.device = resolve_device(device)
        wp = self.wp
        self._points = wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=self.device)
        self._indices = wp.array(np.asarray(faces, np.int32).ravel(), dtype=int, device=self.device)
        self.mesh = wp.Mesh(points=self._points, indices=self._indices)

    def cast(self, origins: np.ndarray, directions: np.ndarray, max_distance: float):
        """Cast rays from ``origins`` ([N, 3] or one [3], m, the world's frame) along unit ``directions`` [N,
        3] up to ``max_distance`` (m): hit distances [N] (-1 for a miss), hit faces [N] (-1 for a miss)
        and unit normals [N, 3]."""
        wp, n = self.wp, len(directions)
        origins = np.broadcast_to(np.asarray(origins, np.float32), (n, 3))
        distance = wp.empty(n, dtype=float, device=self.device)
        face = wp.empty(n, dtype=int, device=self.device)
        normal = wp.empty(n, dtype=wp.vec3, device=self.device)
        if n:
            wp.launch(self._kernel, dim=n, device=self.device, inputs=[
                self.mesh.id, wp.array(np.ascontiguousarray(origins), dtype=wp.vec3, device=self.device),
                wp.array(np.asarray(directions, np.float32), dtype=wp.vec3, device=self.device), float(max_distance),
                distance, face, normal])
        return distance.numpy(), face.numpy(), normal.numpy()


@dataclass
class LidarScan:
    """One LiDAR scan: points [beams * azimuth_steps, 4] float32 (x, y, z in m, LiDAR frame, and intensity;
    zeros where no return) and each point's RELLIS-3D ontology id (0 where no return)."""

    points: np.ndarray  # [beams * azimuth_steps, 4] float32 x, y, z, intensity in the LiDAR frame; zeros where no return
    original_id: np.ndarray  # [same] uint32 RELLIS-3D ontology id per point (0 where no return)


def lidar_directions(params: LidarParams) -> np.ndarray:
    """[beams * azimuth_steps, 3] unit beam directions in the LiDAR frame, beam-major rows."""
    elevation = np.radians(np.linspace(params.fov_up_deg, params.fov_down_deg, params.beams))
    azimuth = np.radians(180.0 - 360.0 * np.arange(params.azimuth_steps) / params.azimuth_steps)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)


def scan_lidar(caster: RayCaster, world: World, pose: np.ndarray, params: LidarParams, rng: np.random.Generator,
               local: np.ndarray | None = None) -> LidarScan:
    """One scan from ``pose``; ``local``: the beam directions (``lidar_directions``), given when scanning many poses."""
    local = lidar_directions(params) if local is None else local
    distance, face, normal = caster.cast(pose[:3, 3], local @ pose[:3, :3].T, params.max_range_m)
    hit = face >= 0
    material = np.where(hit, world.face_material[np.maximum(face, 0)], -1)
    keep_probability = np.where(material == MATERIAL_INDEX["puddle"], 1 - params.water_dropout, 1 - params.dropout)
    hit &= rng.random(len(hit)) < keep_probability
    measured = distance + rng.normal(0, params.range_noise_m, len(distance))
    points = np.zeros((len(local), 4), np.float32)
    points[hit, :3] = local[hit] * measured[hit, None]
    world_dirs = local @ pose[:3, :3].T
    incidence = np.abs((normal * world_dirs).sum(1))
    reflectivity = np.array([m.reflectivity for m in MATERIALS])
    points[hit, 3] = reflectivity[material[hit]] * incidence[hit]
    original_id = np.zeros(len(local), np.uint32)
    original_id[hit] = world.face_original_id[face[hit]]
    return LidarScan(points, original_id)


def camera_to_lidar(params: CameraParams) -> np.ndarray:
    """4x4 camera -> LiDAR transform of the mount (what RELLIS-3D's transforms.yaml stores)."""
    # Optical axes in LiDAR coordinates: x right = -y, y down = -z, z forward = +x ...
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pitch = np.radians(params.pitch_deg)  # ... then tilted about the LiDAR y axis (negative looks down)
    tilt = np.array([[np.cos(pitch), 0, -np.sin(pitch)], [0, 1, 0], [np.sin(pitch), 0, np.cos(pitch)]])
    return rigid(tilt @ level, params.offset_m)


def camera_model(params: CameraParams) -> PinholeCamera:
    """The pinhole camera of a preset's camera section."""
    return PinholeCamera.from_fov(params.width, params.height, params.hfov_deg, params.distortion)


@dataclass
class CameraFrame:
    """One camera frame: RGB [H, W, 3] uint8, each pixel's RELLIS-3D ontology id [H, W] (sky where rays
    escape) and its distance along the ray (m, inf for sky)."""

    rgb: np.ndarray  # [H, W, 3] uint8
    original_id: np.ndarray  # [H, W] uint8 RELLIS-3D ontology id per pixel (7 = sky where rays escape)
    depth: np.ndarray  # [H, W] float32 distance along the ray, inf for sky


SKY_ORIGINAL_ID = 7


def render_camera(caster: RayCaster, world: World, pose: np.ndarray, params: CameraParams, domain: str,
                  noise_sigma: float, rng: np.random.Generator, max_distance: float = 400.0,
                  pixel_rays: np.ndarray | None = None) -> CameraFrame:
    """One image from the camera on the LiDAR at ``pose``; ``pixel_rays``: camera-frame rays [H * W, 3]
    (``camera_model(params).pixel_rays()``), given when rendering many poses."""
    if pixel_rays is None:
        pixel_rays = camera_model(params).pixel_rays().reshape(-1, 3)
    camera_pose = pose @ camera_to_lidar(params)
    directions = pixel_rays @ camera_pose[:3, :3].T
    origin = camera_pose[:3, 3]
    distance, face, normal = caster.cast(origin, directions, max_distance)
    hit = face >= 0
    radiance = sky_color(domain, directions)
    hit_points = origin + directions[hit] * distance[hit, None]
    # Shadow rays towards the sun from every visible surface point.
    facing = np.where((normal[hit] * directions[hit]).sum(1, keepdims=True) > 0, -normal[hit], normal[hit])
    _, blocker, _ = caster.cast(hit_points + facing * SHADOW_BIAS_M, np.broadcast_to(sun_direction(domain), hit_points.shape), max_distance)
    radiance[hit] = shade(domain, MATERIALS, world.face_material[face[hit]], hit_points, normal[hit], directions[hit],
                          distance[hit], blocker < 0, face[hit], world.seed)
    original_id = np.full(len(face), SKY_ORIGINAL_ID, np.uint8)
    original_id[hit] = world.face_original_id[face[hit]]
    depth = np.where(hit, distance, np.inf).astype(np.float32)
    shape = (params.height, params.width)
    return CameraFrame(add_sensor_noise(radiance.reshape(*shape, 3), noise_sigma, rng), original_id.reshape(shape), depth.reshape(shape))


def lidar_points_in_world(scan: LidarScan, pose: np.ndarray) -> np.ndarray:
    """The scan's returned points [M, 3] (m) in the world frame, through the LiDAR ``pose`` [4, 4]."""
    returned = np.any(scan.points[:, :3] != 0, axis=1)
    return transform_points(pose, scan.points[returned, :3])
