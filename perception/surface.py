"""What a depth-map bin holds, from the points binned into it (:mod:`perception.depthmap`).

Two rules, chosen per checkpoint (``DepthMapParams.method``):

- ``"nearest_point"`` (the paper's, §III-B.3): a bin holds the minimum gel y of its points; an
  empty bin with enough occupied neighbours is a sampling gap and takes their minimum
  (:func:`perception.binning.fill_sampling_gaps`). At a steep wall a bin holds the rim's nearest point wherever in
  the bin it lies, so the rim reads up to a bin wider than it is, and a cloud sparser than the bins
  leaves most bins empty (y_far: no surface), which the renderer draws as a field of spikes.
- ``"surface"``: a bin holds where the surface is at the bin's centre, along the gel normal
  (:func:`surface_maps`). Each bin's front-most point (the kernel's sample: the least y, ties by
  x then z, so every path picks the same one) is a sample of the surface seen from the gel; the
  value at a bin centre is a least-squares plane through the samples of the 3 x 3 bins around
  it, evaluated at the centre. A sample is used only where it continues the surface of the bin's
  own sample (or of the front-most one around an empty bin; a height step steeper than
  ``MAX_SLOPE`` is another surface: a wall's foot, a back face) and where the plane fits it (while
  one is off by more than half a bin, the sample farthest in height from the bin's own goes: the
  far face of a step). An empty bin is answered only from samples around its centre (within their convex
  hull: interpolation, never extrapolation); an occupied bin's plane may reach the half bin to
  its centre. Where its own sample continues no surface around it, the bin is read as a gap in
  the front surface (a small object's far side showing through a bin its front left unsampled)
  when the front-most samples around surround its centre, else it holds its nearest point. A bin
  no level can answer is left empty (y_far) and not ``known``.
  Where the surface bends, level 0's planes are read again from quadrics
  (:mod:`perception.surface_bend`).

Sparse clouds: the samples are pooled into cells of 2, 4, 8 ... bins (the front-most of each
cell), and a bin the finer levels left empty is answered by the planes of coarser cells, up to
one level above the cloud's own spacing (the first level at which most occupied cells have
occupied cells beside them): a gap of the cloud's sampling is filled, a hole much wider than the
spacing (a mug's opening, the space beside an edge) is not.

Why by hand: a moving-least-squares surface over binned samples with these rules is no library's
function (Open3D and PCL fit surfaces to whole clouds, at seconds a cloud); this is one compiled
pass per level over each map's bins, on the threads that cut the maps. Level 0's occupied bins,
most of a map, take a fast path: a row at a time in vector instructions, with the general path's
sums in its order (the same bits), the general path only where their first plane does not fit:
~0.4 ms a 100 x 100 map on one core, against ~1.2 ms bin by bin.
"""

from __future__ import annotations

import numba
import numpy as np

from perception.binning import bin_centres
from perception.errors import DepthMapError
from perception.surface_bend import bend_corrected
from perception.threads import run_shares

DEPTH_MAP_METHODS = ("surface", "nearest_point")
# Steepest height change, |dy| / horizontal distance, between samples of one surface (75°): a
# steeper step between two samples is a wall between two surfaces, not one surface.
MAX_SLOPE = 3.7
# A plane is kept only where it fits every sample it stands on to this fraction of the cells'
# size (half a bin, ~0.12 mm, at the finest level: a 6 mm sphere's curvature over three bins at
# 45 deg is a quarter of that); else samples are dropped, the farthest in height first.
RESIDUAL_FRACTION = 0.5
# A plane needs at least this many samples, and samples spread in two directions: the smaller
# eigenvalue of their spread at least this fraction of the larger one's (not on one line).
_MIN_SAMPLES = 3
_MIN_SPREAD_RATIO = 1e-3
_Grids = tuple[np.ndarray, np.ndarray, np.ndarray]  # a map's or a level's samples: y, x, z
_Centres = tuple[np.ndarray, np.ndarray]  # the bins' x and z centres
_Index = int | np.uint64  # the fast path's are np.uint64 (_row_planes)


