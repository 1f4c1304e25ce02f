"""The original S-BKI's block update as a gather kernel (docs/compatibility.md §1) (Warp).

S-BKI predicts, for every test block T (a block holding points or a face neighbour of one), from the
points of the blocks of T's extended block (T and its 6 face neighbours). Here one thread per test block
finds or inserts its cells once (one probe of the map's brick cache for a block whose rows are
consecutive, else one table probe per cell; ``VoxelMap._allocate_brick_cache``), reads those points once
and weighs each against all of T's cells with the float32 kernel of the scatter form (``kernels.scatter``
MODE_SBKI_BLOCKS): no atomics, and a fixed order for every sum. The points arrive divided by ell in
float32, as the C++ scales them (``scale_points``), and the cells' centers are scaled once per block. That
float32 kernel is zero from d = 0.984 ell on (every float32 distance from 0.95 to 8 ell checked,
tests/test_sbki_compat.py), so no reach test is needed beyond the kernel's own sign, and a point at 0.99
ell or more from the box of the block's cell centers is skipped with one test. A face neighbour's points
are read through the scan's near-face masks (``near_face_masks``: per 64 sorted points and face, those
that may lie nearer than that), so the half of them beyond reach is never visited and the skip test
rarely fails. Each thread prefetches the
cells of the block a few threads ahead. The cell loop is written cell by cell, with a branch on the
kernel's sign: the compiler turns it into AVX-512 code over a block's 8 cells (the kernel in 8 lanes, then
masked adds). A form without the branch, which adds every cell's value and counts the positive ones,
compiles to vector code too and measured slower (tools/kernel_study.py keeps both forms and times them);
forms the compiler does not vectorise measured slower still (docs/performance.md, "Measurements behind the
code's choices").

The kernel is made per (class count, cells per block) (``gather_sbki_kernel``) from the block gathers' one
traversal (``block_gather_kernel``: a thread per target block, its cells found or inserted once, then the
method's sums); its loops are not unrolled, which compiles much faster at the same speed.

numpy twin: ``evsemmap_warp/reference/block_gather.py``.
"""

import functools

import warp as wp

from . import MODULE_OPTIONS
from .device_counts import PAST_COUNT_KEY
from .hash_table import PREFETCH_AHEAD, PREFETCH_NEARER, HashTable, block_cell, block_first_cell, find_block_rows, prefetch_brick
from .indexing import nonnegative
from .scatter import ONE64, ZERO64, sbki_sparse_kernel_scaled, sbki_voxel_center, tally_row, touch_row

wp.set_module_options(MODULE_OPTIONS)

f64 = wp.float64


# The float32 S-BKI kernel is zero (not positive) at this distance over ell and beyond (its last
# positive value is at 0.983759; tests/test_sbki_compat.py checks every float32 distance up to 8).
SBKI_ZERO_BEYOND = 0.99
# A point is skipped when its squared distance (over ell) to the box of the block's scaled cell centers is
# at least this: the box distance comes from the same float32 differences as the cells' distances, so no
# cell is nearer than the box by more than rounding, far inside the margin from 0.984 to 0.99.
BOX_SKIP_DISTANCE2 = SBKI_ZERO_BEYOND * SBKI_ZERO_BEYOND


@wp.func
def box_distance2(lo: wp.vec3, hi: wp.vec3, p: wp.vec3):
    """Squared distance from p to the box [lo, hi] (0 inside)."""
    dx = wp.max(wp.max(lo[0] - p[0], p[0] - hi[0]), 0.0)
    dy = wp.max(wp.max(lo[1] - p[1], p[1] - hi[1]), 0.0)
    dz = wp.max(wp.max(lo[2] - p[2], p[2] - hi[2]), 0.0)
    return dx * dx + dy * dy + dz * dz


# The sorted points in words of PAIRS_PER_WORD: bit i of a word's mask stands for point word * 64 + i.
PAIRS_PER_WORD = wp.constant(64)
ALL_PAIRS = wp.constant(wp.int64(-1))
# The face neighbours of a block in the order of the sources after the block itself (the 6 faces of
# ``methods.sbki_compat.EXTENDED_BLOCK_OFFSETS``, tested): +x, -x, +y, -y, +z, -z.
FACE_COUNT = 6
# A near-face mask's reach (squared, over ell) along the face's axis: above the gather's own test
# (BOX_SKIP_DISTANCE2), which decides; the mask only has to keep every point that test keeps, with room
# for any device's rounding of the box.
NEAR_FACE_DISTANCE2 = 1.0


