"""Touch-calibrated geometry: every grasp of a session shows where the object really is.

A grasp's gel pose is known from the arm (to ~0.03 mm) and its tactile image shows where on
the gel the object touched. The depth-map cut from the registered model predicts the same
contact; where the two disagree in the gel plane, the registration is off. The steps, each on
arrays with frames and units in their names:

1. A touch's offset: its depth-map moved over a grid of places in the gel plane and depths
   (:func:`moved_depth_map`), each drawn by the GelSight renderer and compared with the frame;
   :func:`profiled_fit` takes the best place with depth fitted too, and the curvature there as
   its information. A contact cut by the field's edge shows one side, which moves with depth
   as much as with place, so it pins little (a flat face filling the gel nothing; a can's side
   one direction): the information says so.
2. Each camera's table levelled onto z = 0 (:func:`table_levelling`: its height and tilt).
3. :func:`solve_cell` — every camera's place and turn on the table and every object's, fitted
   at once to the touches' offsets and to the cameras' points on the objects' models: a camera
   sees an object from one side only, the touches see it from every side they touched, and
   they tie the cameras to the arm's frame.

Why by hand: Open3D and OpenCV register clouds and match images, but no library fits cameras
and objects to in-plane touch offsets with per-touch information; the least squares is short.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from perception.errors import PerceptionError
from perception.pointcloud import principal_spread_m
from perception.segmentation import plane_to_table
from workcell.kinematics import KinematicsError, rigid_transform

# What a camera's or an object's correction is held to where nothing pins it: a careful
# hand-eye calibration and registration are within a few millimetres and a degree.
_PRIOR_SIGMA_MM = 5.0
_PRIOR_SIGMA_DEG = 1.0
_REALS = (int, float, np.integer, np.floating)


class TouchCalibrationError(PerceptionError):
    """Touches or clouds that cannot calibrate: too few, unobservable, or malformed."""


@dataclasses.dataclass(frozen=True)
class TouchOffset:
    """One touch: measured minus predicted contact, in the gel plane.

    ``offset_gel_mm`` is (x, z) in the gel frame; ``information_gel`` the 2 x 2 inverse
    covariance of it (1/mm²); ``contact_world_m`` where on the object it was measured;
    ``gel_to_world`` the gel's pose from the arm."""

    offset_gel_mm: np.ndarray
    information_gel: np.ndarray
    contact_world_m: np.ndarray
    gel_to_world: np.ndarray

    def __post_init__(self) -> None:
        # One NaN offset or infinite information would make every pose of the joint fit NaN, so
        # a touch is checked as it is made, and kept read-only so that it stays as checked.
        information = _finite_array(self.information_gel, "information_gel", (2, 2))
        scale = 1e-9 * float(np.abs(information).max())
        if np.abs(information - information.T).max() > scale or np.linalg.eigvalsh(information)[0] < -scale:
            raise TouchCalibrationError(f"information_gel must be symmetric and >= 0, got {information.tolist()}")
        checked = {
            "offset_gel_mm": _finite_array(self.offset_gel_mm, "offset_gel_mm", (2,)),
            "information_gel": information,
            "contact_world_m": _finite_array(self.contact_world_m, "contact_world_m", (3,)),
            "gel_to_world": _rigid(self.gel_to_world, "gel_to_world"),
        }
        for name, array in checked.items():
            array.setflags(write=False)
            object.__setattr__(self, name, array)


