"""Where a depth-map's surface bends, each bin read from a quadric instead of a plane.

perception.surface reads a bin as the plane through the samples (each bin's front-most point) of
the 3 x 3 bins around it. On a curved surface that plane is a chord: off the surface at the bin's
centre by the samples' sag, and by a different amount in each bin as its samples fall in other
places in their bins, a texture of a few to tens of um that the GelSight renderer draws as
shading (a 2 mm ball at the model clouds' 0.1 mm points: the median bin 32 um off, where the
renderer's image of the exact surface changes by nothing at 3 um). Where the plane values of
neighbouring bins bend by more than FLAT_BEND_M, the bin is read again from the least-squares
quadric through the same samples, kept only where it fits every one of them
(QUADRIC_FIT_FRACTION), lies within their heights and stays near the plane's value: a rim, a
crease, a step or a noisy camera cloud keeps its plane. The same 2 mm ball then reads within
1.2 um at the median (tests/test_surface_depthmap.py).

Why by hand: a six-term least-squares fit per bin over nine samples, on the threads that cut
the maps, is one small compiled loop; it is solved only where the surface bends (a flat face costs
the bend test alone; the YCB scans at 0.1 mm bend in 500-2,270 bins of a planner's map, from the
cracker box to the drill), those bins side by side in one vector loop: 0.08-0.20 ms a map on one
core (an Intel Xeon; bin by bin 0.12-0.33). Self-contained, called from Python after each map's
levels: numba's cache does not see a change in another file's jitted callee.
"""

from __future__ import annotations

import numba
import numpy as np

# Where level 0's plane values bend by more than this between neighbours (a second difference),
# the surface curves enough for the plane's chord to matter and the quadric reads it again: a
# sphere of under ~3 mm radius on the default 0.24 x 0.19 mm bins (a 2 mm ball bends 28 um along a
# row). A gentler surface keeps its planes, whose chords are a few um (a 6 mm sphere at most 13
# um, 2-8 at the median), about what the renderer draws (a 3 um texture changes no image). At 2,
# 5 and 10 um the quadric also read a faceted mesh's kinks, 1-6 um apart (the YCB can at 0.2 mm: 4,064,
# 2,507 and 1,287 bins of a grasp's map, 1.5, 0.95 and 0.62 ms; at 20 um 371 bins, 0.21 ms,
# before the LDL^T solve and the border rule: now 331 bins, 0.14 ms), and the real presses
# scored the same at all four.
FLAT_BEND_M = 20e-6
# The quadric is kept where every sample it stands on is within this fraction of the bins' size
# of it (24 um at 0.24 mm bins: a 2 mm ball's samples lie within 0.1 um of theirs up to 45 deg, a
# few um towards its equator; a crease's or a camera cloud's do not), its value lies within the
# samples' heights (a quadric bridging a step overshoots it), and it moves the plane's value by at
# most MAX_BEND_CORRECTION of the bins' size. At 0.02 (5 um) the 30 real presses' bins towards
# the ball's equator kept their chords: window SSIM 0.882 against 0.883. Half a bin: a 1.5 mm
# ball's chord at 43 deg is 80 um off (a quarter bin, 72 um, kept it); on the YCB planner's maps
# the bins a half rather than a quarter lets the quadric move (4-24 a map) come 45-65 um closer
# to the mesh at the median (78-90 % of them closer).
QUADRIC_FIT_FRACTION = 0.1
MAX_BEND_CORRECTION = 0.5
_MIN_QUADRIC_SAMPLES = 7
_MIN_PIVOT_RATIO = 1e-6

Grids = tuple[np.ndarray, np.ndarray, np.ndarray]  # a map's samples: y, x, z
_Sample = tuple[float, float, float, float]  # a sample as the quadric takes it: u, v, y, weight
_Nine = tuple[_Sample, _Sample, _Sample, _Sample, _Sample, _Sample, _Sample, _Sample, _Sample]
# The normal equations' sums: the lower triangle's first five rows, its last row, the right-hand side.
_Sums = tuple[tuple[float, ...], tuple[float, float, float, float, float, float], tuple[float, ...]]


