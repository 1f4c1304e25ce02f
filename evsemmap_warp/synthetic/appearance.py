"""How the synthetic world looks to the camera: per-class colors, surface patterns, sun and sky light,
cast shadows, distance haze and sensor noise, under named appearance domains.

A domain (season, time of day, palette) changes colors and light but not geometry or labels, so a
network trained in one domain meets the same scene looking different in another: the paper's
"unseen environment" experiment, reproducible.
"""

from __future__ import annotations

import numpy as np

from .noise import value_noise

# Per-class base colors (by v3 class name), the sun's elevation and strength, sky colors, haze.
DOMAINS = {
    "summer": {"sky": (150, 190, 235), "vegetation": (40, 100, 35), "grass": (95, 160, 60), "dirt": (120, 90, 60),
               "paved": (110, 110, 115), "unpaved": (170, 150, 120), "water": (70, 90, 110), "object": (200, 60, 40),
               "void": (90, 80, 80), "light": 1.0,
               "sun_elevation_deg": 55.0, "sun_azimuth_deg": 30.0, "sky_zenith": (70, 120, 205), "haze_m": 400.0},
    "autumn": {"sky": (175, 185, 200), "vegetation": (150, 90, 30), "grass": (165, 145, 70), "dirt": (110, 80, 55),
               "paved": (95, 95, 100), "unpaved": (160, 135, 105), "water": (80, 85, 90), "object": (60, 90, 200),
               "void": (80, 70, 75), "light": 0.9,
               "sun_elevation_deg": 30.0, "sun_azimuth_deg": 120.0, "sky_zenith": (120, 135, 165), "haze_m": 180.0},
    "dusk": {"sky": (230, 150, 110), "vegetation": (25, 50, 30), "grass": (60, 90, 45), "dirt": (85, 60, 45),
             "paved": (70, 70, 80), "unpaved": (120, 100, 85), "water": (50, 55, 75), "object": (170, 50, 40),
             "void": (60, 55, 60), "light": 0.6,
             "sun_elevation_deg": 6.0, "sun_azimuth_deg": 250.0, "sky_zenith": (60, 60, 110), "haze_m": 250.0},
}
AMBIENT = 0.35  # share of light that reaches shadowed and back-facing surfaces


def sun_direction(domain: str) -> np.ndarray:
    """Unit vector towards the sun, world frame (z up)."""
    style = DOMAINS[domain]
    elevation, azimuth = np.radians(style["sun_elevation_deg"]), np.radians(style["sun_azimuth_deg"])
    return np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])


def sky_color(domain: str, directions: np.ndarray) -> np.ndarray:
    """[N, 3] float sky radiance for ray ``directions`` [N, 3]: horizon color blending to the zenith."""
    style = DOMAINS[domain]
    t = np.clip(directions[:, 2], 0, 1)[:, None] ** 0.6
    return (np.array(style["sky"], float) * (1 - t) + np.array(style["sky_zenith"], float) * t) * style["light"]


def shade(
    domain: str,
    materials,
    face_material: np.ndarray,
    hit_points: np.ndarray,
    normals: np.ndarray,
    directions: np.ndarray,
    distances: np.ndarray,
    lit: np.ndarray,
    face_index: np.ndarray,
    seed: int,
) -> np.ndarray:
    """[N, 3] float radiance (0-255 scale) of N surface hits.

    ``face_material`` [N] indexes ``materials`` (scene.MATERIALS); ``lit`` [N] bool says whether the
    sun reaches the point; ``face_index`` [N] gives each object part a stable color variation.
    """
    style = DOMAINS[domain]
    base = np.array([np.array(style[m.color_class], float) * m.tint for m in materials])
    scale = np.array([m.texture_scale_m for m in materials])
    amplitude = np.array([m.texture_amplitude for m in materials])
    color = base[face_material]
    # Surface pattern in world coordinates (so it stays put as the camera moves): two octaves.
    coords = hit_points[:, :2] + hit_points[:, 2:3] * 0.7  # vertical faces still vary with height
    pattern = 0.65 * value_noise(coords / scale[face_material, None], 1.0, seed) + 0.35 * value_noise(coords / scale[face_material, None], 0.37, seed + 1)
    color = color * (1 + amplitude[face_material, None] * (pattern[:, None] - 0.5) * 2)
    # Objects and plants differ a little from each other (by face group); ground does not.
    varies = np.array([not m.ground for m in materials])[face_material]
    variation = ((face_index.astype(np.int64) // 64 * 2654435761) % 1000) / 1000.0
    color = color * np.where(varies, 0.9 + 0.2 * variation, 1.0)[:, None]
    facing = np.where((normals * directions).sum(1, keepdims=True) > 0, -normals, normals)
    diffuse = np.clip(facing @ sun_direction(domain), 0, 1) * lit
    light = (AMBIENT + (1 - AMBIENT) * diffuse)[:, None] * style["light"]
    radiance = color * light
    haze = 1 - np.exp(-np.asarray(distances, float) / style["haze_m"])
    return radiance * (1 - haze[:, None]) + np.array(style["sky"], float) * style["light"] * haze[:, None]


def add_sensor_noise(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Float image -> uint8 with Gaussian read noise of ``sigma`` grey levels."""
    noisy = image + rng.normal(0, sigma, image.shape) if sigma > 0 else image
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)
