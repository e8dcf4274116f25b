"""The calibrated GelSight renderer as a physics prior that the network corrects.

Learning alone (the paper) must find what a contact looks like from a few objects' experience;
physics alone (Taxim; ``sim.gelsight``) draws any contact but knows only what the depth-map
holds and nothing of the sensor it was not calibrated for. A generator trained with a prior
(``GeneratorConfig.prior``) is given, beside the depth-map, the renderer's image of that same
depth-map (``sim.gelsight.render_depth_maps``, no sensor effects) and starts from it: its output
is that image plus what the network adds (models/networks.py), so it learns the correction —
what the registration's offset, the surface relief and the sensor do to the ideal image.

The prior is fixed by the scene whose GelSight it renders and the crop the depth-maps cover;
a checkpoint stores both (``PriorSpec``), so serving renders exactly what training rendered.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any

import cv2
import numpy as np
import torch

from dataset.images import resize_rgb
from models.errors import ModelConfigError
from models.prior_tensor import TensorPrior
from sim.gelsight import (
    MAX_RENDERED_PIXELS,
    GelSightRenderError,
    checked_depth_maps,
    render_depth_maps,
    scene_renderer,
)
from workcell.scene import Scene, SceneError, load_scene


def area_matrix(source: int, target: int) -> np.ndarray:
    """OpenCV's INTER_AREA resize of one axis from ``source`` to ``target`` pixels (as
    dataset.images.resize_rgb shrinks an image) as a target x source float32 matrix: the resize
    of each unit vector. It is separable, so an image's is rows @ image @ cols.T."""
    return cv2.resize(np.eye(source), (source, target), interpolation=cv2.INTER_AREA).astype(np.float32)


# Largest in-plane pose uncertainty (mm, one sigma) the prior blurs over: a quarter of the 19.9 mm
# sensed width; beyond it a contact is spread over the whole field and no longer has a place. The
# blur's cost grows with it: an image at 5 mm takes 2.2 ms at 100 x 100 and 30 ms at 256 x 256
# (0.7 and 3.3 ms sharp); 1e5 mm took seconds at 32 x 32.
MAX_POSE_SIGMA_MM = 5.0


