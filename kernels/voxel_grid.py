"""PCL VoxelGrid's leaf index of every point (docs/compatibility.md §1) (Warp).

``leaf_indices``: x fastest over the leaves' bounding box, from the float32 floor(p / leaf) PCL
computes. The centroids stay numpy's ``add.reduceat`` (sorting and summing on the host): its
summation order is the one whose maps match the C++ toy maps exactly, and a sequential float32 sum
in a kernel changed one of the toy S-CSM map's 64,130 cells.

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