def moved_depth_map(
    depth_map_m: np.ndarray, bin_pitch_mm: tuple[float, float], shift_gel_mm: np.ndarray, y_far_m: float
) -> np.ndarray:
    """A contact depth-map (rows along gel z, columns along gel x, m; ``y_far_m`` = nothing
    there) as it would be with the object moved by ``shift_gel_mm`` = (x, z, y) mm in the gel
    frame: resampled in the plane (bilinear; bins from beyond the crop read as nothing) and
    ``y`` nearer the gel (deeper) where there is a surface."""
    # A NaN shift or a zero pitch warps every bin off the map: the contact would vanish unsaid.
    surface = _finite_array(depth_map_m, "depth_map_m", (None, None)).astype(np.float32)
    if not surface.size:
        raise TouchCalibrationError(f"depth_map_m must have bins, got shape {surface.shape}")
    pitch = _finite_array(bin_pitch_mm, "bin_pitch_mm", (2,))
    if not (pitch > 0).all():
        raise TouchCalibrationError(f"bin_pitch_mm must be positive, got {pitch.tolist()}")
    pitch_rows, pitch_cols = pitch
    shift = _finite_array(shift_gel_mm, "shift_gel_mm", (3,))
    y_far_m = _real(y_far_m, "y_far_m")
    warp = np.array([[1.0, 0.0, shift[0] / pitch_cols], [0.0, 1.0, shift[1] / pitch_rows]], dtype=np.float32)
    rows, cols = surface.shape
    moved = cv2.warpAffine(
        surface, warp, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float(y_far_m)
    )
    return np.where(moved < y_far_m, moved - np.float32(shift[2] * 1e-3), moved).astype(np.float32)


def profiled_fit(
    ssd: np.ndarray, grid_mm: tuple[np.ndarray, np.ndarray, np.ndarray], pixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """The best (x, z, y) mm of a touch from the sum of squared differences between its frame
    and the renderer's image of its depth-map moved over a grid (``ssd`` indexed x, z, y over
    the three axes of ``grid_mm``), and the 2 x 2 information (1/mm²) of (x, z) with y fitted:
    the curvature of the SSD minimised over y, over twice the residual variance per pixel
    (Gauss-Newton), from a parabola through the minimum and its neighbours; 0 where the
    minimum sits at the grid's edge in that direction (a contact cut by the field's edge shows
    one side, which moves with depth as much as with place: a flat face pins nothing)."""
    grid_mm = _even_grid(grid_mm)
    ssd = _finite_array(ssd, "ssd", (None, None, None))
    if ssd.shape != tuple(len(g) for g in grid_mm):
        raise TouchCalibrationError(f"ssd {ssd.shape} does not match grid_mm's {[len(g) for g in grid_mm]}")
    if (ssd < 0).any():
        raise TouchCalibrationError(f"ssd must be sums of squares (>= 0), got a minimum of {ssd.min()}")
    pixels = _whole(pixels, "pixels")
    profiled = ssd.min(axis=2)
    ix, iz = np.unravel_index(int(np.argmin(profiled)), profiled.shape)
    best_y = grid_mm[2][int(np.argmin(ssd[ix, iz]))]
    variance = max(float(profiled[ix, iz]) / pixels, 1e-9)
    fit = np.array([grid_mm[0][ix], grid_mm[1][iz], best_y], dtype=np.float64)
    information = np.zeros(2)
    for axis, (index, line) in enumerate(((ix, profiled[:, iz]), (iz, profiled[ix, :]))):
        grid = grid_mm[axis]
        if not 0 < index < len(grid) - 1:
            continue
        step = float(grid[1] - grid[0])
        curvature = (line[index + 1] - 2.0 * line[index] + line[index - 1]) / step**2
        if curvature <= 0:
            continue
        fit[axis] += float(np.clip(-(line[index + 1] - line[index - 1]) / (2.0 * step * curvature), -step, step))
        information[axis] = curvature / (2.0 * variance)
    return fit, np.diag(information)


def table_levelling(points_world_m: np.ndarray, inlier_m: float = 0.004) -> np.ndarray:
    """4 x 4 world-frame transform that lays one camera's table (the largest plane of its cloud
    cropped to the workspace) onto z = 0 by the smallest rotation: a RANSAC plane refined by
    least squares over the points within ``inlier_m`` of it."""
    points = _finite_array(points_world_m, "points_world_m", (None, 3))
    inlier_m = _real(inlier_m, "inlier_m", positive=True)
    if len(points) < 100:
        raise TouchCalibrationError(
            f"points_world_m: a camera needs >= 100 table points to level it, got {len(points)}"
        )
    _spans_plane(points, inlier_m, "points_world_m")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    plane, _ = cloud.segment_plane(inlier_m, 3, 1000, probability=0.9999)
    for _ in range(3):
        near = points[np.abs(points @ np.asarray(plane[:3]) + plane[3]) < inlier_m]
        _spans_plane(near, inlier_m, "points_world_m's table plane (its points within inlier_m)")
        centre = near.mean(axis=0)
        normal = np.linalg.svd(near - centre, full_matrices=False)[2][-1]
        normal = normal if normal[2] > 0 else -normal
        plane = np.append(normal, -normal @ centre)
    return plane_to_table(plane)


def _spans_plane(points_m: np.ndarray, inlier_m: float, name: str) -> None:
    """TouchCalibrationError unless ``points_m`` spread over more than ``inlier_m`` (standard
    deviation) along two directions: a plane's points lie within ``inlier_m`` of it, so across a
    narrower strip its tilt about the strip is noise (a line gave a 55 or 90 degree turn)."""
    spread_m = principal_spread_m(points_m) if len(points_m) else np.zeros(3)
    if not spread_m[1] > inlier_m:
        raise TouchCalibrationError(
            f"{name}: {len(points_m)} points spread {spread_m[1] * 1e3:.3g} mm across their widest line, "
            f"under inlier_m = {inlier_m * 1e3:g} mm; identical or collinear points have no plane to level"
        )


def pose_error(estimate_to_world: np.ndarray, truth_to_world: np.ndarray) -> tuple[float, float]:
    """How far an estimated pose is from the truth: (mm the frame's origin is off, degrees it
    is turned), as ``extrinsic_offset`` states a camera's calibration error."""
    error = np.linalg.inv(estimate_to_world) @ truth_to_world
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(error[:3, :3]).as_rotvec())))
    return float(np.linalg.norm(error[:3, 3]) * 1e3), angle


