"""PCL VoxelGrid's leaf index of every point (docs/compatibility.md §1) (Warp).

``leaf_indices``: x fastest over the leaves' bounding box, from the float32 floor(p / leaf) PCL
computes. ``leaf_centroids``: each leaf's float32 centroid as PCL's CentroidPoint forms it, the points
added one by one to a float32 sum that starts at zero, then divided by their count. A leaf that gathers
thousands of copies of one point far from the origin (the sensor origin's leaf of the free samples, one
copy per hit) drifts from that point as the C++'s does: numpy's pairwise order, used here before, kept
it in place and so moved the origin's free sample by up to ~1 cm against the C++ (on the bench
workload at free_res 100, the cells within 0.6 m of the 30 sensor origins differed by up to 0.54 in
alpha; now by float32 noise). Within a leaf PCL sums in the order its std::sort leaves, which no
stable order reproduces; ours is the input order (see docs/compatibility.md §1.5 for the one toy cell
this moves). One thread walks all leaves (launch with dim=1): the per-scan preprocessing already runs
one scan per worker, and the points are read in place, where numpy's row gather ``points[order]`` alone
took a third of the free samples' VoxelGrid.

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
    """centroids[l] = the float32 mean of points[order[starts[l]:starts[l] + counts[l]]]: their float32
    sum in that order, from zero, over the count."""
    last = order.shape[0] - 1
    for leaf in range(starts.shape[0]):
        start = int(starts[leaf])
        n = int(counts[leaf])
        # The points are read in sorted order, from all over the cloud: ask for the ones this many
        # positions ahead while this leaf sums (a hint, compiled out on CUDA).
        for k in range(n):
            _prefetch_point(points, int(order[wp.min(start + k + POINTS_AHEAD, last)]))
        total = wp.vec3(0.0, 0.0, 0.0)
        for k in range(n):
            total = total + points[int(order[start + k])]
        centroids[leaf] = total / float(n)
