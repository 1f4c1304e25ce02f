"""A procedural off-road world: one triangle mesh (trimesh) with a material, and through it a RELLIS-3D
ontology id, per face.

Rolling terrain carries a road, paved except for a gravel stretch (the trajectory follows it), an
unpaved trail, dirt and mud patches and puddles on grass; trees, bushes, rocks, poles, barrels,
vehicles and barriers stand on it.
Sky is whatever a ray misses. Everything is drawn from one seeded generator, so a preset and a seed
give the same world on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..classes import original_to_v3_table
from .noise import value_noise
from .preset import TrajectoryParams, WorldParams


@dataclass(frozen=True)
class Material:
    """A surface of the synthetic world: the RELLIS-3D ontology id its points and pixels are labelled with,
    its look (base color class, tint, surface pattern), its LiDAR reflectivity and whether it is ground."""

    name: str
    original_id: int  # RELLIS-3D ontology id written to the label files (id 11 "gravel" is RUGD's)
    color_class: str  # which appearance-domain color it starts from
    tint: tuple[float, float, float]  # multiplies that color
    texture_scale_m: float  # feature size of its surface pattern
    texture_amplitude: float  # relative brightness variation of that pattern
    reflectivity: float  # LiDAR intensity at normal incidence
    ground: bool = False  # part of the terrain surface


MATERIALS = (
    Material("grass", 3, "grass", (1.0, 1.0, 1.0), 0.15, 0.35, 0.45, ground=True),
    Material("asphalt", 10, "paved", (1.0, 1.0, 1.0), 0.4, 0.10, 0.20, ground=True),
    Material("gravel", 11, "unpaved", (1.0, 1.0, 1.0), 0.08, 0.30, 0.35, ground=True),
    Material("dirt", 1, "dirt", (1.0, 1.0, 1.0), 0.3, 0.25, 0.30, ground=True),
    Material("mud", 33, "dirt", (0.75, 0.72, 0.7), 0.5, 0.20, 0.25, ground=True),
    Material("puddle", 31, "water", (1.0, 1.0, 1.0), 1.0, 0.08, 0.05, ground=True),
    Material("trunk", 4, "dirt", (0.8, 0.75, 0.7), 0.1, 0.30, 0.40),
    Material("canopy", 4, "vegetation", (1.0, 1.0, 1.0), 0.25, 0.45, 0.50),
    Material("bush", 19, "vegetation", (1.25, 1.2, 1.1), 0.15, 0.40, 0.50),
    Material("rock", 9, "void", (1.25, 1.25, 1.25), 0.2, 0.30, 0.40),
    Material("pole", 5, "object", (0.8, 0.8, 0.8), 1.0, 0.05, 0.60),
    Material("barrel", 9, "object", (1.0, 1.0, 1.0), 1.0, 0.05, 0.70),
    Material("vehicle", 8, "object", (1.0, 1.0, 1.0), 2.0, 0.05, 0.80),
    Material("barrier", 27, "void", (1.6, 1.5, 1.3), 1.0, 0.10, 0.60),
)
MATERIAL_INDEX = {m.name: i for i, m in enumerate(MATERIALS)}
MATERIAL_ORIGINAL_IDS = np.array([m.original_id for m in MATERIALS], np.uint8)


@dataclass
class World:
    """A rendered world as one triangle mesh: vertices [V, 3] (m, float32), faces [F, 3], each face's
    material, the road's center line [M, 3], and the parameters and seed it came from."""

    vertices: np.ndarray  # [V, 3] float32, metres
    faces: np.ndarray  # [F, 3] int32
    face_material: np.ndarray  # [F] int16 index into MATERIALS
    road: np.ndarray  # [M, 3] center line of the paved road, sampled densely
    params: WorldParams
    seed: int

    @property
    def face_original_id(self) -> np.ndarray:
        """[F] the RELLIS-3D ontology id of each face."""
        return MATERIAL_ORIGINAL_IDS[self.face_material]

    @property
    def face_v3(self) -> np.ndarray:
        """[F] the 9-class (remap v3) id of each face."""
        return original_to_v3_table()[self.face_original_id].astype(np.int16)

    def mesh(self) -> trimesh.Trimesh:
        """The world as a trimesh (for export and inspection) with the per-face ids attached."""
        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        mesh.face_attributes["material"] = self.face_material
        mesh.face_attributes["original_id"] = self.face_original_id
        return mesh


