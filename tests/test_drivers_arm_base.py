"""Arm limits, workspace, UR kinematics and backend selection: no controller needed."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.arm import make_backend
from drivers.arm.base import MotionLimitError, MotionLimits, WorkspaceBox, WorkspaceError
from drivers.arm.ur import URArm, URArmConfig
from workcell.ur_kinematics import tcp_pose


def test_the_workspace_names_the_axis_and_the_bound() -> None:
    box = WorkspaceBox(x_min_m=-0.5, x_max_m=0.5, y_min_m=-0.5, y_max_m=0.5, z_min_m=0.1, z_max_m=0.6)
    box.check(np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0]))
    with pytest.raises(WorkspaceError, match=r"x = 0\.6000 m is above x_max_m = 0\.5 m"):
        box.check(np.array([0.6, 0.0, 0.3, 0.0, 0.0, 0.0]))
    with pytest.raises(WorkspaceError, match=r"y = -0\.7000 m is below y_min_m = -0\.5 m"):
        box.check(np.array([0.0, -0.7, 0.3, 0.0, 0.0, 0.0]))


def test_an_empty_workspace_is_rejected() -> None:
    with pytest.raises(ValueError, match="workspace z"):
        WorkspaceBox(z_min_m=0.5, z_max_m=0.2)


def test_limits_reject_too_fast_and_non_positive_requests() -> None:
    limits = MotionLimits(max_tcp_speed_m_s=0.2, max_joint_accel_rad_s2=1.0)
    limits.check_linear(0.2, 1.0)
    with pytest.raises(MotionLimitError, match="exceeds the limit of 0.2 m/s"):
        limits.check_linear(0.21, 1.0)
    with pytest.raises(MotionLimitError, match="positive"):
        limits.check_linear(0.0, 1.0)
    with pytest.raises(MotionLimitError, match="positive"):
        limits.check_joint(float("nan"), 1.0)


def test_ur5e_forward_kinematics_matches_the_published_zero_pose() -> None:
    # With all joints at zero a UR5e's flange is at (-a2 - a3, -d4 - d6, d1 - d5).
    np.testing.assert_allclose(tcp_pose(np.zeros(6))[:3], [-0.8172, -0.2329, 0.0628], atol=1e-12)


def test_a_tcp_offset_moves_the_tcp_along_the_flange_axis() -> None:
    q = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])  # tool pointing down
    flange = tcp_pose(q)
    tool = tcp_pose(q, tcp_offset=np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(tool[:3] - flange[:3], [0.0, 0.0, -0.15], atol=1e-12)


def test_make_backend_builds_the_ur_backend_with_nested_config() -> None:
    backend = make_backend(
        {
            "backend": "ur_rtde",
            "robot_ip": "10.0.0.5",
            "workspace": {"z_min_m": 0.02},
            "limits": {"max_tcp_speed_m_s": 0.1},
        }
    )
    assert isinstance(backend, URArm)
    assert backend.config == URArmConfig(
        robot_ip="10.0.0.5", workspace=WorkspaceBox(z_min_m=0.02), limits=MotionLimits(max_tcp_speed_m_s=0.1)
    )


def test_make_backend_lists_what_is_allowed() -> None:
    with pytest.raises(ValueError, match=r"allowed: \['simulated', 'ur_rtde'\]"):
        make_backend({"backend": "kuka"})
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['robot_port'\].*allowed: .*robot_ip"):
        make_backend({"backend": "ur_rtde", "robot_port": 30004})
    with pytest.raises(ValueError, match="unknown UR model"):
        make_backend({"backend": "ur_rtde", "model": "ur99"})


@pytest.mark.parametrize("rate", [0.0, -125.0, float("nan"), float("inf")])
def test_an_rtde_rate_that_is_no_rate_is_refused(rate: float) -> None:
    with pytest.raises(ValueError, match="rtde_frequency_hz must be a positive rate in Hz or left out"):
        URArmConfig(rtde_frequency_hz=rate)
    assert URArmConfig().rtde_frequency_hz is None  # left out: the controller's own rate
