"""Compiled binning of contact depth-maps (numba): the hot path of :mod:`perception.depthmap`.

One pass over the model points transforms them to a gel frame, crops them to its contact volume
and keeps the minimum y per x-z bin, by the bin rule of :mod:`perception.depthmap`'s module
docstring (bin i holds [edge_i, edge_i+1), the far crop edge belongs to the last bin). The
kernels are what ``dtx bench perception`` and ``dtx bench serve`` time; :func:`region_groups`
shares their regions out (among threads here, among chunks in perception.depthmap_tensor), and
:func:`cells_meeting_crops` says which of the index's cells a gel's crop can reach before any
point is read.
"""

from __future__ import annotations

import numba
import numpy as np

from perception.errors import DepthMapError

# Points are transformed in chunks of this many and binned in batches of at least this many
# (cut_kernel): the bin indices of a batch are computed without a branch, and the rare batch
# holding a value within rounding of a bin edge is binned again by comparing with the edges (a
# branch per point, even never taken, made the loop 4x slower). Each binning call passes a dozen
# arrays, each counted in and out: at 512 rather than 256 a planner's region (~50,000 points kept)
# takes half the calls, its kernel 5 % less time (0.415 -> 0.395 ms on the YCB cracker box).
_CHUNK = 512


@numba.njit(cache=True, nogil=True)
def _exact_bin(value: float, index: int, edges: np.ndarray) -> int:
    """The bin [edge_i, edge_i+1) of ``value`` in [-half, half] from a scaled-floor ``index`` at
    most one bin off (edges = linspace(-half, half, count + 1)); the far edge belongs to the last
    bin. Always a valid bin, even for a value outside (clamped: no read or write out of bounds)."""
    count = edges.shape[0] - 1
    index = min(max(index, 0), count - 1)
    if value < edges[index]:
        index -= 1
    if index < count - 1 and value >= edges[index + 1]:
        index += 1
    return max(index, 0)


@numba.njit(cache=True, nogil=True)
def _chunk_bins(
    x: np.ndarray,
    z: np.ndarray,
    count: int,
    half_x: float,
    half_z: float,
    x_edges: np.ndarray,
    z_edges: np.ndarray,
    flat: np.ndarray,
) -> None:
    """flat[i] = the bin row * cols + col of each of the first ``count`` points, all
    inside the crop (one outside lands in an edge bin, never out of bounds). The scaled floor is
    exact unless a value lies within 1e-6 bin of an edge (rounding is < 1e-9 bin as crop_bounds
    keeps bins wide): only batches holding such a value are compared with the edge arrays, which
    keeps the rule exact at full speed."""
    cols, rows = x_edges.shape[0] - 1, z_edges.shape[0] - 1
    scale_x, scale_z = cols / (2.0 * half_x), rows / (2.0 * half_z)
    near = False
    for i in range(np.uint64(count)):  # unsigned: no index fix-ups (_to_gel)
        a = (x[i] + half_x) * scale_x  # >= 0 inside the crop: int() is the floor
        b = (z[i] + half_z) * scale_z
        col, row = min(max(int(a), 0), cols - 1), min(max(int(b), 0), rows - 1)
        in_col, in_row = a - col, b - row
        near |= (in_col < 1e-6) | (in_col > 1.0 - 1e-6) | (in_row < 1e-6) | (in_row > 1.0 - 1e-6)
        flat[i] = row * cols + col
    if near:
        for i in range(count):
            flat[i] = _exact_bin(z[i], int((z[i] + half_z) * scale_z), z_edges) * cols + _exact_bin(
                x[i], int((x[i] + half_x) * scale_x), x_edges
            )


@numba.njit(cache=True, nogil=True)
def _keep_least_y(y: np.ndarray, count: int, flat: np.ndarray, min_y: np.ndarray) -> None:
    """min_y[flat[i]] = min(min_y[flat[i]], y[i]) for the first ``count`` points."""
    for i in range(count):
        min_y[flat[i]] = min(min_y[flat[i]], y[i])