class _Terrain:
    """Height field with a road flattened into it; heights of any (x, y) by bilinear lookup.

    The hills and the road are drawn from ``shape_rng``, everything else from ``rng``; they are one
    generator for a single world. A corridor world (tiles along x) shares ``shape_rng``'s draws
    between its tiles and shifts each tile by ``x_offset``: hills, noise and road are functions of
    world coordinates, so neighbouring tiles meet without a seam."""

    def __init__(self, params: WorldParams, rng: np.random.Generator, shape_rng: np.random.Generator | None = None, x_offset: float = 0.0):
        shape_rng = rng if shape_rng is None else shape_rng
        self.params = params
        half = params.size_m / 2
        self.n = int(round(params.size_m / params.terrain_cell_m))
        self.axis = np.linspace(-half, half, self.n + 1)  # y
        self.x_axis = x_offset + self.axis
        x, y = np.meshgrid(self.x_axis, self.axis, indexing="ij")
        height = np.zeros_like(x)
        for _ in range(4):  # rolling hills: a few random plane waves, 25-70 m long
            direction = shape_rng.normal(size=2)
            direction /= np.linalg.norm(direction)
            wavelength = shape_rng.uniform(25, 70)
            height += params.hill_amplitude_m / 2 * np.sin(2 * np.pi * (x * direction[0] + y * direction[1]) / wavelength + shape_rng.uniform(0, 2 * np.pi))
        height += 0.15 * (value_noise(np.stack([x, y], -1), 3.0, int(shape_rng.integers(1 << 30))) - 0.5)
        self.road_amplitude = shape_rng.uniform(0.08, 0.15) * params.size_m
        self.road_wavelength = shape_rng.uniform(0.7, 1.1) * params.size_m
        self.road_phase = shape_rng.uniform(0, 2 * np.pi)
        self.x_offset = x_offset
        # The road is graded: near it the ground blends into the height of the road's center line.
        road_height = self._grid_height(height, x, self.road_y(x))
        blend = np.clip((np.abs(y - self.road_y(x)) - params.road_half_width_m - 0.5) / 4.0, 0, 1)
        self.height = road_height + (height - road_height) * blend
        self.trail_x0 = x_offset + rng.uniform(-0.25, 0.25) * params.size_m
        self.trail_amplitude = rng.uniform(0.05, 0.12) * params.size_m
        self.trail_phase = rng.uniform(0, 2 * np.pi)

    def road_y(self, x):
        return self.road_amplitude * np.sin(2 * np.pi * x / self.road_wavelength + self.road_phase)

    def trail_x(self, y):
        return self.trail_x0 + self.trail_amplitude * np.sin(2 * np.pi * y / (0.8 * self.params.size_m) + self.trail_phase)

    def _grid_height(self, height, x, y):
        c = self.params.terrain_cell_m
        fx = np.clip((x - self.x_axis[0]) / c, 0, self.n - 1e-6)
        fy = np.clip((y - self.axis[0]) / c, 0, self.n - 1e-6)
        i, j = fx.astype(int), fy.astype(int)
        ax, ay = fx - i, fy - j
        return (height[i, j] * (1 - ax) * (1 - ay) + height[i + 1, j] * ax * (1 - ay)
                + height[i, j + 1] * (1 - ax) * ay + height[i + 1, j + 1] * ax * ay)

    def height_at(self, x, y):
        return self._grid_height(self.height, np.asarray(x, float), np.asarray(y, float))


def _road_distance(terrain: _Terrain, x, y):
    """Distance to the road center line, approximated by the vertical offset scaled by the slope."""
    slope = terrain.road_amplitude * 2 * np.pi / terrain.road_wavelength * np.cos(2 * np.pi * x / terrain.road_wavelength + terrain.road_phase)
    return np.abs(y - terrain.road_y(x)) / np.sqrt(1 + slope**2)


def _trail_distance(terrain: _Terrain, x, y):
    size = 0.8 * terrain.params.size_m
    slope = terrain.trail_amplitude * 2 * np.pi / size * np.cos(2 * np.pi * y / size + terrain.trail_phase)
    return np.abs(x - terrain.trail_x(y)) / np.sqrt(1 + slope**2)