@wp.struct
class SbkiBlocks:
    """One scan's S-BKI gather inputs: the test ``blocks`` [T], their 7 ``sources`` [T, 7] (indices of
    blocks holding points, -1 for none), the points of block s at ``point_start[s]:point_start[s + 1]``
    (``scaled_points``: float32 and divided by ell, as ``scale_points`` makes them; ``labels``), the
    points' ``near_faces`` masks (``near_face_masks``) and the kernel's ``length`` ell (m), ``sigma0``
    (sf2) and the lattice (``resolution``, ``grid_offset``, m)."""

    blocks: wp.array(dtype=wp.vec3i)
    sources: wp.array2d(dtype=int)
    point_start: wp.array(dtype=int)
    scaled_points: wp.array(dtype=wp.vec3)
    labels: wp.array(dtype=int)
    near_faces: wp.array2d(dtype=wp.int64)
    length: wp.float64
    sigma0: wp.float64
    resolution: wp.float64
    grid_offset: wp.float64


def sbki_blocks(*, blocks, sources, point_start, scaled_points, labels, near_faces, length: float, sigma0: float, resolution: float,
                grid_offset: float) -> SbkiBlocks:
    """An ``SbkiBlocks`` over device arrays."""
    inputs = SbkiBlocks()
    inputs.blocks, inputs.sources, inputs.point_start, inputs.scaled_points, inputs.labels = blocks, sources, point_start, scaled_points, labels
    inputs.near_faces = near_faces
    inputs.length, inputs.sigma0 = wp.float64(length), wp.float64(sigma0)
    inputs.resolution, inputs.grid_offset = wp.float64(resolution), wp.float64(grid_offset)
    return inputs


def near_face_words(pairs: int) -> int:
    """The rows of the near-face masks of ``pairs`` sorted points."""
    return (pairs + PAIRS_PER_WORD - 1) // PAIRS_PER_WORD


@wp.func
def pair_bits_between(lowest: int, end: int) -> wp.int64:
    """The bits i of a word with lowest <= i < end (either may lie outside 0..64)."""
    bits = ALL_PAIRS
    if lowest > 0:
        bits = bits & ~((wp.int64(1) << wp.int64(lowest)) - wp.int64(1))
    if end < PAIRS_PER_WORD:
        bits = bits & ((wp.int64(1) << wp.int64(wp.max(end, 0))) - wp.int64(1))
    return bits


@wp.func
def scaled_cell_coordinate(index: int, resolution: float, grid_offset: float, length: float) -> float:
    """A cell center's coordinate along one axis in float32, divided by ell (``sbki_voxel_center``)."""
    return ((float(index) + 0.5) * resolution + grid_offset) / length


face_bounds = wp.types.vector(length=FACE_COUNT, dtype=wp.float32)
face_words = wp.types.vector(length=FACE_COUNT, dtype=wp.int64)


