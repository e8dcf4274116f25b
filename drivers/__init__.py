"""Hardware backends, one package per device kind (LeRobot style).

Each ``drivers/<kind>/`` holds the real backends and the simulated one side by side behind
the same methods (``connect()``, ``read()``, ``disconnect()`` plus kind-specific commands),
and exposes ``make_backend(params)``: ``params["backend"]`` picks the class, the remaining
keys fill its config dataclass. Backends are imported only when chosen, so a lab without
OpenNI2 can still run the GelSight, and the simulation needs no hardware library at all.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any


class DeviceError(RuntimeError):
    """A device failure told to people: ``reason`` says what is wrong and, where an operator
    can act on it, ``fix`` says what to do (``dtx hw check`` prints them on a line each)."""

    def __init__(self, reason: str, fix: str = "") -> None:
        super().__init__(f"{reason}; fix: {fix}" if fix else reason)
        self.reason = reason
        self.fix = fix


@dataclasses.dataclass(frozen=True)
class BackendEntry:
    """Where a backend lives: ``module`` holds both ``backend_class`` and ``config_class``."""

    module: str
    backend_class: str
    config_class: str


def build_backend(kind: str, params: dict[str, Any], backends: dict[str, BackendEntry], **extras: Any) -> Any:
    """Build the backend ``params["backend"]`` names, its config from the other params;
    ``extras`` are handed to the backend's constructor beside the config.

    Raises ValueError naming the allowed backends, or the allowed config keys, when
    ``params`` asks for something that does not exist.
    """
    remaining = dict(params)
    choice = remaining.pop("backend", None)
    if choice not in backends:
        raise ValueError(f"{kind}: unknown backend {choice!r}; allowed: {sorted(backends)}")
    entry = backends[choice]
    module = importlib.import_module(entry.module)
    config_class = getattr(module, entry.config_class)
    allowed = {field.name for field in dataclasses.fields(config_class)}
    unknown = sorted(set(remaining) - allowed)
    if unknown:
        raise ValueError(f"{kind} backend {choice!r}: unknown parameter(s) {unknown}; allowed: {sorted(allowed)}")
    return getattr(module, entry.backend_class)(config_class(**remaining), **extras)


def require_text(config: Any, *names: str) -> None:
    """Raise ValueError if a config field meant as text came from YAML as a number.

    Launch files are YAML: an unquoted serial such as 003726261447 reads as an octal
    integer and a USB port such as 3 as an int, silently changing which device is meant.
    """
    for name in names:
        value = getattr(config, name)
        if not isinstance(value, str):
            raise ValueError(
                f"{type(config).__name__}.{name} must be text, got {value!r} "
                f"({type(value).__name__}); quote it in the launch file"
            )