def _terrain_mesh(terrain: _Terrain, params: WorldParams, rng: np.random.Generator, seed: int, tile: int | None = None):
    n = terrain.n
    x, y = np.meshgrid(terrain.x_axis, terrain.axis, indexing="ij")
    height = terrain.height.copy()
    # Puddles: shallow flat discs on the trail and beside the road, where water gathers.
    puddles = []
    for k in range(params.puddles):
        if k % 2 == 0:
            py = rng.uniform(-0.4, 0.4) * params.size_m
            px = terrain.trail_x(py) + rng.uniform(-0.5, 0.5) * params.trail_half_width_m
        else:
            px = terrain.x_offset + rng.uniform(-0.4, 0.4) * params.size_m
            py = terrain.road_y(px) + rng.choice([-1, 1]) * (params.road_half_width_m + rng.uniform(0.8, 2.5))
        radius = rng.uniform(0.8, 2.2)
        inside = (x - px) ** 2 + (y - py) ** 2 < (radius + params.terrain_cell_m) ** 2
        if inside.any():
            height[inside] = height[inside].min() - 0.03
        puddles.append((px, py, radius))
    vertices = np.stack([x, y, height], -1).reshape(-1, 3)
    index = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])  # counter-clockwise from above: normals up
    center = vertices[faces].mean(axis=1)
    cx, cy = center[:, 0], center[:, 1]
    material = np.full(len(faces), MATERIAL_INDEX["grass"], np.int16)
    patches = value_noise(center[:, :2], 6.0, seed + 11)
    material[patches > np.quantile(patches, 1 - params.dirt_fraction)] = MATERIAL_INDEX["dirt"]
    trail_distance = _trail_distance(terrain, cx, cy)
    material[trail_distance < params.trail_half_width_m] = MATERIAL_INDEX["gravel"]
    muddy = (trail_distance >= params.trail_half_width_m) & (trail_distance < params.trail_half_width_m + 0.6)
    material[muddy & (value_noise(center[:, :2], 2.0, seed + 12) > 0.6)] = MATERIAL_INDEX["mud"]
    road = _road_distance(terrain, cx, cy) < params.road_half_width_m
    material[road] = MATERIAL_INDEX["asphalt"]
    # Off-road tracks change surface: one stretch of the road is gravel (its own generator, so that the
    # rest of the world does not depend on it).
    stretch = params.gravel_road_fraction * params.size_m
    stretch_rng = np.random.default_rng(seed + 13 if tile is None else [seed + 13, tile])
    start = terrain.x_offset + stretch_rng.uniform(-params.size_m / 2, params.size_m / 2 - stretch) if stretch else 0.0
    material[road & (cx >= start) & (cx < start + stretch)] = MATERIAL_INDEX["gravel"]
    for px, py, radius in puddles:
        material[(cx - px) ** 2 + (cy - py) ** 2 < radius**2] = MATERIAL_INDEX["puddle"]
    return vertices, faces, material


def _place(terrain, rng, count, min_road_m, size_m):
    """``count`` ground positions at least ``min_road_m`` from the road's center line."""
    out = []
    for _ in range(20 * max(count, 1)):
        if len(out) >= count:
            break
        x, y = rng.uniform(-0.48, 0.48, 2) * size_m
        x = terrain.x_offset + x
        if _road_distance(terrain, x, y) >= min_road_m:
            out.append((x, y))
    return out


def _roadside(terrain, rng, count, params, offset):
    out = []
    for _ in range(count):
        x = terrain.x_offset + rng.uniform(-0.45, 0.45) * params.size_m
        side = rng.choice([-1, 1])
        out.append((x, terrain.road_y(x) + side * (params.road_half_width_m + offset + rng.uniform(0, 1.5))))
    return out


def _jitter(mesh: trimesh.Trimesh, rng, amount):
    mesh.vertices = mesh.vertices * (1 + rng.uniform(-amount, amount, size=(len(mesh.vertices), 1)))
    return mesh


