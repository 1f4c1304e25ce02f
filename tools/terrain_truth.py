"""Terrain layers against the synthetic world's truth (docs/terrain.md, "Checked against ground truth").

Renders a synthetic drive (LiDAR only), maps it with ``ebs`` from its per-point labels as ``evsemmap
map`` does, computes the layers, and compares them with what the world knows, per cell center:

- true terrain height and surface class: a ray straight down onto the terrain's faces only;
- true obstacles: a ray straight down onto the whole world hitting a non-ground face (trunk, canopy,
  bush, rock, pole, barrel, vehicle, barrier) less than the layers' clearance above the terrain.

Reported: elevation error (layer - truth) in the cells with a layer elevation (cells the LiDAR saw):
median, 95th percentile of |error| and the median signed error; surface-class accuracy there; the
class error rate by decile of the semantic variance, of the winning probability, of the uncommitted mass and of the
surface conflict; the road-vs-rest ROC AUC of the cost; the slope error against the true terrain's (the same plane
fit on the true heights); the median class cost and cost of well-observed cells (u < 0.5) by true class, for each
cost rule; and an A* plan on the traversability cost from
the drive's first pose to its last (8-connected, step cost = length x (BASE_COST + cost), lethal and
unknown cells impassable): its length, its share on the true road, and its clearance from the true
obstacles; the uncommitted mass u by true class, and the AUC were u charged at the cost of the unknown.
The minimum-evidence setting is swept (0 keeps every OCCUPIED voxel). ``before_after`` sets the
issue's starting point (rule ``expected``, the semantic variance as the uncertainty) beside the defaults (rule
``evidential``, the surface conflict). Figures go to
``--out`` (docs/terrain/PRESET/ by default), with ``truth.json``; the last line printed is that JSON.

    python tools/terrain_truth.py [--world default] [--work DIR] [--out docs/terrain/WORLD]
"""

from __future__ import annotations

import argparse
import heapq
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BASE_COST = 0.05  # per metre, so that a free path still prefers to be short
ROBOT_RADIUS_M = 0.4  # lethal cells are grown by this much for the plan (a costmap's inflation)


def _inflate(mask: np.ndarray, radius_cells: float) -> np.ndarray:
    """Cells within ``radius_cells`` of a set cell."""
    out = mask.copy()
    reach = int(math.floor(radius_cells))
    rows, columns = mask.shape
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr or dc) and math.hypot(dr, dc) <= radius_cells:
                shifted = np.zeros_like(mask)
                shifted[max(dr, 0):rows + min(dr, 0), max(dc, 0):columns + min(dc, 0)] = mask[max(-dr, 0):rows + min(-dr, 0),
                                                                                                   max(-dc, 0):columns + min(-dc, 0)]
                out |= shifted
    return out


SWEEP = (0.0, 0.2, 0.5)
# a cell is well observed when its support voxel's belief outweighs its uncommitted mass (u < 0.5: more evidence
# than the prior's weight); the support voxels are mostly kernel tails above the surface, so a stricter bound
# (u < 0.1: 81 units of evidence in 9 classes) leaves few road cells to judge
WELL_OBSERVED_U = 0.5


def _world_truth(world, grid, clearance_m: float, device: str):
    """Per cell (north-up): terrain height, ground v3 class (-1 off the world) and obstacle mask."""
    from evsemmap_warp.synthetic.scene import MATERIALS
    from evsemmap_warp.synthetic.sensors import RayCaster

    x, y = grid.cell_centers()
    xx, yy = np.meshgrid(x, y)
    top = 500.0
    origins = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, top)], 1)
    down = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    ground_material = np.array([m.ground for m in MATERIALS])[world.face_material]
    ground_faces = np.flatnonzero(ground_material)
    ground = RayCaster(world.vertices, world.faces[ground_faces], device=device)
    distance, face, _ = ground.cast(origins, down, 2 * top)
    hit = face >= 0
    height = np.where(hit, top - distance, np.nan)
    v3 = world.face_v3
    ground_class = np.where(hit, v3[ground_faces[np.clip(face, 0, None)]], -1)
    everything = RayCaster(world.vertices, world.faces, device=device)
    # obstacles below the clearance: cast down from just above it
    start = np.where(hit, height + clearance_m, top)
    distance_all, face_all, _ = everything.cast(np.stack([origins[:, 0], origins[:, 1], start], 1), down, 2 * top)
    obstacle = hit & (face_all >= 0) & ~ground_material[np.clip(face_all, 0, None)]
    shape = xx.shape
    return height.reshape(shape), ground_class.reshape(shape), obstacle.reshape(shape)


