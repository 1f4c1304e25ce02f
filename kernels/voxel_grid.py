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

The parallel forms below (``leaf_runs`` to ``leaf_majority_labels``) do the same on a device, one
thread per point or per leaf, after a stable radix sort of the leaf indices (``wp.utils.radix_sort_pairs``):
``methods.sbki_device`` chains them, and its tests hold them to the one-thread forms bit for bit.

numpy twins: ``evsemmap_warp/reference/voxel_grid.py``.
"""

import warp as wp

from . import MODULE_OPTIONS
from .device_counts import PAST_COUNT_KEY
from .indexing import nonnegative

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def _leaf_index(p: wp.vec3, inverse_leaf: wp.float32, lowest: wp.vec3l, leaves_x: wp.int64, leaves_y: wp.int64) -> wp.int64:
    rx = wp.int64(wp.floor(p[0] * inverse_leaf)) - lowest[0]
    ry = wp.int64(wp.floor(p[1] * inverse_leaf)) - lowest[1]
    rz = wp.int64(wp.floor(p[2] * inverse_leaf)) - lowest[2]
    return rx + ry * leaves_x + rz * (leaves_x * leaves_y)


@wp.kernel
def leaf_indices(
    points: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=int),
    inverse_leaf: wp.float32,
    lowest_x: wp.int64,
    lowest_y: wp.int64,
    lowest_z: wp.int64,
    leaves_x: wp.int64,
    leaves_y: wp.int64,
    leaf: wp.array(dtype=wp.int64),
):
    """leaf[i] = point i's leaf index: floor(p * inverse_leaf) - lowest per axis, x fastest, for the first
    count[0] points; ``device_counts.PAST_COUNT_KEY`` past them."""
    i = wp.tid()
    if i >= count[0]:
        leaf[i] = PAST_COUNT_KEY
        return
    leaf[i] = _leaf_index(points[i], inverse_leaf, wp.vec3l(lowest_x, lowest_y, lowest_z), leaves_x, leaves_y)


@wp.kernel
def packed_leaf_indices(points: wp.array(dtype=wp.vec3), inverse_leaf: wp.float32, lowest: wp.vec3l, leaves_x: wp.int64, leaves_y: wp.int64,
                        position_bits: int, packed: wp.array(dtype=wp.int64)):
    """packed[i] = point i's leaf index (``leaf_indices``) << position_bits | i: the host path's sort values
    (``methods.sbki_compat.stable_sort``), packed in the pass that computes them."""
    i = wp.tid()
    packed[i] = (_leaf_index(points[i], inverse_leaf, lowest, leaves_x, leaves_y) << wp.int64(position_bits)) | wp.int64(i)


# leaf_centroids asks for the point this many places ahead in sorted order (docs/performance.md, "Measurements behind the code's choices").
POINTS_AHEAD = wp.constant(32)


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
__builtin_prefetch(&points.data[index]);
#endif
""")
def _prefetch_point(points: wp.array(dtype=wp.vec3), index: int): ...


@wp.func
def _leaf_centroid(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), start: int, n: int) -> wp.vec3:
    """The float32 mean of points[order[start:start + n]]: their float32 sum in that order, from zero, over n."""
    total = wp.vec3(0.0, 0.0, 0.0)
    for k in range(n):
        total = total + points[nonnegative(int(order[start + k]))]
    return total / float(n)


@wp.kernel
def leaf_centroids(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64),
                   counts: wp.array(dtype=wp.int64), centroids: wp.array(dtype=wp.vec3)):
    """centroids[l] = the float32 mean of points[order[starts[l]:starts[l] + counts[l]]]: their float32
    sum in that order, from zero, over the count."""
    last = order.shape[0] - 1
    leaves = starts.shape[0]
    leaf = int(0)
    while leaf < leaves:  # (a while loop and nonnegative indices: kernels.indexing)
        start = nonnegative(int(starts[leaf]))
        n = int(counts[leaf])
        # The points are read in sorted order, from all over the cloud: ask for the ones this many
        # positions ahead while this leaf sums (a hint, compiled out on CUDA).
        k = int(0)
        while k < n:
            _prefetch_point(points, int(order[wp.min(start + k + POINTS_AHEAD, last)]))
            k += 1
        centroids[leaf] = _leaf_centroid(points, order, start, n)
        leaf += 1


# leaf_centroids_of_sorted in place of listing the order and the runs' starts, then leaf_centroids
# (docs/performance.md, "Measurements behind the code's choices").
@wp.kernel
def leaf_centroids_of_sorted(points: wp.array(dtype=wp.vec3), packed: wp.array(dtype=wp.int64), position_bits: int,
                             centroids: wp.array(dtype=wp.vec3), leaf_count: wp.array(dtype=int)):
    """``leaf_centroids`` straight from the sorted packed leaf indices (``packed_leaf_indices``, sorted by
    leaf; one thread): each run of one leaf's points summed in float32 from zero in sorted order, over its
    count, into centroids[leaf]; leaf_count[0] = the leaves. One pass, where listing the order and the
    runs' starts first took a second one."""
    shift = wp.int64(position_bits)
    mask = (wp.int64(1) << shift) - wp.int64(1)
    n = packed.shape[0]
    leaves = int(0)
    previous = wp.int64(0)
    total = wp.vec3(0.0, 0.0, 0.0)
    count = int(0)
    k = int(0)
    while k < n:  # (a while loop and nonnegative indices: kernels.indexing)
        value = packed[k]
        _prefetch_point(points, int(packed[wp.min(k + POINTS_AHEAD, n - 1)] & mask))
        key = value >> shift
        if k > 0 and key != previous:
            centroids[leaves] = total / float(count)
            leaves += 1
            total = wp.vec3(0.0, 0.0, 0.0)
            count = 0
        total = total + points[nonnegative(int(value & mask))]
        count += 1
        previous = key
        k += 1
    if n > 0:
        centroids[leaves] = total / float(count)
        leaves += 1
    leaf_count[0] = leaves