@wp.kernel
def near_face_masks(scaled_points: wp.array(dtype=wp.vec3), pair_count: wp.array(dtype=int), point_start: wp.array(dtype=int),
                    block_count: wp.array(dtype=int), blocks: wp.array(dtype=wp.vec3i), cells_per_block: int, resolution: float,
                    grid_offset: float, length: float, near: wp.array2d(dtype=wp.int64)):
    """One thread per word of 64 of the pair_count[0] sorted points (block s, blocks[s], owns
    point_start[s]:point_start[s + 1] of block_count[0] blocks): near[word, f] has bit i set where point
    64 word + i lies less than sqrt(NEAR_FACE_DISTANCE2) ell, along face f's axis, from the box of the
    scaled cell centers of the test block whose f-th face neighbour is the point's block. A point the
    gather's box test keeps lies within that reach, so the gather visits only a word's set bits for a
    neighbour's points: about half of them, and no mispredicted skips."""
    word = wp.tid()
    first_pair = word * PAIRS_PER_WORD
    end = wp.min(first_pair + PAIRS_PER_WORD, pair_count[0])
    masks = face_words()
    if first_pair < end:
        # the block of the word's first point: the last s with point_start[s] <= first_pair
        s = int(0)
        top = block_count[0] - 1
        while s < top:
            middle = (s + top + 1) / 2
            if point_start[middle] <= first_pair:
                s = middle
            else:
                top = middle - 1
        lo = face_bounds()
        hi = face_bounds()
        n = cells_per_block
        q = first_pair
        while q < end and s < block_count[0]:  # the word's part of block s, block by block
            block = blocks[s]
            for f in range(FACE_COUNT):
                # the test block is this block less the face's offset (+1 along the axis for even f)
                test_first = (block[f / 2] - (1 - 2 * (f % 2))) * n - n / 2
                lo[f] = scaled_cell_coordinate(test_first, resolution, grid_offset, length)
                hi[f] = scaled_cell_coordinate(test_first + n - 1, resolution, grid_offset, length)
            block_end = wp.min(point_start[s + 1], end)
            for p in range(q, block_end):
                point = scaled_points[p]
                bit = wp.int64(1) << wp.int64(p - first_pair)
                for f in range(FACE_COUNT):
                    x = point[f / 2]
                    d = wp.max(wp.max(lo[f] - x, x - hi[f]), 0.0)
                    if d * d < wp.static(NEAR_FACE_DISTANCE2):
                        masks[f] = masks[f] | bit
            q = wp.max(q, block_end)
            s += 1
    for f in range(FACE_COUNT):
        near[word, f] = masks[f]


def scale_points(points, length_m: float):
    """The points [P, 3] as the kernel reads them: float32 coordinates divided by float32 ell, as the
    C++ covSparse scales both sides."""
    import numpy as np

    return np.asarray(points, dtype=np.float32) / np.float32(length_m)


@functools.cache
def block_rows_type(cells: int):
    """The vector of a block's ``cells`` rows (one type per size, shared by the skeleton and the methods)."""
    return wp.types.vector(length=cells, dtype=int)


def block_gather_kernel(Inputs, gather_block, *, cells_per_block: int, prefetch: bool):
    """The block gathers' one traversal, a kernel (launch_ids, block_ids, block_count, scan: Inputs, table,
    bricks, voxel_data, failed, update_count): thread t takes target block b = block_ids[launch_ids[t]] (its
    index ``scan.blocks[b]``; none where b is not below block_count[0], the blocks a device counted), asks for the blocks a few threads ahead (``prefetch_brick``, with ``prefetch``),
    finds or inserts its n^3 cells once (``find_block_rows`` through the brick cache ``bricks``; a block
    that does not fit adds nothing and is flagged in ``failed`` for a relaunch after the table grew),
    marks them touched (``touch_row``, before any read of them) and hands them to the method's
    ``gather_block(scan, b, first, rows, voxel_data) -> float64``, which sums the block's source points
    into its cells' rows and returns how many contributions it added. One Warp module per kernel, its
    loops not unrolled (a much faster cold compile at the same speed) and without an adjoint (a module of
    its own does not take this file's module options; tools/bench_compile.py times the compile)."""
    n = cells_per_block
    n3 = n * n * n
    cell_rows = block_rows_type(n3)

    @wp.kernel(module="unique", module_options={**MODULE_OPTIONS, "max_unroll": 1})
    def gather_blocks(
        launch_ids: wp.array(dtype=int),
        block_ids: wp.array(dtype=int),
        block_count: wp.array(dtype=int),
        scan: Inputs,
        table: HashTable,
        bricks: HashTable,
        voxel_data: wp.array2d(dtype=wp.float64),
        failed: wp.array(dtype=int),
        update_count: wp.array(dtype=wp.int64),
    ):
        t = wp.tid()
        if wp.static(prefetch):
            last = launch_ids.shape[0] - 1
            prefetch_brick(table, bricks, voxel_data, block_first_cell(scan.blocks[block_ids[launch_ids[wp.min(t + PREFETCH_AHEAD, last)]]], n),
                           block_first_cell(scan.blocks[block_ids[launch_ids[wp.min(t + PREFETCH_NEARER, last)]]], n), n3)
        b = block_ids[launch_ids[t]]
        if b >= block_count[0]:
            return
        first = block_first_cell(scan.blocks[b], n)
        rows = find_block_rows(cell_rows(), table, bricks, first, n)
        if rows[0] < 0:
            failed[t] = 1
            return
        for j in range(n3):
            touch_row(voxel_data, rows[j])
        wp.atomic_add(update_count, 0, wp.int64(wp.static(gather_block)(scan, b, first, rows, voxel_data)))

    return gather_blocks