@numba.njit(cache=True, nogil=True)
def _keep_front_points(
    kept: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    count: int,
    flat: np.ndarray,
    front: tuple[np.ndarray, np.ndarray],
) -> None:
    """For the first ``count`` points ``kept`` = (y, x, z, x's bits, z's bits) in bins ``flat``:
    each bin's least y and that point's x and z (ties by the least x, then z: the same point in
    any order of the points, perception.surface) in ``front`` = (bins x 3: each bin's y, x, z;
    the same memory seen as int64, made once by the caller).

    A bin's three values side by side: one cache line a point rather than one in each of three
    80 kB arrays, which a 100 x 100 map's do not fit the L1 cache with (the kernel 0.39 -> 0.35 ms
    a region on the YCB cracker box, copying each region's in and out). The x and z are taken by
    a bit mask, not a branch (which the compiler makes of any select here): a new front-most point
    is about as likely as not, and the mispredicted branches cost a region's cut 0.54 -> 0.46 ms.
    Ties (equal y) are rare: a branch."""
    y, x, z, x_bits, z_bits = kept
    fronts, front_bits = front
    for i in range(np.uint64(count)):  # unsigned: no index fix-ups (_to_gel)
        b = np.uint64(flat[i])
        yi, front_y = y[i], fronts[b, 0]
        if yi == front_y and (x[i] < fronts[b, 1] or (x[i] == fronts[b, 1] and z[i] < fronts[b, 2])):
            fronts[b, 1], fronts[b, 2] = x[i], z[i]
        new = -np.int64(yi < front_y)
        front_bits[b, 1] = (x_bits[i] & new) | (front_bits[b, 1] & ~new)
        front_bits[b, 2] = (z_bits[i] & new) | (front_bits[b, 2] & ~new)
        fronts[b, 0] = min(front_y, yi)  # front_y where equal, as the rule keeps it


@numba.njit(cache=True, nogil=True)
def _min_y_kernel(
    x: np.ndarray,
    z: np.ndarray,
    y: np.ndarray,
    half_x: float,
    half_z: float,
    x_edges: np.ndarray,
    z_edges: np.ndarray,
    min_y: np.ndarray,
) -> None:
    """min_y[row * cols + col] = min(min_y[...], y) for every point (all inside the crop)."""
    flat = np.empty(_CHUNK, np.int64)
    for start in range(0, y.shape[0], _CHUNK):
        stop = min(start + _CHUNK, y.shape[0])
        _chunk_bins(x[start:stop], z[start:stop], stop - start, half_x, half_z, x_edges, z_edges, flat)
        _keep_least_y(y[start:stop], stop - start, flat, min_y)


@numba.njit(cache=True, nogil=True)
def _to_gel(
    flat_points: np.ndarray,
    first: int,
    count: int,
    model_to_gel: np.ndarray,
    bounds: np.ndarray,
    gel: np.ndarray,
    inside: np.ndarray,
) -> None:
    """gel[:, j] = (x, y, z) of point ``first + j`` (j < count; ``flat_points`` = the (n, 3)
    points as one row) through ``model_to_gel`` (3 x 4, float64) and inside[j] = 1 where it lies
    in ``bounds`` (:func:`cut_kernel`), else 0.

    A loop of its own because the compiler makes vector code of it where the kernel's compaction
    (a store at the count kept so far) keeps a loop scalar; so do numba's fix-up of a possibly
    negative index (a few instructions an access: the indices are unsigned) and a 2-D index's
    stride (the points are read as one row; ``points[i, 0]`` is 1.5 x as slow).
    A planner's region's transform and crop: 0.57-0.79 -> 0.28-0.45 ms on the five YCB clouds,
    one core of an AVX-512 Xeon; the same bits (no fused multiply-add either way)."""
    half_x, half_z, y_near, y_far = bounds[0], bounds[1], bounds[2], bounds[3]
    xx, xy, xz, xt = model_to_gel[0, 0], model_to_gel[0, 1], model_to_gel[0, 2], model_to_gel[0, 3]
    yx, yy, yz, yt = model_to_gel[1, 0], model_to_gel[1, 1], model_to_gel[1, 2], model_to_gel[1, 3]
    zx, zy, zz, zt = model_to_gel[2, 0], model_to_gel[2, 1], model_to_gel[2, 2], model_to_gel[2, 3]
    at = np.uint64(3) * np.uint64(first)
    for j in range(np.uint64(count)):
        px, py, pz = (
            float(flat_points[at]),
            float(flat_points[at + np.uint64(1)]),
            float(flat_points[at + np.uint64(2)]),
        )
        at += np.uint64(3)
        y = yx * px + yy * py + yz * pz + yt
        x = xx * px + xy * py + xz * pz + xt
        z = zx * px + zy * py + zz * pz + zt
        gel[0, j], gel[1, j], gel[2, j] = x, y, z
        inside[j] = (y >= y_near) & (y <= y_far) & (abs(x) <= half_x) & (abs(z) <= half_z)


