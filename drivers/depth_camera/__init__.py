"""Depth camera backends: Kinect v2 through OpenNI2 or libfreenect2, and the ray-cast scene."""

from __future__ import annotations

from typing import Any

from drivers import BackendEntry, build_backend
from drivers.depth_camera.base import DepthCamera, DepthCameraError

BACKENDS = {
    "openni2": BackendEntry("drivers.depth_camera.openni2", "OpenNI2DepthCamera", "OpenNI2DepthCameraConfig"),
    "freenect2": BackendEntry("drivers.depth_camera.freenect2", "Freenect2DepthCamera", "Freenect2DepthCameraConfig"),
    "simulated": BackendEntry("drivers.depth_camera.simulated", "SimulatedDepthCamera", "SimulatedDepthCameraConfig"),
}

__all__ = ["BACKENDS", "DepthCameraError", "make_backend"]


def make_backend(params: dict[str, Any], **extras: Any) -> DepthCamera:
    """Depth camera backend chosen by ``params["backend"]``."""
    return build_backend(DepthCamera, "depth_camera", params, BACKENDS, **extras)