@functools.cache
def gather_sbki_kernel(num_classes: int, cells_per_block: int, *, branch_free: bool = False, prefetch: bool = True, near_faces: bool = True):
    """The gather kernel (``block_gather_kernel`` over ``SbkiBlocks``) for K = num_classes and blocks of
    cells_per_block^3 cells (one Warp module per form, compiled on first use). The other forms are for the
    study (tools/kernel_study.py): ``branch_free`` (every cell's kernel value added, zeros included,
    instead of the branch on its sign; both compile to vector code over the cells), ``prefetch`` off,
    ``near_faces`` off (the masks ignored: every point of a neighbour visited and box-tested).
    Every form gives the same map bit for bit."""
    n = cells_per_block
    n3 = n * n * n
    # Sums per class and cell, cells along the rows: in the branch-free form a point's kernel values for
    # all cells add into one row (its label's) as one vector.
    class_cell_sums = wp.types.matrix(shape=(num_classes, n3), dtype=wp.float64)
    cell_scalars = wp.types.vector(length=n3, dtype=wp.float64)
    cell_floats = wp.types.vector(length=n3, dtype=wp.float32)
    cell_rows = block_rows_type(n3)

    # One function over ~80 lines, and its per-block work one Warp function: the cell sums are local
    # vectors and matrices, which a Warp function takes and returns by value, so a helper per step would
    # copy the block's sums in and out for every point instead of adding to them in registers.
    @wp.func
    def gather_sbki_block(scan: SbkiBlocks, b: int, first: wp.vec3i, rows: cell_rows, voxel_data: wp.array2d(dtype=wp.float64)) -> wp.float64:
        """Test block b (first cell ``first``, its cells' ``rows``): for each of its 7 source blocks
        scan.sources[b, :] (-1: holds no points; block s owns points point_start[s]:point_start[s + 1],
        given as ``scale_points`` makes them), each point adds the S-BKI kernel, where positive, for its
        label to every cell; every cell is marked touched. The block's own points are all visited, a face
        neighbour's through their near-face mask, then the box test (only a skip: a point beyond it adds
        nothing). Returns the contributions."""
        length32 = float(scan.length)
        sigma32 = float(scan.sigma0)
        resolution32 = float(scan.resolution)
        offset32 = float(scan.grid_offset)
        # Per cell, once per block: its center in float32 divided by ell (as the C++ scales both sides),
        # one coordinate per vector (the cell loops then vectorise).
        scaled_x = cell_floats()
        scaled_y = cell_floats()
        scaled_z = cell_floats()
        for j in range(n3):
            cell = block_cell(first, j, n)
            scaled = sbki_voxel_center(cell[0], cell[1], cell[2], resolution32, offset32) / length32
            scaled_x[j] = scaled[0]
            scaled_y[j] = scaled[1]
            scaled_z[j] = scaled[2]
        evidence = class_cell_sums()
        weight_sum = cell_scalars()
        hits = cell_scalars()
        # The scaled cell centers' box (the centers grow with the cell index): a point SBKI_ZERO_BEYOND or
        # more from it is as far from every cell center, where the kernel is zero, so one test skips it.
        box_lo = wp.vec3(scaled_x[0], scaled_y[0], scaled_z[0])
        box_hi = wp.vec3(scaled_x[n3 - 1], scaled_y[n3 - 1], scaled_z[n3 - 1])
        for f in range(scan.sources.shape[1]):
            s = scan.sources[b, f]
            if s >= 0:
                start = scan.point_start[s]
                end = scan.point_start[s + 1]
                for word in range(start / PAIRS_PER_WORD, (end + PAIRS_PER_WORD - 1) / PAIRS_PER_WORD):
                    base = word * PAIRS_PER_WORD
                    # all of the block's own points; of a neighbour's, those near the shared face
                    near = wp.where(f == 0 or not wp.static(near_faces), ALL_PAIRS, scan.near_faces[word, wp.max(f - 1, 0)])
                    pending = near & pair_bits_between(start - base, end - base)
                    while pending != wp.int64(0):
                        lowest = pending & (-pending)
                        pending = pending ^ lowest
                        q = base + wp.bit_count(lowest - wp.int64(1))
                        scaled_point = scan.scaled_points[q]
                        if f != 0 and box_distance2(box_lo, box_hi, scaled_point) >= wp.static(BOX_SKIP_DISTANCE2):
                            continue
                        label = scan.labels[q]
                        if wp.static(branch_free):
                            # Kernel values for all cells without branches (zeros where the kernel is not
                            # positive; the C++ adds only positive ones), then added in: adding 0 leaves a sum
                            # as it was.
                            weights = cell_scalars()
                            for j in range(n3):
                                weights[j] = f64(sbki_sparse_kernel_scaled(wp.vec3(scaled_x[j], scaled_y[j], scaled_z[j]), scaled_point, sigma32))
                            for j in range(n3):
                                evidence[label, j] = evidence[label, j] + weights[j]
                                weight_sum[j] = weight_sum[j] + weights[j]
                                hits[j] = hits[j] + wp.where(weights[j] > ZERO64, ONE64, ZERO64)
                        else:
                            for j in range(n3):
                                w = f64(sbki_sparse_kernel_scaled(wp.vec3(scaled_x[j], scaled_y[j], scaled_z[j]), scaled_point, sigma32))
                                if w > ZERO64:
                                    evidence[label, j] = evidence[label, j] + w
                                    weight_sum[j] = weight_sum[j] + w
                                    hits[j] = hits[j] + ONE64
        total = ZERO64
        for j in range(n3):
            row = rows[j]
            for c in range(num_classes):
                voxel_data[row, c] = voxel_data[row, c] + evidence[c, j]
            tally_row(voxel_data, row, num_classes, weight_sum[j], ZERO64, hits[j])  # S-BKI points carry no uncertainty
            total += hits[j]
        return total

    return block_gather_kernel(SbkiBlocks, gather_sbki_block, cells_per_block=n, prefetch=prefetch)