@numba.njit(cache=True, nogil=True)
def _curved(planes: np.ndarray, r: int, c: int) -> bool:
    """Whether level 0's plane values around bin (r, c) bend by more than FLAT_BEND_M: a second
    difference along a row, a column or a diagonal of the 3 x 3 bins, where both neighbours are
    planes (a bin on the map's border, or beside a rim, bends along the lines it has)."""
    rows, cols = planes.shape
    if r == 0 or c == 0 or r == rows - 1 or c == cols - 1:
        return False
    centre = 2.0 * planes[r, c]
    # A NaN (a line without two planes) compares False: that line does not bend.
    bent = abs(planes[r, c - 1] - centre + planes[r, c + 1]) > FLAT_BEND_M
    bent |= abs(planes[r - 1, c] - centre + planes[r + 1, c]) > FLAT_BEND_M
    bent |= abs(planes[r - 1, c - 1] - centre + planes[r + 1, c + 1]) > FLAT_BEND_M
    return bent | (abs(planes[r - 1, c + 1] - centre + planes[r + 1, c - 1]) > FLAT_BEND_M)


# The bend pass in three steps: the bins that bend are listed and their 3 x 3 samples copied
# side by side (bend_corrected), then each bin's quadric is solved in one loop over those bins
# (_quadric_values) that the compiler makes vector code of (four bins a 256-bit vector): no
# branch (a sample's keep test and a pivot's check are masks; an unpinned quadric's divisions
# run, on inf or NaN, and are not used, hence error_model="numpy": a division by zero gives inf,
# not an exception), the nine samples written out (a loop over them, also numba.literal_unroll's,
# kept the loop scalar), every sum in scalars and no array passed to a helper (a tuple of arrays
# was reference-counted in the loop and kept it scalar). The same sums in the same order, to the
# bits of the bin-by-bin pass it replaced on the YCB planner's 320 maps, at 0.6-0.7 x its time (a
# drill map 0.33 -> 0.20 ms).
@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _sample(point: tuple[float, float, float], at: tuple[float, float, float], reach: tuple[float, float]) -> _Sample:
    """A sample ``point`` (y, x, z; +inf y: none) as the quadric of the bin ``at`` (plane_y, centre
    x, centre z) takes it: (u, v, y - plane_y, weight), u and v its offsets from the centre in
    bins, all four 0.0 where it is dropped (no sample, or no continuation of the plane's value: a
    height change beyond max_slope times the distance plus the bin size, ``reach`` = (bin size,
    max_slope), perception.surface._continues). A dropped sample adds +0.0 to every sum: the sums
    of the samples kept, to the bit."""
    y, x, z = point
    plane_y, centre_x, centre_z = at
    tolerance, max_slope = reach
    step = abs(y - plane_y) - tolerance
    dx, dz = x - centre_x, z - centre_z
    keep = (y < np.inf) & ((step <= 0.0) | (step * step <= max_slope * max_slope * (dx * dx + dz * dz)))
    u, v = (dx / tolerance if keep else 0.0), (dz / tolerance if keep else 0.0)
    return u, v, (y - plane_y if keep else 0.0), (1.0 if keep else 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _with_sample(sums: _Sums, sample: _Sample) -> _Sums:
    """The quadric's normal equations ``sums`` with ``sample`` (u, v, y, weight) added: the lower
    triangle row by row (n00, n10, n11, n20, ... n55), then the right-hand side (b0 .. b5), each
    the products t_a t_b of the terms (1, u, v, u², u v, v²) in the order the terms come."""
    (
        (n00, n10, n11, n20, n21, n22, n30, n31, n32, n33, n40, n41, n42, n43, n44),
        (n50, n51, n52, n53, n54, n55),
        (b0, b1, b2, b3, b4, b5),
    ) = sums
    u, v, y, weight = sample
    uu, uv, vv = u * u, u * v, v * v
    return (
        (
            n00 + weight,
            n10 + u,
            n11 + u * u,
            n20 + v,
            n21 + v * u,
            n22 + v * v,
            n30 + uu,
            n31 + uu * u,
            n32 + uu * v,
            n33 + uu * uu,
            n40 + uv,
            n41 + uv * u,
            n42 + uv * v,
            n43 + uv * uu,
            n44 + uv * uv,
        ),
        (n50 + vv, n51 + vv * u, n52 + vv * v, n53 + vv * uu, n54 + vv * uv, n55 + vv * vv),
        (b0 + y, b1 + u * y, b2 + v * y, b3 + uu * y, b4 + uv * y, b5 + vv * y),
    )


@numba.njit(cache=True, nogil=True, inline="always")
def _fitted(
    state: tuple[bool, float, float], solution: tuple[float, ...], sample: _Sample, fit: float
) -> tuple[bool, float, float]:
    """``state`` (whether every sample so far is within ``fit`` of the quadric ``solution``, the
    least and greatest y of those kept) with ``sample`` (u, v, y, weight; weight 0: dropped)."""
    fits, low, high = state
    u, v, y, weight = sample
    value = solution[0] + solution[1] * u + solution[2] * v
    value += solution[3] * u * u + solution[4] * u * v + solution[5] * v * v
    kept = weight > 0.0
    fits &= (not kept) | (abs(y - value) <= fit)
    return fits, min(low, y if kept else np.inf), max(high, y if kept else -np.inf)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _quadric_values(
    gathered: Grids, at: tuple[np.ndarray, np.ndarray, np.ndarray], reach: tuple[float, float], values: np.ndarray
) -> None:
    """values[b]: the surface's y at bend bin b's centre from the least-squares quadric y = h + gx u
    + gz v + a u² + b u v + c v² through its nine ``gathered`` samples (y, x, z, (9, bins) each; the
    ones :func:`_sample` keeps), or NaN where it cannot say: under _MIN_QUADRIC_SAMPLES, too close
    to a conic to pin six terms (:func:`_solved`), one sample off the quadric by over
    QUADRIC_FIT_FRACTION of the bin size (a rim, a crease, a noisy cloud), or a value outside the
    samples' heights give or take that (a quadric bridging a step overshoots it). ``at``: each
    bin's (plane_y, centre x, centre z); ``reach``: (bin size, max_slope)."""
    (sy, sx, sz), (plane_ys, centre_xs, centre_zs) = gathered, at
    fit = QUADRIC_FIT_FRACTION * reach[0]
    for b in range(values.shape[0]):
        bin_at = (plane_ys[b], centre_xs[b], centre_zs[b])
        samples = (
            _sample((sy[0, b], sx[0, b], sz[0, b]), bin_at, reach),
            _sample((sy[1, b], sx[1, b], sz[1, b]), bin_at, reach),
            _sample((sy[2, b], sx[2, b], sz[2, b]), bin_at, reach),
            _sample((sy[3, b], sx[3, b], sz[3, b]), bin_at, reach),
            _sample((sy[4, b], sx[4, b], sz[4, b]), bin_at, reach),
            _sample((sy[5, b], sx[5, b], sz[5, b]), bin_at, reach),
            _sample((sy[6, b], sx[6, b], sz[6, b]), bin_at, reach),
            _sample((sy[7, b], sx[7, b], sz[7, b]), bin_at, reach),
            _sample((sy[8, b], sx[8, b], sz[8, b]), bin_at, reach),
        )
        sums = _normal_equations(samples)
        pinned, solution = _solved(sums)
        fits, low, high = _fit(samples, solution, fit)
        within = (low - fit <= solution[0]) & (solution[0] <= high + fit)
        kept = pinned & (sums[0][0] >= _MIN_QUADRIC_SAMPLES) & fits & within
        values[b] = plane_ys[b] + solution[0] if kept else np.nan


@numba.njit(cache=True, nogil=True, inline="always")
def _normal_equations(samples: _Nine) -> _Sums:
    """The quadric's normal equations through the nine ``samples`` in order (:func:`_with_sample`)."""
    s0, s1, s2, s3, s4, s5, s6, s7, s8 = samples
    sums = _with_sample(((0.0,) * 15, (0.0,) * 6, (0.0,) * 6), s0)
    sums = _with_sample(sums, s1)
    sums = _with_sample(sums, s2)
    sums = _with_sample(sums, s3)
    sums = _with_sample(sums, s4)
    sums = _with_sample(sums, s5)
    sums = _with_sample(sums, s6)
    sums = _with_sample(sums, s7)
    return _with_sample(sums, s8)


@numba.njit(cache=True, nogil=True, inline="always")
def _fit(samples: _Nine, solution: tuple[float, ...], fit: float) -> tuple[bool, float, float]:
    """Whether every sample kept is within ``fit`` of the quadric ``solution``, and the least and
    greatest y of those kept (:func:`_fitted`)."""
    s0, s1, s2, s3, s4, s5, s6, s7, s8 = samples
    state = _fitted((True, np.inf, -np.inf), solution, s0, fit)
    state = _fitted(state, solution, s1, fit)
    state = _fitted(state, solution, s2, fit)
    state = _fitted(state, solution, s3, fit)
    state = _fitted(state, solution, s4, fit)
    state = _fitted(state, solution, s5, fit)
    state = _fitted(state, solution, s6, fit)
    state = _fitted(state, solution, s7, fit)
    return _fitted(state, solution, s8, fit)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _solved(sums: _Sums) -> tuple[bool, tuple[float, float, float, float, float, float]]:
    """The least-squares quadric's six coefficients from its normal equations' ``sums``
    (:func:`_with_sample`): (whether the samples pin six terms, the coefficients). LDL^T (symmetric
    positive definite), column by column, each pivot checked against _MIN_PIVOT_RATIO of the
    largest diagonal term, then L z = b and D L^T x = z, in scalars, which stay in registers (an
    update of a 6 x 7 array is a load and a store, chained: the drill's bend pass 0.37 -> 0.29 ms a
    map bin by bin). Where a pivot fails the rest still runs, on inf or NaN, and is not used."""
    (
        (n00, n10, n11, n20, n21, n22, n30, n31, n32, n33, n40, n41, n42, n43, n44),
        (n50, n51, n52, n53, n54, n55),
        (b0, b1, b2, b3, b4, b5),
    ) = sums
    least = _MIN_PIVOT_RATIO * max(max(max(max(max(max(0.0, n00), n11), n22), n33), n44), n55)
    d0 = n00
    l10, l20, l30, l40, l50 = n10 / d0, n20 / d0, n30 / d0, n40 / d0, n50 / d0
    d1 = n11 - l10 * l10 * d0
    l21 = (n21 - l20 * l10 * d0) / d1
    l31 = (n31 - l30 * l10 * d0) / d1
    l41 = (n41 - l40 * l10 * d0) / d1
    l51 = (n51 - l50 * l10 * d0) / d1
    d2 = n22 - l20 * l20 * d0 - l21 * l21 * d1
    l32 = (n32 - l30 * l20 * d0 - l31 * l21 * d1) / d2
    l42 = (n42 - l40 * l20 * d0 - l41 * l21 * d1) / d2
    l52 = (n52 - l50 * l20 * d0 - l51 * l21 * d1) / d2
    d3 = n33 - l30 * l30 * d0 - l31 * l31 * d1 - l32 * l32 * d2
    l43 = (n43 - l40 * l30 * d0 - l41 * l31 * d1 - l42 * l32 * d2) / d3
    l53 = (n53 - l50 * l30 * d0 - l51 * l31 * d1 - l52 * l32 * d2) / d3
    d4 = n44 - l40 * l40 * d0 - l41 * l41 * d1 - l42 * l42 * d2 - l43 * l43 * d3
    l54 = (n54 - l50 * l40 * d0 - l51 * l41 * d1 - l52 * l42 * d2 - l53 * l43 * d3) / d4
    d5 = n55 - l50 * l50 * d0 - l51 * l51 * d1 - l52 * l52 * d2 - l53 * l53 * d3 - l54 * l54 * d4
    pinned = (d0 > least) & (d1 > least) & (d2 > least) & (d3 > least) & (d4 > least) & (d5 > least)
    z1 = b1 - l10 * b0
    z2 = b2 - l20 * b0 - l21 * z1
    z3 = b3 - l30 * b0 - l31 * z1 - l32 * z2
    z4 = b4 - l40 * b0 - l41 * z1 - l42 * z2 - l43 * z3
    z5 = b5 - l50 * b0 - l51 * z1 - l52 * z2 - l53 * z3 - l54 * z4
    x5 = z5 / d5
    x4 = z4 / d4 - l54 * x5
    x3 = z3 / d3 - l43 * x4 - l53 * x5
    x2 = z2 / d2 - l32 * x3 - l42 * x4 - l52 * x5
    x1 = z1 / d1 - l21 * x2 - l31 * x3 - l41 * x4 - l51 * x5
    x0 = b0 / d0 - l10 * x1 - l20 * x2 - l30 * x3 - l40 * x4 - l50 * x5
    return pinned, (x0, x1, x2, x3, x4, x5)


@numba.njit(cache=True, nogil=True)
def bend_corrected(
    samples: Grids,
    centres: tuple[np.ndarray, np.ndarray],
    reach: tuple[float, float],
    bounds: tuple[float, float],
    out: np.ndarray,
    planar: np.ndarray,
) -> None:
    """``out``'s plane values (``planar``: level 0's planes, perception.surface) read again
    where the surface bends (:func:`_curved`) from the quadric through the same samples
    (:func:`_quadric_values`; ``reach`` = (bin size, max_slope)), where it fits and moves the
    plane's value by at most MAX_BEND_CORRECTION of the bin size; clamped to ``bounds`` (y_near,
    y_far). ``samples``: each bin's front-most point (y, x, z; +inf y: none), (rows, cols) each."""
    (sy, sx, sz), (x_centres, z_centres) = samples, centres
    rows, cols = sy.shape
    # Level 0's planes, NaN elsewhere, before any bin is read again; filled by a loop, which takes
    # 12 us a map where np.where took 28.
    planes = np.empty_like(out)
    for r in range(rows):
        for c in range(cols):
            planes[r, c] = out[r, c] if planar[r, c] else np.nan
    bending = np.empty(rows * cols, np.int64)
    count = 0
    for r in range(rows):
        for c in range(cols):
            if not np.isnan(planes[r, c]) and _curved(planes, r, c):
                bending[count] = r * cols + c
                count += 1
    # Only an interior bin bends (_curved): its 3 x 3 needs no clipping to the map.
    gathered = (np.empty((9, count)), np.empty((9, count)), np.empty((9, count)))
    at = (np.empty(count), np.empty(count), np.empty(count))
    for b in range(count):
        r, c = bending[b] // cols, bending[b] % cols
        at[0][b], at[1][b], at[2][b] = planes[r, c], x_centres[c], z_centres[r]
        for k in range(9):
            i, j = r - 1 + k // 3, c - 1 + k % 3
            gathered[0][k, b], gathered[1][k, b], gathered[2][k, b] = sy[i, j], sx[i, j], sz[i, j]
    values = np.empty(count)
    _quadric_values(gathered, at, reach, values)
    for b in range(count):
        r, c = bending[b] // cols, bending[b] % cols
        if abs(values[b] - planes[r, c]) <= MAX_BEND_CORRECTION * reach[0]:
            out[r, c] = min(max(values[b], bounds[0]), bounds[1])