@numba.njit(cache=True, nogil=True)
def cut_kernel(
    points: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    runs: np.ndarray,
    model_to_gel: np.ndarray,
    bounds: np.ndarray,
    x_edges: np.ndarray,
    z_edges: np.ndarray,
    min_y: np.ndarray,
    counts: np.ndarray,
    at_x: np.ndarray,
    at_z: np.ndarray,
    places: bool,
) -> None:
    """Transform, crop and bin in one pass, for every region k: the points of runs
    runs[k]..runs[k+1] of (starts, ends) through model_to_gel[k] (3 x 4, float64), kept inside
    ``bounds`` = (half_x, half_z, y_near, y_far) (inclusive), binned into min_y[k] (rows * cols,
    +inf) and, with ``places``, at_x[k], at_z[k] (:func:`_keep_front_points`; C-contiguous like
    min_y); counts[k] = points kept. ``points`` (n, 3) is C-contiguous.

    Why a kernel: NumPy needs a dozen passes over the points (dot products, masks, a gather, bin
    indices, np.minimum.at) where one pass reads each point once, and no library crops and
    min-reduces by bin (benchmarks/perception.py measures both). Arithmetic is float64 (the
    transform composed in float64), so nothing is lost far from the origin; no branch compacts."""
    flat_points = points.reshape(-1)
    # Room for a chunk past a batch not yet binned: the points in the crop are binned _CHUNK or
    # more at a time (a whole cloud's chunks keep a few points each, and each binning call
    # passes ten arrays: the kernel of a grasp's cut of a 1.5 M point cloud 4.2 -> 3.8 ms, the
    # nearest point's 3.7).
    kept_x, kept_z, kept_y = np.empty(2 * _CHUNK), np.empty(2 * _CHUNK), np.empty(2 * _CHUNK)
    kept = (kept_y, kept_x, kept_z, kept_x.view(np.int64), kept_z.view(np.int64))
    gel, inside = np.empty((3, _CHUNK)), np.empty(_CHUNK, np.int64)
    front_places = np.empty((min_y.shape[1] if places else 0, 3))  # a region's bins' (y, x, z)
    front = (front_places, front_places.view(np.int64))
    flat = np.empty(2 * _CHUNK, np.int64)
    for k in range(model_to_gel.shape[0]):
        for b in range(front_places.shape[0]):
            front_places[b, 0], front_places[b, 1], front_places[b, 2] = min_y[k, b], at_x[k, b], at_z[k, b]
        in_crop, m = 0, 0
        for run in range(runs[k], runs[k + 1]):
            for start in range(starts[run], ends[run], _CHUNK):
                count = min(start + _CHUNK, ends[run]) - start
                _to_gel(flat_points, start, count, model_to_gel[k], bounds, gel, inside)
                for j in range(np.uint64(count)):
                    slot = m & (2 * _CHUNK - 1)  # = m, which stays below 2 * _CHUNK: no index fix-up
                    kept_x[slot], kept_y[slot], kept_z[slot] = gel[0, j], gel[1, j], gel[2, j]
                    m += inside[j]
                if m >= _CHUNK:
                    _bin_kept(kept, m, bounds, x_edges, z_edges, flat, front, min_y[k], places)
                    in_crop, m = in_crop + m, 0
        _bin_kept(kept, m, bounds, x_edges, z_edges, flat, front, min_y[k], places)
        counts[k] = in_crop + m
        for b in range(front_places.shape[0]):
            min_y[k, b], at_x[k, b], at_z[k, b] = front_places[b, 0], front_places[b, 1], front_places[b, 2]


