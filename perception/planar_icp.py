"""Planar ICP of a model standing upright on the table, and the yaw sweep built on it: the
steps of the upright search of :mod:`perception.registration` (``_register_resting``).

A model resting on the table as its mesh frame stands keeps its height; only a turn about the
vertical and a shift along the table are free, a pose (yaw rad, x m, y m). The model is given as
its points and a k-d tree of them; the observed points are in the same frame as the table.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

# (yaw rad, x m, y m) of a model standing on the table; a sweep row: (fitness, -RMSE m, pose).
PlanarPose = tuple[float, float, float]
SweepRow = tuple[float, float, PlanarPose]


def planar_icp(
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    pose: PlanarPose,
    model_z_m: float,
    distances_m: tuple[float, ...],
    max_iterations: int,
) -> tuple[PlanarPose, float, float]:
    """ICP over (yaw, x, y) of a model standing at height ``model_z_m``: the observed points pair
    with their nearest model points within each distance in turn, and a 2-D Kabsch fit on the
    pairs' x, y moves the model (a turn about z keeps every z). (pose, fitness, RMSE metres of
    the returned pose at the last distance)."""
    if len(distances_m) == 0:
        raise ValueError("distances_m must hold at least one pairing distance")
    yaw, x_m, y_m = pose
    for distance_m in distances_m:
        for _ in range(max_iterations):
            _, index, paired, _, _ = _pairs(observed_m, model_tree, (yaw, x_m, y_m), model_z_m, distance_m)
            if paired.sum() < 3:
                break
            model_xy, seen_xy = model_points_m[index[paired], :2], observed_m[paired, :2]
            model_mean, seen_mean = model_xy.mean(axis=0), seen_xy.mean(axis=0)
            h = (model_xy - model_mean).T @ (seen_xy - seen_mean)
            new_yaw = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
            c, s = np.cos(new_yaw), np.sin(new_yaw)
            new_x_m, new_y_m = seen_mean - np.array([[c, -s], [s, c]]) @ model_mean
            # Converged when a step moves points less than ~10 um (a turn counted 0.1 m from the centre).
            step_m = np.hypot(new_x_m - x_m, new_y_m - y_m) + abs(np.angle(np.exp(1j * (new_yaw - yaw)))) * 0.1
            yaw, x_m, y_m = new_yaw, float(new_x_m), float(new_y_m)
            if step_m < 1e-5:
                break
    return _judged(observed_m, model_tree, (yaw, x_m, y_m), model_z_m, distances_m[-1])


def sweep_subset(observed_m: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    """At most ``max_points`` of the observed points, a seeded random subset: ranking the yaws
    needs only a fitness estimate, which a few hundred observed points give."""
    if len(observed_m) <= max_points:
        return observed_m
    return observed_m[np.random.default_rng(seed).choice(len(observed_m), max_points, replace=False)]


def sweep_yaws(
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    model_centre_xy: np.ndarray,
    model_z_m: float,
    yaw_steps: int,
    distances_m: tuple[float, ...],
    iterations: int,
) -> list[SweepRow]:
    """(fitness, -RMSE, pose) after ``iterations`` planar ICP steps from each of ``yaw_steps``
    yaws evenly spread over a turn, the model's centre ``model_centre_xy`` under the observed one."""
    sweep = []
    for yaw in np.arange(yaw_steps) * 2.0 * np.pi / yaw_steps:
        c, s = np.cos(yaw), np.sin(yaw)
        start_xy = observed_m[:, :2].mean(axis=0) - np.array([[c, -s], [s, c]]) @ model_centre_xy
        pose, fitness, rmse_m = planar_icp(
            observed_m, model_tree, model_points_m, (float(yaw), *start_xy), model_z_m, distances_m, iterations
        )
        sweep.append((fitness, -rmse_m, pose))
    return sweep


def refine_best(
    sweep: list[SweepRow],
    candidates: int,
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    model_z_m: float,
    distances_m: tuple[float, ...],
    max_iterations: int,
) -> PlanarPose:
    """The best pose after refining the sweep's ``candidates`` best poses by planar ICP through
    ``distances_m``; best = highest fitness, then lowest RMSE."""
    refined = []
    for _, _, pose in sorted(sweep, key=lambda row: row[:2], reverse=True)[:candidates]:
        pose, fitness, rmse_m = planar_icp(
            observed_m, model_tree, model_points_m, pose, model_z_m, distances_m, max_iterations
        )
        refined.append((fitness, -rmse_m, pose))
    return max(refined, key=lambda row: row[:2])[2]


