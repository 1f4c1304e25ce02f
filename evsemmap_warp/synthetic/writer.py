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
import json
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import Image
from tqdm import tqdm

from .. import __version__
from ..geometry.camera import matrix_to_quaternion
from ..classes import palette, remap_ids
from ..data.log_writer import LOG_ROOT_FRAME
from ..data.sequences import FRAME_FILE, Rellis3DSequence
from ..frames import run_id
from .preset import SynthPreset
from .scene import concatenate_worlds, corridor_road, generate_world, poses_along_road, road_trajectory
from .sensors import RayCaster, camera_model, camera_to_lidar, lidar_directions, render_camera, scan_lidar

FRAME_PERIOD_S = 0.1  # 10 Hz, like RELLIS-3D's LiDAR


def frame_stem(index: int) -> str:
    """The file stem of frame ``index`` as RELLIS-3D names its camera files: ``frameNNNNNN-<sec>_<msec>``,
    from a fixed start time and frame period."""
    stamp = 1_600_000_000 + index * FRAME_PERIOD_S
    return f"frame{index:06d}-{int(stamp)}_{int(round((stamp % 1) * 1000)):03d}"


def color_lut() -> np.ndarray:
    """[256, 3] uint8: ontology id -> RELLIS-3D label color."""
    lut = np.zeros((256, 3), np.uint8)
    for rgb, original in palette("rellis3d_colors").items():
        lut[original] = rgb
    return lut


def write_sequence_metadata(out: Path, preset: SynthPreset, poses: np.ndarray) -> None:
    """Write a sequence's calibration and poses beside its frames: ``camera_info.txt``,
    ``camera_distortion.txt``, ``transforms.yaml`` (the camera's LiDAR mount), ``poses.txt`` (every digit
    of the LiDAR poses [F, 4, 4]) and ``frame.yaml`` (the poses' frame name)."""
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
    # the poses' frame, by the name the logs written from this folder give their TF root; an odom frame is
    # one run's, and the run is the preset's drive (its halves, copied with this file, stay one run)
    run = run_id(json.dumps(dataclasses.asdict(preset), sort_keys=True))
    (out / FRAME_FILE).write_text(yaml.safe_dump({"name": LOG_ROOT_FRAME, "run": run}))


class _CorridorWorld:
    """The tiles of a corridor world within sensor range of a pose, built when the drive reaches
    them and dropped behind it: memory stays that of three tiles for a drive of any length."""

    def __init__(self, preset: SynthPreset, device):
        self.preset, self.device = preset, device
        self.window: tuple[int, ...] = ()
        self.world = self.caster = None
        reach = max(preset.lidar.max_range_m, 60.0)  # the camera sees what the LiDAR sees, and the sky beyond
        self.tiles_each_side = int(np.ceil(reach / preset.world.size_m))

    def at(self, pose: np.ndarray):
        size, tiles = self.preset.world.size_m, self.preset.world.corridor_tiles
        center = int(np.floor((pose[0, 3] + size / 2) / size))
        window = tuple(t for t in range(center - self.tiles_each_side, center + self.tiles_each_side + 1) if 0 <= t < tiles)
        if window != self.window:
            parts = [generate_world(self.preset.world, self.preset.seed, tile=t) for t in window]
            self.world = concatenate_worlds(parts)
            self.caster = RayCaster(self.world.vertices, self.world.faces, device=self.device)
            self.window = window
        return self.world, self.caster


def sequence_poses(preset: SynthPreset) -> np.ndarray:
    """The drive's LiDAR poses: along the road of the square world, or of the whole corridor."""
    if preset.world.corridor_tiles:
        size, tiles = preset.world.size_m, preset.world.corridor_tiles
        road = corridor_road(preset.world, preset.seed, tiles)
        return poses_along_road(road, -size / 2 + preset.trajectory.margin_m, (tiles - 0.5) * size - preset.trajectory.margin_m,
                                preset.trajectory, f"a corridor of {tiles} x {size} m")
    return road_trajectory(generate_world(preset.world, preset.seed), preset.trajectory)


