"""Lit meshes in the viewer: viser draws meshes (``--style boxes``, the terrain surface) with three.js's
MeshStandardMaterial under the client's ACES filmic tone mapping, and point clouds unlit and not
tone mapped. A mesh's color c (0..1, taken as linear reflectance) lit by an ambient light A and a
directional light D at angle t to the face's normal leaves the face with radiance c (A + D cos t) / pi,
which is tone mapped, ACES(x) = OUT . rrt(IN . x / 0.6), and sRGB-encoded. Under viser's default
lights (an environment map and two directional lights) the same colors come out pale: the boxes looked
washed out beside the points. ``configure_lighting`` sets one ambient and one directional light, and
``mesh_colors`` inverts the chain for faces that look up, so that their tops show the palette's color
(as closely as ACES can render it) while the sides, lit less, shade the boxes.
"""

from __future__ import annotations

import math
import threading

import numpy as np

AMBIENT_INTENSITY = 5.0
SUN_INTENSITY = 9.0
SUN_POSITION = (3.0, -4.0, 10.0)  # the directional light shines from here towards the scene origin
TOP_GAIN = (AMBIENT_INTENSITY + SUN_INTENSITY * SUN_POSITION[2] / math.hypot(*SUN_POSITION)) / math.pi
# three.js ACESFilmicToneMapping (column-major mat3 in GLSL, written here as row-major matrices acting on x)
_ACES_IN = np.array([[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]])
_ACES_OUT = np.array([[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]])
_RRT = (0.0245786, 0.000090537, 0.983729, 0.4329510, 0.238081)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB values 0..255 as linear light 0..1 (the standard sRGB transfer curve)."""
    s = np.asarray(rgb, np.float64) / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear light 0..1 as sRGB values 0..255 (the inverse of srgb_to_linear)."""
    v = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return 255.0 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def aces(radiance: np.ndarray) -> np.ndarray:
    """three.js's ACES filmic tone map of linear radiance [..., 3] (output linear, 0..1)."""
    a, b, c, d, e = _RRT
    v = (np.asarray(radiance, np.float64) / 0.6) @ _ACES_IN.T
    v = (v * (v + a) - b) / (v * (c * v + d) + e)
    return np.clip(v @ _ACES_OUT.T, 0.0, 1.0)


def aces_inverse(linear: np.ndarray) -> np.ndarray:
    """The radiance whose tone map is ``linear`` (clipped to >= 0 where ACES cannot reach the color)."""
    a, b, c, d, e = _RRT
    z = np.clip(np.asarray(linear, np.float64) @ np.linalg.inv(_ACES_OUT).T, 0.0, 0.999 / c)
    # rrt(v) = z  <=>  v^2 (1 - c z) + v (a - d z) - (b + e z) = 0, the root >= 0
    qa, qb, qc = 1.0 - c * z, a - d * z, -(b + e * z)
    v = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    return np.maximum(0.6 * (v @ np.linalg.inv(_ACES_IN).T), 0.0)


_MESH_COLOR_CACHE: dict[int, tuple[int, int, int]] = {}
_MESH_COLOR_LOCK = threading.Lock()  # GUI callbacks run on viser's threads


def _solve_mesh_colors(table: np.ndarray) -> np.ndarray:
    """[n, 3] sent colors (float 0..255) whose top faces render nearest to the sRGB colors ``table``."""
    target = table.astype(np.float64)
    levels = np.arange(256, dtype=np.float64)

    def error(candidates):  # [colors, n, 3] sent -> [colors, n] max channel error, ties broken by the squared error
        shown = linear_to_srgb(aces(candidates / 255.0 * TOP_GAIN))
        diff = np.abs(shown - target[:, None, :])
        return diff.max(axis=-1) + 1e-3 * (diff ** 2).sum(axis=-1)

    # the exact inverse where ACES reaches the color, or the best of a coarse grid; then, per channel in
    # turn, the value whose rendering is nearest (this also settles the colors ACES cannot reach exactly)
    exact = np.round(np.clip(aces_inverse(srgb_to_linear(table)) / TOP_GAIN, 0.0, 1.0) * 255.0)
    coarse = np.array([0, 2, 5, 10, 18, 30, 48, 75, 110, 160, 210, 255], np.float64)
    grid = np.stack(np.meshgrid(coarse, coarse, coarse, indexing="ij"), axis=-1).reshape(1, -1, 3)
    starts = np.concatenate([exact[:, None, :], np.repeat(grid, len(table), axis=0)], axis=1)
    sent = starts[np.arange(len(table)), np.argmin(error(starts), axis=1)]
    for _ in range(3):
        for channel in range(3):
            candidates = np.repeat(sent[:, None, :], 256, axis=1)
            candidates[:, :, channel] = levels
            sent[:, channel] = levels[np.argmin(error(candidates), axis=1)]
    return sent


def mesh_colors(rgb: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 instance colors that a mesh face looking up renders as ``rgb`` (sRGB) under
    ``configure_lighting`` (``rendered_top_color`` gives what it renders as). Solved once per distinct
    color (cached), 256 colors at a time."""
    rgb = np.asarray(rgb, np.uint8)
    flat = rgb.reshape(-1, 3)
    keys = (flat[:, 0].astype(np.int64) << 16) | (flat[:, 1].astype(np.int64) << 8) | flat[:, 2].astype(np.int64)
    unique, inverse = np.unique(keys, return_inverse=True)
    with _MESH_COLOR_LOCK:
        if len(_MESH_COLOR_CACHE) + len(unique) > 200_000:  # a bound on memory: color ramps of many values
            _MESH_COLOR_CACHE.clear()
        missing = np.array([k for k in unique.tolist() if k not in _MESH_COLOR_CACHE], np.int64)
        for start in range(0, len(missing), 256):
            chunk = missing[start:start + 256]
            table = np.stack([(chunk >> 16) & 255, (chunk >> 8) & 255, chunk & 255], axis=1).astype(np.uint8)
            for key, sent in zip(chunk.tolist(), _solve_mesh_colors(table).astype(np.uint8).tolist()):
                _MESH_COLOR_CACHE[key] = tuple(sent)
        solved = np.array([_MESH_COLOR_CACHE[k] for k in unique.tolist()], np.uint8).reshape(-1, 3)
    return solved[inverse.reshape(-1)].reshape(rgb.shape)


def rendered_top_color(sent: np.ndarray) -> np.ndarray:
    """What the browser shows for a face looking up with instance color ``sent`` (the forward model)."""
    return np.round(linear_to_srgb(aces(np.asarray(sent, np.float64) / 255.0 * TOP_GAIN))).astype(np.uint8)


def configure_lighting(scene) -> None:
    """One ambient and one directional light instead of viser's environment map and default lights."""
    scene.configure_environment_map(None)
    scene.configure_default_lights(enabled=False)
    scene.add_light_ambient("/lights/ambient", intensity=AMBIENT_INTENSITY)
    scene.add_light_directional("/lights/sun", intensity=SUN_INTENSITY, position=SUN_POSITION)