# A block and its 6 face neighbours: the blocks of S-BKI's extended block (``methods.sbki_compat``).
EXTENDED_BLOCK_COUNT = 7


@wp.kernel
def extended_block_tables(keys: wp.array(dtype=wp.int64), shifts: wp.array(dtype=wp.int64), last: wp.int64, tests: wp.array(dtype=wp.int64),
                          sources: wp.array2d(dtype=int), test_count: wp.array(dtype=int)):
    """The test blocks t (those with a block at t + shifts[f] for some f) in key order in
    tests[:test_count[0]], and sources[t, f] = the index of the block at t + shifts[f] (-1: none), from
    the distinct blocks' keys ascending, packed in a box one block wider than them on every side (so that
    a neighbour's key is the key plus a constant shift), followed by one key above ``last`` + every shift
    (``last``: the largest key a test block can have). For each f, keys[b] - shifts[f] ascends too: the
    test blocks are the merge of those runs without repeats, and the runs whose next key is the test
    block name its sources. One thread (launch with dim=1), no branch but the loop's end, and no grid
    over the blocks' bounding box to clear, fill and walk."""
    cursor = wp.vector(length=wp.static(EXTENDED_BLOCK_COUNT), dtype=int)
    count = int(0)
    while True:
        t = last + wp.int64(1)
        for f in range(wp.static(EXTENDED_BLOCK_COUNT)):
            t = wp.min(t, keys[nonnegative(cursor[f])] - shifts[f])
        if t > last:
            break
        tests[count] = t
        for f in range(wp.static(EXTENDED_BLOCK_COUNT)):
            source = wp.where(keys[nonnegative(cursor[f])] - shifts[f] == t, cursor[f], -1)
            sources[count, f] = source
            cursor[f] = cursor[f] + wp.where(source >= 0, 1, 0)
        count += 1
    test_count[0] = count