def generate_world(params: WorldParams, seed: int, *, tile: int | None = None) -> World:
    """The world of ``seed``; with ``tile``, the tile-th square of the corridor world of ``seed``
    (centered at x = tile * size_m; its hills and road continue into its neighbours, its objects,
    puddles, trail and patches are its own), so a drive of any length needs only the tiles in view."""
    rng = np.random.default_rng(seed if tile is None else [seed, tile])
    terrain = _corridor_terrain(params, seed, tile, rng) if tile is not None else _Terrain(params, rng)
    vertices, faces, material = _terrain_mesh(terrain, params, rng, seed, tile)
    parts: list[tuple[trimesh.Trimesh, str]] = []
    hectares = params.size_m**2 / 10_000
    road_clear = params.road_half_width_m + 4

    def put(mesh, name, x, y, sink=0.0, yaw=None):
        if yaw is None:
            yaw = rng.uniform(0, 2 * np.pi)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(yaw, (0, 0, 1)))
        mesh.apply_translation((x, y, float(terrain.height_at(x, y)) - sink))
        parts.append((mesh, name))

    for x, y in _place(terrain, rng, int(params.trees_per_hectare * hectares), road_clear, params.size_m):
        height, radius = rng.uniform(2.0, 4.5), rng.uniform(1.2, 2.8)
        trunk = trimesh.creation.cylinder(radius=rng.uniform(0.12, 0.3), height=height + 0.5, sections=8)
        trunk.apply_translation((0, 0, (height + 0.5) / 2))
        put(trunk, "trunk", x, y, sink=0.3)
        canopy = _jitter(trimesh.creation.icosphere(subdivisions=1, radius=radius), rng, 0.2)
        canopy.apply_scale((1, 1, rng.uniform(0.8, 1.4)))
        canopy.apply_translation((0, 0, height + radius * 0.6))
        put(canopy, "canopy", x, y)
    for x, y in _place(terrain, rng, int(params.bushes_per_hectare * hectares), params.road_half_width_m + 1.5, params.size_m):
        bush = _jitter(trimesh.creation.icosphere(subdivisions=1, radius=rng.uniform(0.4, 1.1)), rng, 0.25)
        bush.apply_scale((1, 1, 0.7))
        put(bush, "bush", x, y, sink=0.2)
    for x, y in _place(terrain, rng, int(params.rocks_per_hectare * hectares), params.road_half_width_m + 0.5, params.size_m):
        rock = _jitter(trimesh.creation.icosphere(subdivisions=1, radius=rng.uniform(0.25, 0.8)), rng, 0.3)
        rock.apply_scale((1, 1, 0.6))
        put(rock, "rock", x, y, sink=0.15)
    for x, y in _roadside(terrain, rng, params.poles, params, 0.5):
        pole = trimesh.creation.cylinder(radius=0.08, height=3.0, sections=8)
        pole.apply_translation((0, 0, 1.5))
        put(pole, "pole", x, y, sink=0.1)
    for x, y in _roadside(terrain, rng, params.barrels, params, 0.3):
        barrel = trimesh.creation.cylinder(radius=0.3, height=0.9, sections=12)
        barrel.apply_translation((0, 0, 0.45))
        put(barrel, "barrel", x, y, sink=0.05)
    for x, y in _roadside(terrain, rng, params.vehicles, params, 1.2):
        yaw = np.arctan(terrain.road_amplitude * 2 * np.pi / terrain.road_wavelength
                        * np.cos(2 * np.pi * x / terrain.road_wavelength + terrain.road_phase))
        body = trimesh.creation.box((4.3, 1.8, 0.9))
        body.apply_translation((0, 0, 0.75))
        cabin = trimesh.creation.box((2.2, 1.6, 0.7))
        cabin.apply_translation((-0.3, 0, 1.55))
        put(trimesh.util.concatenate([body, cabin]), "vehicle", x, y, sink=0.05, yaw=yaw)
    for x, y in _roadside(terrain, rng, params.barriers, params, 0.6):
        barrier = trimesh.creation.box((2.0, 0.4, 0.9))
        barrier.apply_translation((0, 0, 0.45))
        put(barrier, "barrier", x, y, sink=0.05)

    all_vertices, all_faces, all_material = [vertices], [faces], [material]
    offset = len(vertices)
    for mesh, name in parts:
        all_vertices.append(np.asarray(mesh.vertices))
        all_faces.append(np.asarray(mesh.faces) + offset)
        all_material.append(np.full(len(mesh.faces), MATERIAL_INDEX[name], np.int16))
        offset += len(mesh.vertices)
    road_x = terrain.x_offset + np.linspace(-params.size_m / 2, params.size_m / 2, int(params.size_m * 4) + 1)
    road_y = terrain.road_y(road_x)
    road = np.stack([road_x, road_y, terrain.height_at(road_x, road_y)], 1)
    return World(
        vertices=np.concatenate(all_vertices).astype(np.float32),
        faces=np.concatenate(all_faces).astype(np.int32),
        face_material=np.concatenate(all_material),
        road=road,
        params=params,
        seed=seed,
    )


