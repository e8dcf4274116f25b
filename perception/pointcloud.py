"""Depth images to point clouds: back-projection with distortion, and merging cameras in world.

A depth pixel holds the z coordinate (metres) of the surface point in the camera's optical
frame (z forward, x right, y down), as the Kinect v2 / OpenNI report it — not the range
along the ray.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Iterator, Sequence

import cv2
import numba
import numpy as np
import open3d as o3d

from msgs.sensors import CameraIntrinsics, DepthImage
from perception.errors import PointCloudError
from workcell.kinematics import ROTATION_TOLERANCE, KinematicsError, rigid_transform

# Kinect v2 working range; returns outside it are unreliable or spurious.
DEFAULT_RANGE_M = (0.5, 4.5)


def check_transform(a_to_b: np.ndarray, name: str = "transform") -> np.ndarray:
    """Return ``a_to_b`` as a float64 4x4 rigid transform (workcell.kinematics.rigid_transform),
    or raise PointCloudError, as every other bad input of this module does."""
    try:
        return rigid_transform(a_to_b, name)
    except KinematicsError as err:
        raise PointCloudError(str(err)) from None


def check_transforms(stack: np.ndarray, name: str = "transforms") -> np.ndarray:
    """``stack`` (N, 4, 4) as float64, each a rigid transform by :func:`check_transform`'s rule
    (named ``name[i]`` in the error), or PointCloudError. A planner's request carries hundreds
    of poses: one vectorised screen, twice as strict as the rule, passes the usual ones, and only
    those it does not pass are judged one by one by the rule itself (so the rule stays the one in
    workcell.kinematics, and rounding near its tolerance cannot let a bad one through)."""
    raw = np.asarray(stack)
    if raw.dtype.kind not in "biuf":  # complex would be cast, text parsed
        raise PointCloudError(f"{name} must be real numbers (bool, integer or float), got {raw.dtype}")
    matrices = raw.astype(np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (4, 4):
        raise PointCloudError(f"{name} must be (N, 4, 4), got shape {matrices.shape}")
    rotations = matrices[:, :3, :3]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN or inf entries fail the screen
        error = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2), initial=0.0)
        passed = (
            np.isfinite(matrices).all(axis=(1, 2))
            & (error <= 0.5 * ROTATION_TOLERANCE)
            & (np.linalg.det(np.nan_to_num(rotations)) > 0.5)
            & (matrices[:, 3] == [0.0, 0.0, 0.0, 1.0]).all(axis=1)
        )
    for i in np.flatnonzero(~passed):
        check_transform(matrices[i], f"{name}[{i}]")
    return matrices


def principal_spread_m(points_m: np.ndarray) -> np.ndarray:
    """Standard deviation (metres) of (N, 3) points, N >= 1, along each principal axis,
    ascending: the second is ~0 for identical or collinear points, the first for coplanar ones."""
    centred = points_m - points_m.mean(axis=0)
    # Clipped at 0: rounding can make a zero eigenvalue slightly negative (its root NaN).
    return np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / len(points_m)), 0.0))


def transform_points(points_a_m: np.ndarray, a_to_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points (metres, any real dtype or strides, N >= 0) from frame a to frame b;
    computed and returned in float64, (N, 3). Any other shape, a non-finite coordinate or a
    non-rigid ``a_to_b`` (:func:`check_transform`) raises PointCloudError: an (N, 4)
    homogeneous or (M, 2) array is refused, never reshaped into other points."""
    try:
        raw = np.asarray(points_a_m)
    except (TypeError, ValueError) as err:
        raise PointCloudError(f"points_a_m must be an (N, 3) array of numbers: {err}") from None
    if raw.dtype.kind not in "biuf":  # complex would be cast, text parsed
        raise PointCloudError(f"points_a_m must be real numbers (bool, integer or float), got {raw.dtype}")
    points = raw.astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"points_a_m must be (N, 3), got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise PointCloudError("points_a_m contains NaN or inf")
    matrix = check_transform(a_to_b, "a_to_b")
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _intrinsics_key(intrinsics: CameraIntrinsics) -> tuple:
    distortion = tuple(float(d) for d in intrinsics.distortion)
    return (
        int(intrinsics.width),
        int(intrinsics.height),
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.cx),
        float(intrinsics.cy),
        distortion,
    )


