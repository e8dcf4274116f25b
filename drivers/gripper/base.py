"""The gripper contract: what the gripper node asks of any parallel gripper backend.

Widths are the distance between the fingers in metres, speeds in m/s, forces in N. Every
command blocks until the gripper reports the motion done and returns the state it ended in.
"""

from __future__ import annotations

import abc

from drivers import Device, DeviceNotConnectedError
from drivers.gripper.protocol import GripperError
from msgs import GripperState


class GripperNotConnectedError(DeviceNotConnectedError, GripperError):
    """A gripper read or commanded before ``connect()`` or after ``disconnect()``."""


class Gripper(Device):
    NOT_CONNECTED = GripperNotConnectedError

    @abc.abstractmethod
    def read(self) -> GripperState:
        """Current opening, grasping force and grasping state."""

    @abc.abstractmethod
    def acknowledge(self) -> GripperState:
        """Clear a fault the gripper reported, so it accepts motions again."""

    @abc.abstractmethod
    def home(self) -> GripperState:
        """Reference the fingers (needed after power-up before any motion)."""

    @abc.abstractmethod
    def move(self, width_m: float, speed_m_s: float) -> GripperState:
        """Move the fingers to ``width_m`` without expecting a part."""

    @abc.abstractmethod
    def grasp(self, width_m: float, speed_m_s: float, force_n: float) -> GripperState:
        """Close on a part expected at ``width_m`` and hold it with ``force_n``."""

    @abc.abstractmethod
    def release(self, width_m: float, speed_m_s: float) -> GripperState:
        """Let go of a held part, opening to ``width_m``."""

    @abc.abstractmethod
    def stop(self) -> GripperState:
        """Stop any motion at once."""
