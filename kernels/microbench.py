"""Kernels that only the performance study launches (tools/kernel_study.py): a streaming copy for the
bandwidth roof, and a keyed row add in float32 and float64 for the cost of the precision (Warp).

numpy twin: ``evsemmap_warp/reference/microbench.py``.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.kernel
def stream_copy(src: wp.array(dtype=wp.float64), dst: wp.array(dtype=wp.float64)):
    """Kernel, one thread per element: dst[i] = src[i] (float64), the streaming-bandwidth roof of the kernel
    study."""
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def add_rows64(rows: wp.array(dtype=int), weights: wp.array(dtype=wp.float64), data: wp.array2d(dtype=wp.float64)):
    """data[rows[t], :] += weights[t] with atomics, as the scatter's per-update row add."""
    t = wp.tid()
    for c in range(data.shape[1]):
        wp.atomic_add(data, rows[t], c, weights[t])


@wp.kernel
def add_rows32(rows: wp.array(dtype=int), weights: wp.array(dtype=wp.float32), data: wp.array2d(dtype=wp.float32)):
    """Kernel, one thread per update: atomically adds weights[t] to every column of float32 row rows[t] of
    ``data`` (the float32 side of the study's precision comparison)."""
    t = wp.tid()
    for c in range(data.shape[1]):
        wp.atomic_add(data, rows[t], c, weights[t])