@numba.njit(cache=True, nogil=True)
def _bin_kept(
    kept: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    count: int,
    bounds: np.ndarray,
    x_edges: np.ndarray,
    z_edges: np.ndarray,
    flat: np.ndarray,
    front: tuple[np.ndarray, np.ndarray],
    min_y: np.ndarray,
    places: bool,
) -> None:
    """The first ``count`` points of ``kept`` (:func:`_keep_front_points`) binned: with ``places``
    each bin's least y and that point's x and z into ``front``, else the least y into ``min_y``."""
    _chunk_bins(kept[1], kept[2], count, bounds[0], bounds[1], x_edges, z_edges, flat)
    if places:
        _keep_front_points(kept, count, flat, front)
    else:
        _keep_least_y(kept[0], count, flat, min_y)


# Added to a cell's half-size when testing it against a crop: a point's cell comes from a
# rounded floor((p - origin) / cell), so a point may lie a few ulps (~1e-12 m at 1 km) outside it.
_CELL_MARGIN_M = 1e-6


@numba.njit(cache=True, nogil=True)
def cells_meeting_crops(
    corners: np.ndarray,
    owner: np.ndarray,
    cell_m: float,
    model_to_gel: np.ndarray,
    bounds: tuple[float, float, float, float],
) -> np.ndarray:
    """Which cells (low ``corners`` (n, 3), m) can hold a point of their gel's crop box
    (``model_to_gel[owner[i]]``: cell i's gel, (N, 4, 4)). The index hands out the cells of a cube
    around the crop's reach (~40 mm across for a 24 x 19 x 4 mm crop), several times the points
    the crop holds; a cell is dropped when one of the gel's axes separates it from the box (the
    separating-axis test on the box's own axes: conservative, it never drops a cell that meets
    the box), so the kernel, which crops each point exactly, gives the same maps. Compiled: in
    NumPy, each cell's gel transform gathered and the test's dozen passes took 0.45 ms of a
    64-gel request's plan."""
    half_x, half_z, y_near, y_far = bounds
    half_cell = 0.5 * cell_m + _CELL_MARGIN_M
    meets = np.empty(corners.shape[0], np.bool_)
    for i in range(corners.shape[0]):
        g = model_to_gel[owner[i]]
        cx, cy, cz = corners[i, 0] + 0.5 * cell_m, corners[i, 1] + 0.5 * cell_m, corners[i, 2] + 0.5 * cell_m
        # The cell's centre and half-extent along each of the gel's axes.
        x, reach_x = g[0, 0] * cx + g[0, 1] * cy + g[0, 2] * cz + g[0, 3], abs(g[0, 0]) + abs(g[0, 1]) + abs(g[0, 2])
        y, reach_y = g[1, 0] * cx + g[1, 1] * cy + g[1, 2] * cz + g[1, 3], abs(g[1, 0]) + abs(g[1, 1]) + abs(g[1, 2])
        z, reach_z = g[2, 0] * cx + g[2, 1] * cy + g[2, 2] * cz + g[2, 3], abs(g[2, 0]) + abs(g[2, 1]) + abs(g[2, 2])
        meets[i] = (
            (abs(x) <= half_x + half_cell * reach_x)
            & (abs(z) <= half_z + half_cell * reach_z)
            & (y >= y_near - half_cell * reach_y)
            & (y <= y_far + half_cell * reach_y)
        )
    return meets