# ------------------------------------------------------------------ parallel forms (one thread per point or leaf)


@wp.kernel
def point_bounds(points: wp.array(dtype=wp.vec3), count: wp.array(dtype=int), lowest: wp.array(dtype=wp.float32), highest: wp.array(dtype=wp.float32)):
    """lowest/highest (3 values each, starting at +/-inf) = the first count[0] points' per-axis minimum and maximum."""
    i = wp.tid()
    if i >= count[0]:
        return
    p = points[i]
    for axis in range(3):
        wp.atomic_min(lowest, axis, p[axis])
        wp.atomic_max(highest, axis, p[axis])


@wp.kernel
def positions(values: wp.array(dtype=wp.int64)):
    """values[i] = i: the input order the stable sort carries along."""
    i = wp.tid()
    values[i] = wp.int64(i)


@wp.kernel
def leaf_runs(sorted_leaf: wp.array(dtype=wp.int64), count: wp.array(dtype=int), leaf_of: wp.array(dtype=int)):
    """leaf_of[k] = 1 where sorted position k (of the first count[0]) starts a new leaf, else 0, and 0 past
    the count (an inclusive scan of it, minus one, is position k's leaf number; its last value the leaf count)."""
    k = wp.tid()
    head = 1
    if k >= count[0]:
        head = 0
    elif k > 0:
        if sorted_leaf[k] == sorted_leaf[k - 1]:
            head = 0
    leaf_of[k] = head


@wp.kernel
def leaf_starts(leaf_rank: wp.array(dtype=int), count: wp.array(dtype=int), starts: wp.array(dtype=wp.int64)):
    """starts[leaf] = the first sorted position of each leaf among the first count[0]; leaf_rank is the
    inclusive scan of ``leaf_runs`` (leaf numbers from 1). starts[leaf count] = the point count (0 for none)."""
    k = wp.tid()
    n = count[0]
    if k >= n:
        if k == 0:
            starts[0] = wp.int64(0)
        return
    if k == 0 or leaf_rank[k] != leaf_rank[wp.max(k - 1, 0)]:
        starts[leaf_rank[k] - 1] = wp.int64(k)
    if k == n - 1:
        starts[leaf_rank[k]] = wp.int64(n)


@wp.kernel
def leaf_centroids_parallel(points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64),
                            leaf_count: wp.array(dtype=int), centroids: wp.array(dtype=wp.vec3)):
    """``leaf_centroids``, one thread per leaf of leaf_count[0] (leaf l owns sorted positions starts[l]:starts[l + 1])."""
    leaf = wp.tid()
    if leaf >= leaf_count[0]:
        return
    start = int(starts[leaf])
    centroids[leaf] = _leaf_centroid(points, order, start, int(starts[leaf + 1]) - start)


@wp.kernel
def leaf_label_keys(order: wp.array(dtype=wp.int64), leaf_rank: wp.array(dtype=int), labels: wp.array(dtype=wp.int64), count: wp.array(dtype=int),
                    label_min: wp.int64, label_span: wp.int64, keys: wp.array(dtype=wp.int64), positions: wp.array(dtype=wp.int64)):
    """keys[k] = (leaf number of sorted position k) * label_span + its point's label - label_min: sorted,
    each leaf's labels in ascending order; ``device_counts.PAST_COUNT_KEY`` past the first count[0]. positions[k] = k."""
    k = wp.tid()
    positions[k] = wp.int64(k)
    if k >= count[0]:
        keys[k] = PAST_COUNT_KEY
        return
    keys[k] = wp.int64(leaf_rank[k] - 1) * label_span + labels[int(order[k])] - label_min


@wp.kernel
def leaf_majority_labels(sorted_keys: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64), leaf_count: wp.array(dtype=int),
                         label_min: wp.int64, label_span: wp.int64, majority: wp.array(dtype=wp.int64)):
    """majority[l] = leaf l's most frequent label, the smallest on ties: its labels ascending in
    sorted_keys[starts[l]:starts[l + 1]] (from ``leaf_label_keys``), counted run by run, for the leaf_count[0] leaves."""
    leaf = wp.tid()
    if leaf >= leaf_count[0]:
        return
    start = int(starts[leaf])
    end = int(starts[leaf + 1])
    best_label = sorted_keys[start] % label_span
    best_count = int(0)
    run_label = best_label
    run_count = int(0)
    for k in range(start, end):
        label = sorted_keys[k] % label_span
        if label != run_label:
            run_label = label
            run_count = 0
        run_count += 1
        if run_count > best_count:  # strictly more: on ties the smaller label, met first, stays
            best_count = run_count
            best_label = run_label
    majority[leaf] = best_label + label_min