@functools.lru_cache(maxsize=16)
def _normalised_rays(key: tuple) -> np.ndarray:
    # Undistorting 200k pixels costs tens of ms; a camera's rays never change, so cache them.
    width, height, fx, fy, cx, cy, distortion = key
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    camera_matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    undistorted = cv2.undistortPoints(pixels, camera_matrix, np.asarray(distortion, dtype=np.float64))
    rays = undistorted.reshape(height, width, 2)
    rays.setflags(write=False)
    return rays


def pixel_rays(intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H, W, 2) undistorted normalised image coordinates (x/z, y/z) of every pixel centre."""
    if intrinsics.width <= 0 or intrinsics.height <= 0:
        raise PointCloudError(f"image size must be positive, got {intrinsics.width}x{intrinsics.height}")
    if not (intrinsics.fx > 0 and intrinsics.fy > 0):
        raise PointCloudError(f"focal lengths must be positive, got fx={intrinsics.fx} fy={intrinsics.fy}")
    if len(intrinsics.distortion) not in (4, 5, 8, 12, 14):
        raise PointCloudError(f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {len(intrinsics.distortion)}")
    key = _intrinsics_key(intrinsics)
    if not all(np.isfinite(v) for v in key[2:6] + key[6]):
        raise PointCloudError("intrinsics must be finite")
    return _normalised_rays(key)


def depth_to_points_camera(
    depth_m: np.ndarray, intrinsics: CameraIntrinsics, range_m: tuple[float, float] = DEFAULT_RANGE_M
) -> np.ndarray:
    """Back-project a depth image (H, W, metres, NaN = no return) to (N, 3) float64 points in
    the camera frame. NaN, inf and depths outside ``range_m`` (inclusive) are dropped."""
    depth = np.asarray(depth_m)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise PointCloudError(f"depth image is {depth.shape}, intrinsics say {(intrinsics.height, intrinsics.width)}")
    near, far = float(range_m[0]), float(range_m[1])
    if not (0.0 < near < far and np.isfinite(far)):
        raise PointCloudError(f"depth range must satisfy 0 < near < far < inf, got {range_m}")
    rays = pixel_rays(intrinsics)
    z = depth.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):  # NaN compares False, which is what drops it
        valid = (z >= near) & (z <= far)
    z_valid = z[valid]
    rays_valid = rays[valid]
    return np.column_stack([rays_valid[:, 0] * z_valid, rays_valid[:, 1] * z_valid, z_valid])


def depth_images_to_world(
    images: Sequence[DepthImage], range_m: tuple[float, float] = DEFAULT_RANGE_M
) -> list[np.ndarray]:
    """One (N_i, 3) float64 world cloud per depth image, using each image's ``camera_to_world``."""
    if len(images) == 0:
        raise PointCloudError("no depth images given")
    return [
        transform_points(depth_to_points_camera(image.depth_m(), image.intrinsics, range_m), image.camera_to_world)
        for image in images
    ]


def merge_depth_images(images: Sequence[DepthImage], range_m: tuple[float, float] = DEFAULT_RANGE_M) -> np.ndarray:
    """All cameras' points merged in ``world``, (N, 3) float64."""
    return np.concatenate(depth_images_to_world(images, range_m), axis=0)


_OPEN3D_RANDOM = threading.Lock()


@contextlib.contextmanager
def seeded_open3d(*keys: int) -> Iterator[None]:
    """Run Open3D's random work (RANSAC, sampling) reproducibly: its global generator seeded
    from any integers (it takes 31 bits), on one thread, one such block per process at a time.

    One thread, because Open3D's parallel RANSAC loops draw from that one shared generator in
    whatever order their threads run: with two threads a seeded table-plane fit gave another
    plane in 1 of 4 runs on a loaded machine, so two sessions with the same seed registered
    objects 0.01-0.5 mm apart. The thread limit is process-wide and restored on leaving."""
    state = np.random.SeedSequence([abs(int(k)) for k in keys]).generate_state(1)[0]
    with _OPEN3D_RANDOM:
        threads = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(1)
        try:
            o3d.utility.random.seed(int(state >> 1))
            yield
        finally:
            o3d.utility.set_max_threads(threads)


# A grid of at most this many cells per point (plus 2^20) is bucketed by counting sort.
COUNTING_SORT_CELLS_PER_POINT = 4


