"""The scatter family's launch (``kernels.scatter``): each point adds its kernel's weights to the voxels
it reaches, one kernel per (mode, fusion, media), relaunched where it ran out of table room. The clean
point kernels, ConvBKI's stencil and S-CSM's own-block counts all run through ``scatter``, each
integrator handing it its mode's reach and parameters."""

from __future__ import annotations

import numpy as np
import warp as wp

from ...kernels import load_once
from ...kernels import scatter as sc
from ..voxel_map import VoxelMap


def radius_scan(shard: VoxelMap, points, lengths, point_uncertainty, labels, class_weights) -> sc.ScanPoints:
    """A scan's points and payload on the device, through the shard's staging buffers."""
    upload = shard.staging.upload
    return sc.scan_points(points=upload("points", np.reshape(points, (-1, 3)), wp.vec3d, np.float64), lengths=upload("lengths", lengths, wp.float64, np.float64),
                          uncertainty=upload("uncertainty", point_uncertainty, wp.float64, np.float64),
                          labels=None if labels is None else upload("labels", labels, wp.int32, np.int32),
                          class_weights=None if class_weights is None else upload("class_weights", class_weights, wp.float64, np.float64))


def scatter(
    shard: VoxelMap,
    points: np.ndarray,
    lengths: np.ndarray,
    point_uncertainty: np.ndarray,
    *,
    mode: int,
    sigma0: float,
    reach: float | None,
    labels: np.ndarray | None = None,
    class_weights: np.ndarray | None = None,
    owner_blocks: np.ndarray | None = None,
    fusion: int = sc.FUSION_BAYES,
    **params,
) -> int:
    """One scatter launch over all points into ``shard`` (relaunching failed ones after growth); returns
    updates. ``reach``: how far (m) the points' kernels reach, checked against the key range before
    anything is written (None: the caller's inserted blocks hold every target); ``params``: the mode's
    further ``kernels.scatter.scatter_params`` (its blocks' cells per side, the stencil)."""
    n = len(points)
    if n == 0:
        return 0
    if (mode == sc.MODE_STENCIL or fusion == sc.FUSION_DEMPSTER) and class_weights is None:
        raise ValueError("the stencil mode and Dempster fusion read per-class weights: pass class_weights, not labels")
    kernel = sc.scatter_kernel(mode, fusion, labels is not None)
    load_once(kernel.module, shard.device)
    if reach is not None:
        shard.check_reach(points, reach)
    d = shard.device
    scan = radius_scan(shard, points, lengths, point_uncertainty, labels, class_weights)
    if owner_blocks is not None:
        scan.owner_blocks = shard.staging.upload("owner_blocks", owner_blocks, wp.vec3i, np.int32)
    scatter_params = sc.scatter_params(resolution=shard.resolution_m, grid_offset=shard.grid_offset_m, sigma0=sigma0, **params)

    def launch(ids, failed):
        scan.point_ids = ids
        wp.launch(kernel, dim=len(ids), device=d, inputs=[scan, scatter_params, shard.target(failed)])

    inserts = sc.scatter_inserts(mode)  # the other modes' points fail only where a target was never inserted (a bug): always read
    return shard.launch_until_done(n, launch, may_insert=inserts, kind=f"scatter{mode}", most_new=n, fails_only_when_full=inserts, resumes=inserts)
