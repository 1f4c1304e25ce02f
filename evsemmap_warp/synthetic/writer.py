"""Generate a synthetic sequence and write it in the RELLIS-3D layout (docs/algorithm.md §5.3), so that the one
RELLIS-3D loader reads real and synthetic data alike.

Written per sequence folder: ``os1_cloud_node_kitti_bin/NNNNNN.bin`` (float32 x y z intensity, every
beam and azimuth step, zeros where nothing returned), ``os1_cloud_node_semantickitti_label_id/NNNNNN.label``
(uint32 ontology ids), ``pylon_camera_node/frameNNNNNN-<sec>_<msec>.jpg``, the matching
``pylon_camera_node_label_color/*.png`` and ``pylon_camera_node_label_id/*.png``, ``poses.txt``,
``camera_info.txt``, ``transforms.yaml``; plus two files RELLIS-3D lacks: ``camera_distortion.txt``
(k1 k2 p1 p2 k3; RELLIS-3D hard-codes its own) and ``synth.yaml`` (the preset, the seed, the version:
everything needed to generate the same sequence again).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import Image
from tqdm import tqdm

from .. import __version__
from ..geometry.camera import matrix_to_quaternion
from ..classes import palette
from .preset import SynthPreset
from .scene import generate_world, road_trajectory
from .sensors import RayCaster, camera_model, camera_to_lidar, lidar_directions, render_camera, scan_lidar

FRAME_PERIOD_S = 0.1  # 10 Hz, like RELLIS-3D's LiDAR


def frame_stem(index: int) -> str:
    stamp = 1_600_000_000 + index * FRAME_PERIOD_S
    return f"frame{index:06d}-{int(stamp)}_{int(round((stamp % 1) * 1000)):03d}"


def colour_lut() -> np.ndarray:
    """[256, 3] uint8: ontology id -> RELLIS-3D label colour."""
    lut = np.zeros((256, 3), np.uint8)
    for rgb, original in palette("rellis3d_colors").items():
        lut[original] = rgb
    return lut


def write_sequence_metadata(out: Path, preset: SynthPreset, poses: np.ndarray) -> None:
    camera = camera_model(preset.camera)
    (out / "camera_info.txt").write_text(f"{camera.fx:.6f} {camera.fy:.6f} {camera.cx:.6f} {camera.cy:.6f}\n")
    (out / "camera_distortion.txt").write_text(" ".join(f"{d:.6f}" for d in camera.distortion) + "\n")
    mount = camera_to_lidar(preset.camera)
    q, t = matrix_to_quaternion(mount[:3, :3]), mount[:3, 3]
    transforms = {"os1_cloud_node-pylon_camera_node": {
        "q": {"w": float(q[3]), "x": float(q[0]), "y": float(q[1]), "z": float(q[2])},
        "t": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])}}}
    (out / "transforms.yaml").write_text(yaml.safe_dump(transforms, sort_keys=False))
    # every digit: a log written from this folder carries the poses as quaternions, and maps from both agree to rounding
    np.savetxt(out / "poses.txt", poses[:, :3, :].reshape(len(poses), 12), fmt="%.17g")


def generate_sequence(preset: SynthPreset, out, *, device: str | None = "cpu", progress: bool = True) -> dict:
    """Render ``preset`` into the folder ``out`` (created; existing frame files are overwritten).
    Returns a summary with the counts and timings."""
    out = Path(out)
    started = time.perf_counter()
    world = generate_world(preset.world, preset.seed)
    poses = road_trajectory(world, preset.trajectory)
    caster = RayCaster(world.vertices, world.faces, device=device)
    world_s = time.perf_counter() - started
    folders = {name: out / name for name in ("os1_cloud_node_kitti_bin", "os1_cloud_node_semantickitti_label_id", "pylon_camera_node",
                                             "pylon_camera_node_label_color", "pylon_camera_node_label_id")}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    write_sequence_metadata(out, preset, poses)
    lut = colour_lut()
    beams = lidar_directions(preset.lidar)
    pixel_rays = camera_model(preset.camera).pixel_rays().reshape(-1, 3)
    lidar_rays = 0
    for index in tqdm(range(len(poses)), desc=f"synth {preset.name}", unit="frame", disable=not progress):
        rng = np.random.default_rng([preset.seed, index])
        scan = scan_lidar(caster, world, poses[index], preset.lidar, rng, beams)
        frame = render_camera(caster, world, poses[index], preset.camera, preset.appearance.domain, preset.appearance.noise_sigma, rng,
                              pixel_rays=pixel_rays)
        scan.points.tofile(folders["os1_cloud_node_kitti_bin"] / f"{index:06d}.bin")
        scan.original_id.tofile(folders["os1_cloud_node_semantickitti_label_id"] / f"{index:06d}.label")
        stem = frame_stem(index)
        Image.fromarray(frame.rgb).save(folders["pylon_camera_node"] / f"{stem}.jpg", quality=preset.camera.jpeg_quality)
        Image.fromarray(lut[frame.original_id]).save(folders["pylon_camera_node_label_color"] / f"{stem}.png")
        Image.fromarray(frame.original_id).save(folders["pylon_camera_node_label_id"] / f"{stem}.png")
        lidar_rays += len(scan.points)
    elapsed = time.perf_counter() - started
    summary = {
        "frames": len(poses), "triangles": int(len(world.faces)), "lidar_rays": int(lidar_rays),
        "world_seconds": round(world_s, 3), "seconds": round(elapsed, 3),
    }
    record = {"generator": "evsemmap_warp", "version": __version__, "preset": dataclasses.asdict(preset), "summary": summary}
    (out / "synth.yaml").write_text(yaml.safe_dump(record, sort_keys=False))
    return summary
