"""Scores of an object pose estimate against the truth, in metres: ADD and ADD-S (Hinterstoisser
et al. 2012), for ``dtx perception register-check``, the perception benchmark and the tests."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def add_error_m(model_points_m: np.ndarray, estimate_to_world: np.ndarray, truth_to_world: np.ndarray) -> float:
    """ADD: mean distance between each model point under the estimated and the true pose."""
    points = np.asarray(model_points_m, dtype=np.float64)
    estimated = points @ estimate_to_world[:3, :3].T + estimate_to_world[:3, 3]
    true = points @ truth_to_world[:3, :3].T + truth_to_world[:3, 3]
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
    other, a floor of 1 mm for a 2 mm cloud that hid every error below it on a symmetric object."""
    points = np.asarray(model_points_m, dtype=np.float64)
    estimate_to_truth = np.linalg.inv(np.asarray(truth_to_world, dtype=np.float64)) @ estimate_to_world
    in_model = points @ estimate_to_truth[:3, :3].T + estimate_to_truth[:3, 3]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(surface))
    distances = scene.compute_distance(
        o3d.core.Tensor(in_model.astype(np.float32), o3d.core.float32, o3d.core.Device("CPU:0"))
    ).numpy()
    return float(distances.mean())
