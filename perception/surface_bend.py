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
cracker box to the drill, 0.13-0.46 ms on one core). Self-contained, called from Python after
each map's levels: numba's cache does not see a change in another file's jitted callee.
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


# The two per-bin functions are inlined into the bin loop: a call passing them the map's and the
# scratch's arrays costs a reference count up and down on each (atomic): on the YCB drill's maps
# the bend pass took 0.55 ms a map with the calls, 0.46 inlined.
@numba.njit(cache=True, nogil=True, inline="always")
def _quadric_at(
    samples: Grids,
    r: int,
    c: int,
    centre: tuple[float, float],
    plane_y: float,
    reach: tuple[float, float],
    kept: np.ndarray,
) -> float:
    """The surface's y at ``centre`` (x, z) from the quadric y = h + gx u + gz v + a u² + b u v + c
    v² (u, v: offsets in bins) through the samples of the 3 x 3 bins around (r, c), a bin off the
    map's border, that continue the surface of the plane's value ``plane_y`` at the centre (a height
    change within max_slope times the distance plus the bins' size, ``reach`` = (bin size,
    max_slope): the plane's own rule, perception.surface._continues), or NaN where they cannot say:
    under _MIN_QUADRIC_SAMPLES, too close to a conic to pin six terms (:func:`_quadric`), or one off
    the quadric by over QUADRIC_FIT_FRACTION of the bin size (a rim, a crease, a noisy cloud: the
    plane stays). ``kept``: (3, 9) scratch for the samples kept."""
    sy, sx, sz = samples
    tolerance, max_slope = reach
    n = 0
    # Only an interior bin bends (_curved), so the 3 x 3 needs no clipping to the map; and the
    # test is one expression of & and |, not short-circuit branches: together the drill's bend
    # pass 0.43 -> 0.37 ms a map, the same bits.
    for i in range(r - 1, r + 2):
        for j in range(c - 1, c + 2):
            step = abs(sy[i, j] - plane_y) - tolerance
            dx, dz = sx[i, j] - centre[0], sz[i, j] - centre[1]
            if (sy[i, j] < np.inf) & ((step <= 0.0) | (step * step <= max_slope * max_slope * (dx * dx + dz * dz))):
                kept[0, n] = dx / tolerance
                kept[1, n] = dz / tolerance
                kept[2, n] = sy[i, j] - plane_y
                n += 1
    if n < _MIN_QUADRIC_SAMPLES:
        return np.nan
    pinned, solution = _quadric(_normal_equations(n, kept))
    if not pinned:
        return np.nan
    fit = QUADRIC_FIT_FRACTION * tolerance
    low, high = np.inf, -np.inf
    for k in range(n):
        u, v = kept[0, k], kept[1, k]
        fitted = solution[0] + solution[1] * u + solution[2] * v
        fitted += solution[3] * u * u + solution[4] * u * v + solution[5] * v * v
        if not abs(kept[2, k] - fitted) <= fit:
            return np.nan
        low, high = min(low, kept[2, k]), max(high, kept[2, k])
    # Within the samples' heights (give or take the fit): a quadric bridging a step overshoots it.
    return plane_y + solution[0] if low - fit <= solution[0] <= high + fit else np.nan


