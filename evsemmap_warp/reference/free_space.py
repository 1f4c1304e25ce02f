"""numpy twin of ``evsemmap_warp.kernels.free_space``: the same rows, one hit at a time."""

from __future__ import annotations

import numpy as np


def ray_samples(direction, ray_length, origin, free_resolution, steps, samples_per_hit, first_row, total_rows: int) -> np.ndarray:
    """Twin of ``kernels.free_space.ray_samples``: per hit h, rows first_row[h]... of the [total_rows, 3]
    float32 output: the sensor origin, samples_per_hit[h] samples at ``steps`` along the ray, and one at
    ray_length[h] - free_resolution when the ray is longer than that (m, the scan's frame)."""
    out = np.zeros((total_rows, 3), np.float32)
    origin = np.asarray(origin, np.float32)
    f = np.float32(free_resolution)
    for h in range(len(direction)):
        row = int(first_row[h])
        out[row] = origin
        for k in range(int(samples_per_hit[h])):
            out[row + 1 + k] = origin + direction[h] * steps[k]
        if ray_length[h] > f:
            out[row + 1 + int(samples_per_hit[h])] = origin + direction[h] * np.float32(ray_length[h] - f)
    return out
