"""Image helpers for a dataset's tactile images: the background-subtracted copy, resizing to
the dataset's size and the deformation strength read from the copy."""

from __future__ import annotations

import cv2
import numpy as np

from dataset.records import DatasetError

_DIFF_OFFSET = 128


def subtract_background(image_rgb: np.ndarray, background_rgb: np.ndarray) -> np.ndarray:
    """The background-subtracted copy stored beside each image: image - background + 128,
    clipped to uint8, so that no change reads as mid-grey and the file stays viewable."""
    image = check_rgb(image_rgb, "image")
    background = check_rgb(background_rgb, "background")
    if image.shape != background.shape:
        raise DatasetError(f"image {image.shape} and background {background.shape} differ in shape")
    diff = image.astype(np.int16) - background.astype(np.int16) + _DIFF_OFFSET
    return np.clip(diff, 0, 255).astype(np.uint8)


def resize_rgb(image_rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """An H x W x 3 image at ``height`` x ``width``: area-averaged when it shrinks (no aliasing
    of the gel's fine shading), bilinear when it grows; the same array when the size is right."""
    if image_rgb.shape[:2] == (height, width):
        return image_rgb
    shrink = image_rgb.shape[0] > height
    return cv2.resize(
        np.ascontiguousarray(image_rgb), (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    )


def deformation_map(tactile_diff_rgb: np.ndarray) -> np.ndarray:
    """Per-pixel deformation strength (H x W float32): summed |change| over RGB from the
    background-subtracted copy."""
    diff = check_rgb(tactile_diff_rgb, "tactile_diff").astype(np.float32) - _DIFF_OFFSET
    return np.abs(diff).sum(axis=2)


def check_rgb(array: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(array)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
        raise DatasetError(f"{name} must be H x W x 3 uint8 RGB, got {array.shape} {array.dtype}")
    return array