@numba.njit(cache=True, nogil=True, inline="always")
def _normal_equations(n: int, kept: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """The lower triangle of the quadric's normal equations through the first ``n`` (u, v, y)
    columns of ``kept``, row by row (n00, n10, n11, n20, ... n44; n50 ... n55), then the
    right-hand side (b0 .. b5): each sum the products t_a t_b of the terms (1, u, v, u², u v, v²),
    summed in scalars, which stay in registers (summed into an array's elements, each loaded and
    stored at every term, the drill's bend pass took 0.68 ms a map; 0.55 this way), in the order
    the terms come."""
    n00 = n10 = n11 = n20 = n21 = n22 = n30 = n31 = n32 = n33 = n40 = n41 = n42 = n43 = n44 = 0.0
    n50 = n51 = n52 = n53 = n54 = n55 = b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    for k in range(n):
        u, v, y = kept[0, k], kept[1, k], kept[2, k]
        uu, uv, vv = u * u, u * v, v * v
        n00, n10, n11 = n00 + 1.0, n10 + u, n11 + u * u
        n20, n21, n22 = n20 + v, n21 + v * u, n22 + v * v
        n30, n31, n32, n33 = n30 + uu, n31 + uu * u, n32 + uu * v, n33 + uu * uu
        n40, n41, n42, n43, n44 = n40 + uv, n41 + uv * u, n42 + uv * v, n43 + uv * uu, n44 + uv * uv
        n50, n51, n52, n53, n54, n55 = n50 + vv, n51 + vv * u, n52 + vv * v, n53 + vv * uu, n54 + vv * uv, n55 + vv * vv
        b0, b1, b2, b3, b4, b5 = b0 + y, b1 + u * y, b2 + v * y, b3 + uu * y, b4 + uv * y, b5 + vv * y
    return (
        (n00, n10, n11, n20, n21, n22, n30, n31, n32, n33, n40, n41, n42, n43, n44),
        (n50, n51, n52, n53, n54, n55),
        (b0, b1, b2, b3, b4, b5),
    )


@numba.njit(cache=True, nogil=True, inline="always")
def _quadric(
    sums: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]],
) -> tuple[bool, tuple[float, float, float, float, float, float]]:
    """The least-squares quadric's six coefficients from its normal equations' ``sums``
    (:func:`_normal_equations`): (whether the samples pin six terms, the coefficients, zeros where
    they do not). LDL^T (symmetric positive definite), column by column, each pivot checked
    against _MIN_PIVOT_RATIO of the largest diagonal term, then L z = b and D L^T x = z; each sum
    of products taken in the column order a loop over a 6 x 7 array takes (whose every update was a
    load and a store, chained: the drill's bend pass 0.37 -> 0.29 ms a map in scalars, which stay
    in registers; the same bits on the 320 YCB planner maps)."""
    (
        (n00, n10, n11, n20, n21, n22, n30, n31, n32, n33, n40, n41, n42, n43, n44),
        (n50, n51, n52, n53, n54, n55),
        (b0, b1, b2, b3, b4, b5),
    ) = sums
    least = _MIN_PIVOT_RATIO * max(max(max(max(max(max(0.0, n00), n11), n22), n33), n44), n55)
    none = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    d0 = n00
    if not d0 > least:
        return False, none
    l10, l20, l30, l40, l50 = n10 / d0, n20 / d0, n30 / d0, n40 / d0, n50 / d0
    d1 = n11 - l10 * l10 * d0
    if not d1 > least:
        return False, none
    l21 = (n21 - l20 * l10 * d0) / d1
    l31 = (n31 - l30 * l10 * d0) / d1
    l41 = (n41 - l40 * l10 * d0) / d1
    l51 = (n51 - l50 * l10 * d0) / d1
    d2 = n22 - l20 * l20 * d0 - l21 * l21 * d1
    if not d2 > least:
        return False, none
    l32 = (n32 - l30 * l20 * d0 - l31 * l21 * d1) / d2
    l42 = (n42 - l40 * l20 * d0 - l41 * l21 * d1) / d2
    l52 = (n52 - l50 * l20 * d0 - l51 * l21 * d1) / d2
    d3 = n33 - l30 * l30 * d0 - l31 * l31 * d1 - l32 * l32 * d2
    if not d3 > least:
        return False, none
    l43 = (n43 - l40 * l30 * d0 - l41 * l31 * d1 - l42 * l32 * d2) / d3
    l53 = (n53 - l50 * l30 * d0 - l51 * l31 * d1 - l52 * l32 * d2) / d3
    d4 = n44 - l40 * l40 * d0 - l41 * l41 * d1 - l42 * l42 * d2 - l43 * l43 * d3
    if not d4 > least:
        return False, none
    l54 = (n54 - l50 * l40 * d0 - l51 * l41 * d1 - l52 * l42 * d2 - l53 * l43 * d3) / d4
    d5 = n55 - l50 * l50 * d0 - l51 * l51 * d1 - l52 * l52 * d2 - l53 * l53 * d3 - l54 * l54 * d4
    if not d5 > least:
        return False, none
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
    return True, (x0, x1, x2, x3, x4, x5)


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
    (:func:`_quadric_at`; ``reach`` = (bin size, max_slope)), where it fits and moves the plane's
    value by at most MAX_BEND_CORRECTION of the bin size; clamped to ``bounds`` (y_near, y_far).
    ``samples``: each bin's front-most point (y, x, z; +inf y: none), (rows, cols) each."""
    sy, (x_centres, z_centres) = samples[0], centres
    # Level 0's planes, NaN elsewhere, before any bin is read again; filled by a loop, which takes
    # 12 us a map where np.where took 28.
    planes = np.empty_like(out)
    for r in range(sy.shape[0]):
        for c in range(sy.shape[1]):
            planes[r, c] = out[r, c] if planar[r, c] else np.nan
    kept = np.empty((3, 9))
    for r in range(sy.shape[0]):
        for c in range(sy.shape[1]):
            if np.isnan(planes[r, c]) or not _curved(planes, r, c):
                continue
            y = _quadric_at(samples, r, c, (x_centres[c], z_centres[r]), planes[r, c], reach, kept)
            if abs(y - planes[r, c]) <= MAX_BEND_CORRECTION * reach[0]:
                out[r, c] = min(max(y, bounds[0]), bounds[1])
