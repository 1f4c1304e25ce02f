"""The released EvSemMap's block models as one gather kernel (docs/compatibility.md §4) (Warp).

In the release every block holding points trains a model on the points of its extended block (itself
and its 6 face neighbours) and predicts for the blocks of that extended block that hold points. So a
point of block M reaches a target block T through every occupied model block N with N in M's
extended block and T in N's; targets lie within L1 distance 2 of M. Here each cell of a target block
is one thread that walks the points of its up to 25 source blocks once, each weighted by how many
models carry it (``methods.evsemmap_release.release_blocks`` computes both tables): no model is ever
built, no atomics, and the order of every sum is fixed, so the map does not depend on threads.

The kernel is made per class count K (``gather_release_kernel(K)``): a cell's K evidence sums live
in a register vector and are written once, which measured 2x faster than adding into the table row
per contribution.

numpy twin: ``evsemmap_warp/reference/release.py`` (a literal block-by-block model loop).
"""

from __future__ import annotations

import functools

import warp as wp

from .hash_table import pack_key, table_find
from .scatter import (_BELIEF_EPSILON, _ONE, _ZERO, COL_HITS, COL_WEIGHT, COL_WEIGHTED_UNCERTAINTY,
                      FUSION_DEMPSTER, sbki_voxel_center)

wp.set_module_options({"enable_backward": False})

f64 = wp.float64


def _sparse_kernel_polynomial(degree: int = 14):
    """Power-series coefficients in s = 2x - 1 of the sparse kernel's shape on x = d / l in [0, 1],
    k(x) = (2 + cos 2 pi x)(1 - x) / 3 + sin(2 pi x) / (2 pi), from a Chebyshev fit: max error 2.5e-9,
    below float32's resolution of the release's own float32 arithmetic. Two float32 trig calls per
    candidate cost 45 ns here; the polynomial is a few FMAs."""
    import numpy as np
    from numpy.polynomial import chebyshev

    x = np.linspace(0.0, 1.0, 20001)
    shape = (2 + np.cos(2 * np.pi * x)) * (1 - x) / 3 + np.sin(2 * np.pi * x) / (2 * np.pi)
    return chebyshev.cheb2poly(chebyshev.chebfit(2 * x - 1, shape, degree))


_POLY = _sparse_kernel_polynomial()
_vec_poly = wp.types.vector(length=len(_POLY), dtype=wp.float64)
_POLY_COEFFS = wp.constant(_vec_poly(*[float(c) for c in _POLY]))
_POLY_TOP = wp.constant(len(_POLY) - 1)


@wp.func
def release_sparse_kernel(d2: float, length: wp.float64, sf2: float) -> float:
    """The release's covSparseUnc for a float32 squared distance d2: the distance divided in double by
    ell * e, the kernel shape (polynomial above), times sf2, rounded to float32; 0 from d = l on."""
    x = f64(wp.sqrt(d2)) / length
    if x >= _ONE:
        return 0.0
    s = f64(2.0) * x - _ONE
    k = _POLY_COEFFS[_POLY_TOP]
    for i in range(_POLY_TOP):
        k = k * s + _POLY_COEFFS[_POLY_TOP - 1 - i]
    return float(wp.max(k, _ZERO)) * sf2


@functools.cache
def gather_release_kernel(num_classes: int):
    """The gather kernel for K = num_classes (one Warp module per K, compiled on first use)."""
    vec_k = wp.types.vector(length=num_classes, dtype=wp.float64)

    @wp.kernel(module="unique")
    def gather_release_blocks(
        blocks: wp.array(dtype=wp.vec3i),
        block_ids: wp.array(dtype=int),
        source_blocks: wp.array2d(dtype=int),
        source_mult: wp.array2d(dtype=int),
        point_start: wp.array(dtype=int),
        points: wp.array(dtype=wp.vec3),
        class_weights: wp.array(dtype=vec_k),
        point_uncertainty: wp.array(dtype=wp.float64),
        length: wp.float64,
        sigma0: float,
        resolution: float,
        cells_per_block: int,
        fusion: int,
        table_keys: wp.array(dtype=wp.int64),
        voxel_data: wp.array2d(dtype=wp.float64),
        failed: wp.array(dtype=int),
        update_count: wp.array(dtype=wp.int64),
    ):
        """One thread per cell of target block blocks[block_ids[t / cells^3]]: the points of its source
        blocks source_blocks[b, :] (indices into ``blocks``, -1 for none; block s owns points
        point_start[s]:point_start[s + 1], one row per (point, block holding it) pair), each counted
        source_mult[b, :] times. Adds k(d) * y (Bayes) or the log commonality ratios (Dempster) and the
        bookkeeping columns into the cell's row, which must exist."""
        t = wp.tid()
        n = cells_per_block
        n3 = n * n * n
        b = block_ids[t / n3]
        j = t - (t / n3) * n3
        first = blocks[b] * n - wp.vec3i(n / 2, n / 2, n / 2)
        ix = first[0] + j / (n * n)
        iy = first[1] + (j / n) % n
        iz = first[2] + j % n
        slot = table_find(table_keys, pack_key(ix, iy, iz))
        if slot < 0:
            failed[t] = 1
            return
        centre = sbki_voxel_center(ix, iy, iz, resolution, 0.0)
        reach = float(length)
        reach2 = reach * reach
        evidence = vec_k()
        weight_sum = _ZERO
        weighted_u = _ZERO
        hits = _ZERO
        for o in range(source_blocks.shape[1]):
            s = source_blocks[b, o]
            if s >= 0:
                mult = f64(source_mult[b, o])
                for q in range(point_start[s], point_start[s + 1]):
                    p = points[q]
                    diff = centre - p
                    d2 = wp.dot(diff, diff)
                    if d2 < reach2:
                        w = f64(release_sparse_kernel(d2, length, sigma0))
                        if w > _ZERO:
                            y = class_weights[q]
                            if fusion == FUSION_DEMPSTER:
                                wb = wp.min(w, _ONE)
                                committed = _ZERO
                                for c in range(num_classes):
                                    committed += wp.clamp(y[c] * wb, _ZERO, _ONE - _BELIEF_EPSILON)
                                uncommitted = wp.max(_ONE - committed, _BELIEF_EPSILON)
                                for c in range(num_classes):
                                    evidence[c] += mult * wp.log(_ONE + wp.clamp(y[c] * wb, _ZERO, _ONE - _BELIEF_EPSILON) / uncommitted)
                            else:
                                evidence += (mult * w) * y
                            weight_sum += mult * w
                            weighted_u += mult * w * point_uncertainty[q]
                            hits += mult
        for c in range(num_classes):
            voxel_data[slot, c] = voxel_data[slot, c] + evidence[c]
        k = num_classes
        voxel_data[slot, k + COL_WEIGHT] = voxel_data[slot, k + COL_WEIGHT] + weight_sum
        voxel_data[slot, k + COL_WEIGHTED_UNCERTAINTY] = voxel_data[slot, k + COL_WEIGHTED_UNCERTAINTY] + weighted_u
        voxel_data[slot, k + COL_HITS] = voxel_data[slot, k + COL_HITS] + hits
        wp.atomic_add(update_count, 0, wp.int64(hits))

    return gather_release_blocks


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_release_blocks": gather_release_kernel}


def vector_type(num_classes: int):
    """The per-point class-weight row type the kernel for K classes reads."""
    return wp.types.vector(length=num_classes, dtype=wp.float64)
