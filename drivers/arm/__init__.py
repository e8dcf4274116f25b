"""Arm backends behind one interface; ``make_backend`` builds one from launch parameters.

Every backend has ``connect()``, ``read() -> msgs.ArmState``, ``move_linear(tcp_pose,
speed_m_s, accel_m_s2)``, ``move_joints(q_rad, speed_rad_s, accel_rad_s2)``, ``stop()`` and
``disconnect()``, and raises the errors of ``drivers.arm.base``.
"""

from __future__ import annotations

import dataclasses
import importlib
import typing
from typing import Any

# backend name -> (module, backend class, config class); modules load only when chosen,
# so the simulated world does not need ur_rtde and the lab does not need the simulator.
BACKENDS = {
    "ur_rtde": ("drivers.arm.ur", "URArm", "URArmConfig"),
    "simulated": ("drivers.arm.simulated", "SimulatedArm", "SimulatedArmConfig"),
}


def make_backend(params: dict[str, Any]) -> Any:
    """Build the arm backend named by ``params["backend"]`` with the other entries as its
    config fields. A field holding a config dataclass (e.g. ``workspace``) takes a dict.

    Raises ValueError naming the allowed backends or config fields.
    """
    params = dict(params)
    name = params.pop("backend", None)
    if name not in BACKENDS:
        raise ValueError(f"unknown arm backend {name!r}; allowed: {sorted(BACKENDS)}")
    module_name, backend_name, config_name = BACKENDS[name]
    module = importlib.import_module(module_name)
    config = build_config(getattr(module, config_name), params)
    return getattr(module, backend_name)(config)


def build_config(config_class: type, params: dict[str, Any]) -> Any:
    """Instantiate a config dataclass from a dict, recursing into nested config dataclasses."""
    fields = {field.name: field for field in dataclasses.fields(config_class)}
    unknown = sorted(set(params) - set(fields))
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown} for {config_class.__name__}; allowed: {sorted(fields)}")
    hints = typing.get_type_hints(config_class)
    values = {}
    for key, value in params.items():
        field_type = hints[key]
        if dataclasses.is_dataclass(field_type) and isinstance(value, dict):
            value = build_config(field_type, value)
        values[key] = value
    return config_class(**values)