@numba.njit(cache=True, nogil=True)
def _extent(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """lo, hi = per-axis minimum and maximum (prefilled +inf, -inf); False when a coordinate
    is NaN or infinite. One pass: NumPy's axis-0 reductions of an (N, 3) array are strided
    (three of them took ~75 % of building an index of millions of points)."""
    finite = True
    for i in range(points.shape[0]):
        for axis in range(3):
            value = float(points[i, axis])
            finite &= value - value == 0.0  # NaN for NaN and +-inf
            lo[axis] = min(lo[axis], value)
            hi[axis] = max(hi[axis], value)
    return finite


@numba.njit(cache=True, nogil=True)
def _cell_keys(points: np.ndarray, origin: np.ndarray, cell_m: float, shape: np.ndarray, keys: np.ndarray) -> None:
    """keys[i] = row-major index of the cell of points[i]: floor((p - origin) / cell) per axis
    in float64, in one pass (NumPy needed ~20 passes and (N,) float64 temporaries per axis)."""
    for i in range(points.shape[0]):
        key = 0
        for axis in range(3):
            key = key * shape[axis] + int(np.floor((float(points[i, axis]) - origin[axis]) / cell_m))
        keys[i] = key


@numba.njit(cache=True, nogil=True)
def _slots_in_boxes(
    keys: np.ndarray, shape: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(box, slot) of the ``keys`` (ascending row-major cell keys of a grid of ``shape``) whose
    cells lie in each box lo[b]..hi[b] (inclusive cell indices; hi < lo on an axis: none), box by
    box, keys ascending in each. A box's cells along its last axis are consecutive keys: one
    binary search a column of the box, then a walk over the occupied cells in it; a box with more
    columns than there are occupied cells (a small cloud, a huge radius) scans those instead.

    Why compiled: a planner's request looks up the ~700 cells around each of its tens of gels;
    NumPy enumerated every box's cells in a dozen whole-array passes, ~1.1 ms for 64 gels, the
    most of a request's plan that the node makes before its lanes can start."""
    occupied, rows, depth = keys.shape[0], shape[1], shape[2]
    found = np.empty((1024, 2), np.int64)  # (box, slot) rows
    count = 0
    for b in range(lo.shape[0]):
        if hi[b, 0] < lo[b, 0] or hi[b, 1] < lo[b, 1] or hi[b, 2] < lo[b, 2]:
            continue
        if (hi[b, 0] - lo[b, 0] + 1) * (hi[b, 1] - lo[b, 1] + 1) > occupied:
            for slot in range(occupied):
                x, rest = divmod(keys[slot], rows * depth)
                y, z = divmod(rest, depth)
                if lo[b, 0] <= x <= hi[b, 0] and lo[b, 1] <= y <= hi[b, 1] and lo[b, 2] <= z <= hi[b, 2]:
                    found, count = _appended(found, count, b, slot)
            continue
        for x in range(lo[b, 0], hi[b, 0] + 1):
            for y in range(lo[b, 1], hi[b, 1] + 1):
                column = (x * rows + y) * depth
                slot = np.searchsorted(keys, column + lo[b, 2])
                while slot < occupied and keys[slot] <= column + hi[b, 2]:
                    found, count = _appended(found, count, b, slot)
                    slot += 1
    return found[:count, 0].copy(), found[:count, 1].copy()


@numba.njit(cache=True, nogil=True, inline="always")
def _appended(found: np.ndarray, count: int, box: int, slot: int) -> tuple[np.ndarray, int]:
    """``found`` (grown when full) with row ``count`` = (box, slot), and the new count."""
    if count == found.shape[0]:
        found = np.concatenate((found, np.empty_like(found)))
    found[count, 0], found[count, 1] = box, slot
    return found, count + 1


@numba.njit(cache=True, nogil=True)
def _scatter_by_key(points: np.ndarray, keys: np.ndarray, next_slot: np.ndarray, out: np.ndarray) -> None:
    """The scatter of a stable counting sort: each point to the next free slot of its key
    (``next_slot`` starts at each key's first slot and is advanced). No NumPy function scatters
    rows by a running per-key counter; argsort + take costs a sort and a gather instead."""
    for i in range(points.shape[0]):
        slot = next_slot[keys[i]]
        next_slot[keys[i]] = slot + 1
        out[slot, 0], out[slot, 1], out[slot, 2] = points[i, 0], points[i, 1], points[i, 2]


def _checked_balls(centres_m: np.ndarray, radius_m: float, single: bool) -> tuple[np.ndarray, float]:
    """(centres as (N, 3) float64, radius) of balls a VoxelIndex is asked about: finite centres
    (``single``: one, any shape of 3 numbers), a radius >= 0 (inf: everything); otherwise
    PointCloudError naming what is wrong."""
    try:
        centres = np.asarray(centres_m, dtype=np.float64)
        radius = float(radius_m)
    except (TypeError, ValueError) as err:
        raise PointCloudError(f"centres must be numbers (3 each) and radius_m a number: {err}") from None
    shaped = centres.size == 3 if single else (centres.ndim == 2 and centres.shape[1] == 3)
    if not shaped or not np.all(np.isfinite(centres)):
        raise PointCloudError(f"{'centre_m' if single else 'centres_m'} must be finite (x, y, z), got {centres_m!r}")
    if not radius >= 0:  # NaN fails too
        raise PointCloudError(f"radius_m must be >= 0 (inf: everything), got {radius_m!r}")
    return centres.reshape(-1, 3), radius


class VoxelIndex:
    """Points bucketed into cubic cells, to hand out the few near a place quickly.

    A contact depth-map needs the few cm² of a dense model cloud (millions of points) that a gel
    touches. Sorting the points by cell once makes each query a gather of contiguous slices:
    ~1 ms for a 20 mm ball in a 6 M-point cloud, where scipy's k-d tree takes ~100 ms to return
    its Python list of indices and more than 6 s to build.

    Contract: ``points_m`` is a finite (N, 3) array (metres, any real dtype); ``cell_m`` a
    finite positive edge. The cells spanning the cloud's bounding box must number at most
    MAX_GRID_CELLS (2^62, so cell keys fit int64): a cloud 1 km across in 1 mm cells is
    fine, 100 km across in every axis in 5 mm cells is refused with PointCloudError, never wrapped around.
    Memory: O(N).
    """

    # Cell keys are int64 row-major indices of the bounding grid of cells.
    MAX_GRID_CELLS = 2**62

    def __init__(self, points_m: np.ndarray, cell_m: float = 0.005) -> None:
        # float32 points are kept as they are (exact, and half the memory and memory traffic of a
        # dense model cloud); every other dtype is used in float64.
        points = np.asarray(points_m)
        if points.dtype.kind not in "biuf":  # complex would be cast, text parsed
            raise PointCloudError(f"points must be real numbers (bool, integer or float), got {points.dtype}")
        points = np.ascontiguousarray(points, dtype=np.float32 if points.dtype == np.float32 else np.float64)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        if points.ndim != 2 or points.shape[1] != 3 or not _extent(points, lo, hi):
            raise PointCloudError(f"points must be finite (N, 3), got shape {points.shape}")
        if not (isinstance(cell_m, (int, float, np.integer, np.floating)) and np.isfinite(cell_m) and cell_m > 0):
            raise PointCloudError(f"cell size must be a positive number of metres, got {cell_m!r}")
        self.cell_m = float(cell_m)
        self.origin_m = lo if len(points) else np.zeros(3)
        with np.errstate(over="ignore"):  # a grid too fine overflows to inf, refused below
            extent_cells = np.floor((hi - self.origin_m) / self.cell_m) + 1 if len(points) else np.ones(3)
            grid_cells = np.prod(extent_cells)
        if not grid_cells <= self.MAX_GRID_CELLS:
            raise PointCloudError(
                f"points span {np.ptp(points, axis=0)} m: {extent_cells} cells of {self.cell_m} m, "
                f"more than 2^62; use larger cells or drop far outliers"
            )
        self.shape = extent_cells.astype(np.int64)
        keys = np.empty(len(points), np.int64)
        _cell_keys(points, self.origin_m, self.cell_m, self.shape, keys)
        grid_size = int(np.prod(self.shape))
        if grid_size <= COUNTING_SORT_CELLS_PER_POINT * len(points) + 2**20:
            # Few cells for the points (a dense model cloud: ~10^4 cells of 5 mm for millions of
            # points): a stable counting sort, O(N + cells), ~10x faster than the argsort below.
            counts = np.bincount(keys, minlength=grid_size)
            self.keys = np.flatnonzero(counts)
            first = np.cumsum(counts) - counts
            self.starts = first[self.keys]
            self.ends = self.starts + counts[self.keys]
            self.points_m = np.empty_like(points)
            _scatter_by_key(points, keys, first, self.points_m)
        else:
            order = np.argsort(keys, kind="stable")
            self.points_m = np.take(points, order, axis=0)
            sorted_keys = keys[order]
            self.starts = (
                np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
                if len(points)
                else np.zeros(0, np.int64)
            )
            self.keys = sorted_keys[self.starts]
            self.ends = np.r_[self.starts[1:], len(points)].astype(self.starts.dtype)

    def within(self, centre_m: np.ndarray, radius_m: float) -> np.ndarray:
        """The points of every cell that meets the ball (a superset of the points inside it),
        in a fixed order: the same query always returns the same array.

        ``centre_m``: 3 finite coordinates (metres); ``radius_m``: >= 0, +inf allowed (every
        point). NaN or a wrong shape raises PointCloudError. Time and memory are
        O(min(cells in the query's box, occupied cells) + points returned), whatever the
        radius and cell size: a box larger than the occupied cells scans those instead.
        """
        starts, ends = self.slices_within(centre_m, radius_m)
        if starts.size == 0:
            return self.points_m[:0]
        return np.concatenate([self.points_m[s:e] for s, e in zip(starts, ends)])

    def slices_within(self, centre_m: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`within` returns, as (starts, ends) of runs of ``points_m``, without
        copying a point: a kernel that reads the runs in place (perception.depthmap's batched
        depth-maps) saves the gather. Same contract and bounds as :meth:`within`."""
        slot = self._slots_within(centre_m, radius_m)
        return self.starts[slot], self.ends[slot]

    def cells_within_many(
        self, centres_m: np.ndarray, radius_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For many balls at once (``centres_m`` (N, 3), one radius): the runs :meth:`within`
        reads for each, as (owner: the ball of each run, starts, ends, the low corner of each
        run's cell ((n, 3) float64 m; the cell spans corner .. corner + ``cell_m``)), ball by
        ball in order and each ball's runs as :meth:`slices_within` gives them, so that a caller
        with a tighter shape than a ball can drop the cells that miss it before reading them.

        Why batched: a planner's request asks about hundreds of gels, and a query per gel costs
        ~0.1 ms of Python and NumPy calls on a few hundred cells; here they are one pass."""
        owner, slot = self._slots_in_balls(centres_m, radius_m, single=False)
        cells = np.stack(np.unravel_index(self.keys[slot], tuple(self.shape)), axis=1)
        return owner, self.starts[slot], self.ends[slot], self.origin_m + cells * self.cell_m

    def _cell_boxes(self, centres: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """The grid's cells around each ball as (lo, hi) (N, 3) int64, inclusive (hi < lo on an
        axis: none), for checked ``centres`` (N, 3) and ``radius``."""
        top = (self.shape - 1).astype(np.float64)
        # Clipped in float64 before the cast: a radius of 1e30 or inf cannot overflow int64.
        lo = np.clip(np.floor((centres - radius - self.origin_m) / self.cell_m), -1.0, top + 1).astype(np.int64)
        hi = np.clip(np.floor((centres + radius - self.origin_m) / self.cell_m), -1.0, top + 1).astype(np.int64)
        return np.maximum(lo, 0), np.minimum(hi, self.shape - 1)

    def _slots_within(self, centre_m: np.ndarray, radius_m: float) -> np.ndarray:
        """Indices into keys/starts/ends of the occupied cells :meth:`within` reads."""
        return self._slots_in_balls(centre_m, radius_m, single=True)[1]

    def _slots_in_balls(self, centres_m: np.ndarray, radius_m: float, single: bool) -> tuple[np.ndarray, np.ndarray]:
        """(ball, slot) of the occupied cells in each ball's box of cells (the balls checked as
        ``single`` or many), ball by ball and keys ascending in each: indices into
        keys/starts/ends (:func:`_slots_in_boxes`)."""
        lo, hi = self._cell_boxes(*_checked_balls(centres_m, radius_m, single=single))
        return _slots_in_boxes(self.keys, self.shape, lo, hi)
