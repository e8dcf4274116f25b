"""Kinect v2 through libfreenect2's own Python binding (``pylibfreenect2``), for labs that
built libfreenect2 and prefer it to the OpenNI2 path. Optional: imported only when chosen.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
from typing import Any

import numpy as np

from drivers import requires_connection
from drivers.depth_camera.base import (
    Calibration,
    DepthCamera,
    DepthCameraError,
    DepthCameraTimeoutError,
    depth_image,
    load_calibration,
)
from msgs import DepthImage

PIPELINES = {
    "cpu": "CpuPacketPipeline",
    "opengl": "OpenGLPacketPipeline",
    "opencl": "OpenCLPacketPipeline",
    "cuda": "CudaPacketPipeline",
}
_INSTALL = (
    "build libfreenect2 (https://github.com/OpenKinect/libfreenect2), then "
    "`LIBFREENECT2_INSTALL_PREFIX=<its prefix> pip install 'dtx[freenect2]'`"
)


@dataclasses.dataclass
class Freenect2DepthCameraConfig:
    """Which Kinect (serial; empty: the only one), the depth decoding pipeline, the calibration."""

    name: str = "left"
    calibration_file: str = "launch/calibration/camera_left.yaml"
    serial: str = ""
    pipeline: str = "cpu"  # cpu | opengl | opencl | cuda
    read_timeout_s: float = 1.0


def _import_binding() -> Any:
    try:
        return importlib.import_module("pylibfreenect2")
    except ImportError as exc:
        raise DepthCameraError(
            f"the freenect2 backend needs pylibfreenect2, which is not installed "
            f"({exc}): {_INSTALL}; or use backend: openni2"
        ) from exc


class Freenect2DepthCamera(DepthCamera):
    """``read()`` gives uint16 millimetre frames (512x424) with the calibration."""

    def __init__(self, config: Freenect2DepthCameraConfig) -> None:
        if config.pipeline not in PIPELINES:
            raise DepthCameraError(f"unknown pipeline {config.pipeline!r}; choose from {sorted(PIPELINES)}")
        self.config = config
        self.calibration: Calibration | None = None
        self._lib: Any = None
        self._device: Any = None
        self._listener: Any = None
        self._seq = 0

    def connect(self) -> None:
        self.calibration = load_calibration(self.config.calibration_file)
        self._lib = lib = _import_binding()
        freenect = lib.Freenect2()
        serials = [freenect.getDeviceSerialNumber(i) for i in range(freenect.enumerateDevices())]
        wanted = self.config.serial.encode()
        matches = [s for s in serials if wanted in s]
        if len(matches) != 1:
            raise DepthCameraError(
                f"{'no' if not matches else len(matches)} Kinect v2 "
                f"{'with serial ' + self.config.serial + ' ' if wanted else ''}found by "
                f"libfreenect2; serials: {[s.decode() for s in serials] or 'none'}. "
                "Connect it to a USB 3 port; with several, set serial."
            )
        pipeline = getattr(lib, PIPELINES[self.config.pipeline])()
        self._device = freenect.openDevice(matches[0], pipeline=pipeline)
        self._listener = lib.SyncMultiFrameListener(lib.FrameType.Depth)
        self._device.setIrAndDepthFrameListener(self._listener)
        self._device.startStreams(rgb=False, depth=True)

    def disconnect(self) -> None:
        if self._device is not None:
            self._device.stop()
            self._device.close()
            self._device = None

    @property
    def is_connected(self) -> bool:
        return self._device is not None and self.calibration is not None

    @requires_connection
    def read(self) -> DepthImage:
        """The next depth frame; DepthCameraTimeoutError when none comes within ``read_timeout_s``."""
        calibration = self.calibration
        assert calibration is not None  # requires_connection
        # Poll rather than block: the binding's waitForNewFrame() has no time-out.
        deadline = time.monotonic() + self.config.read_timeout_s
        while not self._listener.hasNewFrame():
            if time.monotonic() > deadline:
                raise DepthCameraTimeoutError(
                    f"no depth frame from Kinect {self.config.serial or '(any)'} "
                    f"within {self.config.read_timeout_s} s: was it unplugged?"
                )
            time.sleep(0.002)
        frames = self._listener.waitForNewFrame()
        try:
            # libfreenect2 gives float32 millimetres, 0 where there is no return.
            depth_mm = np.rint(frames["depth"].asarray(np.float32)).astype(np.uint16)
        finally:
            self._listener.release(frames)
        self._seq += 1
        return depth_image(depth_mm, calibration, self.config.name, self._seq)
