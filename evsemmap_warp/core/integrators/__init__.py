"""Integrators, and their one registry: each integration method is one module here that owns its work (its
kernels' launches, through the map's grow-and-relaunch protocol, and its host preparation), behind one
protocol (``base.Integrator``): made from (config, num_classes) through the registry (``make_integrator``,
keyed by the integration method: the compatibility mode and the kernel), each declares what it needs of a
scan (``ScanNeeds``: the sensor origin, the payload kinds) and the kernel modules it runs
(``kernel_modules(device)``: the Mapper compiles those, and only those, before its first scan), and turns a
validated scan into its launch with ``prepare(scan, device)`` (host work only, no map access); the launch
runs the kernels on the shards. The map (``core.voxel_map``) is storage and knows no method.

* ``point_kernel.PointKernelIntegrator``: the paper's clean algorithm (docs/algorithm.md §3) for S-CSM,
  S-BKI, EBS and the ablations: optional per-insertion uncertainty threshold, optional adaptive length,
  one scatter. With ``fusion: dempster`` the same scatter fuses belief masses instead (§3.7).
* ``convbki.ConvBkiIntegrator``: ConvBKI (docs/compatibility.md §2): voxelise, then a per-class stencil scatter.
* ``see_csom.SeeCsomIntegrator``: SEE-CSOM (docs/compatibility.md §3): block statistics, then a block-gated scatter.
* ``sbki.SbkiCompatIntegrator``: the original S-BKI / S-CSM C++ (docs/compatibility.md §1).
* ``release.ReleaseCompatIntegrator``: the release mode, the released EvSemMap C++ for ebs and dempster
  (docs/compatibility.md §4).

Shared by several: ``scatter`` (the scatter family's launch) and ``gathers`` (the block gathers' launch).
All receive the map as a list of shards (``core.shards``: each CPU worker scatters a contiguous part of
the scan into its own shard; the block gathers put each block in the shard its index picks, so their
maps do not depend on the number of workers). A new method adds its module and one line below.
"""

from __future__ import annotations

from ...config import Compat, Kernel, MappingConfig
from .base import (IntegrationStats, Integrator, Launch, ScanNeeds, ScanPayload, SensorOrigin, dirichlet_beliefs, launch_step,
                   per_class_quantile_mask, scatter_fusion, threshold_mask, uncertainty_quantile_mask)
from .convbki import ConvBkiIntegrator
from .point_kernel import PointKernelIntegrator
from .release import ReleaseCompatIntegrator
from .sbki import SbkiCompatIntegrator
from .see_csom import SeeCsomIntegrator

__all__ = ["INTEGRATORS", "ConvBkiIntegrator", "IntegrationStats", "Integrator", "Launch", "PointKernelIntegrator",
           "ReleaseCompatIntegrator", "SbkiCompatIntegrator", "ScanNeeds", "ScanPayload", "SeeCsomIntegrator", "SensorOrigin",
           "dirichlet_beliefs", "launch_step", "make_integrator", "per_class_quantile_mask", "register_integrator", "scatter_fusion",
           "threshold_mask", "uncertainty_quantile_mask"]

# (compat, kernel) -> the integrator class of that integration method.
INTEGRATORS: dict[tuple[Compat, Kernel], type] = {}


def register_integrator(compat: Compat, *kernels: Kernel):
    """Register ``cls`` (``register_integrator(compat, *kernels)(cls)``) as the integrator of mode ``compat``
    with each of ``kernels``; a method registered twice is refused (ValueError)."""

    def register(cls):
        for kernel in kernels:
            if (compat, kernel) in INTEGRATORS:
                raise ValueError(f"two integrators for {compat.value} mode with the {kernel.value} kernel")
            INTEGRATORS[compat, kernel] = cls
        return cls

    return register


register_integrator(Compat.CLEAN, Kernel.SPARSE, Kernel.COUNT)(PointKernelIntegrator)
register_integrator(Compat.CLEAN, Kernel.COMPOUND)(ConvBkiIntegrator)
register_integrator(Compat.CLEAN, Kernel.TRIANGULAR)(SeeCsomIntegrator)
register_integrator(Compat.SBKI, Kernel.SPARSE, Kernel.COUNT)(SbkiCompatIntegrator)
register_integrator(Compat.RELEASE, Kernel.SPARSE)(ReleaseCompatIntegrator)


def make_integrator(config: MappingConfig, num_classes: int) -> Integrator:
    """The integrator of ``config``'s method (its compatibility mode and kernel) for K = num_classes."""
    try:
        cls = INTEGRATORS[config.compat, config.kernel]
    except KeyError:
        raise ValueError(f"no integrator for mapping.compat {config.compat.value} with mapping.kernel {config.kernel.value}") from None
    return cls(config, num_classes)
