"""The fake UR controller's arm: a kinematic UR5e (or UR5) and the moves it makes.

moveJ interpolates the joints, moveL the TCP (position linearly, orientation by slerp) with
the joints following by inverse kinematics (damped least squares), both with a trapezoidal
speed profile; a stop decelerates along the same path. The controller core
(:mod:`sim.ur_controller.controller`) advances them one tick at a time.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from workcell.ur_kinematics import joint_frames, pose_to_matrix


def _skew(vector: np.ndarray) -> np.ndarray:
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula; plain numpy because scipy's per-call cost does not fit a tick."""
    k = _skew(axis)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix, robust at half turns (a tool pointing
    straight down is one)."""
    angle = float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-6:
        return _small_rotation_vector(rotation)
    sine_axis = _small_rotation_vector(rotation)
    if angle > np.pi - 1e-6:
        # Near a half turn R + I = 2 k k^T: take its largest column, signed like sin(angle) k.
        symmetric = rotation + np.eye(3)
        column = symmetric[:, int(np.argmax(np.linalg.norm(symmetric, axis=0)))]
        axis = column / np.linalg.norm(column)
        return angle * (-axis if float(axis @ sine_axis) < 0.0 else axis)
    return angle * sine_axis / np.sin(angle)


def _pose(transform: np.ndarray) -> np.ndarray:
    """[x, y, z, rx, ry, rz] (m, rad) of a 4x4 transform."""
    return np.concatenate([transform[:3, 3], _rotation_vector(transform[:3, :3])])


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs more than the whole IK step)."""
    return (a[:, [1, 2, 0]] * b[:, [2, 0, 1]]) - (a[:, [2, 0, 1]] * b[:, [1, 2, 0]])


def _small_rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix close to identity (error terms, per-tick turns)."""
    return 0.5 * np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )


@dataclasses.dataclass
class Motion:
    """One move along a path parametrised by s in [0, length]: joint angle of the leading
    joint (moveJ, rad) or TCP travel (moveL, m; rad for a pure rotation)."""

    kind: str  # "joint" | "linear"
    start: np.ndarray  # joints (rad), or the TCP as a 4x4 transform
    target: np.ndarray
    length: float
    speed: float
    accel: float
    asynchronous: bool
    turn_axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    turn_angle: float = 0.0  # the moveL orientation change, as one rotation about turn_axis
    s: float = 0.0
    v: float = 0.0
    stop_decel: float | None = None  # set by stopL/stopJ

    @staticmethod
    def joint(q_start: np.ndarray, q_target: np.ndarray, speed: float, accel: float, asynchronous: bool) -> "Motion":
        length = float(np.max(np.abs(q_target - q_start)))
        return Motion("joint", q_start, q_target, length, speed, accel, asynchronous)

    @staticmethod
    def linear(
        tcp_start: np.ndarray, pose_target: np.ndarray, speed: float, accel: float, asynchronous: bool
    ) -> "Motion":
        target = pose_to_matrix(pose_target)
        turn = Rotation.from_matrix(tcp_start[:3, :3].T @ target[:3, :3]).as_rotvec()
        turn_angle = float(np.linalg.norm(turn))
        travel = float(np.linalg.norm(target[:3, 3] - tcp_start[:3, 3]))
        length = travel if travel > 1e-9 else turn_angle
        motion = Motion("linear", tcp_start, target, length, speed, accel, asynchronous)
        if turn_angle > 1e-12:
            motion.turn_axis, motion.turn_angle = turn / turn_angle, turn_angle
        return motion

    @property
    def finished(self) -> bool:
        return self.s >= self.length or (self.stop_decel is not None and self.v <= 0.0)

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds: accelerate, cruise, brake to arrive, or stop."""
        remaining = self.length - self.s
        if self.stop_decel is not None:
            self.v = max(0.0, self.v - self.stop_decel * dt)
        else:
            self.v = min(
                self.speed,
                self.v + self.accel * dt,
                float(np.sqrt(2.0 * self.accel * max(remaining, 0.0))) + self.accel * dt,
            )
        self.s = min(self.length, self.s + self.v * dt)

    def setpoint(self) -> np.ndarray:
        """Joint angles (joint move) or the TCP transform (linear move) at the current s:
        position on the straight line, orientation turned by the same fraction."""
        fraction = 1.0 if self.length <= 0.0 else self.s / self.length
        if self.kind == "joint":
            return self.start + fraction * (self.target - self.start)
        transform = np.eye(4)
        transform[:3, 3] = self.start[:3, 3] + fraction * (self.target[:3, 3] - self.start[:3, 3])
        transform[:3, :3] = self.start[:3, :3] @ _axis_angle_matrix(self.turn_axis, fraction * self.turn_angle)
        return transform


class KinematicArm:
    """Joint state of a UR arm (``model``, a key of workcell.ur_kinematics.DH_PARAMETERS) and
    its TCP; linear moves drive the joints by damped least squares inverse kinematics."""

    def __init__(self, q: Sequence[float], model: str = "ur5e") -> None:
        self.model = model
        self.q = np.asarray(q, dtype=np.float64)
        self.qd = np.zeros(6)
        self.tcp_transform = joint_frames(self.q, model)[-1]
        self.tcp = _pose(self.tcp_transform)
        self.tcp_speed = np.zeros(6)

    def update_tcp(self, previous_q: np.ndarray, dt: float) -> None:
        """Recompute the TCP and the joint and TCP velocities after the joints moved."""
        previous = self.tcp_transform
        self.tcp_transform = joint_frames(self.q, self.model)[-1]
        self.tcp = _pose(self.tcp_transform)
        self.qd = (self.q - previous_q) / dt
        self.tcp_speed = np.concatenate(
            [
                (self.tcp_transform[:3, 3] - previous[:3, 3]) / dt,
                _small_rotation_vector(self.tcp_transform[:3, :3] @ previous[:3, :3].T) / dt,
            ]
        )

    def track(self, target: np.ndarray, iterations: int) -> float:
        """Move the joints toward a TCP transform by damped least squares steps; return the
        position error (m) before the last step, which is what a failure shows in."""
        position_error = 0.0
        for _ in range(iterations):
            frames = joint_frames(self.q, self.model)
            tcp = frames[-1]
            error = np.concatenate(
                [
                    target[:3, 3] - tcp[:3, 3],
                    _small_rotation_vector(target[:3, :3] @ tcp[:3, :3].T),
                ]
            )
            position_error = float(np.linalg.norm(error[:3]))
            if np.linalg.norm(error) < 1e-13:
                break
            axes = np.array([frame[:3, 2] for frame in frames[:6]])
            lever = tcp[:3, 3] - np.array([frame[:3, 3] for frame in frames[:6]])
            jacobian = np.vstack([_cross_rows(axes, lever).T, axes.T])
            damping = 1e-9 * np.eye(6)
            self.q = self.q + jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping, error)
        return position_error
