"""2.5-D terrain layers from a voxel map (Warp): the column reduction over the map's voxels and the
neighbourhood filters on the cell grid (docs/terrain.md).

Cells: cell (i, j) of a grid spans x in [x0 + i * cell, x0 + (i + 1) * cell), y likewise with row j
(j grows with y here; the Python layer turns grids north-up). A voxel belongs to the cell its center
falls in. Voxel indices arrive relative to a reference voxel (``shift`` is that voxel's lower corner
minus the grid's lower corner, m), so every number stays small however far the map lies from (0, 0, 0).

Column reduction (one thread per voxel, int64 atomics, so the result does not depend on the order the
threads run in): a cell keeps, packed as (z index << 32) | row, the highest occupied voxel
(``top_key``), the highest occupied voxel of a surface class (``support_key``), the lowest occupied z
index, and the sum of its voxels' contribution counts; a second launch (``column_cover``) finds the
highest occupied voxel at most ``clearance_voxels`` above the support (or above the lowest occupied
voxel where the cell has no support): what a robot standing on the surface meets. Ties between voxels
of one z index (cells larger than a voxel) go to the highest row. Counts are integers in float64, so
their sum is exact in any order.

Filters (one thread per cell, 2-D launch over [rows, columns]): a least-squares plane z = a x + b y + c
over the known cells of a (2 r + 1)^2 window gives the slope (degrees) and the roughness (RMS residual,
m); the step is the largest |z - z_n| to a known cell of the (2 r + 1)^2 window. Unknown cells are NaN.

numpy twins: ``evsemmap_warp/reference/terrain.py``.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

Z_OFFSET = 1 << 30  # packed z index = z + Z_OFFSET >= 0 for |z| < 2^30
NO_VOXEL = -1  # a cell's key before any voxel reached it
_Z_OFFSET = wp.constant(wp.int64(Z_OFFSET))
_ROW_MASK = wp.constant(wp.int64((1 << 32) - 1))


@wp.func
def pack_voxel(z: int, row: int) -> wp.int64:
    """A column entry as one int64, (z + Z_OFFSET) << 32 | row, so that an atomic max picks the highest voxel
    (z index, then row)."""
    return ((wp.int64(z) + _Z_OFFSET) << wp.int64(32)) | wp.int64(row)


@wp.func
def packed_z(key: wp.int64) -> int:
    """The z index a ``pack_voxel`` entry holds."""
    return int((key >> wp.int64(32)) - _Z_OFFSET)


@wp.struct
class ColumnGrid:
    """The cell grid the column kernels reduce onto, as they see it: ``voxel_m`` the voxel size (m);
    ``shift_x``, ``shift_y`` the reference voxel's lower corner minus the grid's lower corner (m);
    ``cell_m`` the cell size (m); ``width``, ``height`` the cells per row and the rows; ``z_low``,
    ``z_high`` the voxel z indices kept (inclusive, relative to the reference voxel)."""

    voxel_m: wp.float64
    shift_x: wp.float64
    shift_y: wp.float64
    cell_m: wp.float64
    width: int
    height: int
    z_low: int
    z_high: int


def column_grid(voxel_m: float, shift_x: float, shift_y: float, cell_m: float, width: int, height: int, z_low: int,
                z_high: int) -> ColumnGrid:
    """The ``ColumnGrid`` struct of a grid (host side)."""
    grid = ColumnGrid()
    grid.voxel_m = wp.float64(voxel_m)
    grid.shift_x = wp.float64(shift_x)
    grid.shift_y = wp.float64(shift_y)
    grid.cell_m = wp.float64(cell_m)
    grid.width = int(width)
    grid.height = int(height)
    grid.z_low = int(z_low)
    grid.z_high = int(z_high)
    return grid


@wp.func
def cell_of(v: wp.vec3i, grid: ColumnGrid) -> int:
    """The cell (j * width + i) holding voxel v's center, -1 outside the grid or the z range."""
    if v[2] < grid.z_low or v[2] > grid.z_high:
        return -1
    i = int(wp.floor(((wp.float64(v[0]) + wp.float64(0.5)) * grid.voxel_m + grid.shift_x) / grid.cell_m))
    j = int(wp.floor(((wp.float64(v[1]) + wp.float64(0.5)) * grid.voxel_m + grid.shift_y) / grid.cell_m))
    if i < 0 or i >= grid.width or j < 0 or j >= grid.height:
        return -1
    return j * grid.width + i


@wp.kernel
def column_extremes(index: wp.array(dtype=wp.vec3i), label: wp.array(dtype=wp.int32), occupied: wp.array(dtype=wp.int32),
                    surface_class: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.float64), grid: ColumnGrid,
                    top_key: wp.array(dtype=wp.int64), support_key: wp.array(dtype=wp.int64), low_z: wp.array(dtype=wp.int32),
                    observations: wp.array(dtype=wp.float64)):
    """Per cell: the highest occupied voxel, the highest occupied surface-class voxel (packed keys),
    the lowest occupied z index, and the summed contribution counts of all its voxels."""
    row = wp.tid()
    v = index[row]
    c = cell_of(v, grid)
    if c < 0:
        return
    wp.atomic_add(observations, c, hits[row])
    if occupied[row] == 0:
        return
    key = pack_voxel(v[2], row)
    wp.atomic_max(top_key, c, key)
    wp.atomic_min(low_z, c, v[2])
    if surface_class[label[row]] != 0:
        wp.atomic_max(support_key, c, key)