def _road_mask(world, grid) -> np.ndarray:
    """Cells within the road's half width of its center line (north-up)."""
    x, y = grid.cell_centers()
    xx, yy = np.meshgrid(x, y)
    road = world.road[:, :2]
    distance = np.full(xx.shape, np.inf)
    for a, b in zip(road[:-1], road[1:]):  # segment distances, vectorised over cells
        d = b - a
        t = np.clip(((xx - a[0]) * d[0] + (yy - a[1]) * d[1]) / max(d @ d, 1e-12), 0, 1)
        distance = np.minimum(distance, np.hypot(xx - a[0] - t * d[0], yy - a[1] - t * d[1]))
    return distance <= world.params.road_half_width_m


def astar(cost: np.ndarray, passable: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cell_m: float):
    """8-connected A* on a north-up grid; step cost = length (m) x (BASE_COST + cost of the cell entered).
    Returns the cells [(row, column), ...] from start to goal, or [] when none connects them."""
    rows, columns = cost.shape
    best = np.full(cost.shape, np.inf)
    came = np.full(cost.shape + (2,), -1, np.int64)
    best[start] = 0.0
    heuristic = lambda r, c: BASE_COST * cell_m * math.hypot(r - goal[0], c - goal[1])  # noqa: E731
    queue = [(heuristic(*start), 0.0, start)]
    moves = [(dr, dc, cell_m * math.hypot(dr, dc)) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    while queue:
        _, g, (r, c) = heapq.heappop(queue)
        if (r, c) == goal:
            break
        if g > best[r, c]:
            continue
        for dr, dc, length in moves:
            nr, nc = r + dr, c + dc
            if 0 <= nr < rows and 0 <= nc < columns and passable[nr, nc]:
                candidate = g + length * (BASE_COST + cost[nr, nc])
                if candidate < best[nr, nc]:
                    best[nr, nc] = candidate
                    came[nr, nc] = (r, c)
                    heapq.heappush(queue, (candidate + heuristic(nr, nc), candidate, (nr, nc)))
    if not np.isfinite(best[goal]):
        return []
    path = [goal]
    while path[-1] != start:
        path.append(tuple(came[path[-1]]))
    return path[::-1]


def _cell_of(grid, x: float, y: float) -> tuple[int, int]:
    column = int(math.floor((x - grid.x0_m) / grid.cell_m))
    row = int(math.floor((grid.y1_m - y) / grid.cell_m))
    return row, column


def _nearest(mask: np.ndarray, cell: tuple[int, int]) -> tuple[int, int]:
    rows, columns = np.nonzero(mask)
    k = int(np.argmin((rows - cell[0]) ** 2 + (columns - cell[1]) ** 2))
    return int(rows[k]), int(columns[k])


def _connected(passable: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    """The cells 8-connected to ``seed`` through passable cells (breadth first)."""
    from collections import deque

    reached = np.zeros(passable.shape, bool)
    reached[seed] = True
    queue = deque([seed])
    rows, columns = passable.shape
    while queue:
        r, c = queue.popleft()
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                nr, nc = r + dr, c + dc
                if 0 <= nr < rows and 0 <= nc < columns and passable[nr, nc] and not reached[nr, nc]:
                    reached[nr, nc] = True
                    queue.append((nr, nc))
    return reached


def _road_auc(bands, ground_class, classes) -> float:
    """ROC AUC of the traversability cost separating the cells whose true surface is road (paved, unpaved) from
    every other cell the layers know (lower cost: road), by ranks (Mann-Whitney; ties count half)."""
    cost = bands["traversability_cost"]
    known = np.isfinite(cost)
    road = np.isin(ground_class, [classes.index("paved"), classes.index("unpaved")])[known]
    score = -cost[known]
    order = np.argsort(score, kind="stable")
    ranks = np.empty(len(score))
    sorted_score = score[order]
    first = np.r_[0, np.flatnonzero(np.diff(sorted_score)) + 1]
    last = np.r_[first[1:], len(score)]
    for a, b in zip(first, last):  # average ranks of ties
        ranks[order[a:b]] = (a + b + 1) / 2
    positives, negatives = int(road.sum()), int((~road).sum())
    return round(float((ranks[road].sum() - positives * (positives + 1) / 2) / (positives * negatives)), 4)


def _uncommitted_reading(bands, ground_class, classes, unknown_cost: float) -> dict:
    """How much of the support voxels is uncommitted, by true class (10th, 50th, 90th percentiles of u), and the
    road-vs-rest AUC of the cost were u charged at ``unknown_cost`` (class cost (1 - u) c + u unknown_cost, the
    rest of the cost as it is): why the evidential rule leaves u out of the cost (docs/terrain.md §4)."""
    u = bands["surface_uncommitted"]
    costed = np.isfinite(bands["traversability_cost"]) & np.isfinite(u)
    quantiles = {classes[c]: [round(float(q), 3) for q in np.quantile(u[costed & (ground_class == c)], [0.1, 0.5, 0.9])]
                 for c in np.unique(ground_class[costed]) if c >= 0}
    charged = bands["traversability_cost"] + u * (unknown_cost - bands["class_cost_mean"])
    charged = np.where(bands["lethal"] > 0, 1.0, np.clip(charged, 0.0, 1.0))
    return {"uncommitted_quantiles_by_true_class": quantiles,
            "road_vs_rest_auc_charging_uncommitted": _road_auc(bands | {"traversability_cost": np.where(costed, charged, np.nan)},
                                                               ground_class, classes)}


def _slope_error(slope: np.ndarray, true_slope: np.ndarray) -> dict:
    both = np.isfinite(slope) & np.isfinite(true_slope)
    error = slope[both] - true_slope[both]
    return {"cells": int(both.sum()), "rms": round(float(np.sqrt(np.mean(error ** 2))), 3),
            "p95_abs": round(float(np.quantile(np.abs(error), 0.95)), 3), "median_signed": round(float(np.median(error)), 3)}


def class_error_by_decile(values: np.ndarray, correct: np.ndarray):
    """Class error rate per decile of ``values``, lowest first, and the decile edges. Cells of one value share
    their error rate (each counts the mean error of the cells tied with it), so a run of ties that straddles
    deciles gives them the same rate, whatever the cells' order: a band that is 0 in most cells (the surface
    conflict) would otherwise rank its errors by where the cells lie."""
    order = np.argsort(values, kind="stable")
    _, first, counts = np.unique(values[order], return_index=True, return_counts=True)
    shared = np.repeat(np.add.reduceat((~correct[order]).astype(np.float64), first) / counts, counts)
    decile = np.arange(len(values)) * 10 // len(values)
    rates = [round(float(shared[decile == d].mean()), 4) for d in range(10)]
    return rates, [float(f"{np.quantile(values, q):.3g}") for q in np.linspace(0, 1, 11)]


def _class_errors(bands, classified, correct) -> dict:
    """The surface class's error rate by decile of each reading of its uncertainty."""
    variance_rates, variance_edges = class_error_by_decile(bands["semantic_variance"][classified], correct)
    # the winning class's probability, least sure first: the same Dirichlet read another way
    probability_rates, probability_edges = class_error_by_decile(bands["surface_probability"][classified], correct)
    # subjective logic's two readings of the support voxel: the uncommitted mass u = K prior / S (how little was
    # seen) and the conflict 1 - e_label / sum e (how much of what was seen disagrees with the label)
    uncommitted_rates, uncommitted_edges = class_error_by_decile(bands["surface_uncommitted"][classified], correct)
    conflict_rates, conflict_edges = class_error_by_decile(bands["surface_conflict"][classified], correct)
    return {
        "class_error_rate_by_variance_decile": variance_rates, "variance_decile_edges": variance_edges,
        "class_error_rate_by_probability_decile": probability_rates, "probability_decile_edges": probability_edges,
        "class_error_rate_by_uncommitted_decile": uncommitted_rates, "uncommitted_decile_edges": uncommitted_edges,
        "class_error_rate_by_conflict_decile": conflict_rates, "conflict_decile_edges": conflict_edges,
    }


def _costs(bands, ground_class, road, classes, true_slope, well_observed) -> dict:
    """Slope on the flat road and the traversability cost by true class, on the road and off it."""
    result = {}
    road_class = np.isin(ground_class, [classes.index("paved"), classes.index("unpaved")])
    flat_road = road_class & (true_slope < 1.0) & well_observed & np.isfinite(bands["slope"])
    result["slope_on_flat_road_deg"] = {"cells": int(flat_road.sum()), "median": round(float(np.median(bands["slope"][flat_road])), 3),
                                        "p95": round(float(np.quantile(bands["slope"][flat_road], 0.95)), 3)} if flat_road.any() else None
    costed = well_observed & np.isfinite(bands["traversability_cost"])
    for band, key in (("class_cost_mean", "median_class_cost_by_true_class_well_observed"),
                      ("traversability_cost", "median_cost_by_true_class_well_observed")):
        result[key] = {classes[c]: round(float(np.median(bands[band][(ground_class == c) & costed])), 4)
                       for c in np.unique(ground_class[costed]) if c >= 0}
    result["well_observed_cells_by_true_class"] = {classes[c]: int(((ground_class == c) & costed).sum())
                                                   for c in np.unique(ground_class[costed]) if c >= 0}
    known_cost = np.isfinite(bands["traversability_cost"])
    result["median_cost_on_road"] = round(float(np.median(bands["traversability_cost"][known_cost & road])), 4)
    result["median_cost_off_road"] = round(float(np.median(bands["traversability_cost"][known_cost & ~road])), 4)
    return result


def _plan(layers, road, obstacle, poses) -> dict:
    """A* on the layers' traversability cost from the first pose to the last: how far the endpoints moved to
    passable cells, and the plan (None where there is none)."""
    bands, grid = layers.bands, layers.grid
    cost = np.nan_to_num(bands["traversability_cost"], nan=1.0)
    passable = (bands["known"] > 0) & ~_inflate(bands["lethal"] > 0, ROBOT_RADIUS_M / grid.cell_m)
    # the cells of the first and last poses, or the nearest cells connected to each other where a pose's own
    # cell is unknown or lethal (the cells around the first pose are only seen from behind it)
    goal = _nearest(passable, _cell_of(grid, poses[-1, 0, 3], poses[-1, 1, 3]))
    start_cell = _cell_of(grid, poses[0, 0, 3], poses[0, 1, 3])
    start = _nearest(_connected(passable, goal), start_cell)
    result = {"plan_endpoints_moved_m": [round(math.dist(start, start_cell) * grid.cell_m, 2),
                                         round(math.dist(goal, _cell_of(grid, poses[-1, 0, 3], poses[-1, 1, 3])) * grid.cell_m, 2)]}
    path = astar(cost, passable, start, goal, grid.cell_m)
    if not path:
        return result | {"plan": None}
    cells = np.array(path)
    steps = np.hypot(*np.diff(cells, axis=0).T) * grid.cell_m
    on_road = road[cells[:, 0], cells[:, 1]]
    obstacle_cells = np.argwhere(obstacle)
    clearance = min(float(np.min(np.hypot(obstacle_cells[:, 0] - r, obstacle_cells[:, 1] - c))) for r, c in path) * grid.cell_m
    return result | {"plan": {"length_m": round(float(steps.sum()), 2),
                              "straight_line_m": round(float(math.hypot(poses[-1, 0, 3] - poses[0, 0, 3], poses[-1, 1, 3] - poses[0, 1, 3])), 2),
                              "share_on_road": round(float(on_road.mean()), 4), "cells_on_true_obstacles": int(obstacle[cells[:, 0], cells[:, 1]].sum()),
                              "clearance_from_obstacles_m": round(clearance, 2), "cells": [list(map(int, p)) for p in path]}}


def _plan_on_true_classes(grid, truth, road, poses, costs_of_classes: np.ndarray) -> dict:
    """The same plan on the cost the true classes would give (no uncertainty, true obstacles lethal): what the
    cost table asks for when the map is perfect ({} where there is no such plan)."""
    height, ground_class, obstacle = truth
    true_cost = np.where(ground_class >= 0, costs_of_classes[np.clip(ground_class, 0, None)], 1.0)
    true_passable = np.isfinite(height) & ~_inflate(obstacle, ROBOT_RADIUS_M / grid.cell_m)
    true_goal = _nearest(true_passable, _cell_of(grid, poses[-1, 0, 3], poses[-1, 1, 3]))
    true_start = _nearest(_connected(true_passable, true_goal), _cell_of(grid, poses[0, 0, 3], poses[0, 1, 3]))
    true_path = np.array(astar(true_cost, true_passable, true_start, true_goal, grid.cell_m))
    if not len(true_path):
        return {}
    steps = np.hypot(*np.diff(true_path, axis=0).T) * grid.cell_m
    return {"plan_on_true_classes": {"length_m": round(float(steps.sum()), 2),
                                     "share_on_road": round(float(road[true_path[:, 0], true_path[:, 1]].mean()), 4)}}


def evaluate(layers, truth, road, poses, classes, costs_of_classes: np.ndarray, true_slope: np.ndarray) -> dict:
    height, ground_class, obstacle = truth
    bands = layers.bands
    seen = np.isfinite(bands["elevation"]) & np.isfinite(height)
    error = (bands["elevation"] - height)[seen]
    classified = seen & (ground_class >= 0)
    true = ground_class[classified]
    correct = bands["surface_class"][classified].astype(int) == true
    result = {
        "cells_seen": int(seen.sum()), "cells_with_truth": int(np.isfinite(height).sum()),
        "elevation_error_m": {"median_abs": round(float(np.median(np.abs(error))), 4), "p95_abs": round(float(np.quantile(np.abs(error), 0.95)), 4),
                              "median_signed": round(float(np.median(error)), 4)},
        "surface_class_accuracy": round(float(correct.mean()), 4),
        "per_class": {classes[c]: {"cells": int((true == c).sum()), "recall": round(float(correct[true == c].mean()), 4)} for c in np.unique(true)},
    }
    result |= _class_errors(bands, classified, correct)
    result["road_vs_rest_auc"] = _road_auc(bands, ground_class, classes)
    result["slope_error_deg"] = _slope_error(bands["slope"], true_slope)
    well_observed = bands["surface_uncommitted"] < WELL_OBSERVED_U  # NaN (no support voxel) compares False
    result |= _costs(bands, ground_class, road, classes, true_slope, well_observed)
    result |= _plan(layers, road, obstacle, poses)
    return result | _plan_on_true_classes(layers.grid, truth, road, poses, costs_of_classes)


def _overview_figure(plt, layers, result, poses, classes, colors):
    """The layers side by side, the A* plan and the drive over the cost."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    grid, bands = layers.grid, layers.bands
    extent = (grid.x0_m, grid.x1_m, grid.y0_m, grid.y1_m)
    palette = ListedColormap(np.asarray(colors) / 255.0)
    fig, axes = plt.subplots(2, 3, figsize=(16, 10))
    panels = [("elevation", "terrain", "m"), ("slope", "magma", "deg"), ("step", "magma", "m"),
              ("surface_class", None, None), ("semantic_variance", "inferno", "1"), ("traversability_cost", "RdYlGn_r", "[0, 1]")]
    for ax, (name, cmap, unit) in zip(axes.ravel(), panels):
        ax.set_facecolor((0.85, 0.85, 0.85))
        values = np.ma.masked_invalid(bands[name])
        if cmap is None:
            ax.imshow(values, extent=extent, cmap=palette, vmin=-0.5, vmax=len(classes) - 0.5, interpolation="nearest")
            present = sorted({int(v) for v in np.unique(bands[name][np.isfinite(bands[name])])})
            ax.legend(handles=[Patch(facecolor=np.asarray(colors[c]) / 255, label=classes[c]) for c in present], fontsize=7, loc="lower right")
        else:
            kwargs = {"vmin": 0, "vmax": 1} if name == "traversability_cost" else {}
            if name == "step":
                kwargs = {"vmin": 0, "vmax": 1.0}
            image = ax.imshow(values, extent=extent, cmap=cmap, interpolation="nearest", **kwargs)
            fig.colorbar(image, ax=ax, shrink=0.7, label=unit)
        if name == "traversability_cost":
            ax.imshow(np.ma.masked_where(bands["lethal"] == 0, bands["lethal"]), extent=extent, cmap=ListedColormap(["k"]), interpolation="nearest")
            if result["plan"]:
                cells = np.array(result["plan"]["cells"])
                x, y = grid.cell_centers()
                ax.plot(x[cells[:, 1]], y[cells[:, 0]], color="blue", lw=1.5, label="A* plan")
                ax.plot(poses[:, 0, 3], poses[:, 1, 3], color="white", lw=0.8, ls="--", label="drive")
                ax.legend(fontsize=7, loc="lower right")
        ax.set_title(name.replace("_", " "))
    fig.suptitle(f"Terrain layers of a synthetic drive ({layers.grid.cell_m} m cells); black: lethal")
    fig.tight_layout()
    return fig


def _truth_check_figure(plt, layers, truth, result, sweep):
    """The elevation error against the true terrain, its spread by minimum evidence, class errors by uncertainty."""
    grid, bands = layers.grid, layers.bands
    extent = (grid.x0_m, grid.x1_m, grid.y0_m, grid.y1_m)
    height = truth[0]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    seen = np.isfinite(bands["elevation"]) & np.isfinite(height)
    error = np.where(seen, bands["elevation"] - height, np.nan)
    image = axes[0].imshow(np.ma.masked_invalid(error), extent=extent, cmap="RdBu_r", vmin=-0.4, vmax=0.4, interpolation="nearest")
    fig.colorbar(image, ax=axes[0], shrink=0.8, label="layer - true terrain height (m)")
    axes[0].set_title("elevation error, cells the LiDAR saw")
    for setting, row in sweep.items():
        values = row["errors"]
        axes[1].hist(values, bins=np.arange(-0.4, 0.61, 0.02), histtype="step", label=f"min_evidence {setting}")
    axes[1].set_xlabel("elevation error (m)")
    axes[1].set_ylabel("cells")
    axes[1].legend(fontsize=8)
    axes[1].set_title("elevation error by minimum evidence")
    axes[2].bar(np.arange(1, 11) - 0.2, result["class_error_rate_by_variance_decile"], width=0.4, color="tab:red",
                label="by semantic variance p(1-p)/(S+1), lowest first")
    axes[2].bar(np.arange(1, 11) + 0.2, result["class_error_rate_by_conflict_decile"], width=0.4, color="tab:blue",
                label="by surface conflict 1 - e_label / sum e, lowest first")
    axes[2].set_xlabel("decile")
    axes[2].set_ylabel("surface class error rate")
    axes[2].legend(fontsize=8)
    axes[2].set_title(f"class errors by uncertainty decile (accuracy {result['surface_class_accuracy']:.3f})")
    fig.tight_layout()
    return fig


def _plan_figure(plt, layers, truth, road, plan, poses):
    """The A* plan over the cost, with the true road and obstacles."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    grid, bands = layers.grid, layers.bands
    extent = (grid.x0_m, grid.x1_m, grid.y0_m, grid.y1_m)
    obstacle = truth[2]
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.imshow(np.ma.masked_invalid(bands["traversability_cost"]), extent=extent, cmap="RdYlGn_r", vmin=0, vmax=1, interpolation="nearest")
    ax.imshow(np.ma.masked_where(~road, road.astype(float)), extent=extent, cmap=ListedColormap([(0.2, 0.2, 1.0)]), alpha=0.15,
              interpolation="nearest")
    ax.imshow(np.ma.masked_where(~obstacle, obstacle.astype(float)), extent=extent, cmap=ListedColormap(["k"]), interpolation="nearest")
    cells = np.array(plan["cells"])
    x, y = grid.cell_centers()
    ax.plot(x[cells[:, 1]], y[cells[:, 0]], color="blue", lw=2)
    ax.plot(poses[:, 0, 3], poses[:, 1, 3], color="magenta", lw=1, ls="--")
    ax.legend(handles=[Patch(color="blue", label="A* plan on traversability_cost"), Patch(color="magenta", label="the drive"),
                       Patch(color="k", label="true obstacles"), Patch(color=(0.2, 0.2, 1.0), alpha=0.3, label="true road")],
              loc="lower right", fontsize=8)
    ax.set_title(f"A* plan: {plan['length_m']} m, {plan['share_on_road'] * 100:.0f} % on the road, "
                 f"{plan['clearance_from_obstacles_m']} m from the nearest obstacle")
    fig.tight_layout()
    return fig


def _figures(out: Path, layers, truth, road, result, poses, classes, colors, sweep) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []

    def save(fig, name):
        written.append(out / f"{name}.png")
        fig.savefig(written[-1], dpi=72)
        plt.close(fig)

    save(_overview_figure(plt, layers, result, poses, classes, colors), "layers_overview")
    save(_truth_check_figure(plt, layers, truth, result, sweep), "truth_check")
    if result["plan"]:
        save(_plan_figure(plt, layers, truth, road, result["plan"], poses), "plan")
    return written


def _drive_and_map(args, preset):
    """(the drive's folder, its map, the seconds rendering and mapping took where this run did them): the
    drive and map under ``--work`` are kept and reused."""
    from evsemmap_warp.config import load_config
    from evsemmap_warp.core.mapper import Mapper, load_map
    from evsemmap_warp.data.datasets import open_dataset
    from evsemmap_warp.synthetic.writer import generate_sequence

    drive = args.work / f"{args.world}_drive"
    map_path = args.work / f"{args.world}_{args.method}.npz"
    timings = {}
    if not (drive / "poses.txt").exists():
        started = time.perf_counter()
        generate_sequence(preset, drive, progress=False, camera=False)
        timings["render_s"] = round(time.perf_counter() - started, 1)
    if not map_path.exists():
        run = load_config([str(drive)], method=args.method)
        dataset = open_dataset(run.dataset)
        mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names or None, frame=dataset.frame, device=args.device)
        started = time.perf_counter()
        mapper.integrate_many(dataset)
        timings["map_s"] = round(time.perf_counter() - started, 1)
        mapper.save(map_path)
    return drive, load_map(map_path, device=args.device), timings


def _sweep(mapper, world, poses, classes, base, device):
    """The layers at each SWEEP minimum evidence, scored against the world's truth: (the truth (height,
    class, obstacle), the road mask, the true slope, setting -> {result, elevation errors}, (layers,
    result) of the default setting)."""
    from evsemmap_warp.terrain import compute_layers
    from evsemmap_warp.terrain.layers import neighbourhood_filters

    truth = road = true_slope = None
    sweep, chosen = {}, None
    for setting in SWEEP:
        config = replace(base, layers=replace(base.layers, min_evidence=setting))
        started = time.perf_counter()
        layers = compute_layers(mapper, config=config, device=device)
        seconds = time.perf_counter() - started
        if truth is None:
            truth = _world_truth(world, layers.grid, base.layers.clearance_m, device)
            road = _road_mask(world, layers.grid)
            # the true terrain's slope, by the same plane fit over the same window as the layers' (a slope's
            # magnitude reads the same north-up)
            true_slope = neighbourhood_filters(truth[0], truth[0], cell_m=layers.grid.cell_m, config=base, device=device)["slope"]
        result = evaluate(layers, truth, road, poses, classes, np.array([base.costs.classes[n] for n in classes]), true_slope)
        result["layer_seconds"] = round(seconds, 3)
        seen = np.isfinite(layers.bands["elevation"]) & np.isfinite(truth[0])
        sweep[setting] = {"result": result, "errors": (layers.bands["elevation"] - truth[0])[seen]}
        if setting == base.layers.min_evidence:
            chosen = (layers, result)
        print(f"min_evidence {setting}: {json.dumps({k: v for k, v in result.items() if k not in ('plan', 'per_class')})} "
              f"plan {json.dumps({k: v for k, v in (result['plan'] or {}).items() if k != 'cells'})}", file=sys.stderr)
    if chosen is None:
        raise SystemExit(f"terrain_truth: the default min_evidence {base.layers.min_evidence} is not in the sweep {SWEEP}")
    return truth, road, true_slope, sweep, chosen


def _cost_rules(mapper, truth, road, true_slope, poses, classes, base, device) -> dict:
    """The cost rules side by side on the same map and settings (terrain/config.py COST_RULES): what each gives a planner."""
    from evsemmap_warp.terrain import compute_layers
    from evsemmap_warp.terrain.config import COST_RULES

    rules = {}
    for rule in COST_RULES:
        ruled = compute_layers(mapper, config=replace(base, costs=replace(base.costs, rule=rule)), device=device)
        scored = evaluate(ruled, truth, road, poses, classes, np.array([base.costs.classes[n] for n in classes]), true_slope)
        rules[rule] = {key: scored[key] for key in ("road_vs_rest_auc", "median_cost_on_road", "median_cost_off_road",
                                                     "median_class_cost_by_true_class_well_observed",
                                                     "median_cost_by_true_class_well_observed")} \
            | {"plan": {key: val for key, val in (scored["plan"] or {}).items() if key != "cells"}}
    return rules


def _before_after(result: dict, rules: dict, rule: str) -> dict:
    """The issue's starting point (rule ``expected``, the paper's semantic variance as the uncertainty band) and
    the defaults (``rule``, the surface conflict) side by side: {figure: {"before": ..., "after": ...}}."""
    before, after = rules["expected"], rules[rule]

    def pair(get):
        return {"before": get(before, "variance"), "after": get(after, "conflict")}

    return {"before": "costs.rule expected, uncertainty band semantic_variance", "after": f"costs.rule {rule}, uncertainty band surface_conflict",
            "road_vs_rest_auc": pair(lambda r, _: r["road_vs_rest_auc"]),
            "median_cost_on_road_and_off_road": pair(lambda r, _: [r["median_cost_on_road"], r["median_cost_off_road"]]),
            "plan_share_on_road": pair(lambda r, _: r["plan"].get("share_on_road")),
            "class_error_rate_by_band_decile": pair(lambda _, band: result[f"class_error_rate_by_{band}_decile"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="default", help="a synthetic world preset with one square world (not a corridor)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/evsemmap_terrain_truth"), help="drive and map here (kept and reused)")
    parser.add_argument("--out", type=Path, default=None, help="figures and truth.json (default: docs/terrain/PRESET)")
    parser.add_argument("--method", default="ebs")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    from evsemmap_warp.classes import class_set
    from evsemmap_warp.data.sequences import read_poses
    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.scene import generate_world
    from evsemmap_warp.terrain import load_terrain_config
    from evsemmap_warp.terrain.pipeline import class_colors

    preset = load_preset(args.world)
    args.out = args.out or REPO / "docs" / "terrain" / args.world
    if preset.world.corridor_tiles:
        raise SystemExit("terrain_truth: give a preset of one square world (demo, default, tiny), not a corridor")
    drive, mapper, timings = _drive_and_map(args, preset)
    poses = read_poses(drive / "poses.txt")
    classes = class_set().names
    base = load_terrain_config()
    truth, road, true_slope, sweep, (layers, result) = _sweep(mapper, generate_world(preset.world, preset.seed), poses, classes, base,
                                                               args.device)
    rules = _cost_rules(mapper, truth, road, true_slope, poses, classes, base, args.device)
    result |= _uncommitted_reading(layers.bands, truth[1], classes, base.costs.unknown_cost)
    args.out.mkdir(parents=True, exist_ok=True)
    figures = _figures(args.out, layers, truth, road, result, poses, classes, class_colors(classes), sweep)
    summary = {
        "preset": args.world, "method": args.method, "voxels": mapper.voxel_count, "cell_m": layers.grid.cell_m, "costs_file": "default",
        "default_min_evidence": base.layers.min_evidence, "timings": timings,
        "result": {k: v for k, v in result.items() if k != "plan"} | {"plan": {k: v for k, v in (result["plan"] or {}).items() if k != "cells"}},
        "sweep": {str(k): {key: v["result"][key] for key in ("cells_seen", "elevation_error_m", "surface_class_accuracy")}
                  | {"plan": {key: val for key, val in (v["result"]["plan"] or {}).items() if key != "cells"}} for k, v in sweep.items()},
        "cost_rules": rules, "before_after": _before_after(result, rules, base.costs.rule),
        "figures": [str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p) for p in figures],
    }
    (args.out / "truth.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
