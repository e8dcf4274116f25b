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

from msgs.config import ConfigError, config_from_dict


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

    Raises ValueError naming the allowed backends, or (msgs.config.ConfigError) the key and
    what it allows when ``params`` asks for something that does not exist or has the wrong type.
    """
    remaining = dict(params)
    choice = remaining.pop("backend", None)
    if choice not in backends:
        raise ValueError(f"{kind}: unknown backend {choice!r}; allowed: {sorted(backends)}")
    entry = backends[choice]
    module = importlib.import_module(entry.module)
    try:
        config = config_from_dict(getattr(module, entry.config_class), remaining)
    except ConfigError as exc:
        raise ConfigError(f"{kind} backend {choice!r}: {exc}") from None
    return getattr(module, entry.backend_class)(config, **extras)
