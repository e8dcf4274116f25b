"""Kinect v2 (or any OpenNI2 depth camera) through the ``openni`` package and libOpenNI2.

A Kinect v2 reaches OpenNI2 through libfreenect2's OpenNI2 driver (libfreenect2-openni2.so
in the library's OpenNI2/Drivers directory); its device URIs carry the serial number, which
is how two Kinects are told apart. An ``.oni`` recording plays back through the same path.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from openni import openni2
from openni.utils import InitializationError, OpenNIError

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


@dataclasses.dataclass
class OpenNI2DepthCameraConfig:
    """Which device (URI, serial or recording), its depth mode, and its calibration."""

    name: str = "left"  # frame id camera_<name>
    calibration_file: str = "launch/calibration/camera_left.yaml"
    uri: str = ""  # exact OpenNI2 URI; empty: pick by serial
    serial: str = ""  # part of the URI; empty: the only device present
    oni_file: str = ""  # play this recording instead of a device
    library_dir: str = "/usr/lib/x86_64-linux-gnu"
    width: int = 512  # Kinect v2 depth: 512x424 px at 30 Hz
    height: int = 424
    fps: int = 30
    registration: bool = False  # map depth onto the colour camera (then calibrate that one)
    read_timeout_s: float = 1.0


def load_openni2(library_dir: str) -> None:
    """Start libOpenNI2 from ``library_dir``; it stays loaded for the rest of the process."""
    directory = Path(library_dir)
    has_development_link = (directory / "libOpenNI2.so").is_file()
    if not has_development_link and not (directory / "libOpenNI2.so.0").is_file():
        raise DepthCameraError(
            f"OpenNI2 library not found in {directory} (no libOpenNI2.so or "
            "libOpenNI2.so.0): install it with `sudo apt-get install libopenni2-0`, "
            "or set library_dir to the directory that holds it"
        )
    if openni2.is_initialized():
        return
    load_from = directory if has_development_link else _loader_directory(directory)
    try:
        openni2.initialize(str(load_from))
    except (InitializationError, OpenNIError) as exc:
        raise DepthCameraError(
            f"OpenNI2 in {directory} failed to start: {exc}. Its drivers must be in {directory / 'OpenNI2' / 'Drivers'}"
        ) from exc


def _loader_directory(directory: Path) -> Path:
    """A directory the ``openni`` loader accepts, pointing at Debian's runtime library.

    The loader only looks for ``libOpenNI2.so`` (the development link Debian ships in
    libopenni2-dev), and libOpenNI2 finds its drivers relative to the path it was loaded
    from; so both are linked here. Links are replaced atomically: cameras start in parallel.
    """
    shim = Path(tempfile.gettempdir()) / f"dtx-openni2-{os.getuid()}"
    (shim / "OpenNI2").mkdir(parents=True, exist_ok=True)
    for link, target in (
        (shim / "libOpenNI2.so", directory / "libOpenNI2.so.0"),
        (shim / "OpenNI2" / "Drivers", directory / "OpenNI2" / "Drivers"),
    ):
        staged = link.with_name(f"{link.name}.{os.getpid()}")
        staged.unlink(missing_ok=True)
        staged.symlink_to(target)
        os.replace(staged, link)
    return shim


def _drivers_present(library_dir: str) -> str:
    drivers = Path(library_dir) / "OpenNI2" / "Drivers"
    names = sorted(p.name for p in drivers.glob("lib*.so*")) if drivers.is_dir() else []
    return f"{drivers} holds {names or 'nothing'}"


def _mode_key(mode: openni2.VideoMode) -> tuple[int, int, int, int]:
    return (mode.resolutionX, mode.resolutionY, mode.fps, mode.pixelFormat)


def _mode_text(mode: openni2.VideoMode) -> str:
    pixel_format = str(mode.pixelFormat).rsplit(".", 1)[-1]
    return f"{mode.resolutionX}x{mode.resolutionY}@{mode.fps} {pixel_format}"


class OpenNI2DepthCamera(DepthCamera):
    """``read()`` gives uint16 millimetre frames in ``camera_<name>`` with the calibration."""

    def __init__(self, config: OpenNI2DepthCameraConfig) -> None:
        self.config = config
        self.calibration: Calibration | None = None
        self._device: openni2.Device | None = None
        self._stream: openni2.VideoStream | None = None
        self._label = config.oni_file or config.uri or f"serial {config.serial or '(any)'}"
        self._seq = 0

    def connect(self) -> None:
        self.calibration = load_calibration(self.config.calibration_file)
        load_openni2(self.config.library_dir)
        self._device = self._open_device()
        try:
            self._start_depth_stream(self._device)
        except (DepthCameraError, OpenNIError) as exc:
            self.disconnect()
            if isinstance(exc, DepthCameraError):
                raise
            raise DepthCameraError(f"{self._label}: starting the depth stream failed: {exc}") from exc

    def disconnect(self) -> None:
        if self._stream is not None:
            self._stream.stop()
            self._stream.close()
            self._stream = None
            # A driver's frame thread may deliver one more frame after stop(); closing the
            # device under it crashes libOpenNI2 (seen with its Dummy driver). Two frame
            # periods let it finish.
            time.sleep(2.0 / self.config.fps)
        if self._device is not None:
            self._device.close()
            self._device = None

    @property
    def is_connected(self) -> bool:
        return self._stream is not None and self.calibration is not None

    @requires_connection
    def read(self) -> DepthImage:
        """The next depth frame; DepthCameraTimeoutError when none comes within ``read_timeout_s``."""
        stream, calibration = self._stream, self.calibration
        assert stream is not None and calibration is not None  # requires_connection
        try:
            ready = openni2.wait_for_any_stream([stream], self.config.read_timeout_s)
            frame = stream.read_frame() if ready is not None else None
        except OpenNIError as exc:
            raise DepthCameraError(f"{self._label} failed after {self._seq} frames: {exc}") from exc
        if frame is None:
            if self.config.oni_file:
                raise DepthCameraTimeoutError(
                    f"recording {self.config.oni_file} gave no frame within "
                    f"{self.config.read_timeout_s} s after {self._seq} of its "
                    f"{stream.get_number_of_frames()} frames"
                )
            raise DepthCameraTimeoutError(
                f"no depth frame from {self._label} within {self.config.read_timeout_s} s "
                f"after {self._seq} frames: was the camera unplugged?"
            )
        try:
            depth = np.frombuffer(frame.get_buffer_as_uint16(), np.uint16)
            depth = depth.reshape(frame.height, frame.width).copy()
        finally:
            frame.close()
        self._seq += 1
        return depth_image(depth, calibration, self.config.name, self._seq)

    def _open_device(self) -> openni2.Device:
        config = self.config
        if config.oni_file:
            if not Path(config.oni_file).is_file():
                raise DepthCameraError(f"recording {config.oni_file} does not exist")
            device = openni2.Device.open_file(config.oni_file.encode())
            device.playback.repeat = False
            return device
        uris = [uri.decode() for uri in openni2.Device.enumerate_uris()]
        uri = config.uri
        if not uri:
            matches = [found for found in uris if config.serial in found]
            if len(matches) != 1:
                wanted = f"with serial {config.serial!r} " if config.serial else ""
                problem = "no" if not matches else f"{len(matches)}"
                raise DepthCameraError(
                    f"{problem} OpenNI2 depth camera {wanted}found; devices: {uris or 'none'}. "
                    "Connect the Kinect v2 to a USB 3 port (`lsusb` shows 045e:02c4 or 02d8) and "
                    "install libfreenect2's OpenNI2 driver (libfreenect2-openni2.so); "
                    f"{_drivers_present(config.library_dir)}. With several cameras, set serial."
                )
            uri = matches[0]
        try:
            return openni2.Device(uri.encode())
        except OpenNIError as exc:
            raise DepthCameraError(
                f"cannot open OpenNI2 device {uri!r}: {exc}; devices found: "
                f"{uris or 'none'}; {_drivers_present(config.library_dir)}"
            ) from exc

    def _start_depth_stream(self, device: openni2.Device) -> None:
        assert self.calibration is not None
        stream = device.create_depth_stream()
        if stream is None:
            raise DepthCameraError(f"{self._label} has no depth sensor")
        # Held at once so that disconnect() destroys it before the device, also on failure:
        # libOpenNI2 crashes when a stream outlives its device.
        self._stream = stream
        if not self.config.oni_file:
            self._set_mode(device, stream)
        mode = stream.get_video_mode()
        if mode.pixelFormat != openni2.PIXEL_FORMAT_DEPTH_1_MM:
            raise DepthCameraError(
                f"{self._label} gives {_mode_text(mode)}; only millimetre depth (PIXEL_FORMAT_DEPTH_1_MM) is supported"
            )
        calibrated = (self.calibration.intrinsics.width, self.calibration.intrinsics.height)
        if (mode.resolutionX, mode.resolutionY) != calibrated:
            raise DepthCameraError(
                f"{self._label} gives {_mode_text(mode)} but its calibration "
                f"({self.config.calibration_file}) is for {calibrated[0]}x{calibrated[1]}"
            )
        stream.start()

    def _set_mode(self, device: openni2.Device, stream: openni2.VideoStream) -> None:
        config = self.config
        wanted = (config.width, config.height, config.fps, openni2.PIXEL_FORMAT_DEPTH_1_MM)
        modes = device.get_sensor_info(openni2.SENSOR_DEPTH).videoModes
        if wanted not in [_mode_key(m) for m in modes]:
            raise DepthCameraError(
                f"{self._label} has no depth mode {config.width}x{config.height}@{config.fps} "
                f"in millimetres; it offers: {[_mode_text(m) for m in modes]}"
            )
        # Only change the mode when needed: some drivers refuse even setting the current one.
        if _mode_key(stream.get_video_mode()) != wanted:
            stream.set_video_mode(modes[[_mode_key(m) for m in modes].index(wanted)])
        if config.registration:
            registration = openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR
            if not device.is_image_registration_mode_supported(registration):
                raise DepthCameraError(f"{self._label} cannot register depth to colour; set registration: false")
            device.set_image_registration_mode(registration)
