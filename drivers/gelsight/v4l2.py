"""GelSight over V4L2 through OpenCV, or a recorded tactile video played back.

The camera is found by the name its USB video driver gives it (/sys/class/video4linux/*/name);
two identical sensors (one per finger) are told apart by the USB port they are plugged in.
Exposure and white balance are fixed, because automatic control would change the gel's
shading under contact and void the background. The first frames after opening are
discarded (the sensor settles), then a no-contact background is averaged.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from drivers import call_with_deadline, requires_connection
from drivers.gelsight.base import (
    EndOfStreamError,
    GelSight,
    GelSightError,
    GelSightTimeoutError,
    SensorPreset,
    preset,
)
from msgs import Header, TactileImage

# V4L2's V4L2_CID_EXPOSURE_AUTO value for manual exposure (OpenCV passes it through).
_V4L2_EXPOSURE_MANUAL = 1


@dataclasses.dataclass
class V4L2GelSightConfig:
    """One GelSight: which camera (or video file), how to set it up, how to crop it."""

    sensor: str = "left"  # finger: left | right
    preset: str = "gelsight"  # gelsight | gelsight_mini (drivers.gelsight.base)
    device_name: str = ""  # part of the V4L2 name; default: the preset's
    usb_port: str = ""  # e.g. "1-2.3", when two cameras share a name
    device_index: int = -1  # /dev/videoN; skips the name search when >= 0
    video_file: str = ""  # play this video instead of a camera
    loop_video: bool = False
    exposure_100us: int = 150  # V4L2 exposure_absolute units (100 us); 0: camera's auto
    white_balance_k: int = 4600  # 0: camera's auto (only for cameras without the control)
    warmup_frames: int = 15
    background_frames: int = 5
    # Consecutive failed reads before the camera counts as lost; OpenCV's V4L2 backend waits
    # up to 10 s per read (OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT) before one fails, hence the deadline.
    max_failed_reads: int = 3
    # Every frame, its retries included, comes within this or the camera counts as lost.
    read_deadline_s: float = 2.0
    mm_per_px: float = 0.0  # 0: the preset's
    sysfs_root: str = "/sys/class/video4linux"


@dataclasses.dataclass(frozen=True)
class V4L2Camera:
    index: int
    name: str
    usb_port: str


def list_cameras(sysfs_root: str) -> list[V4L2Camera]:
    """Capture nodes under ``sysfs_root``, with their names and USB ports."""
    root = Path(sysfs_root)
    cameras = []
    for node in sorted(root.glob("video*"), key=lambda p: int(p.name[len("video") :] or -1)):
        # A UVC camera has a metadata node beside its capture node; only index 0 captures.
        index_file = node / "index"
        if index_file.exists() and index_file.read_text().strip() != "0":
            continue
        name = (node / "name").read_text().strip() if (node / "name").exists() else ""
        # device -> .../usbN/<port>/<port>:<config>.<interface>; the port is before the colon.
        interface = Path(os.path.realpath(node / "device")).name
        cameras.append(V4L2Camera(int(node.name[len("video") :]), name, interface.split(":")[0]))
    return cameras


def find_camera(name: str, usb_port: str, sysfs_root: str) -> V4L2Camera:
    """The one capture node whose name contains ``name`` (and on ``usb_port`` if given)."""
    if not Path(sysfs_root).is_dir():
        raise GelSightError(
            f"no V4L2 cameras at all: {sysfs_root} does not exist. Is the uvcvideo "
            "driver loaded (`modprobe uvcvideo`) and is the GelSight plugged in?"
        )
    cameras = list_cameras(sysfs_root)
    found = ", ".join(f"/dev/video{c.index} {c.name!r} (USB {c.usb_port})" for c in cameras) or "none"
    matches = [c for c in cameras if name.lower() in c.name.lower() and (not usb_port or c.usb_port == usb_port)]
    if not matches:
        where = f" on USB port {usb_port}" if usb_port else ""
        raise GelSightError(
            f"no camera named like {name!r}{where}; cameras found: {found}. "
            "Plug in the GelSight, or set device_name / usb_port / device_index."
        )
    if len(matches) > 1:
        raise GelSightError(
            f"{len(matches)} cameras named like {name!r}: {found}; set usb_port to pick this finger's sensor"
        )
    return matches[0]


class FrameSource:
    """A cv2.VideoCapture, and what to report when it stops giving frames."""

    def __init__(
        self,
        capture: cv2.VideoCapture,
        label: str,
        live: bool,
        max_failed_reads: int,
        deadline_s: float,
        loop: bool = False,
    ) -> None:
        self.capture = capture
        self.label = label
        self.live = live
        self.max_failed_reads = max_failed_reads
        self.deadline_s = deadline_s
        self.loop = loop
        self.frames_read = 0
        # Held from a read's start until OpenCV returns, late or not: a VideoCapture serves
        # one read at a time.
        self._reading = threading.Lock()

    def next_rgb(self) -> np.ndarray:
        """The next frame, HxWx3 uint8 RGB, within the deadline (GelSightTimeoutError)."""
        if not self._reading.acquire(blocking=False):
            raise GelSightTimeoutError(f"{self.label}: an earlier read past its deadline has not returned")
        return call_with_deadline(
            self._read_rgb,
            self.deadline_s,
            f"{self.label}: read a frame",
            GelSightTimeoutError,
            on_return=self._reading.release,
        )

    def _read_rgb(self) -> np.ndarray:
        attempts = self.max_failed_reads if self.live else 1
        for _ in range(attempts):
            ok, frame = self.capture.read()
            if ok:
                self.frames_read += 1
                return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        if self.live:
            raise GelSightError(
                f"{self.label} stopped delivering frames after {self.frames_read} "
                f"frames ({attempts} reads failed): check its USB cable and power"
            )
        if self.loop and self.frames_read:
            self.capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, frame = self.capture.read()
            if ok:
                self.frames_read += 1
                return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        raise EndOfStreamError(f"{self.label} ended after {self.frames_read} frames")

    def release(self) -> None:
        self.capture.release()


class V4L2GelSight(GelSight):
    """``read()`` gives the cropped, resized frame with the background captured at connect."""

    def __init__(self, config: V4L2GelSightConfig) -> None:
        self.config = config
        self._preset: SensorPreset = preset(config.preset)
        self._source: FrameSource | None = None
        self.background = np.zeros((0, 0, 3), np.uint8)
        self._seq = 0

    @property
    def mm_per_px(self) -> float:
        return self.config.mm_per_px or self._preset.mm_per_px

    def connect(self) -> None:
        self._source = self._open_video() if self.config.video_file else self._open_camera()
        try:
            for _ in range(self.config.warmup_frames):
                self._source.next_rgb()
            frames = [self._processed() for _ in range(max(1, self.config.background_frames))]
        except GelSightError:
            self.disconnect()
            raise
        self.background = np.mean(frames, axis=0).round().astype(np.uint8)

    def disconnect(self) -> None:
        if self._source is not None:
            self._source.release()
            self._source = None

    @property
    def is_connected(self) -> bool:
        return self._source is not None

    @requires_connection
    def read(self) -> TactileImage:
        """The next tactile frame (raises EndOfStreamError when a video ends)."""
        image = self._processed()
        self._seq += 1
        header = Header.now(f"gel_{self.config.sensor}")
        header.seq = self._seq
        return TactileImage(
            header=header, image=image, background=self.background, sensor=self.config.sensor, mm_per_px=self.mm_per_px
        )

    def _processed(self) -> np.ndarray:
        assert self._source is not None  # read() requires a connection
        return self._preset.crop_and_resize(self._source.next_rgb())

    def _open_video(self) -> FrameSource:
        path = self.config.video_file
        if not Path(path).is_file():
            raise GelSightError(f"tactile video {path} does not exist")
        capture = cv2.VideoCapture(path)
        if not capture.isOpened():
            raise GelSightError(
                f"OpenCV cannot decode the tactile video {path}; record it losslessly, e.g. FFV1 in an .avi"
            )
        return FrameSource(
            capture,
            f"tactile video {path}",
            live=False,
            max_failed_reads=1,
            deadline_s=self.config.read_deadline_s,
            loop=self.config.loop_video,
        )

    def _open_camera(self) -> FrameSource:
        index = self.config.device_index
        label = f"/dev/video{index}"
        if index < 0:
            camera = find_camera(
                self.config.device_name or self._preset.device_name, self.config.usb_port, self.config.sysfs_root
            )
            index, label = camera.index, f"/dev/video{camera.index} ({camera.name}, USB {camera.usb_port})"
        capture = cv2.VideoCapture(index, cv2.CAP_V4L2)
        if not capture.isOpened():
            raise GelSightError(
                f"cannot open {label} through V4L2: is another program using it, "
                "or is the user not in the 'video' group?"
            )
        settings = [
            (cv2.CAP_PROP_FRAME_WIDTH, self._preset.capture_width, "width"),
            (cv2.CAP_PROP_FRAME_HEIGHT, self._preset.capture_height, "height"),
        ]
        if self.config.exposure_100us > 0:
            settings += [
                (cv2.CAP_PROP_AUTO_EXPOSURE, _V4L2_EXPOSURE_MANUAL, "manual exposure"),
                (cv2.CAP_PROP_EXPOSURE, self.config.exposure_100us, "exposure"),
            ]
        if self.config.white_balance_k > 0:
            settings += [
                (cv2.CAP_PROP_AUTO_WB, 0, "manual white balance"),
                (cv2.CAP_PROP_WB_TEMPERATURE, self.config.white_balance_k, "white balance"),
            ]
        for prop, value, what in settings:
            if not capture.set(prop, value):
                capture.release()
                raise GelSightError(
                    f"{label} refused {what} = {value}; list what it supports with "
                    f"`v4l2-ctl -d /dev/video{index} --list-ctrls --list-formats-ext`"
                )
        return FrameSource(
            capture,
            label,
            live=True,
            max_failed_reads=self.config.max_failed_reads,
            deadline_s=self.config.read_deadline_s,
        )
