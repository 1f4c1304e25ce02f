"""numpy twin of ``evsemmap_warp.kernels.terrain`` (the terrain layers' column reduction and filters).

Brute force: dicts keyed by cell, one plane fit per cell with ``np.linalg.lstsq``. Keys are packed as
the kernels pack them ((z + 2^30) << 32 | row), and results come back in the kernels' array layout.
"""

from __future__ import annotations

import math

import numpy as np

_Z_OFFSET = 1 << 30


def _pack(z: int, row: int) -> int:
    return ((int(z) + _Z_OFFSET) << 32) | int(row)


def _cell(v, voxel_m, shift_x, shift_y, cell_m, width, height, z_low, z_high) -> int:
    if v[2] < z_low or v[2] > z_high:
        return -1
    i = math.floor(((float(v[0]) + 0.5) * voxel_m + shift_x) / cell_m)
    j = math.floor(((float(v[1]) + 0.5) * voxel_m + shift_y) / cell_m)
    if not (0 <= i < width and 0 <= j < height):
        return -1
    return j * width + i


def column_extremes(index, label, occupied, surface_class, hits, voxel_m, shift_x, shift_y, cell_m, width, height, z_low, z_high):
    """(top_key, support_key, low_z, observations), each [width * height]; keys -1 and low_z 2^31 - 1
    where no occupied voxel falls."""
    cells = width * height
    top = {}
    support = {}
    low = {}
    observations = np.zeros(cells)
    for row, v in enumerate(np.asarray(index, np.int64)):
        c = _cell(v, voxel_m, shift_x, shift_y, cell_m, width, height, z_low, z_high)
        if c < 0:
            continue
        observations[c] += float(hits[row])
        if not occupied[row]:
            continue
        key = _pack(v[2], row)
        top[c] = max(top.get(c, -1), key)
        low[c] = min(low.get(c, 2**31 - 1), int(v[2]))
        if surface_class[label[row]]:
            support[c] = max(support.get(c, -1), key)
    out_top = np.full(cells, -1, np.int64)
    out_support = np.full(cells, -1, np.int64)
    out_low = np.full(cells, 2**31 - 1, np.int64)
    for c, key in top.items():
        out_top[c] = key
    for c, key in support.items():
        out_support[c] = key
    for c, z in low.items():
        out_low[c] = z
    return out_top, out_support, out_low.astype(np.int32), observations


def column_cover(index, occupied, voxel_m, shift_x, shift_y, cell_m, width, height, z_low, z_high, clearance_voxels, support_key, low_z):
    """cover_key [width * height]: the highest occupied voxel at most clearance_voxels above the
    support (or the lowest occupied voxel without one); -1 where none."""
    cover = np.full(width * height, -1, np.int64)
    for row, v in enumerate(np.asarray(index, np.int64)):
        if not occupied[row]:
            continue
        c = _cell(v, voxel_m, shift_x, shift_y, cell_m, width, height, z_low, z_high)
        if c < 0:
            continue
        base = (int(support_key[c]) >> 32) - _Z_OFFSET if support_key[c] >= 0 else int(low_z[c])
        if v[2] <= base + clearance_voxels:
            cover[c] = max(int(cover[c]), _pack(v[2], row))
    return cover


def plane_fit(height_m, radius, cell_m, min_cells):
    """(slope_deg, roughness_m) [rows, columns]: per known cell, np.linalg.lstsq of z = a x + b y + c over
    the known cells of its window; NaN with fewer than min_cells cells or a rank-deficient design."""
    height_m = np.asarray(height_m, np.float64)
    rows, columns = height_m.shape
    slope = np.full(height_m.shape, np.nan)
    rough = np.full(height_m.shape, np.nan)
    for j in range(rows):
        for i in range(columns):
            if np.isnan(height_m[j, i]):
                continue
            xs, ys, zs = [], [], []
            for jj in range(max(0, j - radius), min(rows, j + radius + 1)):
                for ii in range(max(0, i - radius), min(columns, i + radius + 1)):
                    if not np.isnan(height_m[jj, ii]):
                        xs.append((ii - i) * cell_m)
                        ys.append((jj - j) * cell_m)
                        zs.append(height_m[jj, ii] - height_m[j, i])
            if len(zs) < min_cells:
                continue
            design = np.column_stack([xs, ys, np.ones(len(zs))])
            if np.linalg.matrix_rank(design) < 3:
                continue
            (a, b, c), *_ = np.linalg.lstsq(design, np.asarray(zs), rcond=None)
            residual = np.asarray(zs) - design @ np.array([a, b, c])
            slope[j, i] = math.degrees(math.atan(math.hypot(a, b)))
            rough[j, i] = math.sqrt(float(residual @ residual) / len(zs))
    return slope, rough


def max_step(height_m, radius):
    """[rows, columns]: max |z - z_n| over the known cells of the window, NaN where undefined."""
    height_m = np.asarray(height_m, np.float64)
    rows, columns = height_m.shape
    out = np.full(height_m.shape, np.nan)
    for j in range(rows):
        for i in range(columns):
            if np.isnan(height_m[j, i]):
                continue
            window = height_m[max(0, j - radius):j + radius + 1, max(0, i - radius):i + radius + 1]
            others = np.abs(window - height_m[j, i])
            known = ~np.isnan(window)
            known[min(j, radius), min(i, radius)] = False  # the cell itself
            if known.any():
                out[j, i] = others[known].max()
    return out
