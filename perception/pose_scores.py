"""Scores of an object pose estimate against the truth, in metres: ADD and ADD-S (Hinterstoisser
et al. 2012), for ``dtx perception register-check``, the perception benchmark and the tests."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from perception.errors import PerceptionError
from perception.pointcloud import check_transform


def add_error_m(model_points_m: np.ndarray, estimate_to_world: np.ndarray, truth_to_world: np.ndarray) -> float:
    """ADD: mean distance between each model point under the estimated and the true pose.

    Contract: ``model_points_m`` P >= 1 finite real points (P x 3, m; the mean of none is no
    score), each pose a rigid transform (perception.pointcloud.check_transform); otherwise
    PerceptionError naming the argument."""
    points = _checked_points(model_points_m)
    estimate, truth = (
        check_transform(estimate_to_world, "estimate_to_world"),
        check_transform(truth_to_world, "truth_to_world"),
    )
    estimated = points @ estimate[:3, :3].T + estimate[:3, 3]
    true = points @ truth[:3, :3].T + truth[:3, 3]
    return float(np.linalg.norm(estimated - true, axis=1).mean())


def add_s_error_m(
    surface: o3d.geometry.TriangleMesh,
    model_points_m: np.ndarray,
    estimate_to_world: np.ndarray,
    truth_to_world: np.ndarray,
) -> float:
    """ADD-S: mean distance from each model point under the estimated pose to the model's
    ``surface`` (its mesh, model frame) under the true pose, so a pose that differs only by an
    object symmetry scores zero.

    The distance is to the surface itself (Open3D's ray-casting scene), not to the nearest of the
    sampled points: those leave about half their spacing between two samples turned against each
    other, a floor of 1 mm for a 2 mm cloud that hid every error below it on a symmetric object.

    Contract: as :func:`add_error_m`, and ``surface`` an Open3D TriangleMesh of at least one
    triangle with finite vertices (no surface is no distance); otherwise PerceptionError naming
    the argument, before Open3D sees it."""
    points = _checked_points(model_points_m)
    estimate, truth = (
        check_transform(estimate_to_world, "estimate_to_world"),
        check_transform(truth_to_world, "truth_to_world"),
    )
    if not isinstance(surface, o3d.geometry.TriangleMesh):
        raise PerceptionError(f"surface must be an Open3D TriangleMesh, got {type(surface).__name__}")
    if not surface.has_triangles() or not np.isfinite(np.asarray(surface.vertices)).all():
        raise PerceptionError(
            f"surface must have at least one triangle and finite vertices, got {len(surface.triangles)} "
            f"triangles on {len(surface.vertices)} vertices"
        )
    estimate_to_truth = np.linalg.inv(truth) @ estimate
    in_model = points @ estimate_to_truth[:3, :3].T + estimate_to_truth[:3, 3]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(surface))
    distances = scene.compute_distance(
        o3d.core.Tensor(in_model.astype(np.float32), o3d.core.float32, o3d.core.Device("CPU:0"))
    ).numpy()
    return float(distances.mean())


def _checked_points(model_points_m: np.ndarray) -> np.ndarray:
    points = np.asarray(model_points_m)
    if points.dtype.kind not in "biuf":  # text would be parsed, complex cast
        raise PerceptionError(f"model_points_m must be real numbers, got {points.dtype}")
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise PerceptionError(f"model_points_m must be P x 3 with P >= 1, got shape {points.shape}")
    points = points.astype(np.float64)
    if not np.isfinite(points).all():
        raise PerceptionError("model_points_m contain NaN or inf")
    return points
