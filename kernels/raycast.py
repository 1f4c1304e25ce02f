"""Ray casting against a triangle mesh (Warp ``wp.Mesh`` BVH): the synthetic world's LiDAR, camera and
shadow rays all go through this one kernel.

numpy twin: ``evsemmap_warp/reference/raycast.py``.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
def cast_rays(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),  # unit length
    max_distance: float,
    distance: wp.array(dtype=float),  # out: hit distance, -1 for a miss
    face: wp.array(dtype=int),  # out: hit triangle, -1 for a miss
    normal: wp.array(dtype=wp.vec3),  # out: unit geometric normal of the hit triangle
):
    """Kernel, one thread per ray: the first hit of ray i (origin, unit direction; m, the mesh's frame) on
    the Warp mesh ``mesh`` within ``max_distance``: its distance, triangle and unit geometric normal, or
    -1 (distance and face) for a miss."""
    i = wp.tid()
    query = wp.mesh_query_ray(mesh, origins[i], directions[i], max_distance)
    if query.result:
        distance[i] = query.t
        face[i] = query.face
        normal[i] = wp.normalize(query.normal)
    else:
        distance[i] = -1.0
        face[i] = -1
        normal[i] = wp.vec3(0.0, 0.0, 0.0)
