"""Planar ICP of an upright model (perception.planar_icp): the point-to-plane refinement that ends
the upright search finds a box's turn and shift from noisy views of two of its faces, where
pairing points with points leaves it turned, and stays finite on views that fix nothing; a box
turned half round about its centre fits its view as well, a quarter round does not."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from perception.planar_icp import planar_icp, planar_icp_to_plane, turned_about_centre

BOX_M = (0.16, 0.06, 0.21)  # a cracker box's x, y, z extents
SPACING_M = 0.004


def box_surface(spacing_m: float = SPACING_M) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward normals on a box standing on z = 0, its origin at the base's centre."""
    hx, hy, h = BOX_M[0] / 2, BOX_M[1] / 2, BOX_M[2]
    xs = np.arange(-hx, hx + 1e-9, spacing_m)
    ys = np.arange(-hy, hy + 1e-9, spacing_m)
    zs = np.arange(0.0, h + 1e-9, spacing_m)
    faces = []
    for sign in (-1.0, 1.0):
        gx, gz = np.meshgrid(xs, zs)
        faces.append((np.c_[gx.ravel(), np.full(gx.size, sign * hy), gz.ravel()], (0.0, sign, 0.0)))
        gy, gz = np.meshgrid(ys, zs)
        faces.append((np.c_[np.full(gy.size, sign * hx), gy.ravel(), gz.ravel()], (sign, 0.0, 0.0)))
    gx, gy = np.meshgrid(xs, ys)
    faces.append((np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, h)], (0.0, 0.0, 1.0)))
    points = np.concatenate([p for p, _ in faces])
    normals = np.concatenate([np.tile(n, (len(p), 1)) for p, n in faces])
    return points, normals


def seen(pose: tuple[float, float, float], noise_m: float, seed: int) -> np.ndarray:
    """The box at ``pose`` seen from -y and +x (its -y and +x faces and its top), resampled finer
    than the model and offset from its samples, with Gaussian noise along each face's normal."""
    points, normals = box_surface(0.0025)
    facing = (normals[:, 1] < -0.5) | (normals[:, 0] > 0.5) | (normals[:, 2] > 0.5)
    rng = np.random.default_rng(seed)
    points = points[facing] + normals[facing] * rng.normal(0.0, noise_m, (facing.sum(), 1))
    yaw, x, y = pose
    c, s = np.cos(yaw), np.sin(yaw)
    return points @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + [x, y, 0.0]


@pytest.mark.parametrize("seed", range(3))
def test_a_box_seen_on_two_faces_is_found_to_hundredths_of_a_degree(seed: int) -> None:
    model, normals = box_surface()
    tree = cKDTree(model)
    truth = (np.radians(20.0), 0.10, -0.05)
    observed = seen(truth, noise_m=0.0015, seed=seed)
    start = (truth[0] + np.radians(1.5), truth[1] + 0.002, truth[2] - 0.002)
    (yaw, x, y), fitness, rmse = planar_icp_to_plane(observed, tree, model, normals, start, 0.0, 0.008, 50)
    assert abs(np.degrees(yaw - truth[0])) < 0.05
    assert np.hypot(x - truth[1], y - truth[2]) < 0.3e-3
    assert fitness > 0.95 and rmse < 0.004
    (point_yaw, _, _), _, _ = planar_icp(observed, tree, model, start, 0.0, (0.008,), 50)
    assert abs(yaw - truth[0]) < abs(point_yaw - truth[0])


@settings(max_examples=20, deadline=None)
@given(
    yaw=st.floats(-np.pi, np.pi),
    shift=st.tuples(st.floats(-0.01, 0.01), st.floats(-0.01, 0.01)),
    distance_m=st.floats(1e-4, 0.05),
)
def test_any_start_and_pairing_distance_give_a_finite_pose(yaw: float, shift: tuple[float, float], distance_m: float):
    """Starts that pair nothing, a view of the top alone (no normal fixes the turn or shift), or
    tiny distances: the pose stays finite and the fitness in [0, 1]."""
    model, normals = box_surface(0.01)
    tree = cKDTree(model)
    top = model[normals[:, 2] > 0.5]
    for observed in (seen((0.0, 0.0, 0.0), 0.001, 0)[::7], top):
        pose, fitness, _ = planar_icp_to_plane(observed, tree, model, normals, (yaw, *shift), 0.0, distance_m, 20)
        assert np.all(np.isfinite(pose))
        assert 0.0 <= fitness <= 1.0


def _upright(pose: tuple[float, float, float]) -> np.ndarray:
    yaw, x, y = pose
    transform = np.eye(4)
    transform[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    transform[:2, 3] = [x, y]
    return transform


@settings(max_examples=10, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), x=st.floats(-0.3, 0.3), y=st.floats(-0.3, 0.3))
def test_a_box_turned_half_round_about_its_centre_fits_its_view_as_well(yaw: float, x: float, y: float) -> None:
    """The box is symmetric under a half turn about its vertical axis: that turn lands on the
    same faces (fitness as high), half a turn from the truth and centred where it was; a quarter
    turn cannot (its long faces are not its short ones)."""
    model, normals = box_surface()
    tree = cKDTree(model)
    truth = _upright((yaw, x, y))
    observed = seen((yaw, x, y), noise_m=0.001, seed=0)
    kept, kept_fitness, _ = turned_about_centre(observed, tree, model, normals, truth, 0.0, 0.008, 50)
    half, half_fitness, _ = turned_about_centre(observed, tree, model, normals, truth, np.pi, 0.008, 50)
    quarter, quarter_fitness, _ = turned_about_centre(observed, tree, model, normals, truth, np.pi / 2, 0.008, 50)
    assert np.linalg.norm(kept[:2, 3] - truth[:2, 3]) < 0.5e-3
    assert half_fitness > kept_fitness - 0.01
    np.testing.assert_allclose(half[:2, :2], -truth[:2, :2], atol=2e-3)
    assert np.linalg.norm(half[:2, 3] - truth[:2, 3]) < 0.5e-3  # the box's origin is its centre
    assert quarter_fitness < kept_fitness - 0.1
    for pose in (kept, half, quarter):
        assert pose[2, 3] == truth[2, 3] and np.allclose(pose[2, :3], [0.0, 0.0, 1.0])


def test_a_pose_that_is_not_upright_is_refused() -> None:
    model, normals = box_surface(0.01)
    lying = np.eye(4)
    lying[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    with pytest.raises(ValueError, match="upright"):
        turned_about_centre(model, cKDTree(model), model, normals, lying, np.pi, 0.008, 10)