@wp.kernel
def column_cover(index: wp.array(dtype=wp.vec3i), occupied: wp.array(dtype=wp.int32), grid: ColumnGrid, clearance_voxels: int,
                 support_key: wp.array(dtype=wp.int64), low_z: wp.array(dtype=wp.int32), cover_key: wp.array(dtype=wp.int64)):
    """Per cell: the highest occupied voxel at most ``clearance_voxels`` above the support voxel (above
    the lowest occupied voxel where there is no support)."""
    row = wp.tid()
    if occupied[row] == 0:
        return
    v = index[row]
    c = cell_of(v, grid)
    if c < 0:
        return
    support = support_key[c]
    base = low_z[c]
    if support >= wp.int64(0):
        base = packed_z(support)
    if v[2] <= base + clearance_voxels:
        wp.atomic_max(cover_key, c, pack_voxel(v[2], row))


@wp.kernel
def plane_fit(height_m: wp.array2d(dtype=wp.float64), radius: int, cell_m: wp.float64, min_cells: int,
              slope_deg: wp.array2d(dtype=wp.float64), roughness_m: wp.array2d(dtype=wp.float64)):
    """Least-squares plane over the known cells of the (2 radius + 1)^2 window around each known cell
    (positions relative to the cell, heights relative to its own): slope = atan(|grad|) in degrees,
    roughness = sqrt(residual sum of squares / cells). NaN for unknown cells, windows of fewer than
    ``min_cells`` known cells, and windows whose cells lie on one line."""
    j, i = wp.tid()
    rows = height_m.shape[0]
    columns = height_m.shape[1]
    nan = wp.float64(wp.nan)
    center = height_m[j, i]
    if wp.isnan(center):
        slope_deg[j, i] = nan
        roughness_m[j, i] = nan
        return
    n = wp.float64(0.0)
    sx = wp.float64(0.0)
    sy = wp.float64(0.0)
    sz = wp.float64(0.0)
    sxx = wp.float64(0.0)
    sxy = wp.float64(0.0)
    syy = wp.float64(0.0)
    sxz = wp.float64(0.0)
    syz = wp.float64(0.0)
    szz = wp.float64(0.0)
    for dj in range(-radius, radius + 1):
        for di in range(-radius, radius + 1):
            jj = j + dj
            ii = i + di
            if jj >= 0 and jj < rows and ii >= 0 and ii < columns:
                z = height_m[jj, ii]
                if not wp.isnan(z):
                    x = wp.float64(di) * cell_m
                    y = wp.float64(dj) * cell_m
                    z = z - center
                    n += wp.float64(1.0)
                    sx += x
                    sy += y
                    sz += z
                    sxx += x * x
                    sxy += x * y
                    syy += y * y
                    sxz += x * z
                    syz += y * z
                    szz += z * z
    if n < wp.float64(min_cells):
        slope_deg[j, i] = nan
        roughness_m[j, i] = nan
        return
    cxx = sxx - sx * sx / n
    cxy = sxy - sx * sy / n
    cyy = syy - sy * sy / n
    cxz = sxz - sx * sz / n
    cyz = syz - sy * sz / n
    czz = szz - sz * sz / n
    det = cxx * cyy - cxy * cxy
    if det <= wp.float64(1e-9) * cxx * cyy or cxx <= wp.float64(0.0) or cyy <= wp.float64(0.0):
        slope_deg[j, i] = nan
        roughness_m[j, i] = nan
        return
    a = (cxz * cyy - cyz * cxy) / det
    b = (cyz * cxx - cxz * cxy) / det
    rss = wp.max(czz - a * cxz - b * cyz, wp.float64(0.0))
    slope_deg[j, i] = wp.atan(wp.sqrt(a * a + b * b)) * wp.float64(57.29577951308232)
    roughness_m[j, i] = wp.sqrt(rss / n)


@wp.kernel
def max_step(height_m: wp.array2d(dtype=wp.float64), radius: int, step_m: wp.array2d(dtype=wp.float64)):
    """The largest |z - z_n| between a known cell and the known cells of its (2 radius + 1)^2 window;
    NaN for unknown cells and for cells without a known neighbour."""
    j, i = wp.tid()
    rows = height_m.shape[0]
    columns = height_m.shape[1]
    center = height_m[j, i]
    best = wp.float64(-1.0)
    if not wp.isnan(center):
        for dj in range(-radius, radius + 1):
            for di in range(-radius, radius + 1):
                jj = j + dj
                ii = i + di
                if (dj != 0 or di != 0) and jj >= 0 and jj < rows and ii >= 0 and ii < columns:
                    z = height_m[jj, ii]
                    if not wp.isnan(z):
                        best = wp.max(best, wp.abs(z - center))
    if best < wp.float64(0.0):
        step_m[j, i] = wp.float64(wp.nan)
    else:
        step_m[j, i] = best