def planar_transform(yaw_rad: float, x_mm: float, y_mm: float) -> np.ndarray:
    """4 x 4 world-frame turn about the vertical through the origin, then shift on the table."""
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec([0.0, 0.0, yaw_rad]).as_matrix()
    transform[:2, 3] = np.array([x_mm, y_mm]) * 1e-3
    return transform


def _planar_jacobian(points_mm: np.ndarray) -> np.ndarray:
    """N x 3 x 3: d(point displacement, mm) / d(yaw rad, x mm, y mm) of a planar correction."""
    jacobian = np.zeros((len(points_mm), 3, 3))
    jacobian[:, 0, 0], jacobian[:, 1, 0] = -points_mm[:, 1], points_mm[:, 0]
    jacobian[:, 0, 1] = jacobian[:, 1, 2] = 1.0
    return jacobian


@dataclasses.dataclass(frozen=True)
class CellCorrection:
    """The joint fit of a cell: each camera's planar correction (4 x 4, world frame, after its
    table levelling) and each object's touched pose (4 x 4), with what the fit rests on."""

    cameras: dict[str, np.ndarray]
    objects: dict[str, np.ndarray]
    touch_residual_before_mm: dict[str, float]
    touch_residual_after_mm: dict[str, float]
    touch_outliers: dict[str, int]
    point_residual_mm: dict[str, float | None]  # None: none of the camera's points lies on a model
    unobservable: dict[str, list[str]]


