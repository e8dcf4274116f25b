"""Arm and gripper state and commands. Poses are metres and radians in ``world``."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class ArmState(Message):
    """TCP pose (x, y, z, rx, ry, rz: position in m, rotation vector in rad, UR convention),
    joint positions (rad) and velocities (rad/s), the controller's safety status, and the
    code of the last thing that went wrong with the arm (drivers.arm.base.ArmErrorCode; empty
    while all is well)."""

    SCHEMA = "dtx.robot.ArmState"
    VERSION = 2

    tcp_pose: np.ndarray = empty((6,), np.float64)
    joint_positions: np.ndarray = empty((6,), np.float64)
    joint_velocities: np.ndarray = empty((6,), np.float64)
    moving: bool = False
    safety_status: str = "normal"  # normal | protective_stop | emergency_stop | disconnected
    error_code: str = ""


@dataclasses.dataclass
class GripperState(Message):
    """Finger opening (m), grasping force (N) and the gripper's state word."""

    SCHEMA = "dtx.robot.GripperState"
    VERSION = 1

    width_m: float = 0.0
    force_n: float = 0.0
    state: str = "idle"  # idle | moving | holding | no_part | blocked | error
    status_code: int = 0


@dataclasses.dataclass
class ArmMoveRequest(Message):
    """Service request: move the TCP linearly (``moveL``) or in joint space (``moveJ``)."""

    SCHEMA = "dtx.robot.ArmMoveRequest"
    VERSION = 1

    target: np.ndarray = empty((6,), np.float64)
    mode: str = "moveL"
    speed: float = 0.25
    acceleration: float = 1.2


@dataclasses.dataclass
class GripperCommand(Message):
    """Service request to the gripper: ``home``, ``move`` (to width), ``grasp`` (close on a part
    of nominal width at speed with a force limit), ``release``, ``stop`` or ``acknowledge`` (a
    FAST STOP). SI units."""

    SCHEMA = "dtx.robot.GripperCommand"
    VERSION = 1

    action: str = "grasp"
    width_m: float = 0.0
    speed_m_s: float = 0.05
    force_n: float = 10.0


@dataclasses.dataclass
class GraspCommand(Message):
    """One grasp of Algorithm 1: palm parallel to the table, (x, y, z) in ``world`` and the
    rotation theta_z about the world z axis; closed with a constant contact force."""

    SCHEMA = "dtx.robot.GraspCommand"
    VERSION = 1

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    theta_z: float = 0.0
    force_n: float = 10.0
    object_name: str = ""
    grasp_id: int = 0
