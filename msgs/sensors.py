"""Sensor streams: depth images, point clouds, tactile images."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class CameraIntrinsics:
    """Pinhole intrinsics in pixels and Brown-Conrady distortion (k1, k2, p1, p2, k3)."""

    width: int = 512
    height: int = 424
    fx: float = 365.5
    fy: float = 365.5
    cx: float = 254.9
    cy: float = 205.4
    distortion: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 5)


@dataclasses.dataclass
class DepthImage(Message):
    """One depth frame in frame ``camera_<name>`` (z forward, x right, y down).

    ``depth`` is HxW, either uint16 millimetres (0 = no return, as the Kinect sends it) or
    float32 metres (NaN = no return). ``intrinsics`` are the camera's; ``camera_to_world`` is
    the 4x4 extrinsic the driver was configured with (row-major, metres).
    """

    SCHEMA = "dtx.sensors.DepthImage"
    VERSION = 1

    depth: np.ndarray = empty((0, 0), np.uint16)
    intrinsics: CameraIntrinsics = dataclasses.field(default_factory=CameraIntrinsics)
    camera_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))

    def depth_m(self) -> np.ndarray:
        """Depth in metres, float32, NaN where there is no return."""
        if self.depth.dtype == np.uint16:
            out = self.depth.astype(np.float32) * 1e-3
            out[self.depth == 0] = np.nan
            return out
        return self.depth.astype(np.float32, copy=False)


@dataclasses.dataclass
class PointCloud(Message):
    """Nx3 points (metres) in ``header.frame_id``; optional Nx3 uint8 colours."""

    SCHEMA = "dtx.sensors.PointCloud"
    VERSION = 1

    points: np.ndarray = empty((0, 3), np.float32)
    colors: np.ndarray = empty((0, 3), np.uint8)


@dataclasses.dataclass
class TactileImage(Message):
    """One GelSight frame (HxWx3 uint8 RGB) from ``sensor`` (``left`` or ``right``).

    ``background`` is the no-contact frame captured at start (same shape) so a consumer can
    form the background-subtracted image; ``mm_per_px`` is the gel's scale.
    """

    SCHEMA = "dtx.sensors.TactileImage"
    VERSION = 1

    image: np.ndarray = empty((0, 0, 3), np.uint8)
    background: np.ndarray = empty((0, 0, 3), np.uint8)
    sensor: str = ""
    mm_per_px: float = 0.0
