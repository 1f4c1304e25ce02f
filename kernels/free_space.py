"""S-BKI's free-space samples along each ray (docs/compatibility.md §1) (Warp).

One thread per hit writes its rows of the training set's free samples: the sensor origin, then
origin + direction * d for the distances d = f, 2f, ... below the hit's range (accumulated in float32 on
the host, as the C++ loop does), then one at range - f when the range exceeds f. Every coordinate is
a float32 multiply then add, as in the C++ (no fused multiply-add: each operation is its own
statement).

``ray_geometry`` and ``samples_per_ray`` compute on a device what the host path computes
with numpy before ``ray_samples`` (``methods.sbki_device``; its tests hold them to the host path bit for
bit).

numpy twin: ``evsemmap_warp/reference/free_space.py``.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
def ray_samples(
    direction: wp.array(dtype=wp.vec3),
    ray_length: wp.array(dtype=wp.float32),
    hit_count: wp.array(dtype=int),
    origin: wp.vec3,
    free_resolution: wp.float32,
    steps: wp.array(dtype=wp.float32),
    samples_per_hit: wp.array(dtype=int),
    first_row: wp.array(dtype=int),
    out: wp.array(dtype=wp.vec3),
):
    """Hit h's rows out[first_row[h]:] (h below hit_count[0]): the origin, samples_per_hit[h] samples at
    steps[k], and the sample at ray_length[h] - free_resolution when ray_length[h] > free_resolution. Only
    rows within out are written (a scan whose rows outgrow it, its total seen by the caller, still has
    every row below out's end written: the rows are the hits' in order)."""
    h = wp.tid()
    if h >= hit_count[0]:
        return
    row = first_row[h]
    count = samples_per_hit[h]
    room = out.shape[0]
    if row < 0 or row >= room:  # past the room (or past an int's range, the total then seen as too large)
        return
    out[row] = origin
    d = direction[h]
    for k in range(wp.min(count, room - row - 1)):
        out[row + 1 + k] = origin + d * steps[k]
    if ray_length[h] > free_resolution and row + 1 + count < room:
        out[row + 1 + count] = origin + d * (ray_length[h] - free_resolution)


@wp.kernel
def ray_geometry(hits: wp.array(dtype=wp.vec3), hit_count: wp.array(dtype=int), origin: wp.vec3, direction: wp.array(dtype=wp.vec3),
                 ray_length: wp.array(dtype=wp.float32)):
    """Each of the hit_count[0] hits' float32 ray from the origin: its length, sqrt((dx*dx + dy*dy) + dz*dz)
    (numpy's order over three columns), and its direction, the difference over the length."""
    h = wp.tid()
    if h >= hit_count[0]:
        return
    d = hits[h] - origin
    length = wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    ray_length[h] = length
    direction[h] = d / length


@wp.kernel
def samples_per_ray(ray_length: wp.array(dtype=wp.float32), hit_count: wp.array(dtype=int), steps: wp.array(dtype=wp.float32),
                    free_resolution: wp.float32, samples_per_hit: wp.array(dtype=int), rows_per_hit: wp.array(dtype=int),
                    total_rows: wp.array(dtype=wp.int64)):
    """samples_per_hit[h] = how many steps lie below the hit's range (a binary search of the ascending
    steps, as numpy's searchsorted side="left"); rows_per_hit[h] = the origin, those samples and the one
    at range - free_resolution when the range exceeds free_resolution; 0 past the hit_count[0] hits.
    total_rows[0] (from 0) = their sum in int64, which the int prefix sum of rows_per_hit can outgrow."""
    h = wp.tid()
    if h >= hit_count[0]:
        rows_per_hit[h] = 0
        return
    length = ray_length[h]
    low = int(0)
    high = steps.shape[0]
    while low < high:
        middle = (low + high) // 2
        if steps[middle] < length:
            low = middle + 1
        else:
            high = middle
    samples_per_hit[h] = low
    rows = 1 + low + wp.where(length > free_resolution, 1, 0)
    rows_per_hit[h] = rows
    wp.atomic_add(total_rows, 0, wp.int64(rows))



@wp.kernel
def within_range(ray_length: wp.array(dtype=wp.float32), hit_count: wp.array(dtype=int), max_range: wp.float32, keep: wp.array(dtype=int)):
    """keep[h] = 1 where the hit's range is at most max_range (the range filter, in float32); 0 past the
    hit_count[0] hits."""
    h = wp.tid()
    keep[h] = wp.where(h < hit_count[0] and ray_length[h] <= max_range, 1, 0)


@wp.kernel
def compact_rays(keep: wp.array(dtype=int), slot: wp.array(dtype=int), hits: wp.array(dtype=wp.vec3), labels: wp.array(dtype=wp.int64),
                 direction: wp.array(dtype=wp.vec3), ray_length: wp.array(dtype=wp.float32), kept_hits: wp.array(dtype=wp.vec3),
                 kept_labels: wp.array(dtype=wp.int64), kept_direction: wp.array(dtype=wp.vec3), kept_length: wp.array(dtype=wp.float32)):
    """The kept hits and their rays, in input order: hit h goes to slot[h] - 1 (slot: the inclusive scan
    of keep)."""
    h = wp.tid()
    if keep[h] == 1:
        row = slot[h] - 1
        kept_hits[row] = hits[h]
        kept_labels[row] = labels[h]
        kept_direction[row] = direction[h]
        kept_length[row] = ray_length[h]


@wp.kernel
def longest_ray(ray_length: wp.array(dtype=wp.float32), hit_count: wp.array(dtype=int), longest: wp.array(dtype=wp.float32)):
    """longest[0] (starting at 0) = the largest of the hit_count[0] ray lengths."""
    h = wp.tid()
    if h < hit_count[0]:
        wp.atomic_max(longest, 0, ray_length[h])


@wp.kernel
def join_training_set(hits: wp.array(dtype=wp.vec3), hit_labels: wp.array(dtype=wp.int64), hit_count: wp.array(dtype=int),
                      free_points: wp.array(dtype=wp.vec3), free_count: wp.array(dtype=int), free_label: wp.int64,
                      points: wp.array(dtype=wp.vec3), labels: wp.array(dtype=wp.int64), count: wp.array(dtype=int)):
    """The training set, row i: the hit_count[0] hits, then the free_count[0] free points labelled
    ``free_label`` (one thread per row of its capacity); count[0] = their total."""
    i = wp.tid()
    h = hit_count[0]
    if i == 0:
        count[0] = h + free_count[0]
    if i < h:
        points[i] = hits[i]
        labels[i] = hit_labels[i]
    elif i < h + free_count[0]:
        points[i] = free_points[i - h]
        labels[i] = free_label
