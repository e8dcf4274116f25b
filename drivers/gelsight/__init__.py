"""GelSight backends: a V4L2 camera (or a recorded video) through OpenCV, and the renderer."""

from __future__ import annotations

from typing import Any

from drivers import BackendEntry, build_backend
from drivers.gelsight.base import EndOfStreamError, GelSight, GelSightError

BACKENDS = {
    "v4l2": BackendEntry("drivers.gelsight.v4l2", "V4L2GelSight", "V4L2GelSightConfig"),
    "simulated": BackendEntry("drivers.gelsight.simulated", "SimulatedGelSight", "SimulatedGelSightConfig"),
}

__all__ = ["BACKENDS", "EndOfStreamError", "GelSightError", "make_backend"]


def make_backend(params: dict[str, Any], **extras: Any) -> GelSight:
    """GelSight backend chosen by ``params["backend"]``."""
    return build_backend(GelSight, "gelsight", params, BACKENDS, **extras)
