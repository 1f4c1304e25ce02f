"""S-BKI's free-space samples along each ray (docs/compatibility.md §1) (Warp).

One thread per hit writes its rows of the training set's free samples: the sensor origin, then
origin + direction * d for the distances d = f, 2f, ... below the hit's range (accumulated in float32 on
the host, as the C++ loop does), then one at range - f when the range exceeds f. Every coordinate is
a float32 multiply then add, as in the C++ (no fused multiply-add: each operation is its own
statement).

numpy twin: ``evsemmap_warp/reference/free_space.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def ray_samples(
    direction: wp.array(dtype=wp.vec3),
    ray_length: wp.array(dtype=wp.float32),
    origin: wp.vec3,
    free_resolution: wp.float32,
    steps: wp.array(dtype=wp.float32),
    samples_per_hit: wp.array(dtype=int),
    first_row: wp.array(dtype=int),
    out: wp.array(dtype=wp.vec3),
):
    """Hit h's rows out[first_row[h]:]: the origin, samples_per_hit[h] samples at steps[k], and the
    sample at ray_length[h] - free_resolution when ray_length[h] > free_resolution."""
    h = wp.tid()
    row = first_row[h]
    out[row] = origin
    d = direction[h]
    count = samples_per_hit[h]
    for k in range(count):
        out[row + 1 + k] = origin + d * steps[k]
    if ray_length[h] > free_resolution:
        out[row + 1 + count] = origin + d * (ray_length[h] - free_resolution)