def checked_pose_sigma_mm(value: float, name: str = "pose_sigma_mm") -> float:
    """``value`` as a float when it is a real number of mm in [0, MAX_POSE_SIGMA_MM];
    ModelConfigError naming ``name`` otherwise (NaN, inf, bool, text)."""
    number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not (number and 0 <= value <= MAX_POSE_SIGMA_MM):
        raise ModelConfigError(f"{name} must be a finite number of mm in [0, {MAX_POSE_SIGMA_MM:g}], got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class PriorSpec:
    """What a prior renders with: the scene's GelSight, the depth-maps' crop (x, y, z m), and
    the in-plane pose uncertainty (mm, one standard deviation per axis) of the depth-maps it is
    asked about by default: the registration's, for a model trained on a collected session."""

    scene: str
    depth_crop_m: tuple[float, float, float]
    pose_sigma_mm: float = 0.0
    drawn_at: str = "grid"  # PRIOR_DRAWN_AT; a checkpoint that names none was drawn at its grid
    drawn_rows: int = 0  # drawn at the sensor: the rows of square pixels over its field (0: its own)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scene": self.scene,
            "depth_crop_m": list(self.depth_crop_m),
            "pose_sigma_mm": self.pose_sigma_mm,
            "drawn_at": self.drawn_at,
            "drawn_rows": self.drawn_rows,
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> "PriorSpec":
        try:
            crop = tuple(float(v) for v in data["depth_crop_m"])
            return PriorSpec(
                scene=str(data["scene"]),
                depth_crop_m=crop,  # type: ignore[arg-type]
                pose_sigma_mm=float(data.get("pose_sigma_mm", 0.0)),
                drawn_at=str(data.get("drawn_at", "grid")),
                drawn_rows=int(data.get("drawn_rows", 0)),
            )
        except (KeyError, TypeError, ValueError, OverflowError) as err:
            raise ModelConfigError(f"a physics prior needs a scene and a 3-value depth_crop_m, got {data!r}") from err


# Where the prior's renderer draws an image: "grid", at the model's image size (the field's
# pixels 0.2 x 0.15 mm on the default 100 x 100), or "sensor", over the GelSight's field on square
# pixels (its own 0.12 mm ones, or ``drawn_rows`` of them), area-averaged to the grid as every
# target image is (dataset.images.resize_rgb). On the 30 real presses of a 2 mm ball, window SSIM
# 0.883 at the grid, 0.888 at the sensor's 120 x 160 and 0.888 at 84 x 112 (0.18 mm), half the
# sensor's pixels and half their cost (docs/measurements.md).
PRIOR_DRAWN_AT = ("grid", "sensor")


def sensor_pixels(scene: Scene, rows: int) -> tuple[int, int] | None:
    """The (rows, columns) of square pixels that cover ``scene``'s GelSight field in ``rows``
    rows, or None for 0 (its own pixels); ModelConfigError where ``rows`` is not an integer of at
    most the sensor's rows (and at least 3) that divides its field into whole columns too."""
    height, width = scene.gelsight.image_height, scene.gelsight.image_width
    step = height // math.gcd(height, width)  # rows whose columns are whole
    integer = isinstance(rows, (int, np.integer)) and not isinstance(rows, bool)
    if integer and rows == 0:
        return None
    if not (integer and 3 <= rows <= height and rows % step == 0):
        raise ModelConfigError(
            f"the prior's drawn rows must be 0 (the sensor's own {height} x {width}) or a multiple of {step} "
            f"from 3 to {height} (square pixels in whole columns), got {rows!r}"
        )
    return int(rows), int(rows) * width // height


# An 8-bit level in the network's image units, as the CPU computes it from the uint8 image.
IMAGE_UNITS = torch.from_numpy(np.arange(256, dtype=np.uint8).astype(np.float32) / 127.5 - 1.0)


class PhysicsPrior:
    """Renders depth-maps into the prior's images at the model's grid (``size`` x ``size``)."""

    def __init__(self, spec: PriorSpec, size: int) -> None:
        """``spec.depth_crop_m`` three finite positive extents (m), ``size`` an image side the
        renderer draws (an integer in [3, 4096]); otherwise ModelConfigError naming it."""
        crop = spec.depth_crop_m
        if len(crop) != 3 or not all(
            isinstance(v, (int, float, np.integer, np.floating)) and 0 < v < np.inf for v in crop
        ):
            raise ModelConfigError(f"the prior's depth crop must be three positive extents in m, got {crop}")
        if not (isinstance(size, (int, np.integer)) and not isinstance(size, bool) and 3 <= size <= 4096):
            raise ModelConfigError(f"the prior's image size must be an integer in [3, 4096], got {size!r}")
        try:
            scene = load_scene(spec.scene)
        except (SceneError, OSError) as err:
            raise ModelConfigError(f"the physics prior's scene {spec.scene}: {err}") from err
        checked_pose_sigma_mm(spec.pose_sigma_mm, "the prior's pose_sigma_mm")
        if spec.drawn_at not in PRIOR_DRAWN_AT:
            raise ModelConfigError(f"the prior is drawn at one of {PRIOR_DRAWN_AT}, got {spec.drawn_at!r}")
        if spec.drawn_at == "grid" and spec.drawn_rows:
            raise ModelConfigError(f"the prior's drawn rows ({spec.drawn_rows}) draw the sensor's field, not the grid")
        self.spec = spec
        self.size = int(size)
        drawn = (size, size) if spec.drawn_at == "grid" else sensor_pixels(scene, spec.drawn_rows)
        self.renderer = scene_renderer(scene, size=drawn, effects=False)
        self.device = "cpu"
        self._tensor: TensorPrior | None = None
        self._image_units = IMAGE_UNITS  # on the prior's device
        self._area: tuple[torch.Tensor, torch.Tensor] | None = None  # the tensor form's (on)

    def on(self, device: str) -> "PhysicsPrior":
        """This prior drawing on ``device``: "cpu" with the renderer's own NumPy and OpenCV
        (the images training and ``dtx evaluate`` see), "cuda" as batched tensor operations
        (models.prior_tensor, within its stated tolerance of those). ModelConfigError for a
        renderer the tensor form does not cover."""
        moved = copy.copy(self)
        moved.device = device
        moved._tensor = None if device == "cpu" else TensorPrior(self.renderer, self._crop_xz_m, device)
        moved._image_units = IMAGE_UNITS.to(device)
        # The area average to the grid as (rows, cols) matrices, where the renderer draws more pixels.
        height, width = self.renderer.config.shape
        moved._area = (
            None
            if (height, width) == (self.size, self.size)
            else (
                torch.from_numpy(area_matrix(height, self.size)).to(device),
                torch.from_numpy(area_matrix(width, self.size)).to(device),
            )
        )
        return moved

    @property
    def _crop_xz_m(self) -> tuple[float, float]:
        return (self.spec.depth_crop_m[0], self.spec.depth_crop_m[2])

    def images(self, depth_maps_m: np.ndarray, pose_sigma_mm: float | None = None) -> np.ndarray:
        """N x size x size x 3 uint8: the renderer's image of each depth-map (m) (drawn at
        ``spec.drawn_at``, PRIOR_DRAWN_AT), expected over
        an in-plane pose error of ``pose_sigma_mm`` (default: the spec's). A contact seen
        through a registration a millimetre off is a millimetre off in the image, while the
        sensor's background stays where it is; so the expected image is the background plus the
        contact's change blurred by the offsets' Gaussian (the rendering is shift invariant away
        from the field's edge): a sharp contact is drawn only where its place is known.

        Contract: ``depth_maps_m`` as ``sim.gelsight.render_depth_maps`` takes them (N >= 0 real
        float maps: none give none), ``pose_sigma_mm`` as :func:`checked_pose_sigma_mm`;
        otherwise ModelConfigError naming the argument, before anything is drawn. A NaN bin is
        an empty one, as models.data.depth_input reads it: nothing there, drawn exactly as +inf
        and any gap past sim.gelsight.GAP_LIMIT_MM are, here and in the tensor form (the renderer samples
        each pixel's gap bilinearly, so an empty bin beside a press clears the contact up to a
        bin from its centre, as +inf does)."""
        sigma_mm = self._sigma_mm(pose_sigma_mm)
        if self._tensor is not None:
            levels = self._levels_on_device(self._tensor, depth_maps_m, sigma_mm)
            return levels.to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        maps = np.asarray(depth_maps_m)
        pressed = self._pressed(maps)
        try:
            drawn = render_depth_maps(
                self.renderer,
                maps if isinstance(pressed, slice) else maps[pressed],
                self._crop_xz_m,
            )
        except GelSightRenderError as err:
            raise ModelConfigError(f"physics prior: {err}") from err
        if isinstance(pressed, slice):
            images = drawn
        else:  # a gel nothing presses into shows its background (blurred, it stays that)
            images = np.empty((len(maps), *drawn.shape[1:]), np.uint8)
            images[...] = self.renderer.background()
            images[pressed] = drawn
        if sigma_mm == 0:
            return self._on_grid(images)
        pitch_rows_mm, pitch_cols_mm = self.renderer.pixel_pitch_mm
        background = self.renderer.background().astype(np.float32)
        for i in range(len(images)) if isinstance(pressed, slice) else np.flatnonzero(pressed):
            image = images[i]  # in place: one float32 image at a time
            change = cv2.GaussianBlur(
                image.astype(np.float32) - background,
                (0, 0),
                sigmaX=sigma_mm / pitch_cols_mm,
                sigmaY=sigma_mm / pitch_rows_mm,
                borderType=cv2.BORDER_REPLICATE,
            )
            image[...] = np.clip(np.rint(background + change), 0, 255)
        return self._on_grid(images)

    def _on_grid(self, images: np.ndarray) -> np.ndarray:
        """The renderer's images at the model's grid: as they are, or area-averaged from the
        sensor's pixels."""
        if images.shape[1:3] == (self.size, self.size):
            return images
        grid = np.empty((len(images), self.size, self.size, 3), np.uint8)
        for drawn, image in zip(images, grid):
            image[...] = resize_rgb(drawn, self.size, self.size)
        return grid

    def _sigma_mm(self, pose_sigma_mm: float | None) -> float:
        """The pose blur asked for, checked: the spec's for None."""
        return checked_pose_sigma_mm(self.spec.pose_sigma_mm if pose_sigma_mm is None else pose_sigma_mm)

    def _levels_on_device(self, tensor: TensorPrior, depth_maps_m: np.ndarray, sigma_mm: float) -> torch.Tensor:
        """:meth:`images` drawn by ``tensor`` on this prior's device, the same contract, as
        N x 3 x H x W float32 levels there."""
        try:
            maps = checked_depth_maps(self.renderer, depth_maps_m, self._crop_xz_m)
        except GelSightRenderError as err:
            raise ModelConfigError(f"physics prior: {err}") from err
        levels = tensor.images(torch.as_tensor(maps).to(self.device), sigma_mm)
        if self._area is None:
            return levels
        rows, cols = self._area
        return torch.round(rows @ levels @ cols.T)

    def _pressed(self, maps: np.ndarray) -> np.ndarray | slice:
        """Which ``maps`` reach into the gel (a bin below 0, the renderer's indentation), a mask;
        all of them (a slice) unless ``maps`` is an N x H x W float array within the renderer's
        pixel limit, so that render_depth_maps judges them and says what is wrong. Rendering a
        map nothing presses into costs 0.4-0.9 ms for the background it always gives (a
        planner's out-of-reach regions)."""
        h, w = self.renderer.config.shape
        if maps.ndim != 3 or maps.dtype.kind != "f" or len(maps) * h * w > MAX_RENDERED_PIXELS:
            return slice(None)
        return np.asarray((maps < 0).any(axis=(1, 2)))

    def channels(self, depth_maps_m: np.ndarray, pose_sigma_mm: float | None = None) -> torch.Tensor:
        """N x 3 x size x size float32 in [-1, 1] (the network's image units), a tensor on this
        prior's device: on a GPU the images never leave it (each level's unit read from
        IMAGE_UNITS, the CPU's own arithmetic, which a tensor division by 127.5 would round
        otherwise)."""
        if self._tensor is None:
            images = self.images(depth_maps_m, pose_sigma_mm)
            return torch.from_numpy(images.transpose(0, 3, 1, 2).astype(np.float32) / 127.5 - 1.0)
        levels = self._levels_on_device(self._tensor, depth_maps_m, self._sigma_mm(pose_sigma_mm))
        return self._image_units[levels.to(torch.long)]