def solve_cell(
    touches: dict[str, list[TouchOffset]],
    predicted: dict[str, np.ndarray],
    views: dict[str, dict[str, np.ndarray]],
    models: dict[str, o3d.geometry.TriangleMesh],
    iterations: int = 12,
) -> CellCorrection:
    """Every camera's place and turn on the table and every object's, fitted at once.

    ``touches[o]`` are object o's offsets measured against ``predicted[o]`` (its pose, 4 x 4);
    ``views[c][o]`` camera c's (table-levelled) points of object o (N x 3 m); ``models[o]`` its
    mesh (model frame, m). Unknowns: a planar correction (yaw, x, y) per camera and per object.
    Residuals: each touch's offset against the object's move in the gel plane, and each camera
    point's distance to the closest point of the object's mesh along that point's normal, both
    robustly weighted (Cauchy for touches, Tukey for points, each scaled by its own median). A
    camera alone sees an object from one side (a box's face pins one direction); the touches see
    it from every side they touched; together they pin every camera and object, and the touches
    tie them to the arm's frame.

    The corrections turn about the cell's centre (its objects' mean predicted place), not the world
    origin, whose turns need shifts the prior forbids (a cell 30 m out kept 0.02 of a camera's 0.05
    degree turn): the fit is the same wherever the cell stands in the world (a site or map frame)."""
    iterations = _whole(iterations, "iterations")
    predicted, views = _checked_cell(touches, predicted, views, models)
    from_cell = np.eye(4)
    from_cell[:2, 3] = np.mean([pose[:2, 3] for pose in predicted.values()], axis=0)
    cell = _Cell(touches, predicted, views, models, from_cell)
    state = np.zeros(cell.unknowns)
    # A weak prior (the registration's few millimetres and a degree) holds what nothing pins:
    # a can's turn about its own axis, a box's slide along a face only one camera sees.
    prior = np.tile([np.radians(_PRIOR_SIGMA_DEG) ** -2, _PRIOR_SIGMA_MM**-2, _PRIOR_SIGMA_MM**-2], cell.unknowns // 3)
    for _ in range(iterations):
        normal, rhs = cell.normal_equations(state)
        state += np.linalg.solve(normal + np.diag(prior), rhs - prior * state)
    fitted = cell.result(state, normal + np.diag(prior))
    to_cell = np.linalg.inv(from_cell)
    return dataclasses.replace(
        fitted,
        cameras={c: from_cell @ correction @ to_cell for c, correction in fitted.cameras.items()},
        objects={o: from_cell @ pose for o, pose in fitted.objects.items()},
    )


def _checked_cell(
    touches: dict[str, list[TouchOffset]],
    predicted: dict[str, np.ndarray],
    views: dict[str, dict[str, np.ndarray]],
    models: dict[str, o3d.geometry.TriangleMesh],
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """``predicted`` (rigid) and ``views`` (finite N x 3) as float64, once every name the fit
    reads is known to it; TouchCalibrationError naming the argument otherwise."""
    if not predicted:
        raise TouchCalibrationError("predicted names no object: the fit has nothing to place")
    poses = {o: _rigid(pose, f"predicted[{o!r}]") for o, pose in predicted.items()}
    missing = [o for o in poses if not isinstance(models.get(o), o3d.geometry.TriangleMesh)]
    if missing:
        raise TouchCalibrationError(f"models has no TriangleMesh of {missing}, objects of predicted")
    for o, own in touches.items():
        if o not in poses:
            raise TouchCalibrationError(f"touches names {o!r}, an object predicted has no pose of")
        for i, touch in enumerate(own):
            if not isinstance(touch, TouchOffset):
                raise TouchCalibrationError(f"touches[{o!r}][{i}] must be a TouchOffset, got {type(touch).__name__}")
    points: dict[str, dict[str, np.ndarray]] = {}
    for c, seen in views.items():
        if c in poses:
            raise TouchCalibrationError(f"views names camera {c!r}, which predicted names an object too")
        unknown = sorted(set(seen) - set(poses))
        if unknown:
            raise TouchCalibrationError(f"views[{c!r}] names {unknown}, objects predicted has no pose of")
        points[c] = {o: _finite_array(p, f"views[{c!r}][{o!r}]", (None, 3)) for o, p in seen.items()}
    return poses, points


class _Cell:
    """The normal equations of :func:`solve_cell`: cameras first, then objects, 3 unknowns each
    (yaw rad, x mm, y mm of a planar correction about the cell's centre, ``cell_to_world``'s
    origin), every place and pose in the cell's frame."""

    def __init__(
        self,
        touches: dict[str, list[TouchOffset]],
        predicted: dict[str, np.ndarray],
        views: dict[str, dict[str, np.ndarray]],
        models: dict[str, o3d.geometry.TriangleMesh],
        cell_to_world: np.ndarray,
    ) -> None:
        self.names, self.cameras = sorted(predicted), sorted(views)
        to_cell = np.linalg.inv(cell_to_world)
        self.predicted = {o: to_cell @ pose for o, pose in predicted.items()}
        self.views = {c: {o: p + to_cell[:3, 3] for o, p in seen.items()} for c, seen in views.items()}
        self.unknowns = 3 * (len(self.cameras) + len(self.names))
        self.at = {c: 3 * i for i, c in enumerate(self.cameras)}
        self.at.update({o: 3 * (len(self.cameras) + i) for i, o in enumerate(self.names)})
        own = {o: touches.get(o, []) for o in self.names}
        self.offsets = {o: np.array([t.offset_gel_mm for t in own[o]]).reshape(-1, 2) for o in self.names}
        self.jacobians = {
            o: np.array([t.gel_to_world[:3, [0, 2]].T for t in own[o]]).reshape(-1, 2, 3)
            @ _planar_jacobian((np.array([t.contact_world_m for t in own[o]]).reshape(-1, 3) + to_cell[:3, 3]) * 1e3)
            for o in self.names
        }
        # capped at the median touch of the whole cell: an object whose touches pin little (a
        # box's flat faces) weighs little
        cap = _information_cap([t for o in self.names for t in own[o]])
        self.informations = {o: _capped_information(own[o], cap) for o in self.names}
        self.surfaces = {o: _surface(models[o]) for o in self.names}
        self.touch_residuals: dict[str, np.ndarray] = {}
        self.touch_inliers: dict[str, np.ndarray] = {}

    def pose(self, state: np.ndarray, name: str) -> np.ndarray:
        """An object's pose (or, for a camera, its planar correction) in ``state``."""
        correction = planar_transform(*state[self.at[name] : self.at[name] + 3])
        return correction @ self.predicted[name] if name in self.predicted else correction

    def normal_equations(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton normal matrix and right-hand side of the increment at ``state``."""
        normal, rhs = np.zeros((self.unknowns, self.unknowns)), np.zeros(self.unknowns)
        for o in self.names:
            if not len(self.offsets[o]):
                continue
            jacobian = self.jacobians[o]
            residual = self.offsets[o] - jacobian @ state[self.at[o] : self.at[o] + 3]
            weights, self.touch_inliers[o] = _touch_weights(residual, self.informations[o])
            self.touch_residuals[o] = residual
            block = slice(self.at[o], self.at[o] + 3)
            weighted = self.informations[o] * weights[:, None, None]
            normal[block, block] += np.einsum("nki,nkl,nlj->ij", jacobian, weighted, jacobian)
            rhs[block] += np.einsum("nki,nkl,nl->i", jacobian, weighted, residual)
        for c in self.cameras:
            for o, points in self.views[c].items():
                residual, by_camera, by_object, weights = _point_rows(
                    points, self.pose(state, c), self.pose(state, o), self.surfaces[o]
                )
                rows = np.hstack([by_camera, by_object])
                index = np.r_[self.at[c] : self.at[c] + 3, self.at[o] : self.at[o] + 3]
                normal[np.ix_(index, index)] += rows.T @ (rows * weights[:, None])
                rhs[index] -= rows.T @ (weights * residual)
        return normal, rhs

    def result(self, state: np.ndarray, normal: np.ndarray) -> CellCorrection:
        """The fitted state as transforms, with residuals and each camera's weak directions (a
        standard deviation over 0.1 mm, or a turn that moves a point 100 mm away by as much)."""
        covariance = np.linalg.inv(normal)
        unobservable, point_residual = {}, {}
        for c in self.cameras:
            sigma = np.sqrt(np.maximum(np.diag(covariance)[self.at[c] : self.at[c] + 3], 0.0)) * [100.0, 1.0, 1.0]
            unobservable[c] = [_PLANAR[i] for i in range(3) if sigma[i] > 0.1]
            residuals = [
                _point_rows(points, self.pose(state, c), self.pose(state, o), self.surfaces[o])[0]
                for o, points in self.views[c].items()
            ]
            found = np.concatenate(residuals) if residuals else np.zeros(0)
            point_residual[c] = float(np.median(np.abs(found))) if len(found) else None
        touched = list(self.touch_residuals)
        return CellCorrection(
            cameras={c: self.pose(state, c) for c in self.cameras},
            objects={o: self.pose(state, o) for o in self.names},
            touch_residual_before_mm={o: float(np.median(np.linalg.norm(self.offsets[o], axis=1))) for o in touched},
            touch_residual_after_mm={
                o: float(np.median(np.linalg.norm(self.touch_residuals[o][self.touch_inliers[o]], axis=1)))
                for o in touched
            },
            touch_outliers={o: int(np.count_nonzero(~self.touch_inliers[o])) for o in touched},
            point_residual_mm=point_residual,
            unobservable=unobservable,
        )


_PLANAR = ("rotation about z", "x", "y")
# How far (mm) a camera point may be from its object's model to count as on it.
_POINT_REACH_MM = 5.0
# Points of one camera's view of one object a cell fit reads at most (a regular draw): its
# errors (flying pixels, relief) are not independent, so more would only over-weight it.
_MAX_VIEW_POINTS = 3000


def _finite_array(value: object, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (None: any length there), every entry finite,
    or TouchCalibrationError naming it."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as err:
        raise TouchCalibrationError(f"{name} must be an array of numbers: {err}") from None
    if raw.dtype.kind not in "biuf":  # complex would be cast, text parsed
        raise TouchCalibrationError(f"{name} must be real numbers, got {raw.dtype}")
    if raw.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, raw.shape)):
        wanted = " x ".join("N" if n is None else str(n) for n in shape)
        raise TouchCalibrationError(f"{name} must be {wanted}, got shape {raw.shape}")
    array = raw.astype(np.float64)
    if not np.isfinite(array).all():
        raise TouchCalibrationError(f"{name} must be finite, got {np.count_nonzero(~np.isfinite(array))} NaN or inf")
    return array


def _rigid(value: np.ndarray, name: str) -> np.ndarray:
    try:
        return rigid_transform(value, name)
    except KinematicsError as err:
        raise TouchCalibrationError(str(err)) from None


def _real(value: object, name: str, positive: bool = False) -> float:
    """``value`` as a finite float (and > 0 with ``positive``), or TouchCalibrationError."""
    number = float(value) if isinstance(value, _REALS) and not isinstance(value, bool) else np.nan
    if not (np.isfinite(number) and (number > 0 or not positive)):
        raise TouchCalibrationError(f"{name} must be a finite{' positive' if positive else ''} number, got {value!r}")
    return number


def _whole(value: object, name: str) -> int:
    """``value`` as an int >= 1, or TouchCalibrationError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise TouchCalibrationError(f"{name} must be a whole number >= 1, got {value!r}")
    return int(value)


def _even_grid(grid_mm: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three axes of a profiled fit's grid, each finite and rising by one step (the
    parabola through a minimum and its neighbours assumes it), or TouchCalibrationError."""
    if not isinstance(grid_mm, (tuple, list)) or len(grid_mm) != 3:
        raise TouchCalibrationError(f"grid_mm must be three axes (x, z, y), got {grid_mm!r}")
    axes = tuple(_finite_array(g, f"grid_mm[{i}]", (None,)) for i, g in enumerate(grid_mm))
    for i, axis in enumerate(axes):
        steps = np.diff(axis)
        if not len(axis) or (len(steps) and not (steps[0] > 0 and np.allclose(steps, steps[0], rtol=1e-6, atol=0.0))):
            raise TouchCalibrationError(f"grid_mm[{i}] must rise by one step, got {axis.tolist()}")
    return axes[0], axes[1], axes[2]


def _information_cap(touches: list[TouchOffset]) -> float:
    """The median touch's information (trace, 1/mm²)."""
    return max(float(np.median([np.trace(t.information_gel) for t in touches])), 1e-12) if touches else 1.0


def _capped_information(touches: list[TouchOffset], cap: float) -> np.ndarray:
    """N x 2 x 2 touch informations in units of ``cap``, none above it: a touch's own match
    curvature does not show the model's mismatch, a floor every touch shares."""
    if not touches:
        return np.zeros((0, 2, 2))
    informations = np.stack([t.information_gel for t in touches])
    strength = np.trace(informations, axis1=1, axis2=2)
    return informations * (np.minimum(1.0, cap / np.maximum(strength, 1e-12)) / cap)[:, None, None]


def _touch_weights(
    residual: np.ndarray, information: np.ndarray, outlier_sigma: float = 3.0
) -> tuple[np.ndarray, np.ndarray]:
    """Cauchy weights over the robust scale (the median squared residual of one observed
    dimension, chi² median 0.455) and the inlier mask (within ``outlier_sigma``)."""
    mahalanobis2 = np.einsum("ni,nij,nj->n", residual, information, residual)
    scale2 = max(float(np.median(mahalanobis2)) / 0.455, 1e-12)
    inliers = mahalanobis2 <= outlier_sigma**2 * scale2
    return inliers / (1.0 + mahalanobis2 / scale2) / scale2, inliers


def _surface(mesh: o3d.geometry.TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return surface


def _point_rows(
    points_m: np.ndarray, correction: np.ndarray, pose: np.ndarray, surface: o3d.t.geometry.RaycastingScene
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For a camera's points of an object: residuals (mm along the normal of the mesh's closest
    point), their derivatives by the camera's and the object's planar corrections, and Tukey
    weights. The closest point of the mesh itself, not of points sampled on it: a 2 mm sample's
    tangent plane leaves a bias that depends on where the samples fell, and it turned the
    demo session's left camera 0.02-0.03 degrees (docs/measurements.md)."""
    points = np.asarray(points_m, dtype=np.float64)[:: max(1, len(points_m) // _MAX_VIEW_POINTS)]
    corrected = points @ correction[:3, :3].T + correction[:3, 3]
    in_model = (corrected - pose[:3, 3]) @ pose[:3, :3]
    closest = surface.compute_closest_points(
        o3d.core.Tensor(in_model.astype(np.float32), o3d.core.float32, o3d.core.Device("CPU:0"))
    )
    nearest = closest["points"].numpy().astype(np.float64)
    found = np.linalg.norm(nearest - in_model, axis=1) < _POINT_REACH_MM * 1e-3
    x = corrected[found] * 1e3
    q = (nearest[found] @ pose[:3, :3].T + pose[:3, 3]) * 1e3
    n = closest["primitive_normals"].numpy().astype(np.float64)[found] @ pose[:3, :3].T
    residual = np.einsum("ni,ni->n", n, x - q)
    by_camera = np.column_stack([n[:, 1] * x[:, 0] - n[:, 0] * x[:, 1], n[:, 0], n[:, 1]])
    by_object = -np.column_stack([n[:, 1] * q[:, 0] - n[:, 0] * q[:, 1], n[:, 0], n[:, 1]])
    scale = max(1.4826 * float(np.median(np.abs(residual))), 1e-3) if len(residual) else 1.0
    limit = 4.685 * scale
    weights = np.where(np.abs(residual) < limit, (1.0 - (residual / limit) ** 2) ** 2, 0.0) / scale**2
    return residual, by_camera, by_object, weights