def generate_sequence(preset: SynthPreset, out, *, device: str | None = "cpu", progress: bool = True, camera: bool = True) -> dict:
    """Render ``preset`` into the folder ``out`` (created; existing frame files are overwritten).
    ``camera=False`` writes the LiDAR scans, their labels and the poses only (no images: fast).
    Returns a summary with the counts and timings."""
    out = Path(out)
    started = time.perf_counter()
    corridor = _CorridorWorld(preset, device) if preset.world.corridor_tiles else None
    if corridor is None:
        world = generate_world(preset.world, preset.seed)
        poses = road_trajectory(world, preset.trajectory)
        caster = RayCaster(world.vertices, world.faces, device=device)
    else:
        poses = sequence_poses(preset)
    world_s = time.perf_counter() - started
    names = ["os1_cloud_node_kitti_bin", "os1_cloud_node_semantickitti_label_id"]
    if camera:
        names += ["pylon_camera_node", "pylon_camera_node_label_color", "pylon_camera_node_label_id"]
    folders = {name: out / name for name in names}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    write_sequence_metadata(out, preset, poses)
    lut = color_lut()
    beams = lidar_directions(preset.lidar)
    pixel_rays = camera_model(preset.camera).pixel_rays().reshape(-1, 3) if camera else None
    lidar_rays = 0
    triangles = 0
    for index in tqdm(range(len(poses)), desc=f"synth {preset.name}", unit="frame", disable=not progress):
        if corridor is not None:
            world, caster = corridor.at(poses[index])
        triangles = max(triangles, len(world.faces))
        rng = np.random.default_rng([preset.seed, index])
        scan = scan_lidar(caster, world, poses[index], preset.lidar, rng, beams)
        scan.points.tofile(folders["os1_cloud_node_kitti_bin"] / f"{index:06d}.bin")
        scan.original_id.tofile(folders["os1_cloud_node_semantickitti_label_id"] / f"{index:06d}.label")
        lidar_rays += len(scan.points)
        if not camera:
            continue
        frame = render_camera(caster, world, poses[index], preset.camera, preset.appearance.domain, preset.appearance.noise_sigma, rng,
                              pixel_rays=pixel_rays)
        stem = frame_stem(index)
        Image.fromarray(frame.rgb).save(folders["pylon_camera_node"] / f"{stem}.jpg", quality=preset.camera.jpeg_quality)
        Image.fromarray(lut[frame.original_id]).save(folders["pylon_camera_node_label_color"] / f"{stem}.png")
        Image.fromarray(frame.original_id).save(folders["pylon_camera_node_label_id"] / f"{stem}.png")
    elapsed = time.perf_counter() - started
    drive = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0
    summary = {
        "frames": len(poses), "triangles": int(triangles), "lidar_rays": int(lidar_rays), "drive_m": round(drive, 1),
        "camera": camera, "world_seconds": round(world_s, 3), "seconds": round(elapsed, 3),
    }
    record = {"generator": "evsemmap_warp", "version": __version__, "preset": dataclasses.asdict(preset), "summary": summary}
    (out / "synth.yaml").write_text(yaml.safe_dump(record, sort_keys=False))
    return summary


def write_stand_in_alpha(sequence, folder, *, unsure_evidence: float = 11.0, sure_evidence: float = 201.0) -> Path:
    """Alpha files that stand in for a network's (``evsemmap infer``'s layout: ``FOLDER/<image stem>.npy``,
    float16 [9, H/2, W/2] at every second pixel) for a synthetic ``sequence`` folder: every pixel's evidence
    on its true remap-v3 class, ``unsure_evidence`` on the left half of each image and ``sure_evidence`` on
    the right, so that the uncertainty a map or a scan shows has something to show (with the defaults, u = K/S is
9/208 on the right, sure enough for the rellis3d preset's kernel length to reach voxels, and 0.5 on the left,
too unsure to update anything). Returns ``folder``."""
    images, folder = Rellis3DSequence(sequence), Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for frame in images.frames:
        labels = remap_ids(images.read_label_ids(frame), "t")[::2, ::2]
        alpha = np.ones((9, *labels.shape), np.float16)
        evidence = np.where(np.arange(labels.shape[1]) < labels.shape[1] // 2, unsure_evidence, sure_evidence)
        np.put_along_axis(alpha, labels[None], np.broadcast_to(evidence, labels.shape)[None].astype(np.float16), axis=0)
        np.save(folder / f"{frame.image.stem}.npy", alpha)
    return folder