@numba.njit(cache=True, nogil=True)
def _front(y: float, x: float, z: float, by: float, bx: float, bz: float) -> bool:
    """(y, x, z) before (by, bx, bz): the least y, ties by x, then z (an order every path keeps)."""
    return y < by or (y == by and (x < bx or (x == bx and z < bz)))


@numba.njit(cache=True, nogil=True)
def _pooled(sy: np.ndarray, sx: np.ndarray, sz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The front-most sample of each 2 x 2 cell of (rows, cols) sample grids (+inf y: none)."""
    rows, cols = sy.shape
    out_rows, out_cols = (rows + 1) // 2, (cols + 1) // 2
    py, px, pz = np.full((out_rows, out_cols), np.inf), np.zeros((out_rows, out_cols)), np.zeros((out_rows, out_cols))
    for r in range(rows):
        for c in range(cols):
            if np.isfinite(sy[r, c]) and _front(
                sy[r, c], sx[r, c], sz[r, c], py[r // 2, c // 2], px[r // 2, c // 2], pz[r // 2, c // 2]
            ):
                py[r // 2, c // 2], px[r // 2, c // 2], pz[r // 2, c // 2] = sy[r, c], sx[r, c], sz[r, c]
    return py, px, pz


@numba.njit(cache=True, nogil=True)
def _anchor(
    sy: np.ndarray, sx: np.ndarray, sz: np.ndarray, cell_r: int, cell_c: int, front: bool
) -> tuple[float, float, float]:
    """The sample whose surface a plane at (cell_r, cell_c) continues: the cell's own, or the
    front-most of the 3 x 3 cells around it where it has none or ``front`` (+inf y: none)."""
    ay, ax, az = sy[cell_r, cell_c], sx[cell_r, cell_c], sz[cell_r, cell_c]
    if front or not np.isfinite(ay):
        for r in range(max(cell_r - 1, 0), min(cell_r + 2, sy.shape[0])):
            for c in range(max(cell_c - 1, 0), min(cell_c + 2, sy.shape[1])):
                if np.isfinite(sy[r, c]) and _front(sy[r, c], sx[r, c], sz[r, c], ay, ax, az):
                    ay, ax, az = sy[r, c], sx[r, c], sz[r, c]
    return ay, ax, az


@numba.njit(cache=True, nogil=True)
def _continues(dy: float, dx: float, dz: float, tolerance: float) -> bool:
    """Whether a sample at (dy, dx, dz) from the anchor continues its surface: a sample (y below
    +inf) whose height change is within MAX_SLOPE times their distance plus ``tolerance``. With
    ``&``, not ``and``: a branch would keep :func:`_row_planes` out of vector code."""
    step = abs(dy) - tolerance
    return (dy < np.inf) & (not ((step > 0.0) & (step * step > MAX_SLOPE * MAX_SLOPE * (dx**2 + dz**2))))


@numba.njit(cache=True, nogil=True)
def _plane_at(
    sy: np.ndarray,
    sx: np.ndarray,
    sz: np.ndarray,
    cell_r: int,
    cell_c: int,
    centre_x: float,
    centre_z: float,
    tolerance: float,
    inside: bool,
    front: bool,
    kept: np.ndarray,
) -> float:
    """The surface's y at (centre_x, centre_z) from the samples of the 3 x 3 cells around
    (cell_r, cell_c), or NaN where they cannot say. Kept: the samples continuing the
    :func:`_anchor`'s surface (a height change within MAX_SLOPE times their distance plus
    ``tolerance``, the cells' size), then those the plane through them fits, dropping the one
    farthest in height from the anchor while one is off by over RESIDUAL_FRACTION of ``tolerance``
    (the far face of a step); at least three, not on one line, and with ``inside`` around the
    centre (:func:`_surrounds`). ``kept``: (3, 9) scratch for their offsets from the centre and
    the anchor."""
    ay, ax, az = _anchor(sy, sx, sz, cell_r, cell_c, front)
    if not np.isfinite(ay):
        return np.nan
    n = 0
    for r in range(max(cell_r - 1, 0), min(cell_r + 2, sy.shape[0])):
        for c in range(max(cell_c - 1, 0), min(cell_c + 2, sy.shape[1])):
            if _continues(sy[r, c] - ay, sx[r, c] - ax, sz[r, c] - az, tolerance):
                kept[0, n], kept[1, n], kept[2, n] = sx[r, c] - centre_x, sz[r, c] - centre_z, sy[r, c] - ay
                n += 1
    while n >= _MIN_SAMPLES:
        height, slope_x, slope_z = _plane(kept, n)
        if not np.isfinite(height):
            return np.nan
        worst, farthest, farthest_at = 0.0, -1.0, 0
        for i in range(n):
            worst = max(worst, abs(kept[2, i] - height - slope_x * kept[0, i] - slope_z * kept[1, i]))
            if abs(kept[2, i]) > farthest:
                farthest, farthest_at = abs(kept[2, i]), i
        if worst <= RESIDUAL_FRACTION * tolerance:
            return ay + height if not inside or _surrounds(kept, n) else np.nan
        # Off the plane: the sample farthest in height from the anchor's goes (a step's far face).
        n -= 1
        kept[:, farthest_at] = kept[:, n]
    return np.nan


@numba.njit(cache=True, nogil=True)
def _plane(kept: np.ndarray, n: int) -> tuple[float, float, float]:
    """The least-squares plane y = h + gx dx + gz dz through the first ``n`` (dx, dz, y) columns
    of ``kept``: (h, gx, gz), h NaN where they lie on one line (:func:`_plane_of_moments`)."""
    sum_x, sum_z, sum_y, sum_xx, sum_xz, sum_zz, sum_xy, sum_zy = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for i in range(n):
        dx, dz, dy = kept[0, i], kept[1, i], kept[2, i]
        sum_x += dx
        sum_z += dz
        sum_y += dy
        sum_xx += dx * dx
        sum_xz += dx * dz
        sum_zz += dz * dz
        sum_xy += dx * dy
        sum_zy += dz * dy
    height, slope_x, slope_z, spread = _plane_of_moments(
        (sum_x, sum_z, sum_y, sum_xx, sum_xz, sum_zz, sum_xy, sum_zy, float(n))
    )
    return (height, slope_x, slope_z) if spread else (np.nan, 0.0, 0.0)


@numba.njit(cache=True, nogil=True)
def _plane_of_moments(sums: tuple[float, ...]) -> tuple[float, float, float, bool]:
    """The least-squares plane y = h + gx dx + gz dz of raw moments about the centre (sums of dx,
    dz, y, dx², dx dz, dz², dx y, dz y, and the count): (h, gx, gz, whether the samples spread in
    two directions, _MIN_SPREAD_RATIO). The offsets are a few bins, so float64 loses nothing at
    these scales. Without a branch (:func:`_row_planes`): no samples or no spread divide by 1,
    and such a plane is not kept."""
    sum_x, sum_z, sum_y, sum_xx, sum_xz, sum_zz, sum_xy, sum_zy, n = sums
    count = n if n > 0.0 else 1.0
    mx, mz, my = sum_x / count, sum_z / count, sum_y / count
    cxx, cxz, czz = sum_xx - mx * sum_x, sum_xz - mx * sum_z, sum_zz - mz * sum_z
    cxy, czy = sum_xy - mx * sum_y, sum_zy - mz * sum_y
    det = cxx * czz - cxz * cxz
    trace = cxx + czz
    divisor = det if det != 0.0 else 1.0
    slope_x = (cxy * czz - czy * cxz) / divisor
    slope_z = (czy * cxx - cxy * cxz) / divisor
    return my - slope_x * mx - slope_z * mz, slope_x, slope_z, det > _MIN_SPREAD_RATIO * trace * trace


@numba.njit(cache=True, nogil=True)
def _surrounds(kept: np.ndarray, n: int) -> bool:
    """Whether the centre (0, 0) lies within the convex hull of the first ``n`` (dx, dz) columns
    of ``kept``: no line through it has every sample on one side (such a line can be turned until
    it meets a sample, so the lines through the samples are the ones to try)."""
    for i in range(n):
        if kept[0, i] == 0.0 and kept[1, i] == 0.0:
            return True
    for i in range(n):
        low, high = np.inf, -np.inf
        for j in range(n):
            cross = kept[0, i] * kept[1, j] - kept[1, i] * kept[0, j]
            low, high = min(low, cross), max(high, cross)
        if low >= 0.0 or high <= 0.0:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _knit(sy: np.ndarray) -> bool:
    """Whether the samples of a level are the cloud's own spacing: most occupied cells have at
    least two occupied cells beside them (of four), as a sampled surface's do and a sparse
    cloud's scattered samples do not."""
    rows, cols = sy.shape
    occupied, knit = 0, 0
    for r in range(rows):
        for c in range(cols):
            if sy[r, c] < np.inf:
                occupied += 1
                beside = (r > 0 and sy[r - 1, c] < np.inf) + (r + 1 < rows and sy[r + 1, c] < np.inf)
                beside += (c > 0 and sy[r, c - 1] < np.inf) + (c + 1 < cols and sy[r, c + 1] < np.inf)
                knit += beside >= 2
    return 2 * knit >= occupied


@numba.njit(cache=True, nogil=True)
def _moments(
    sums: tuple[float, ...],
    samples: _Grids,
    i: _Index,
    j: _Index,
    anchor: tuple[float, float, float, float, float],
    tolerance: float,
) -> tuple[float, ...]:
    """``sums``: the raw moments of :func:`_plane` and the count, with the sample (y, x, z) of bin (i, j)
    added where it continues the ``anchor``'s surface (ay, ax, az, centre_x, centre_z). A dropped
    sample adds +0.0, which leaves a sum unchanged to the bit (a sum from +0.0 is never -0.0),
    so the sums are _plane's; without a branch, as :func:`_continues`."""
    (sy, sx, sz), (ay, ax, az, centre_x, centre_z) = samples, anchor
    dy = sy[i, j] - ay
    keep = _continues(dy, sx[i, j] - ax, sz[i, j] - az, tolerance)
    dx = sx[i, j] - centre_x if keep else 0.0
    dz = sz[i, j] - centre_z if keep else 0.0
    dy = dy if keep else 0.0
    sum_x, sum_z, sum_y, sum_xx, sum_xz, sum_zz, sum_xy, sum_zy, n = sums
    first = (sum_x + dx, sum_z + dz, sum_y + dy, sum_xx + dx * dx, sum_xz + dx * dz, sum_zz + dz * dz)
    return first + (sum_xy + dx * dy, sum_zy + dz * dy, n + (1.0 if keep else 0.0))


@numba.njit(cache=True, nogil=True)
def _fits(
    fits: bool,
    samples: _Grids,
    i: _Index,
    j: _Index,
    anchor: tuple[float, float, float, float, float],
    plane: tuple[float, float, float],
    tolerance: float,
) -> bool:
    """``fits``, False where the sample of bin (i, j) continues the ``anchor``'s surface (as in
    :func:`_moments`) but is off the ``plane`` (height, slope_x, slope_z) by over
    RESIDUAL_FRACTION of ``tolerance``: :func:`_plane_at`'s test, without a branch."""
    (sy, sx, sz), (ay, ax, az, centre_x, centre_z) = samples, anchor
    height, slope_x, slope_z = plane
    dy, dx, dz = sy[i, j] - ay, sx[i, j] - centre_x, sz[i, j] - centre_z
    on = abs(dy - height - slope_x * dx - slope_z * dz) <= RESIDUAL_FRACTION * tolerance
    return fits & (on | (not _continues(dy, sx[i, j] - ax, sz[i, j] - az, tolerance)))


@numba.njit(cache=True, nogil=True)
def _row_planes(
    sy: np.ndarray,
    sx: np.ndarray,
    sz: np.ndarray,
    r: np.uint64,
    centres: tuple[np.ndarray, float],
    tolerance: float,
    ys: np.ndarray,
    fits: np.ndarray,
) -> None:
    """The fast path for the occupied bins (r, c + 1) of row ``r`` of samples inside a border of
    none (+inf y), ``centres`` (x_centres, the row's z; x_centres[c] the bin's x): ``ys[c]`` the y
    :func:`_plane_at` gives, to the bit (the same sums in the same order, and _plane_of_moments as
    _plane), where ``fits[c]``: its first plane fits every sample it keeps. For vector code, no
    branch: the 3 x 3 written out, unsigned indices (a possibly negative one is a branch), and the
    divisors guarded where the bin fails anyway (a division that may raise is a branch)."""
    x_centres, centre_z = centres
    samples = (sy, sx, sz)
    one, two = np.uint64(1), np.uint64(2)
    up, down = r - one, r + one
    for c in range(np.uint64(sy.shape[1] - 2)):
        ay = sy[r, c + one]
        anchor = (ay, sx[r, c + one], sz[r, c + one], x_centres[c], centre_z)
        # In _plane_at's order (r-major, then c): the same sums to the bit.
        sums = _moments((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), samples, up, c, anchor, tolerance)
        sums = _moments(sums, samples, up, c + one, anchor, tolerance)
        sums = _moments(sums, samples, up, c + two, anchor, tolerance)
        sums = _moments(sums, samples, r, c, anchor, tolerance)
        sums = _moments(sums, samples, r, c + one, anchor, tolerance)
        sums = _moments(sums, samples, r, c + two, anchor, tolerance)
        sums = _moments(sums, samples, down, c, anchor, tolerance)
        sums = _moments(sums, samples, down, c + one, anchor, tolerance)
        sums = _moments(sums, samples, down, c + two, anchor, tolerance)
        height, slope_x, slope_z, spread = _plane_of_moments(sums)
        plane = (height, slope_x, slope_z)
        ok = (sums[8] >= _MIN_SAMPLES) & spread & (abs(ay + height) < np.inf)
        for i in (up, r, down):
            ok = _fits(ok, samples, i, c, anchor, plane, tolerance)
            ok = _fits(ok, samples, i, c + one, anchor, plane, tolerance)
            ok = _fits(ok, samples, i, c + two, anchor, plane, tolerance)
        ys[c], fits[c] = ay + height, ok


@numba.njit(cache=True, nogil=True)
def _occupied_planes(
    samples: _Grids,
    centres: _Centres,
    tolerance: float,
    bounds: tuple[float, float],
    out: np.ndarray,
    known: np.ndarray,
) -> int:
    """The fast path of level 0 (:func:`_row_planes`), a row at a time: each occupied bin of the
    ``samples`` (y, x, z) whose first plane fits every sample it keeps (most bins) answered as
    :func:`_plane_at` would; returns how many. ``bounds``: (y_near, y_far); the bins left are
    _plane_at's. The samples are copied inside a border of none, which no plane keeps: the
    border bins' sums are _plane_at's too."""
    (sy, sx, sz), (x_centres, z_centres) = samples, centres
    rows, cols = sy.shape
    py, px, pz = np.full((rows + 2, cols + 2), np.inf), np.zeros((rows + 2, cols + 2)), np.zeros((rows + 2, cols + 2))
    for r in range(rows):
        for c in range(cols):
            py[r + 1, c + 1], px[r + 1, c + 1], pz[r + 1, c + 1] = sy[r, c], sx[r, c], sz[r, c]
    ys, fits = np.empty(cols), np.empty(cols, np.bool_)
    answered = 0
    for r in range(rows):
        _row_planes(py, px, pz, np.uint64(r + 1), (x_centres, z_centres[r]), tolerance, ys, fits)
        for c in range(cols):
            if fits[c]:  # never an empty bin: its y is +inf
                out[r, c] = min(max(ys[c], bounds[0]), bounds[1])
                known[r, c] = True
                answered += 1
    return answered


@numba.njit(cache=True, nogil=True)
def _answer_level(
    level_samples: _Grids,
    level: int,
    sy: np.ndarray,
    centres: _Centres,
    tolerance: float,
    bounds: tuple[float, float],
    out: np.ndarray,
    known: np.ndarray,
) -> int:
    """The bins not yet ``known`` answered by :func:`_plane_at` from the cells of ``level`` (the
    ``level_samples`` (y, x, z), cells of 2**level bins; ``sy`` the bins' own samples); returns
    how many. ``bounds``: (y_near, y_far), the range ``out`` is clamped to."""
    (level_y, level_x, level_z), (x_centres, z_centres) = level_samples, centres
    kept, answered = np.empty((3, 9)), 0
    for r in range(sy.shape[0]):
        extent_of, extent = -1, (np.inf, -np.inf, np.inf, -np.inf)
        for c in range(sy.shape[1]):
            # A bin's own points put its centre within half a bin of the samples: its plane may
            # reach that far beyond them (the crop's faces, a rim); an empty bin's may not.
            own = level == 0 and sy[r, c] < np.inf
            cell_r, cell_c = r >> level, c >> level
            if known[r, c]:
                continue
            if not own:
                if cell_c != extent_of:  # the bins of a cell in one row share its samples' extent
                    extent_of, extent = cell_c, _extent(level_samples, cell_r, cell_c)
                if _one_sided(extent, x_centres[c], z_centres[r]):
                    continue
            y = _plane_at(
                level_y, level_x, level_z, cell_r, cell_c, x_centres[c], z_centres[r], tolerance, not own, False, kept
            )
            if own and not np.isfinite(y):
                # A bin whose own sample continues no surface around it may be a gap in the
                # front surface through which a face behind shows (a small object's far side):
                # where the front-most samples around it surround its centre, their plane.
                y = _plane_at(level_y, level_x, level_z, r, c, x_centres[c], z_centres[r], tolerance, True, True, kept)
                if not y < sy[r, c]:
                    y = sy[r, c]  # the bin's own nearest point where no plane can be fitted
            if np.isfinite(y):
                out[r, c] = min(max(y, bounds[0]), bounds[1])
                known[r, c] = True
                answered += 1
    return answered


@numba.njit(cache=True, nogil=True)
def _extent(samples: _Grids, cell_r: int, cell_c: int) -> tuple[float, float, float, float]:
    """(low x, high x, low z, high z) of the samples (y, x, z) of the 3 x 3 cells around (cell_r, cell_c)."""
    (sy, sx, sz), (low_x, high_x, low_z, high_z) = samples, (np.inf, -np.inf, np.inf, -np.inf)
    for r in range(max(cell_r - 1, 0), min(cell_r + 2, sy.shape[0])):
        for c in range(max(cell_c - 1, 0), min(cell_c + 2, sy.shape[1])):
            if sy[r, c] < np.inf:
                low_x, high_x = min(low_x, sx[r, c]), max(high_x, sx[r, c])
                low_z, high_z = min(low_z, sz[r, c]), max(high_z, sz[r, c])
    return low_x, high_x, low_z, high_z


@numba.njit(cache=True, nogil=True)
def _one_sided(extent: tuple[float, float, float, float], centre_x: float, centre_z: float) -> bool:
    """Whether samples of that :func:`_extent` cannot surround the centre (centre_x, centre_z): none,
    or all on one side of it in x or z: _plane_at's NaN for an empty bin (59-79 % of its calls on the
    YCB planner's maps). Coordinates, not offsets: a rounded difference keeps the exact one's sign."""
    low_x, high_x, low_z, high_z = extent
    return (high_x < centre_x) | (low_x > centre_x) | (high_z < centre_z) | (low_z > centre_z)


@numba.njit(cache=True, nogil=True)
def _surface_map(
    sy: np.ndarray,
    sx: np.ndarray,
    sz: np.ndarray,
    x_centres: np.ndarray,
    z_centres: np.ndarray,
    y_near: float,
    y_far: float,
    bin_size: float,
    out: np.ndarray,
    known: np.ndarray,
    planar: np.ndarray,
) -> None:
    """One map's surface (module docstring): ``out`` (rows, cols) y at the bin centres, clamped to
    [y_near, y_far], y_far and ``known`` False where no level can say (``bin_size``: level 0's
    cell, :func:`level_0_tolerance`); ``planar`` where level 0's plane answered (not a bin's own
    nearest point). Levels: up to one above the first whose samples are knit (:func:`_knit`)."""
    out[:, :] = y_far
    known[:, :] = False
    level_y, level_x, level_z = sy, sx, sz
    centres, bounds = (x_centres, z_centres), (y_near, y_far)
    unknown, knit_level, level = sy.size, -1, 0
    while unknown and (knit_level < 0 or level <= knit_level + 1):
        if level > 0:
            if level_y.shape[0] == 1 and level_y.shape[1] == 1:
                break
            level_y, level_x, level_z = _pooled(level_y, level_x, level_z)
        if knit_level < 0 and _knit(level_y):
            knit_level = level
        tolerance = bin_size * (1 << level)
        if level == 0:
            unknown -= _occupied_planes((sy, sx, sz), centres, tolerance, bounds, out, known)
        unknown -= _answer_level((level_y, level_x, level_z), level, sy, centres, tolerance, bounds, out, known)
        if level == 0:
            planar[:, :] = known & (out != sy)
        level += 1


def level_0_tolerance(x_centres: np.ndarray, z_centres: np.ndarray) -> float:
    """The finest level's cell size (m): the larger bin side (1 for a single bin)."""
    cols, rows = len(x_centres), len(z_centres)
    bin_size = max(x_centres[1] - x_centres[0] if cols > 1 else 0.0, z_centres[1] - z_centres[0] if rows > 1 else 0.0)
    return float(bin_size if bin_size > 0.0 else 1.0)


def surface_maps(
    sample_y_m: np.ndarray,
    sample_x_m: np.ndarray,
    sample_z_m: np.ndarray,
    bounds: tuple[float, float, float, float],
    threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The surface's gel y at each bin centre (module docstring) from each bin's front-most point
    (gel frame, metres; (regions, rows, cols) float64, y +inf where the bin holds no point), in
    the crop ``bounds`` = (half_x, half_z, y_near, y_far), the regions shared among up to
    ``threads`` threads. Returns (depth-maps float32 m, y_far where unknown; known bool)."""
    half_x, half_z, y_near, y_far = bounds
    sample_y = np.ascontiguousarray(sample_y_m, np.float64)
    if sample_y.ndim != 3 or sample_x_m.shape != sample_y.shape or sample_z_m.shape != sample_y.shape:
        raise DepthMapError(f"samples must be three (regions, rows, cols) grids, got {sample_y.shape}")
    regions, rows, cols = sample_y.shape
    out, known, planar = np.empty(sample_y.shape), np.empty(sample_y.shape, bool), np.empty(sample_y.shape, bool)
    sample_x, sample_z = (np.ascontiguousarray(grid, np.float64) for grid in (sample_x_m, sample_z_m))
    x_centres, z_centres = bin_centres(half_x, cols), bin_centres(half_z, rows)
    bin_size = level_0_tolerance(x_centres, z_centres)

    def answer(first: int, stop: int) -> None:
        for k in range(first, stop):
            samples = (sample_y[k], sample_x[k], sample_z[k])
            _surface_map(*samples, x_centres, z_centres, y_near, y_far, bin_size, out[k], known[k], planar[k])
            bend_corrected(samples, (x_centres, z_centres), (bin_size, MAX_SLOPE), (y_near, y_far), out[k], planar[k])

    edges = np.linspace(0, regions, min(max(threads, 1), regions) + 1).astype(int)
    run_shares(answer, [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])])
    return out.astype(np.float32), known