@wp.func
def _key_less(a: wp.vec3l, b: wp.vec3l) -> bool:
    """a before b in key order: x, then y, then z."""
    if a[0] != b[0]:
        return a[0] < b[0]
    if a[1] != b[1]:
        return a[1] < b[1]
    return a[2] < b[2]


@wp.kernel
def extended_block_tables_wide(blocks: wp.array(dtype=wp.vec3l), offsets: wp.array(dtype=wp.vec3l), cursor: wp.array(dtype=int),
                               tests: wp.array(dtype=wp.vec3l), sources: wp.array2d(dtype=int), test_count: wp.array(dtype=int)):
    """``extended_block_tables`` for blocks whose box is too large to pack (blocks spread over the whole
    key range, or beyond it): the same merge over the blocks themselves, distinct and in key order,
    compared axis by axis; ``cursor`` holds a zero per offset."""
    for _ in range(blocks.shape[0] * offsets.shape[0]):  # a test block per round; at most every (block, offset)
        t = wp.vec3l()
        found = int(0)
        for f in range(offsets.shape[0]):
            if cursor[f] < blocks.shape[0]:
                candidate = blocks[cursor[f]] - offsets[f]
                if found == 0 or _key_less(candidate, t):
                    t = candidate
                    found = 1
        if found == 0:
            break
        count = test_count[0]
        tests[count] = t
        for f in range(offsets.shape[0]):
            source = int(-1)
            if cursor[f] < blocks.shape[0]:
                if blocks[cursor[f]] - offsets[f] == t:
                    source = cursor[f]
                    cursor[f] = source + 1
            sources[count, f] = source
        test_count[0] = count + 1


# ------------------------------------------------------------------ the scan's tables built in parallel
# ``methods.sbki_compat.gather_tables`` on a device (``methods.sbki_device``): the pairs sorted by their
# block's position in the blocks' bounding box (a stable radix sort), the distinct blocks entered in a
# dense grid, the test blocks marked around them and listed in grid order by a scan of the marks.


@wp.kernel
def block_bounds(blocks: wp.array2d(dtype=wp.int64), count: wp.array(dtype=int), lowest: wp.array(dtype=wp.int64), highest: wp.array(dtype=wp.int64)):
    """lowest/highest (3 values, starting at the int64 extremes) = the first count[0] blocks' per-axis bounds."""
    k = wp.tid()
    if k >= count[0]:
        return
    for axis in range(3):
        wp.atomic_min(lowest, axis, blocks[k, axis])
        wp.atomic_max(highest, axis, blocks[k, axis])


@wp.func
def _box_position(blocks: wp.array2d(dtype=wp.int64), k: int, lowest: wp.vec3l, span_y: wp.int64, span_z: wp.int64) -> wp.int64:
    return ((blocks[k, 0] - lowest[0]) * span_y + (blocks[k, 1] - lowest[1])) * span_z + (blocks[k, 2] - lowest[2])


@wp.kernel
def box_positions(blocks: wp.array2d(dtype=wp.int64), count: wp.array(dtype=int), lowest: wp.vec3l, span_y: wp.int64, span_z: wp.int64,
                  positions: wp.array(dtype=wp.int64), pair_index: wp.array(dtype=wp.int64)):
    """positions[k] = block k's row-major position in the box from ``lowest`` (x, then y, then z: the
    packed keys' order), ``device_counts.PAST_COUNT_KEY`` past the first count[0]; pair_index[k] = k."""
    k = wp.tid()
    pair_index[k] = wp.int64(k)
    if k >= count[0]:
        positions[k] = PAST_COUNT_KEY
        return
    positions[k] = _box_position(blocks, k, lowest, span_y, span_z)


@wp.kernel
def packed_box_positions(blocks: wp.array2d(dtype=wp.int64), lowest: wp.vec3l, span_y: wp.int64, span_z: wp.int64, position_bits: int,
                         packed: wp.array(dtype=wp.int64)):
    """packed[k] = block k's position in the box (``box_positions``) << position_bits | k: the host path's
    sort values (``methods.sbki_compat.group_by_block``), packed in the pass that computes them."""
    k = wp.tid()
    packed[k] = (_box_position(blocks, k, lowest, span_y, span_z) << wp.int64(position_bits)) | wp.int64(k)


