"""Simulated UR arm: the same interface as the real backend, on the kinematic model of
``sim/arm.py`` (trapezoidal motion time, reach, workspace, repeatability effect).

``time_scale`` sets how long a move really blocks: 1.0 = real time, 0.5 = twice as fast,
0.0 = no waiting at all (tests); the simulated clock (:attr:`SimulatedArm.sim_time_s`)
always advances by the full motion time. The reported TCP pose is where the arm really
ended (with the repeatability error when the scene calls for it), in ``world``.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from drivers import requires_connection
from drivers.arm.base import (
    Arm,
    ArmError,
    MotionAbortedError,
    MotionLimits,
    StopFailedError,
    WorkspaceError,
    as_six_vector,
)
from msgs import ArmState, Header
from sim.arm import ArmKinematics, Motion, Repeatability, UnreachablePoseError, plan_joints, plan_linear, pose_matrix
from sim.effects import resolve_effects
from workcell.kinematics import grasp_to_tcp_pose
from workcell.scene import load_scene

__all__ = ["SimulatedArm", "SimulatedArmConfig", "ArmError", "WorkspaceError"]


@dataclasses.dataclass
class SimulatedArmConfig:
    scene: str | None = "scenes/ycb_three.yaml"  # workspace, gripper size, arm_repeatability effect
    seed: int | None = None  # default: the scene's seed
    model: str = "ur5e"
    base_pose_world: list[float] = dataclasses.field(default_factory=lambda: [0.0, -0.4, 0.0, 0.0, 0.0, 0.0])
    tcp_offset: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 6)
    home_tcp_pose: list[float] | None = None  # default: 0.35 m above the workspace centre, tool down
    time_scale: float = 1.0
    workspace_min_m: list[float] | None = None  # override (or replace, without scene) the scene's box
    workspace_max_m: list[float] | None = None
    table_clearance: bool = True  # refuse targets that put the gels below the table top
    max_tcp_speed_m_s: float = 0.25
    max_tcp_accel_m_s2: float = 1.2
    max_joint_speed_rad_s: float = 1.05
    max_joint_accel_rad_s2: float = 1.4

    def __post_init__(self) -> None:
        if not (np.isfinite(self.time_scale) and 0.0 <= self.time_scale <= 100.0):
            raise ValueError(f"time_scale {self.time_scale} outside [0, 100]")


STOP_DEADLINE_S = 1.0  # a stopped move ends within one of its 20 ms waits; this is its deadline
_SEED_JOINTS = np.array([-np.pi / 2, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])


class SimulatedArm(Arm):
    def __init__(self, config: SimulatedArmConfig):
        self.config = config
        self.scene = None
        if config.scene:
            self.scene = resolve_effects(load_scene(config.scene))
        ws_min = np.array(
            config.workspace_min_m
            if config.workspace_min_m is not None
            else (self.scene.workspace_min_m if self.scene else [-0.4, -0.3, 0.0]),
            float,
        )
        ws_max = np.array(
            config.workspace_max_m
            if config.workspace_max_m is not None
            else (self.scene.workspace_max_m if self.scene else [0.4, 0.3, 0.6]),
            float,
        )
        self.workspace = (ws_min, ws_max)
        self.limits = MotionLimits(
            config.max_tcp_speed_m_s,
            config.max_tcp_accel_m_s2,
            config.max_joint_speed_rad_s,
            config.max_joint_accel_rad_s2,
        )
        self.kin = ArmKinematics(
            config.model, pose_matrix(np.asarray(config.base_pose_world, float)), np.asarray(config.tcp_offset, float)
        )
        seed = config.seed if config.seed is not None else (self.scene.seed if self.scene else 0)
        eff = self.scene.effect("arm_repeatability") if self.scene else None
        self.repeatability = Repeatability(eff.params, seed) if eff else None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._connected = False
        self._pose = np.zeros(6)
        self._q = np.zeros(6)
        self._motion: Motion | None = None
        self._motion_start = 0.0
        self._seq = 0
        self.sim_time_s = 0.0
        self.last_motion: Motion | None = None

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        if self.config.home_tcp_pose is not None:
            home = as_six_vector(self.config.home_tcp_pose, "home_tcp_pose")
        else:
            c = 0.5 * (self.workspace[0] + self.workspace[1])
            home = grasp_to_tcp_pose(c[0], c[1], min(self.workspace[1][2], 0.35), 0.0)
        self._check_target(home)
        self._q = self._ik(home, _SEED_JOINTS)
        self._pose = home
        self._connected = True

    def disconnect(self) -> None:
        self.stop()
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    # ------------------------------------------------------------------ state
    def _elapsed(self) -> float:
        scale = self.config.time_scale
        return float("inf") if scale <= 0 else (time.monotonic() - self._motion_start) / scale

    def _current(self) -> tuple[np.ndarray, np.ndarray, bool]:
        with self._lock:
            motion = self._motion
            if motion is None:
                return self._pose.copy(), self._q.copy(), False
            t = self._elapsed()
        pose, q = motion.pose_at(t, self.kin)
        return pose, q, t < motion.duration_s

    @requires_connection
    def read(self) -> ArmState:
        pose, q, moving = self._current()
        qd = np.zeros(6)
        with self._lock:
            motion = self._motion
        if moving and motion is not None:
            dt = 0.01
            t = self._elapsed()
            _, q2 = motion.pose_at(t + dt, self.kin)
            qd = (q2 - q) / dt
        self._seq += 1
        header = Header(stamp_ns=time.time_ns(), seq=self._seq, frame_id="world")
        return ArmState(
            header=header, tcp_pose=pose, joint_positions=q, joint_velocities=qd, moving=moving, safety_status="normal"
        )

    # ------------------------------------------------------------------ commands
    def _check_target(self, pose: np.ndarray) -> None:
        lo, hi = self.workspace
        for i, axis in enumerate("xyz"):
            if pose[i] < lo[i] - 1e-9:
                raise WorkspaceError(f"target {axis} = {pose[i]:.4f} m is below the workspace min {lo[i]} m")
            if pose[i] > hi[i] + 1e-9:
                raise WorkspaceError(f"target {axis} = {pose[i]:.4f} m is above the workspace max {hi[i]} m")
        if self.config.table_clearance and self.scene is not None:
            g = self.scene.gripper
            T = pose_matrix(pose)
            tool_z = T[:3, 2]
            # lowest gel corner: gel centre along tool z, plus half the gel length along it
            lowest = T[2, 3] + tool_z[2] * g.tcp_to_gel_centre_m - abs(tool_z[2]) * g.gel_size_m[1] / 2
            if lowest < 0.0:
                raise WorkspaceError(f"target z = {pose[2]:.4f} m puts the gels {-lowest * 1e3:.1f} mm into the table")

    @requires_connection
    def move_linear(self, tcp_pose: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        """moveL to ``tcp_pose`` (world); blocks until reached. Raises WorkspaceError,
        MotionLimitError (nothing moves) or MotionAbortedError (stopped on the way)."""
        target = as_six_vector(tcp_pose, "tcp_pose")
        self.limits.check_linear(speed_m_s, accel_m_s2)
        self._require_idle()
        self._check_target(target)
        q_target = self._ik(target, self._q)
        motion = plan_linear(self._pose.copy(), self._q.copy(), target, q_target, speed_m_s, accel_m_s2)
        self._run(motion)

    @requires_connection
    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """moveJ to joints ``q_rad``; blocks until reached."""
        q_target = as_six_vector(q_rad, "q_rad")
        self.limits.check_joint(speed_rad_s, accel_rad_s2)
        self._require_idle()
        target = self.kin.fk(q_target)
        self._check_target(target)
        motion = plan_joints(self._pose.copy(), self._q.copy(), target, q_target, speed_rad_s, accel_rad_s2)
        self._run(motion)

    def stop(self) -> None:
        """Stop a move in progress where it is (the blocked move raises MotionAbortedError)
        and return once it has ended; the simulated arm halts at once."""
        self._stop.set()
        deadline = time.monotonic() + STOP_DEADLINE_S
        while self._motion is not None:
            if time.monotonic() > deadline:
                raise StopFailedError(f"the simulated arm's move did not end within {STOP_DEADLINE_S} s of the stop")
            time.sleep(0.002)

    def _ik(self, pose_world: np.ndarray, q_seed: np.ndarray) -> np.ndarray:
        try:
            return self.kin.ik(pose_world, q_seed)
        except UnreachablePoseError as err:
            raise WorkspaceError(str(err)) from None

    def _require_idle(self) -> None:
        with self._lock:
            if self._motion is not None:
                raise ArmError("a move is already in progress")

    def _run(self, motion: Motion) -> None:
        self._stop.clear()
        with self._lock:
            self._motion = motion
            self._motion_start = time.monotonic()
        aborted = False
        wall = motion.duration_s * self.config.time_scale
        deadline = self._motion_start + wall
        while wall > 0:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if self._stop.wait(min(remaining, 0.02)):
                aborted = True
                break
        if aborted:
            t = self._elapsed() if self.config.time_scale > 0 else 0.0
            pose, q = motion.pose_at(min(t, motion.duration_s), self.kin)
            elapsed = min(t, motion.duration_s)
        else:
            pose, q = motion.end.copy(), motion.q_end.copy()
            elapsed = motion.duration_s
            if self.repeatability is not None:
                pose = self.repeatability.perturb(pose)
                q = self._ik(pose, q)
        with self._lock:
            self._pose, self._q = pose, q
            self._motion = None
            self.sim_time_s += elapsed
            self.last_motion = motion
        if aborted:
            raise MotionAbortedError("move stopped before reaching its target")