def bin_edges(half_m: float, count: int) -> np.ndarray:
    """The ``count + 1`` float64 edges of ``count`` equal bins over [-half_m, half_m]."""
    return np.linspace(-half_m, half_m, count + 1)


def bin_centres(half_m: float, count: int) -> np.ndarray:
    """The ``count`` float64 centres of equal bins over [-half_m, half_m]: their edges' midpoints."""
    edges = bin_edges(half_m, count)
    return 0.5 * (edges[:-1] + edges[1:])


def min_y_per_bin(
    x_m: np.ndarray, z_m: np.ndarray, y_m: np.ndarray, half_x_m: float, half_z_m: float, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Minimum y per x-z bin of points already inside the crop; returns (min_y, occupied).

    ``min_y`` is float64 (rows, cols) with +inf in empty bins. One compiled pass (the bin rule of
    perception.depthmap's module docstring, exact): NumPy's np.minimum.at needs the bin indices
    computed first, in several more passes (benchmarks/perception.py, binning, measures both)."""
    rows, cols = shape
    flat = np.full(rows * cols, np.inf)
    x, z, y = (np.ascontiguousarray(a, dtype=np.float64) for a in (x_m, z_m, y_m))
    _min_y_kernel(x, z, y, float(half_x_m), float(half_z_m), bin_edges(half_x_m, cols), bin_edges(half_z_m, rows), flat)
    min_y = flat.reshape(rows, cols)
    return min_y, np.isfinite(min_y)


def region_groups(run_lengths: np.ndarray, runs: np.ndarray, groups: int) -> list[tuple[int, int]]:
    """Up to ``groups`` contiguous, non-empty ranges [first, stop) of the regions, with about
    equal points to read each: region k reads the runs runs[k]..runs[k+1], run i holds
    ``run_lengths[i]`` points. Equal counts of regions would not do: a gel on a face reads
    several times the points of one at an edge."""
    regions = len(runs) - 1
    visits = np.concatenate([[0], np.cumsum(run_lengths)])[runs]  # points read before region k
    cuts = np.searchsorted(visits, visits[-1] * np.arange(1, groups) / groups)
    edges = np.unique(np.clip(np.concatenate([[0], cuts, [regions]]), 0, regions))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def fill_sampling_gaps(depth_map_m: np.ndarray, occupied: np.ndarray, min_neighbours: int) -> np.ndarray:
    """The nearest-point rule's gaps: empty bins inside a sampled surface (at least
    ``min_neighbours`` of their 8 neighbours occupied) take the nearest (minimum y) of their
    occupied neighbours; others are unchanged. ``depth_map_m`` is one map (rows, cols) or a
    stack (..., rows, cols), each map on its own. The 3 x 3 neighbourhoods are sums and minima of
    nine shifted views of the padded maps: a few passes over small arrays, ~5x faster than
    scipy.ndimage's generic filters on 100 x 100."""
    if not 1 <= min_neighbours <= 8:
        raise DepthMapError(f"min_neighbours must be in 1..8, got {min_neighbours}")
    rows, cols = occupied.shape[-2:]
    padded = (*occupied.shape[:-2], rows + 2, cols + 2)  # a border of empty bins
    flags = np.zeros(padded, np.uint8)
    flags[..., 1:-1, 1:-1] = occupied
    surface = np.full(padded, np.inf, np.float32)
    np.copyto(surface[..., 1:-1, 1:-1], depth_map_m, where=occupied)
    neighbours = np.zeros(occupied.shape, np.uint8)
    nearest = np.full(occupied.shape, np.inf, np.float32)
    for dr in range(3):
        for dc in range(3):
            if (dr, dc) != (1, 1):
                neighbours += flags[..., dr : dr + rows, dc : dc + cols]
                np.minimum(nearest, surface[..., dr : dr + rows, dc : dc + cols], out=nearest)
    gaps = ~occupied & (neighbours >= min_neighbours)
    return np.where(gaps, nearest, depth_map_m).astype(np.float32)