@wp.kernel
def distinct_blocks(member_blocks: wp.array2d(dtype=wp.int64), order: wp.array(dtype=wp.int64), starts: wp.array(dtype=wp.int64),
                    block_count: wp.array(dtype=int), grid_lowest: wp.vec3l, blocks: wp.array(dtype=wp.vec3i), grid_blocks: wp.array(dtype=wp.vec3i),
                    grid: wp.array3d(dtype=int)):
    """Block b of block_count[0] (the pairs' b-th distinct block, its first pair order[starts[b]]), in map
    and in grid coordinates, and grid[it] = b."""
    b = wp.tid()
    if b >= block_count[0]:
        return
    k = int(order[int(starts[b])])
    blocks[b] = wp.vec3i(int(member_blocks[k, 0]), int(member_blocks[k, 1]), int(member_blocks[k, 2]))
    c = wp.vec3i(int(member_blocks[k, 0] - grid_lowest[0]), int(member_blocks[k, 1] - grid_lowest[1]), int(member_blocks[k, 2] - grid_lowest[2]))
    grid_blocks[b] = c
    grid[c[0], c[1], c[2]] = b


@wp.kernel
def mark_test_blocks(grid_blocks: wp.array(dtype=wp.vec3i), block_count: wp.array(dtype=int), offsets: wp.array(dtype=wp.vec3i),
                     grid: wp.array3d(dtype=int), marked: wp.array(dtype=int)):
    """marked[cell] = 1 (flat, row-major over the grid) for every block (of block_count[0]) + offset: the test blocks."""
    b, f = wp.tid()
    if b >= block_count[0]:
        return
    c = grid_blocks[b] + offsets[f]
    marked[(c[0] * grid.shape[1] + c[1]) * grid.shape[2] + c[2]] = 1


@wp.kernel
def list_test_blocks(marked: wp.array(dtype=int), slot: wp.array(dtype=int), grid: wp.array3d(dtype=int), offsets: wp.array(dtype=wp.vec3i),
                     grid_lowest: wp.vec3l, tests: wp.array(dtype=wp.vec3i), sources: wp.array2d(dtype=int)):
    """Each marked cell's test block at slot[cell] - 1 (slot: the inclusive scan of the marks, so grid
    order), in map coordinates (grid + grid_lowest), and its sources[t, f] = grid[cell + offsets[f]]."""
    cell = wp.tid()
    if marked[cell] == 0:
        return
    t = slot[cell] - 1
    z = cell % grid.shape[2]
    y = (cell / grid.shape[2]) % grid.shape[1]
    x = cell / (grid.shape[1] * grid.shape[2])
    tests[t] = wp.vec3i(int(wp.int64(x) + grid_lowest[0]), int(wp.int64(y) + grid_lowest[1]), int(wp.int64(z) + grid_lowest[2]))
    for f in range(offsets.shape[0]):
        c = wp.vec3i(x, y, z) + offsets[f]
        sources[t, f] = grid[c[0], c[1], c[2]]


@wp.kernel
def sorted_block_points(points: wp.array(dtype=wp.vec3), labels: wp.array(dtype=wp.int64), point_ids: wp.array(dtype=wp.int64),
                        order: wp.array(dtype=wp.int64), pair_count: wp.array(dtype=int), length: wp.float32, scaled_points: wp.array(dtype=wp.vec3),
                        sorted_labels: wp.array(dtype=int)):
    """The pair_count[0] pairs' points in block order as the gather kernel reads them: divided by ell in
    float32 (``scale_points``), and their labels."""
    k = wp.tid()
    if k >= pair_count[0]:
        return
    i = int(point_ids[int(order[k])])
    scaled_points[k] = points[i] / length
    sorted_labels[k] = int(labels[i])


@wp.kernel
def narrow_starts(wide: wp.array(dtype=wp.int64), block_count: wp.array(dtype=int), narrow: wp.array(dtype=int)):
    """narrow[i] = wide[i] as the gather kernel's int point starts, for the block_count[0] + 1 of them."""
    i = wp.tid()
    if i > block_count[0]:
        return
    narrow[i] = int(wide[i])


# Kernels made by factories, by name (tests/test_twins.py looks their twins up by these names).
KERNEL_FACTORIES = {"gather_sbki_blocks": gather_sbki_kernel}
