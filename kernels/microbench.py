"""Kernels that only the performance study launches (tools/kernel_study.py): a streaming copy for the
bandwidth roof, a keyed row add in float32 and float64 for the cost of the precision, and the radix
sort's scatter pass in each index form (``radix_scatter_form``) for the cost of Warp's wrap of negative
indices (Warp).

numpy twin: ``evsemmap_warp/reference/microbench.py``.
"""

import functools

import warp as wp

from . import MODULE_OPTIONS
from .indexing import nonnegative

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


@wp.func
def as_read(index: int) -> int:
    """``index`` as it is: the form Warp's wrap of a negative index stays on (beside ``nonnegative``)."""
    return index


@functools.cache
def radix_scatter_form(while_loop: bool, masked: bool):
    """``kernels.radix_sort.radix_scatter`` (one thread) with its loop a ``while`` loop or a range loop, and
    its indices through ``indexing.nonnegative`` (the sign bit masked, so the compiler drops Warp's wrap of
    negative indices) or as read: the study times the four forms (``tools/kernel_study.py --index-forms``),
    the same pass either way."""
    index = nonnegative if masked else as_read

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def radix_scatter_form_kernel(values_in: wp.array(dtype=wp.int64), shift: int, digit_bits: int, next_slot: wp.array(dtype=int),
                                  values_out: wp.array(dtype=wp.int64)):
        mask = (wp.int64(1) << wp.int64(digit_bits)) - wp.int64(1)
        n = values_in.shape[0]
        if wp.static(while_loop):
            i = int(0)
            while i < n:
                value = values_in[i]
                digit = wp.static(index)(int((value >> wp.int64(shift)) & mask))
                slot = next_slot[digit]
                next_slot[digit] = slot + 1
                values_out[wp.static(index)(slot)] = value
                i += 1
        else:
            for k in range(n):
                value = values_in[wp.static(index)(k)]
                digit = wp.static(index)(int((value >> wp.int64(shift)) & mask))
                slot = next_slot[digit]
                next_slot[digit] = slot + 1
                values_out[wp.static(index)(slot)] = value

    return radix_scatter_form_kernel


KERNEL_FACTORIES = {"radix_scatter_form": radix_scatter_form}
