"""PCL VoxelGrid's leaf index of every point (docs/compatibility.md §1) (Warp).

``leaf_indices``: x fastest over the leaves' bounding box, from the float32 floor(p / leaf) PCL
computes. ``leaf_centroids``: each leaf's float32 centroid, summed in exactly the order of numpy's
``np.add.reduceat(points[order], starts, axis=0)`` (its first point, plus numpy's pairwise sum of the
rest): that order is the one whose maps match the C++ toy maps exactly (a sequential float32 sum
changed one of the toy S-CSM map's 64,130 cells). One thread walks all leaves (launch with dim=1): the
per-scan preprocessing already runs one scan per worker, and the points are read in place, where
numpy's row gather ``points[order]`` alone took a third of the free samples' VoxelGrid.

numpy twins: ``evsemmap_warp/reference/voxel_grid.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def leaf_indices(
    points: wp.array(dtype=wp.vec3),
    inverse_leaf: wp.float32,
    lowest_x: wp.int64,
    lowest_y: wp.int64,
    lowest_z: wp.int64,
    leaves_x: wp.int64,
    leaves_y: wp.int64,
    leaf: wp.array(dtype=wp.int64),
):
    """leaf[i] = point i's leaf index: floor(p * inverse_leaf) - lowest per axis, x fastest."""
    i = wp.tid()
    p = points[i]
    rx = wp.int64(wp.floor(p[0] * inverse_leaf)) - lowest_x
    ry = wp.int64(wp.floor(p[1] * inverse_leaf)) - lowest_y
    rz = wp.int64(wp.floor(p[2] * inverse_leaf)) - lowest_z
    leaf[i] = rx + ry * leaves_x + rz * (leaves_x * leaves_y)


# numpy's pairwise summation (``pairwise_sum`` in its loops_utils): runs shorter than 8 are summed in
# order, runs up to PAIRWISE_BLOCK in 8 interleaved partial sums, longer runs split in two halves (the
# first a multiple of 8) summed separately. Splitting a run of n < 2^31 points nests fewer than 32 deep.
PAIRWISE_BLOCK = wp.constant(128)
_SPLIT_DEPTH = 40
_depth_ints = wp.types.vector(length=_SPLIT_DEPTH, dtype=int)
_depth_sums = wp.types.matrix(shape=(_SPLIT_DEPTH, 3), dtype=wp.float32)
_partial_sums = wp.types.matrix(shape=(8, 3), dtype=wp.float32)


@wp.func
def _block_sum(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), start: int, n: int) -> wp.vec3:
    """numpy's pairwise sum of points[order[start:start + n]] for n <= PAIRWISE_BLOCK."""
    if n < 8:
        total = wp.vec3(0.0, 0.0, 0.0)
        for i in range(n):
            total = total + points[int(order[start + i])]
        return total
    r = _partial_sums()
    for j in range(8):
        p = points[int(order[start + j])]
        r[j, 0] = p[0]
        r[j, 1] = p[1]
        r[j, 2] = p[2]
    whole = n - n % 8
    i = int(8)
    while i < whole:
        for j in range(8):
            p = points[int(order[start + i + j])]
            r[j, 0] = r[j, 0] + p[0]
            r[j, 1] = r[j, 1] + p[1]
            r[j, 2] = r[j, 2] + p[2]
        i += 8
    total = wp.vec3(0.0, 0.0, 0.0)
    for c in range(3):
        total[c] = ((r[0, c] + r[1, c]) + (r[2, c] + r[3, c])) + ((r[4, c] + r[5, c]) + (r[6, c] + r[7, c]))
    while i < n:
        total = total + points[int(order[start + i])]
        i += 1
    return total


@wp.func
def _first_half(n: int) -> int:
    half = n // 2
    return half - half % 8


@wp.func
def pairwise_sum(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), start: int, n: int) -> wp.vec3:
    """numpy's pairwise sum of points[order[start:start + n]], its recursion unrolled onto a stack: a
    run split in two waits (stage 1) for its first half's sum, then (stage 2) for its second's."""
    run_start = _depth_ints()
    run_length = _depth_ints()
    stage = _depth_ints()
    first_sum = _depth_sums()
    top = int(0)
    run_start[0] = start
    run_length[0] = n
    stage[0] = 0
    while True:
        if run_length[top] <= PAIRWISE_BLOCK:
            total = _block_sum(points, order, run_start[top], run_length[top])
            top -= 1
            # hand the sum up through every run that was waiting for its second half
            while top >= 0 and stage[top] == 2:
                total = wp.vec3(first_sum[top, 0], first_sum[top, 1], first_sum[top, 2]) + total
                top -= 1
            if top < 0:
                return total
            # the run at the top was waiting for its first half: now its second
            first_sum[top, 0] = total[0]
            first_sum[top, 1] = total[1]
            first_sum[top, 2] = total[2]
            stage[top] = 2
            half = _first_half(run_length[top])
            run_start[top + 1] = run_start[top] + half
            run_length[top + 1] = run_length[top] - half
        else:
            stage[top] = 1
            run_start[top + 1] = run_start[top]
            run_length[top + 1] = _first_half(run_length[top])
        top += 1
        stage[top] = 0
    return wp.vec3(0.0, 0.0, 0.0)


# leaf_centroids asks for the point this many places ahead in sorted order (16 to 128 measured alike;
# free_res 0.5, 30 bench scans: 0.34 -> 0.23 s).
POINTS_AHEAD = wp.constant(32)


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
__builtin_prefetch(&points.data[index]);
#endif
""")
def _prefetch_point(points: wp.array(dtype=wp.vec3), index: int): ...


@wp.kernel
def leaf_centroids(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64),
                   counts: wp.array(dtype=wp.int64), centroids: wp.array(dtype=wp.vec3)):
    """centroids[l] = the float32 mean of points[order[starts[l]:starts[l] + counts[l]]]: the first
    point plus the pairwise sum of the rest (numpy's add.reduceat order), over the count."""
    last = order.shape[0] - 1
    for leaf in range(starts.shape[0]):
        start = int(starts[leaf])
        n = int(counts[leaf])
        # The points are read in sorted order, from all over the cloud: ask for the ones this many
        # positions ahead while this leaf sums (a hint, compiled out on CUDA).
        for k in range(n):
            _prefetch_point(points, int(order[wp.min(start + k + POINTS_AHEAD, last)]))
        total = points[int(order[start])]
        if n > PAIRWISE_BLOCK + 1:
            total = total + pairwise_sum(points, order, start + 1, n - 1)
        elif n > 1:  # the same sum without setting up pairwise_sum's stack
            total = total + _block_sum(points, order, start + 1, n - 1)
        centroids[leaf] = total / float(n)