def concatenate_worlds(worlds: list[World]) -> World:
    """Several worlds (a corridor's tiles) as one mesh, with the first one's parameters."""
    offsets = np.cumsum([0] + [len(w.vertices) for w in worlds[:-1]])
    return World(
        vertices=np.concatenate([w.vertices for w in worlds]),
        faces=np.concatenate([w.faces + o for w, o in zip(worlds, offsets)]).astype(np.int32),
        face_material=np.concatenate([w.face_material for w in worlds]),
        road=np.concatenate([w.road for w in worlds]),
        params=worlds[0].params,
        seed=worlds[0].seed,
    )


def _corridor_terrain(params: WorldParams, seed: int, tile: int, rng: np.random.Generator) -> _Terrain:
    return _Terrain(params, rng, shape_rng=np.random.default_rng(seed), x_offset=tile * params.size_m)


def corridor_road(params: WorldParams, seed: int, tiles: int) -> np.ndarray:
    """[M, 3] the road's center line through a corridor world of ``tiles`` tiles (terrain only: no
    tile's objects are built)."""
    parts = []
    for tile in range(tiles):
        terrain = _corridor_terrain(params, seed, tile, np.random.default_rng([seed, tile]))
        x = terrain.x_offset + np.linspace(-params.size_m / 2, params.size_m / 2, int(params.size_m * 4) + 1)
        y = terrain.road_y(x)
        parts.append(np.stack([x, y, terrain.height_at(x, y)], 1)[(1 if tile else 0):])  # seam points once
    return np.concatenate(parts)


def road_trajectory(world: World, params: TrajectoryParams) -> np.ndarray:
    """[F, 4, 4] LiDAR poses (LiDAR -> world) every ``spacing_m`` along the road, x forward along it,
    z up, ``sensor_height_m`` above the road; fewer than ``frames`` if the road is too short."""
    half = world.params.size_m / 2 - params.margin_m
    return poses_along_road(world.road, -half, half, params, f"a {world.params.size_m} m world")


def poses_along_road(road: np.ndarray, x_min: float, x_max: float, params: TrajectoryParams, where: str) -> np.ndarray:
    """The poses of ``road_trajectory`` along any road polyline, between x_min and x_max."""
    step = np.linalg.norm(np.diff(road[:, :2], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    usable = (road[:, 0] > x_min) & (road[:, 0] < x_max)
    if not usable.any():
        raise ValueError(f"the road has no usable stretch inside {where} with margin {params.margin_m} m")
    start, end = arc[usable][0], arc[usable][-1]
    stations = start + params.spacing_m * np.arange(params.frames)
    stations = stations[stations <= end]
    if len(stations) == 0:
        raise ValueError(f"the road has no usable stretch inside {where} with margin {params.margin_m} m")
    poses = np.zeros((len(stations), 4, 4))
    for n, s in enumerate(stations):
        position = np.array([np.interp(s, arc, road[:, k]) for k in range(3)])
        ahead = np.array([np.interp(s + 1.0, arc, road[:, k]) for k in range(2)])
        heading = np.arctan2(ahead[1] - position[1], ahead[0] - position[0])
        c, si = np.cos(heading), np.sin(heading)
        poses[n, :3, :3] = [[c, -si, 0], [si, c, 0], [0, 0, 1]]
        poses[n, :3, 3] = position + (0, 0, params.sensor_height_m)
        poses[n, 3, 3] = 1
    return poses
