"""Kinematic model of the simulated UR arm: motion time, path, reach and repeatability.

No dynamics: a move follows the trapezoidal velocity profile the controller would use with
the commanded speed and acceleration (``moveL``: along the straight TCP line, the rotation
interpolated on the same profile; ``moveJ``: all joints synchronised to the slowest), and
ends at the target plus the repeatability error when the scene calls for the
``arm_repeatability`` effect (UR5/CB3: +-0.1 mm, UR5e: +-0.03 mm per ISO 9283, taken here
as about 3 sigma). Joint positions come from the published DH parameters
(``workcell.ur_kinematics``) and a damped-least-squares inverse kinematics.

Poses are UR poses [x, y, z, rx, ry, rz] in ``world``; ``base_to_world`` places the robot.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from sim.seeding import state_rng
from workcell.ur_kinematics import joint_frames


class UnreachablePoseError(ValueError):
    """Inverse kinematics found no joint angles reaching the pose."""


def trapezoid_duration(distance: float, speed: float, accel: float) -> float:
    """Time (s) to travel ``distance`` from rest to rest with speed and acceleration limits
    (triangular profile when the distance is too short to reach ``speed``)."""
    distance = abs(float(distance))
    if distance == 0.0:
        return 0.0
    if distance >= speed * speed / accel:
        return distance / speed + speed / accel
    return 2.0 * math.sqrt(distance / accel)


def trapezoid_fraction(t: float, distance: float, speed: float, accel: float) -> float:
    """Fraction (0..1) of ``distance`` covered ``t`` seconds into the profile."""
    distance = abs(float(distance))
    total = trapezoid_duration(distance, speed, accel)
    if distance == 0.0 or t >= total:
        return 1.0
    if t <= 0.0:
        return 0.0
    if distance >= speed * speed / accel:
        ta = speed / accel
        if t < ta:
            s = 0.5 * accel * t * t
        elif t < total - ta:
            s = 0.5 * accel * ta * ta + speed * (t - ta)
        else:
            r = total - t
            s = distance - 0.5 * accel * r * r
    else:
        half = total / 2.0
        if t < half:
            s = 0.5 * accel * t * t
        else:
            r = total - t
            s = distance - 0.5 * accel * r * r
    return min(1.0, max(0.0, s / distance))


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(pose[3:6], float)).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def matrix_pose(T: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


@dataclasses.dataclass
class ArmKinematics:
    """UR forward/inverse kinematics with the robot base placed in ``world``."""

    model: str = "ur5e"
    base_to_world: np.ndarray = dataclasses.field(
        default_factory=lambda: pose_matrix(np.array([0.0, -0.4, 0.0, 0, 0, 0]))
    )
    tcp_offset: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(6))

    def __post_init__(self) -> None:
        self._flange_to_tcp = pose_matrix(self.tcp_offset)

    def fk_matrix(self, q: np.ndarray) -> np.ndarray:
        return self.base_to_world @ joint_frames(np.asarray(q, float), self.model)[-1] @ self._flange_to_tcp

    def fk(self, q: np.ndarray) -> np.ndarray:
        return matrix_pose(self.fk_matrix(q))

    def ik(self, pose_world: np.ndarray, q_seed: np.ndarray, iterations: int = 200, tol: float = 1e-9) -> np.ndarray:
        """Joint angles reaching ``pose_world`` (damped least squares from ``q_seed``);
        raises UnreachablePoseError when the pose cannot be reached."""
        target = pose_matrix(pose_world)
        q = np.asarray(q_seed, float).copy()
        eps = 1e-6
        lam = 1e-3
        for _ in range(iterations):
            T = self.fk_matrix(q)
            err = self._error(target, T)
            if float(err @ err) < tol * tol:
                return (q + np.pi) % (2 * np.pi) - np.pi
            J = np.empty((6, 6))
            for j in range(6):
                dq = q.copy()
                dq[j] += eps
                J[:, j] = self._error(self.fk_matrix(dq), T) / eps
            JJt = J @ J.T + (lam * lam) * np.eye(6)
            step = J.T @ np.linalg.solve(JJt, err)
            norm = np.linalg.norm(step)
            if norm > 0.5:
                step *= 0.5 / norm
            q += step
        raise UnreachablePoseError(
            f"pose {np.round(pose_world, 4).tolist()} is out of reach of the {self.model} "
            f"(inverse kinematics did not converge)"
        )

    @staticmethod
    def _error(target: np.ndarray, T: np.ndarray) -> np.ndarray:
        dp = target[:3, 3] - T[:3, 3]
        dr = Rotation.from_matrix(target[:3, :3] @ T[:3, :3].T).as_rotvec()
        return np.concatenate([dp, dr])


@dataclasses.dataclass
class Motion:
    """A planned move: from ``start`` to ``end`` (TCP poses, world) and joints ``q_start`` to
    ``q_end``, lasting ``duration_s``. ``kind`` is ``linear`` or ``joint``."""

    kind: str
    start: np.ndarray
    end: np.ndarray
    q_start: np.ndarray
    q_end: np.ndarray
    duration_s: float
    distance: float  # m (linear) or rad (largest joint / rotation)
    speed: float
    accel: float

    def fraction(self, t: float) -> float:
        if self.duration_s <= 0.0:
            return 1.0
        return trapezoid_fraction(t, self.distance, self.speed, self.accel)

    def pose_at(self, t: float, kin: ArmKinematics) -> tuple[np.ndarray, np.ndarray]:
        """(TCP pose, joints) ``t`` seconds into the move."""
        s = self.fraction(t)
        if s >= 1.0:
            return self.end.copy(), self.q_end.copy()
        if self.kind == "joint":
            q = self.q_start + s * (self.q_end - self.q_start)
            return kin.fk(q), q
        p = self.start[:3] + s * (self.end[:3] - self.start[:3])
        rots = Rotation.from_rotvec(np.stack([self.start[3:], self.end[3:]]))
        r = Slerp([0.0, 1.0], rots)([s])[0].as_rotvec()
        pose = np.concatenate([p, r])
        try:
            q = kin.ik(pose, self.q_start + s * (self.q_end - self.q_start), iterations=20, tol=1e-6)
        except UnreachablePoseError:
            q = self.q_start + s * (self.q_end - self.q_start)
        return pose, q


def plan_linear(
    start: np.ndarray, q_start: np.ndarray, target: np.ndarray, q_target: np.ndarray, speed: float, accel: float
) -> Motion:
    """moveL: translation on the commanded profile; a pure rotation uses the same numbers in
    rad/s and rad/s^2 (as the UR controller does); the slower of the two sets the time."""
    dist = float(np.linalg.norm(target[:3] - start[:3]))
    angle = float((Rotation.from_rotvec(target[3:]) * Rotation.from_rotvec(start[3:]).inv()).magnitude())
    t_lin = trapezoid_duration(dist, speed, accel)
    t_rot = trapezoid_duration(angle, speed, accel)
    if t_lin >= t_rot:
        return Motion("linear", start, target, q_start, q_target, t_lin, dist, speed, accel)
    return Motion("linear", start, target, q_start, q_target, t_rot, angle, speed, accel)


def plan_joints(
    start: np.ndarray, q_start: np.ndarray, target: np.ndarray, q_target: np.ndarray, speed: float, accel: float
) -> Motion:
    """moveJ: all joints start and stop together; the largest joint travel sets the time."""
    dq = float(np.max(np.abs(np.asarray(q_target) - np.asarray(q_start))))
    return Motion("joint", start, target, q_start, q_target, trapezoid_duration(dq, speed, accel), dq, speed, accel)


class Repeatability:
    """The ``arm_repeatability`` effect: a finished move ends at the target plus Gaussian
    error (``sigma_mm`` per axis in position, ``sigma_deg`` about a random axis), drawn keyed
    on (``seed``, the target) so a replayed or resumed session reaches the same places
    (``sim.seeding``)."""

    def __init__(self, params: dict, seed: int):
        self.sigma_m = float(params.get("sigma_mm", 0.0)) * 1e-3
        self.sigma_rad = math.radians(float(params.get("sigma_deg", 0.0)))
        self.seed = int(seed)

    def perturb(self, pose: np.ndarray) -> np.ndarray:
        out = np.asarray(pose, float).copy()
        rng = state_rng(out, self.seed, 7)
        out[:3] += rng.normal(0.0, self.sigma_m, 3) if self.sigma_m > 0 else 0.0
        if self.sigma_rad > 0:
            dr = Rotation.from_rotvec(rng.normal(0.0, self.sigma_rad, 3))
            out[3:] = (dr * Rotation.from_rotvec(out[3:])).as_rotvec()
        return out
