"""Grasp kinematics: top-down TCP poses, UR pose conversions, gel frames."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from perception.pointcloud import transform_points
from workcell.kinematics import (
    GripperGeometry,
    across_the_gels_m,
    gel_poses_world,
    grasp_to_tcp_pose,
    matrix_to_pose,
    pose_to_matrix,
)

angle = st.floats(-10.0, 10.0, allow_nan=False)
coordinate = st.floats(-2.0, 2.0, allow_nan=False)


def assert_rigid(transform):
    rotation = transform[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(transform[3], [0, 0, 0, 1])


@settings(max_examples=100, deadline=None)
@given(x=coordinate, y=coordinate, z=coordinate, theta=angle)
def test_grasp_pose_points_the_tool_down_with_only_yaw_free(x, y, z, theta):
    tcp_to_world = pose_to_matrix(grasp_to_tcp_pose(x, y, z, theta))
    assert_rigid(tcp_to_world)
    np.testing.assert_allclose(tcp_to_world[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(tcp_to_world[:3, 3], [x, y, z])
    np.testing.assert_allclose(tcp_to_world[:3, 0], [np.cos(theta), np.sin(theta), 0], atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(pose=st.tuples(coordinate, coordinate, coordinate, angle, angle, angle))
def test_pose_matrix_round_trip(pose):
    transform = pose_to_matrix(np.array(pose))
    assert_rigid(transform)
    np.testing.assert_allclose(pose_to_matrix(matrix_to_pose(transform)), transform, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(width=st.floats(0.0, 0.11), theta=angle)
def test_gels_face_each_other_at_the_gripper_width(width, theta):
    geometry = GripperGeometry()
    tcp = grasp_to_tcp_pose(0.1, -0.2, 0.3, theta)
    gels = gel_poses_world(tcp, width, geometry)
    left, right = gels["left"], gels["right"]
    for gel in (left, right):
        assert_rigid(gel)
    np.testing.assert_allclose(np.linalg.norm(left[:3, 3] - right[:3, 3]), width, atol=1e-12)
    if width > 1e-6:  # below that the direction is lost in the 0.1 m positions' rounding
        np.testing.assert_allclose(left[:3, 1], (right[:3, 3] - left[:3, 3]) / width, atol=1e-9)
    np.testing.assert_allclose(left[:3, 1], -right[:3, 1], atol=1e-12)
    midpoint = 0.5 * (left[:3, 3] + right[:3, 3])
    np.testing.assert_allclose(midpoint, [0.1, -0.2, 0.3 - geometry.tcp_to_gel_centre_m], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(theta=angle, seed=st.integers(0, 2**32 - 1))
def test_across_the_gels_is_each_open_gels_distance_to_its_face(theta, seed):
    """A point in the band sits across at a, so the open gels' faces are W/2 - a and W/2 + a in
    front of it (gel y, the kinematics' own frames): one at or past half the open width lies
    behind an open gel's face, where a finger coming down lands on it."""
    geometry = GripperGeometry()
    centre = np.array([0.05, -0.1, 0.08])
    gels = gel_poses_world(grasp_to_tcp_pose(*centre[:2], centre[2] + geometry.tcp_to_gel_centre_m, theta), 0.11)
    points = np.random.default_rng(seed).uniform(-0.07, 0.07, (400, 3)) * [1, 1, 0.3]
    across = across_the_gels_m(points, theta, geometry)
    in_left, in_right = (transform_points(points + centre, np.linalg.inv(gels[f])) for f in ("left", "right"))
    length, height = geometry.gel_size_m
    band = (np.abs(in_left[:, 0]) <= length / 2) & (np.abs(in_left[:, 2]) <= height / 2)
    assert len(across) == band.sum()
    in_front = np.sort(np.minimum(in_left[band, 1], in_right[band, 1]))
    np.testing.assert_allclose(in_front, np.sort(geometry.max_width_m / 2 - np.abs(across)), atol=1e-12)


def test_many_composed_small_rotations_stay_orthonormal():
    rng = np.random.default_rng(0)
    transform = np.eye(4)
    step = np.eye(4)
    for _ in range(100_000 // 100):
        step[:3, :3] = Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix()
        for _ in range(100):
            transform = transform @ step
    drift = np.abs(transform[:3, :3].T @ transform[:3, :3] - np.eye(3)).max()
    assert drift > 1e-14  # the naive product did drift
    for gel in gel_poses_world(transform, 0.05).values():
        assert_rigid(gel)
    assert_rigid(pose_to_matrix(matrix_to_pose(transform)))


@pytest.mark.parametrize("width", [-0.001, 0.2, np.nan])
def test_bad_width_is_refused(width):
    with pytest.raises(ValueError, match="gripper width"):
        gel_poses_world(grasp_to_tcp_pose(0, 0, 0.2, 0), width)


@pytest.mark.parametrize("pose", [np.zeros(5), np.array([0, 0, 0, np.nan, 0, 0])])
def test_bad_pose_is_refused(pose):
    with pytest.raises(ValueError, match="6 finite numbers"):
        pose_to_matrix(pose)