def planar_icp_to_plane(
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    model_normals: np.ndarray,
    pose: PlanarPose,
    model_z_m: float,
    distance_m: float,
    max_iterations: int,
) -> tuple[PlanarPose, float, float]:
    """:func:`planar_icp` minimising each pair's distance along the model's surface normal
    (Gauss-Newton on yaw, x, y) instead of to the model point: a point may slide along the face
    it lies on, so the model's sampling does not pull a flat face sideways or turn it.
    (pose, fitness, RMSE metres of the point-to-point gaps, as planar_icp reports them)."""
    yaw, x_m, y_m = pose
    for _ in range(max_iterations):
        rotation, index, paired, _, _ = _pairs(observed_m, model_tree, (yaw, x_m, y_m), model_z_m, distance_m)
        if paired.sum() < 3:
            break
        model_world = model_points_m[index[paired]] @ rotation.T + [x_m, y_m, model_z_m]
        normal_world = model_normals[index[paired]] @ rotation.T
        residual = np.einsum("ij,ij->i", normal_world, model_world - observed_m[paired])
        # d(model point)/d(yaw) = z x (point - centre of turn); the turn is about the model's origin.
        arm = model_world - [x_m, y_m, model_z_m]
        jacobian = np.stack(
            [normal_world[:, 1] * arm[:, 0] - normal_world[:, 0] * arm[:, 1], normal_world[:, 0], normal_world[:, 1]],
            axis=1,
        )
        step, *_ = np.linalg.lstsq(jacobian, -residual, rcond=None)
        yaw, x_m, y_m = yaw + float(step[0]), x_m + float(step[1]), y_m + float(step[2])
        if abs(step[0]) * 0.1 + np.hypot(step[1], step[2]) < 1e-6:
            break
    return _judged(observed_m, model_tree, (yaw, x_m, y_m), model_z_m, distance_m)


def _judged(
    observed_m: np.ndarray, model_tree: cKDTree, pose: PlanarPose, model_z_m: float, distance_m: float
) -> tuple[PlanarPose, float, float]:
    """(pose, fitness, RMSE m) of ``pose`` itself. The loops pair the points before each step, so
    their last figures are those of the pose before the last step; the sweep and the turn judge
    rank poses by these figures, so each pose returned is paired once more."""
    _, _, _, fitness, rmse_m = _pairs(observed_m, model_tree, pose, model_z_m, distance_m)
    return pose, fitness, rmse_m


def _pairs(
    observed_m: np.ndarray, model_tree: cKDTree, pose: PlanarPose, model_z_m: float, distance_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Each observed point's nearest model point within ``distance_m`` with the model at ``pose``:
    (the pose's rotation, model index per point, which are paired, fitness, RMSE m of the pairs)."""
    yaw, x_m, y_m = pose
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    gap_m, index = model_tree.query((observed_m - [x_m, y_m, model_z_m]) @ rotation, distance_upper_bound=distance_m)
    paired = np.isfinite(gap_m)
    rmse_m = float(np.sqrt(np.mean(gap_m[paired] ** 2))) if paired.any() else np.inf
    return rotation, index, paired, float(paired.mean()), rmse_m


def is_upright(model_to_world: np.ndarray) -> bool:
    """Whether a pose stands its model as its mesh frame stands, turned about the vertical only
    (the poses the upright search and :func:`turned_about_centre` work with)."""
    return bool(np.allclose(model_to_world[2, :3], [0.0, 0.0, 1.0], atol=1e-6))


def turned_about_centre(
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    model_normals: np.ndarray,
    model_to_world: np.ndarray,
    turn_rad: float,
    distance_m: float,
    max_iterations: int,
) -> tuple[np.ndarray, float, float]:
    """An upright ``model_to_world`` turned by ``turn_rad`` about the vertical through the
    model's centre (its points' mean), then refined on the observed points as the upright search
    ends (:func:`upright_refined`): the pose a near-symmetric object would have the other way
    round. (model_to_world, fitness, RMSE m)."""
    if not is_upright(model_to_world):
        raise ValueError("model_to_world must stand the model upright (a turn about the vertical only)")
    yaw = float(np.arctan2(model_to_world[1, 0], model_to_world[0, 0])) + turn_rad
    centre_xy = model_points_m[:, :2].mean(axis=0)
    c, s = np.cos(yaw), np.sin(yaw)
    centre_world_xy = model_to_world[:2, :2] @ centre_xy + model_to_world[:2, 3]
    start_xy = centre_world_xy - np.array([[c, -s], [s, c]]) @ centre_xy
    return upright_refined(
        observed_m,
        model_tree,
        model_points_m,
        model_normals,
        (yaw, *start_xy),
        float(model_to_world[2, 3]),
        distance_m,
        max_iterations,
    )


def upright_refined(
    observed_m: np.ndarray,
    model_tree: cKDTree,
    model_points_m: np.ndarray,
    model_normals: np.ndarray,
    pose: PlanarPose,
    model_z_m: float,
    distance_m: float,
    max_iterations: int,
) -> tuple[np.ndarray, float, float]:
    """The upright search's last step from ``pose``: :func:`planar_icp`, then
    :func:`planar_icp_to_plane`, both at ``distance_m``. (model_to_world, fitness, RMSE m)."""
    pose, _, _ = planar_icp(observed_m, model_tree, model_points_m, pose, model_z_m, (distance_m,), max_iterations)
    (yaw, x_m, y_m), fitness, rmse_m = planar_icp_to_plane(
        observed_m, model_tree, model_points_m, model_normals, pose, model_z_m, distance_m, max_iterations
    )
    model_to_world = np.eye(4)
    model_to_world[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    model_to_world[:3, 3] = [x_m, y_m, model_z_m]
    return model_to_world, fitness, rmse_m
