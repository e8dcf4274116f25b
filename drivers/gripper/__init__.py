"""Gripper backends: the WSG-50 over a serial line, and its firmware simulator on a pty."""

from __future__ import annotations

from typing import Any

from drivers import BackendEntry, build_backend
from drivers.gripper.base import Gripper
from drivers.gripper.protocol import GripperError

BACKENDS = {
    "wsg50": BackendEntry("drivers.gripper.wsg50", "WSG50Gripper", "WSG50Config"),
    "simulated": BackendEntry("drivers.gripper.simulated", "SimulatedGripper", "SimulatedGripperConfig"),
}

__all__ = ["BACKENDS", "GripperError", "make_backend"]


def make_backend(params: dict[str, Any], **extras: Any) -> Gripper:
    """Gripper backend chosen by ``params["backend"]``; ``extras`` go to its constructor
    (the simulated world passes ``contact_width_m`` this way)."""
    return build_backend(Gripper, "gripper", params, BACKENDS, **extras)
