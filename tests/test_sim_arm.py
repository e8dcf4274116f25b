"""Simulated arm: trapezoidal motion time, workspace and motion limits, repeatability."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.arm.base import ArmError, MotionAbortedError, MotionLimitError, WorkspaceError
from drivers.arm.simulated import SimulatedArm, SimulatedArmConfig
from sim.arm import trapezoid_duration, trapezoid_fraction
from workcell.kinematics import grasp_to_tcp_pose, pose_to_matrix


def arm(scene: str = "scenes/ideal.yaml", **kw) -> SimulatedArm:
    a = SimulatedArm(SimulatedArmConfig(scene=scene, time_scale=kw.pop("time_scale", 0.0), **kw))
    a.connect()
    return a


def test_trapezoid_profile() -> None:
    # 0.1 m at 0.25 m/s, 1.2 m/s^2: cruise reached -> d/v + v/a
    assert trapezoid_duration(0.1, 0.25, 1.2) == pytest.approx(0.1 / 0.25 + 0.25 / 1.2)
    # 0.02 m: too short to reach the speed -> 2 sqrt(d/a)
    assert trapezoid_duration(0.02, 0.25, 1.2) == pytest.approx(2 * np.sqrt(0.02 / 1.2))
    assert trapezoid_fraction(0.0, 0.1, 0.25, 1.2) == 0.0
    T = trapezoid_duration(0.1, 0.25, 1.2)
    assert trapezoid_fraction(T / 2, 0.1, 0.25, 1.2) == pytest.approx(0.5)
    assert trapezoid_fraction(T, 0.1, 0.25, 1.2) == 1.0
    s = [trapezoid_fraction(t, 0.1, 0.25, 1.2) for t in np.linspace(0, T, 50)]
    assert np.all(np.diff(s) >= 0)


def test_move_linear_time_and_state() -> None:
    a = arm()
    start = a.read().tcp_pose
    target = start.copy()
    target[0] += 0.1
    t0 = a.sim_time_s
    a.move_linear(target, 0.25, 1.2)
    assert a.sim_time_s - t0 == pytest.approx(0.1 / 0.25 + 0.25 / 1.2)
    state = a.read()
    np.testing.assert_allclose(state.tcp_pose, target, atol=1e-12)
    assert not state.moving and state.header.frame_id == "world"
    # joints agree with the pose
    np.testing.assert_allclose(pose_to_matrix(a.kin.fk(state.joint_positions)), pose_to_matrix(target), atol=1e-7)


def test_real_time_scale_blocks_and_reports_motion() -> None:
    a = arm(time_scale=1.0)  # 0.4 s of motion: long enough to be seen mid-way on a busy machine
    target = a.read().tcp_pose.copy()
    target[1] += 0.05
    seen = []

    def watch() -> None:
        time.sleep(0.03)
        seen.append(a.read())

    th = threading.Thread(target=watch)
    t0 = time.monotonic()
    th.start()
    a.move_linear(target, 0.25, 1.2)
    wall = time.monotonic() - t0
    th.join()
    expected = trapezoid_duration(0.05, 0.25, 1.2)
    assert wall > expected * 0.9  # it blocks for the (scaled) motion; no upper bound on a shared machine
    assert seen and seen[0].moving
    assert 0.0 < seen[0].tcp_pose[1] - (target[1] - 0.05) < 0.05


def test_move_joints_time() -> None:
    a = arm()
    q = a.read().joint_positions.copy()
    q[0] += 0.3
    t0 = a.sim_time_s
    a.move_joints(q, 1.0, 1.4)
    assert a.sim_time_s - t0 == pytest.approx(trapezoid_duration(0.3, 1.0, 1.4))
    np.testing.assert_allclose(a.read().joint_positions, q, atol=1e-9)


def test_workspace_and_limits() -> None:
    a = arm()
    with pytest.raises(WorkspaceError):
        a.move_linear(grasp_to_tcp_pose(0.6, 0.0, 0.3, 0.0), 0.1, 0.5)  # outside the box
    with pytest.raises(WorkspaceError, match="table"):
        a.move_linear(grasp_to_tcp_pose(0.0, 0.0, 0.15, 0.0), 0.1, 0.5)  # gels into the table
    with pytest.raises(MotionLimitError):
        a.move_linear(grasp_to_tcp_pose(0.0, 0.0, 0.3, 0.0), 2.0, 0.5)
    with pytest.raises(MotionLimitError):
        a.move_linear(grasp_to_tcp_pose(0.0, 0.0, 0.3, 0.0), 0.1, -1.0)
    with pytest.raises(ValueError):
        a.move_linear([0.0, 0.0, np.nan, 0, 0, 0], 0.1, 0.5)
    assert isinstance(WorkspaceError("x"), ArmError)


def test_repeatability_effect() -> None:
    exact = arm("scenes/ideal.yaml")
    noisy = arm("scenes/effects_arm.yaml", seed=1)
    other = grasp_to_tcp_pose(0.0, 0.0, 0.35, 0.0)
    errs = []
    for i in range(30):
        target = grasp_to_tcp_pose(0.05 + 0.001 * i, 0.05, 0.3, 0.4)
        for a in (exact, noisy):
            a.move_linear(other, 0.25, 1.2)
            a.move_linear(target, 0.25, 1.2)
        np.testing.assert_allclose(exact.read().tcp_pose[:3], target[:3], atol=1e-12)
        errs.append(noisy.read().tcp_pose[:3] - target[:3])
    errs = np.array(errs)
    sigma = errs.std()
    assert 0.015e-3 < sigma < 0.06e-3  # scene: sigma_mm 0.033
    assert np.all(np.abs(errs) < 0.2e-3)


def test_the_repeatability_error_is_keyed_on_the_target() -> None:
    """A move to a target lands where a move to it landed before, in this arm or another with
    the same seed (sim.seeding: a resumed session reaches the same places); another seed lands
    elsewhere."""
    target, other = grasp_to_tcp_pose(0.05, 0.05, 0.3, 0.4), grasp_to_tcp_pose(0.0, 0.0, 0.35, 0.0)

    def landings(seed: int) -> list[np.ndarray]:
        a = arm("scenes/effects_arm.yaml", seed=seed)
        reached = []
        for _ in range(2):
            a.move_linear(target, 0.25, 1.2)
            reached.append(a.read().tcp_pose.copy())
            a.move_linear(other, 0.25, 1.2)
        return reached

    first, again, elsewhere = landings(1), landings(1), landings(2)
    np.testing.assert_array_equal(first[0], first[1])
    np.testing.assert_array_equal(first[0], again[0])
    assert not np.allclose(first[0][:3], target[:3], atol=1e-9)
    assert not np.array_equal(first[0], elsewhere[0])


def test_stop_aborts() -> None:
    a = arm(time_scale=1.0)
    target = a.read().tcp_pose.copy()
    target[0] += 0.2
    threading.Timer(0.1, a.stop).start()
    with pytest.raises(MotionAbortedError):
        a.move_linear(target, 0.1, 0.5)
    pose = a.read().tcp_pose
    assert 0.0 < pose[0] - (target[0] - 0.2) < 0.2
    assert not a.read().moving
