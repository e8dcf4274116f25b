"""What every depth camera backend shares: its error, the calibration file, the frame.

A calibration file (YAML) holds the depth camera's intrinsics (pixels) and its pose in the
world frame (4x4, metres), as an extrinsic calibration of the lab produces them:

    camera: left
    image_size: [512, 424]          # width, height (px)
    intrinsics: {fx: 365.5, fy: 365.5, cx: 254.9, cy: 205.4,
                 distortion: [0.09, -0.27, 0.0, 0.0, 0.09]}   # k1 k2 p1 p2 k3
    camera_to_world: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""

from __future__ import annotations

import abc
import dataclasses
from pathlib import Path

import numpy as np
import yaml

from drivers import Device, DeviceError, DeviceNotConnectedError, DeviceTimeoutError
from msgs import CameraIntrinsics, DepthImage, Header


class DepthCameraError(DeviceError):
    """Any failure of a depth camera backend; the message says what is missing and what to do."""


class DepthCameraTimeoutError(DepthCameraError, DeviceTimeoutError):
    """No frame came within the read deadline."""


class DepthCameraNotConnectedError(DeviceNotConnectedError, DepthCameraError):
    """A depth camera read before ``connect()`` or after ``disconnect()``."""


class DepthCamera(Device):
    """The depth camera contract: ``read()`` blocks until the next frame."""

    NOT_CONNECTED = DepthCameraNotConnectedError

    @abc.abstractmethod
    def read(self) -> DepthImage:
        """The next depth frame (metres, camera optical frame) with the calibrated extrinsics."""


@dataclasses.dataclass
class Calibration:
    camera: str
    intrinsics: CameraIntrinsics
    camera_to_world: np.ndarray  # 4x4, metres


def load_calibration(path: str) -> Calibration:
    """Read and check a calibration file; DepthCameraError naming the file and the problem."""
    file = Path(path)
    if not file.is_file():
        raise DepthCameraError(
            f"calibration file {path} does not exist; copy one from "
            "launch/calibration/ and fill in your camera's values"
        )
    try:
        data = yaml.safe_load(file.read_text())
        width, height = (int(v) for v in data["image_size"])
        k = data["intrinsics"]
        intrinsics = CameraIntrinsics(
            width=width,
            height=height,
            fx=float(k["fx"]),
            fy=float(k["fy"]),
            cx=float(k["cx"]),
            cy=float(k["cy"]),
            distortion=[float(v) for v in k.get("distortion", [0.0] * 5)],
        )
        pose = np.array(data["camera_to_world"], dtype=np.float64)
        camera = str(data.get("camera", file.stem))
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise DepthCameraError(
            f"calibration file {path} is malformed ({exc!r}); expected the layout "
            "documented in drivers/depth_camera/base.py"
        ) from exc
    _check(path, intrinsics, pose)
    return Calibration(camera, intrinsics, pose)


def _check(path: str, intrinsics: CameraIntrinsics, pose: np.ndarray) -> None:
    if min(intrinsics.fx, intrinsics.fy, intrinsics.width, intrinsics.height) <= 0:
        raise DepthCameraError(f"{path}: focal lengths and image size must be positive")
    if len(intrinsics.distortion) != 5:
        raise DepthCameraError(f"{path}: distortion needs 5 values (k1 k2 p1 p2 k3)")
    if pose.shape != (4, 4):
        raise DepthCameraError(f"{path}: camera_to_world must be 4x4, got {pose.shape}")
    rotation = pose[:3, :3]
    rigid = (
        np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
        and np.isclose(np.linalg.det(rotation), 1.0, atol=1e-4)
        and np.allclose(pose[3], [0, 0, 0, 1])
    )
    if not rigid:
        raise DepthCameraError(
            f"{path}: camera_to_world is not a rigid transform "
            "(rotation must be orthonormal with det +1, last row 0 0 0 1)"
        )


def load_calibration_of(path: str, intrinsics: CameraIntrinsics, camera: str) -> Calibration:
    """:func:`load_calibration`, refused unless the file describes ``camera``: a camera of the
    same image size and intrinsics (DepthCameraError naming what differs)."""
    calibration = load_calibration(path)
    differ = [
        name
        for name in ("width", "height", "fx", "fy", "cx", "cy")
        if not np.isclose(getattr(calibration.intrinsics, name), getattr(intrinsics, name), rtol=1e-6, atol=1e-6)
    ]
    if differ:
        raise DepthCameraError(f"{path} describes another camera than {camera}: {', '.join(differ)} differ")
    return calibration


def calibration_yaml(calibration: Calibration, comment: str) -> str:
    """A calibration as the file :func:`load_calibration` reads, with ``comment`` on top."""
    k = calibration.intrinsics
    data = {
        "camera": calibration.camera,
        "image_size": [int(k.width), int(k.height)],
        "intrinsics": {
            "fx": float(k.fx),
            "fy": float(k.fy),
            "cx": float(k.cx),
            "cy": float(k.cy),
            "distortion": [float(v) for v in k.distortion],
        },
        "camera_to_world": [[float(v) for v in row] for row in np.asarray(calibration.camera_to_world)],
    }
    lines = "".join(f"# {line}\n" for line in comment.splitlines())
    return lines + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


def depth_image(depth_mm: np.ndarray, calibration: Calibration, camera_name: str, seq: int) -> DepthImage:
    """Wrap an HxW uint16 millimetre frame (0 = no return) with its calibration."""
    expected = (calibration.intrinsics.height, calibration.intrinsics.width)
    if depth_mm.shape != expected:
        raise DepthCameraError(
            f"camera {camera_name} sends {depth_mm.shape[1]}x{depth_mm.shape[0]} "
            f"frames but its calibration is for {expected[1]}x{expected[0]}"
        )
    header = Header.now(f"camera_{camera_name}")
    header.seq = seq
    return DepthImage(
        header=header,
        depth=depth_mm.astype(np.uint16, copy=False),
        intrinsics=calibration.intrinsics,
        camera_to_world=calibration.camera_to_world,
    )
