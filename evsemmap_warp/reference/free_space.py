"""numpy twin of ``evsemmap_warp.kernels.free_space``: the same rows, one hit at a time."""

from __future__ import annotations

import numpy as np


def ray_samples(direction, ray_length, origin, free_resolution, steps, samples_per_hit, first_row, total_rows: int) -> np.ndarray:
    """Twin of ``kernels.free_space.ray_samples``: per hit h, rows first_row[h]... of the [total_rows, 3]
    float32 output: the sensor origin, samples_per_hit[h] samples at ``steps`` along the ray, and one at
    ray_length[h] - free_resolution when the ray is longer than that (m, the scan's frame); the rows of all
    hits listed in order and cut at total_rows."""
    origin = np.asarray(origin, np.float32)
    f = np.float32(free_resolution)
    rows = []
    for h in range(len(direction)):
        assert int(first_row[h]) == len(rows) or len(rows) >= total_rows
        rows.append(origin)
        for k in range(int(samples_per_hit[h])):
            rows.append(origin + direction[h] * steps[k])
        if ray_length[h] > f:
            rows.append(origin + direction[h] * np.float32(ray_length[h] - f))
    return np.array(rows[:total_rows], np.float32).reshape(-1, 3)


def ray_geometry(hits, origin) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``ray_geometry``: each hit's float32 direction [N, 3] and range [N] from the origin."""
    diff = np.asarray(hits, np.float32) - np.asarray(origin, np.float32)
    ray_length = np.sqrt(np.sum(diff * diff, axis=1, dtype=np.float32), dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        return diff / ray_length[:, None], ray_length


def samples_per_ray(ray_length, steps, free_resolution, count: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Twin of ``samples_per_ray``: (steps below each range, rows per hit, 0 past the first ``count`` hits
    (None: all), their total) [count], [N] (int32), int."""
    ray_length = np.asarray(ray_length, np.float32)
    count = len(ray_length) if count is None else count
    per_hit = np.searchsorted(np.asarray(steps, np.float32), ray_length[:count], side="left")
    rows = 1 + per_hit + (ray_length[:count] > np.float32(free_resolution))
    return per_hit.astype(np.int32), np.r_[rows, np.zeros(len(ray_length) - count, np.int64)].astype(np.int32), int(rows.sum())


def within_range(ray_length, max_range, count: int | None = None) -> np.ndarray:
    """Twin of ``within_range``: 1 where one of the first ``count`` (None: all) ranges is at most max_range
    (float32), else 0 [N] (int32)."""
    ray_length = np.asarray(ray_length, np.float32)
    keep = (ray_length <= np.float32(max_range)).astype(np.int32)
    keep[len(ray_length) if count is None else count:] = 0
    return keep


def compact_rays(keep, slot, hits, labels, direction, ray_length):
    """Twin of ``compact_rays``: the kept hits, labels, directions and ranges, in input order."""
    kept = np.asarray(keep) == 1
    return np.asarray(hits)[kept], np.asarray(labels)[kept], np.asarray(direction)[kept], np.asarray(ray_length)[kept]


def longest_ray(ray_length) -> np.float32:
    """Twin of ``longest_ray``: the largest range, 0 for none."""
    return np.float32(max(0.0, float(np.max(ray_length, initial=0.0))))


def join_training_set(hits, hit_labels, free_points, free_label: int) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``join_training_set``: the hits then the free points, and their labels (``free_label`` for the free)."""
    points = np.concatenate([np.asarray(hits, np.float32).reshape(-1, 3), np.asarray(free_points, np.float32).reshape(-1, 3)])
    return points, np.concatenate([np.asarray(hit_labels, np.int64), np.full(len(free_points), free_label, np.int64)])
