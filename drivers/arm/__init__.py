"""Arm backends behind one interface; ``make_backend`` builds one from launch parameters.

Every backend has ``connect()``, ``read() -> msgs.ArmState``, ``move_linear(tcp_pose,
speed_m_s, accel_m_s2)``, ``move_joints(q_rad, speed_rad_s, accel_rad_s2)``, ``stop()`` and
``disconnect()``, and raises the errors of ``drivers.arm.base``.
"""

from __future__ import annotations

from typing import Any

from drivers import BackendEntry, build_backend
from drivers.arm.base import Arm

# Modules load only when chosen, so the simulated world does not need ur_rtde and the lab
# does not need the simulator.
BACKENDS = {
    "ur_rtde": BackendEntry("drivers.arm.ur", "URArm", "URArmConfig"),
    "simulated": BackendEntry("drivers.arm.simulated", "SimulatedArm", "SimulatedArmConfig"),
}

__all__ = ["BACKENDS", "make_backend"]


def make_backend(params: dict[str, Any]) -> Arm:
    """Arm backend chosen by ``params["backend"]``; a field holding a config dataclass (e.g.
    ``workspace``) takes a mapping."""
    return build_backend(Arm, "arm", params, BACKENDS)
