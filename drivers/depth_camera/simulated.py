"""Simulated Kinect v2: ray casting of a scene (``sim.world.SimWorld``) with the scene's
depth effects, delivered like the real camera (uint16 millimetres, 0 = no return) or as
float32 metres (NaN = no return).

The reported ``camera_to_world`` is the nominal extrinsic of the scene; when the scene calls
for ``extrinsic_offset`` the rays are cast from the true (offset) pose, as with a camera
whose calibration is slightly wrong. With ``calibration_dir`` the camera reports the extrinsic
of ``<calibration_dir>/camera_<camera>.yaml`` instead (e.g. one ``dtx calibrate touches``
wrote), as a real camera reports its calibration file's; the file must describe this camera.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivers import requires_connection
from drivers.depth_camera.base import DepthCamera, DepthCameraError, load_calibration_of
from msgs import CameraIntrinsics, DepthImage, Header
from workcell.scene import SceneError

if TYPE_CHECKING:
    from sim.world import SimWorld

__all__ = ["SimulatedDepthCamera", "SimulatedDepthCameraConfig", "DepthCameraError"]

OUTPUTS = ("uint16_mm", "float32_m")


@dataclasses.dataclass
class SimulatedDepthCameraConfig:
    scene: str = "scenes/ycb_three.yaml"
    camera: str = "left"
    seed: int | None = None  # default: the scene's seed
    rate_hz: float = 30.0  # Kinect v2 depth frame rate
    pace: bool = True  # read() waits for the next frame time, like the real camera
    output: str = "uint16_mm"
    calibration_dir: str = ""  # empty: the scene's nominal extrinsic

    def __post_init__(self) -> None:
        if self.output not in OUTPUTS:
            raise ValueError(f"output {self.output!r} not one of {OUTPUTS}")
        if not (np.isfinite(self.rate_hz) and 0.0 < self.rate_hz <= 1000.0):
            raise ValueError(f"rate_hz {self.rate_hz} outside (0, 1000]")


class SimulatedDepthCamera(DepthCamera):
    def __init__(self, config: SimulatedDepthCameraConfig):
        self.config = config
        self.world: SimWorld | None = None
        self._seq = 0
        self._next_t = 0.0

    def connect(self) -> None:
        from sim.world import shared_world  # noqa: PLC0415 - Open3D loads on connect

        try:
            world = shared_world(self.config.scene, self.config.seed)
        except SceneError as exc:
            raise DepthCameraError(str(exc)) from exc
        if self.config.camera not in world.cameras:
            raise DepthCameraError(
                f"scene {self.config.scene} has no camera {self.config.camera!r} (cameras: {world.camera_names()})"
            )
        spec = world.cameras[self.config.camera].spec
        self.intrinsics = CameraIntrinsics(
            width=spec.width, height=spec.height, fx=spec.fx, fy=spec.fy, cx=spec.cx, cy=spec.cy, distortion=[0.0] * 5
        )
        self.camera_to_world = self._camera_to_world(world)
        self._next_t = time.monotonic()
        self.world = world

    def _camera_to_world(self, world: SimWorld) -> np.ndarray:
        """The nominal extrinsic, or the calibration file's after checking it is this camera's."""
        if not self.config.calibration_dir:
            return world.nominal_camera_to_world(self.config.camera)
        path = Path(self.config.calibration_dir) / f"camera_{self.config.camera}.yaml"
        calibration = load_calibration_of(str(path), self.intrinsics, f"{self.config.camera!r} of {self.config.scene}")
        if calibration.camera not in (self.config.camera, f"camera_{self.config.camera}"):
            raise DepthCameraError(f"{path} is for camera {calibration.camera!r}, not {self.config.camera!r}")
        return calibration.camera_to_world

    def disconnect(self) -> None:
        self.world = None

    @property
    def is_connected(self) -> bool:
        return self.world is not None

    @requires_connection
    def read(self) -> DepthImage:
        if self.config.pace:
            now = time.monotonic()
            if self._next_t > now:
                time.sleep(self._next_t - now)
            self._next_t = max(self._next_t, now) + 1.0 / self.config.rate_hz
        assert self.world is not None  # requires_connection
        z = self.world.render_depth(self.config.camera)
        if self.config.output == "uint16_mm":
            mm = np.rint(np.nan_to_num(z, nan=0.0) * 1000.0)
            depth = np.clip(mm, 0, 65535).astype(np.uint16)
        else:
            depth = z.astype(np.float32, copy=False)
        self._seq += 1
        header = Header(stamp_ns=time.time_ns(), seq=self._seq, frame_id=f"camera_{self.config.camera}")
        return DepthImage(
            header=header, depth=depth, intrinsics=self.intrinsics, camera_to_world=self.camera_to_world.copy()
        )
