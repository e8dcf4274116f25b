"""What every arm backend shares: its errors, the workspace box and the motion limits.

Poses are [x, y, z, rx, ry, rz] in the robot base frame: metres, and a rotation vector in
radians (the Universal Robots convention). The checks here run before a backend sends
anything to the robot, so a refused command never reaches the controller.
"""

from __future__ import annotations

import abc
import dataclasses

import numpy as np
import numpy.typing as npt

from drivers import Device, DeviceError, DeviceNotConnectedError, DeviceTimeoutError
from msgs import ArmState


class ArmErrorCode:
    """What went wrong with the arm, as ``ArmState.error_code`` reports it on ``/arm/state``
    for the collector (and any other process) to branch on; empty while all is well."""

    NONE = ""
    ARM_ERROR = "arm_error"  # any other failure of the arm: its text says which
    COMMAND_TIMEOUT = "command_timeout"  # a command to the controller got no answer in its deadline
    STOP_BY_PROGRAM_END = "stop_by_program_end"  # stopJ not carried out: the control script ended (watchdog, pendant)
    STOP_ESCALATED_DASHBOARD = "stop_escalated_dashboard"  # the arm came to rest only after the dashboard's stop
    STOP_ESCALATED_WATCHDOG = "stop_escalated_watchdog"  # ... only once the link fell silent (watchdog)
    STOP_FAILED = "stop_failed"  # not at rest after every escalation: use the emergency stop
    STOP_UNVERIFIED = "stop_unverified"  # the link was lost: the watchdog stops the arm, unseen


class ArmError(DeviceError):
    """Any failure of the arm; the arm node turns it into a safe session stop. ``code`` is its
    ArmErrorCode, which the ``/arm/*`` services send as their error reply's code."""

    code = ArmErrorCode.ARM_ERROR

    def __init__(self, reason: str, fix: str = "", code: str | None = None) -> None:
        super().__init__(reason, fix)
        if code is not None:
            self.code = code


class ArmConnectionError(ArmError):
    """The controller could not be reached or refused the session."""


class ConnectionLostError(ArmConnectionError):
    """The connection to the controller dropped (or went silent) while in use."""


class ProtectiveStopError(ArmError):
    """The controller is in a protective stop; an operator must clear it on the pendant."""


class EmergencyStopError(ArmError):
    """An emergency stop is pressed; an operator must release it and restart the arm."""


class ArmTimeoutError(ArmError, DeviceTimeoutError):
    """The controller did not answer a command within its deadline."""

    code = ArmErrorCode.COMMAND_TIMEOUT


class StopFailedError(ArmError):
    """The arm was still seen moving after every way of stopping it was tried."""

    code = ArmErrorCode.STOP_FAILED


class ArmNotConnectedError(DeviceNotConnectedError, ArmConnectionError):
    """An arm read or commanded before ``connect()`` or after ``disconnect()``."""


class WorkspaceError(ArmError):
    """A target lies outside the allowed workspace; nothing was sent."""


class MotionLimitError(ArmError):
    """A requested speed or acceleration exceeds the configured limit; nothing was sent."""


class MotionAbortedError(ArmError):
    """A move ended before reaching its target (stopped, or the controller gave up)."""


class Arm(Device):
    """The arm contract. Moves block until the arm arrives; ``stop()`` and ``read()`` may be
    called from another thread while a move waits (the move then raises MotionAbortedError)."""

    NOT_CONNECTED = ArmNotConnectedError

    @abc.abstractmethod
    def read(self) -> ArmState:
        """Joint angles and the TCP pose (base frame) as of the controller's last report."""

    @abc.abstractmethod
    def move_linear(self, tcp_pose: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        """moveL to ``tcp_pose`` [x, y, z, rx, ry, rz] (m, rad)."""

    @abc.abstractmethod
    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """moveJ to joint angles ``q_rad``."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any move in progress where it is, and return once the arm's state says it is at
        rest (StopFailedError if it cannot be brought to or seen at rest)."""


@dataclasses.dataclass(frozen=True)
class WorkspaceBox:
    """Axis-aligned box the TCP must stay in, in the robot base frame (m)."""

    x_min_m: float = -0.8
    x_max_m: float = 0.8
    y_min_m: float = -0.8
    y_max_m: float = 0.8
    z_min_m: float = 0.0
    z_max_m: float = 0.8

    def __post_init__(self) -> None:
        for axis in "xyz":
            low, high = getattr(self, f"{axis}_min_m"), getattr(self, f"{axis}_max_m")
            if not low < high:
                raise ValueError(f"workspace {axis}: min {low} m must be below max {high} m")

    def check(self, tcp_pose: np.ndarray) -> None:
        """Raise WorkspaceError naming the axis and the bound if the TCP position is outside."""
        for index, axis in enumerate("xyz"):
            value = float(tcp_pose[index])
            low, high = getattr(self, f"{axis}_min_m"), getattr(self, f"{axis}_max_m")
            if value < low:
                raise WorkspaceError(f"target {axis} = {value:.4f} m is below {axis}_min_m = {low} m")
            if value > high:
                raise WorkspaceError(f"target {axis} = {value:.4f} m is above {axis}_max_m = {high} m")


@dataclasses.dataclass(frozen=True)
class MotionLimits:
    """Upper bounds on what a move may ask for: TCP (m/s, m/s²) and joint (rad/s, rad/s²)."""

    max_tcp_speed_m_s: float = 0.25
    max_tcp_accel_m_s2: float = 1.2
    max_joint_speed_rad_s: float = 1.05
    max_joint_accel_rad_s2: float = 1.4

    def check_linear(self, speed_m_s: float, accel_m_s2: float) -> None:
        """Raise MotionLimitError if a linear move's speed or acceleration is out of range."""
        _check_limit("TCP speed", speed_m_s, self.max_tcp_speed_m_s, "m/s")
        _check_limit("TCP acceleration", accel_m_s2, self.max_tcp_accel_m_s2, "m/s²")

    def check_joint(self, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Raise MotionLimitError if a joint move's speed or acceleration is out of range."""
        _check_limit("joint speed", speed_rad_s, self.max_joint_speed_rad_s, "rad/s")
        _check_limit("joint acceleration", accel_rad_s2, self.max_joint_accel_rad_s2, "rad/s²")


def _check_limit(name: str, value: float, limit: float, unit: str) -> None:
    if not np.isfinite(value) or value <= 0.0:
        raise MotionLimitError(f"{name} {value} {unit} must be a positive number")
    if value > limit:
        raise MotionLimitError(f"{name} {value} {unit} exceeds the limit of {limit} {unit}")


def as_six_vector(values: npt.ArrayLike, what: str) -> np.ndarray:
    """Return ``values`` as a finite float64 array of shape (6,), or raise ValueError."""
    array = np.asarray(values, dtype=np.float64)
    if array.shape != (6,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be 6 finite numbers, got {values!r}")
    return array
