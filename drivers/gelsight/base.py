"""What every GelSight backend shares: its error, the sensor presets and the frame cropping.

A preset says which part of the camera image shows the gel (margins as fractions of the
image, so they hold at any capture resolution), the size frames are resized to, and the
gel's scale at that size.
"""

from __future__ import annotations

import abc
import dataclasses

import cv2
import numpy as np

from drivers import Device, DeviceError, DeviceNotConnectedError, DeviceTimeoutError
from msgs import TactileImage


class GelSightError(DeviceError):
    """Any failure of a GelSight backend; the message says which device and what to do."""


class GelSightTimeoutError(GelSightError, DeviceTimeoutError):
    """The camera gave no frame within the read deadline."""


class GelSightNotConnectedError(DeviceNotConnectedError, GelSightError):
    """A GelSight read before ``connect()`` or after ``disconnect()``."""


class GelSight(Device):
    """The GelSight contract: ``read()`` blocks until the next tactile frame."""

    NOT_CONNECTED = GelSightNotConnectedError

    @abc.abstractmethod
    def read(self) -> TactileImage:
        """The next frame, cropped to the gel and resized to the preset's size (RGB)."""


class EndOfStreamError(GelSightError):
    """A played-back video has no more frames."""


@dataclasses.dataclass(frozen=True)
class SensorPreset:
    """Gel area within the camera image and the output frame geometry."""

    device_name: str  # what the camera calls itself in /sys/class/video4linux/*/name
    capture_width: int  # px, asked of the camera
    capture_height: int
    margin_left: float  # fraction of the image width cut on the left
    margin_right: float
    margin_top: float  # fraction of the image height cut at the top
    margin_bottom: float
    output_width: int  # px, after crop and resize
    output_height: int
    mm_per_px: float  # gel scale at the output size

    def crop_and_resize(self, frame: np.ndarray) -> np.ndarray:
        """The gel area of ``frame`` (HxWx3), resized to the output size."""
        height, width = frame.shape[:2]
        top, bottom = round(height * self.margin_top), height - round(height * self.margin_bottom)
        left, right = round(width * self.margin_left), width - round(width * self.margin_right)
        gel = frame[top:bottom, left:right]
        if gel.shape[:2] == (self.output_height, self.output_width):
            return np.ascontiguousarray(gel)
        return cv2.resize(gel, (self.output_width, self.output_height), interpolation=cv2.INTER_AREA)


PRESETS = {
    # The sensor of the project's real frames (assets/gelsight): 4:3 camera, full frame used,
    # 160x120 output at 0.1245 mm/px (Taxim's calibration of that sensor).
    "gelsight": SensorPreset("GelSight", 640, 480, 0.0, 0.0, 0.0, 0.0, 160, 120, 0.1245),
    # GelSight Mini: its UVC camera streams 320x240 with the gel's dark rim in the outer
    # seventh of each side (as GelSight's own SDK crops it). The scale is for an 18.6 mm-wide
    # gel over the remaining 5/7 of the width, resized back to 320 px; check it with a
    # calibration target and override ``mm_per_px`` in the launch file if it differs.
    "gelsight_mini": SensorPreset("GelSight Mini", 320, 240, 1 / 7, 1 / 7, 1 / 7, 1 / 7, 320, 240, 0.0581),
}


def preset(name: str) -> SensorPreset:
    """The preset called ``name``; GelSightError listing the known ones otherwise."""
    if name not in PRESETS:
        raise GelSightError(f"unknown GelSight preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
