"""Optional GelSight effects: sensor noise, markers, lighting drift.

Each effect is a small dataclass with physical parameters and one method,
``apply(image, gel_depth_mm, pixel_pitch_mm, rng) -> image``, called by the renderer on the
noise-free float32 RGB image (0..255 scale, before rounding) in the order given. An effect
that is not passed to the renderer is never called, so it costs nothing. ``carries_state``
says whether an effect's image depends on the frames before it (lighting drift), not only on
its arguments: a simulated sensor may show the same gap's frame again only without one.

``gel_depth_mm`` is the deformed gel surface (HxW, mm pushed in from rest, >= 0) and
``pixel_pitch_mm`` the image's pixel pitch on the gel (along rows, along columns), so effects
that follow the gel (markers) can move with it.

This module also defines :class:`GelSightRenderError`, the one exception of the GelSight
part, so that the renderer (``sim.gelsight``) can import the effects without an import cycle.

Shadows are not modelled: the calibration carries no shadow data and the renderer must not
invent lights.
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import numpy as np

from msgs.config import ConfigError, config_from_dict


class GelSightRenderError(ValueError):
    """Bad input to the GelSight renderer, its effects or the calibration check (a failing
    GelSight device is ``drivers.gelsight.GelSightError``)."""


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise GelSightRenderError(message)


def _finite_in(name: str, value: float, lo: float, hi: float, unit: str) -> None:
    _require(
        isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi,
        f"{name} must be a number in [{lo}, {hi}] {unit}, got {value!r}",
    )


@dataclasses.dataclass
class SensorNoise:
    """Camera read noise: independent Gaussian noise per pixel and channel."""

    sigma_levels: float = 1.5  # standard deviation in 8-bit levels
    carries_state: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _finite_in("sensor_noise.sigma_levels", self.sigma_levels, 0.0, 50.0, "levels")

    def apply(
        self, image: np.ndarray, gel_depth_mm: np.ndarray, pixel_pitch_mm: tuple[float, float], rng: np.random.Generator
    ) -> np.ndarray:
        noise = rng.standard_normal(image.shape, dtype=np.float32)
        return image + np.float32(self.sigma_levels) * noise


@dataclasses.dataclass
class Markers:
    """A square grid of dark dots printed on the gel, moving with the gel surface.

    Under a normal press a thin, nearly incompressible elastomer layer is squeezed out from
    under the indenter, so surface points move away from the contact, by about
    ``lateral_shift_per_slope_mm`` times the local surface slope (first-order thin-layer
    approximation). Each pixel looks up its rest position ``p - shift(p)`` on the grid.
    """

    pitch_mm: float = 1.2
    dot_radius_mm: float = 0.2
    darkness: float = 0.7  # fraction of light a dot absorbs
    lateral_shift_per_slope_mm: float = 0.3
    carries_state: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _finite_in("markers.pitch_mm", self.pitch_mm, 0.1, 20.0, "mm")
        _finite_in("markers.dot_radius_mm", self.dot_radius_mm, 0.01, 0.45 * self.pitch_mm, "mm")
        _finite_in("markers.darkness", self.darkness, 0.0, 1.0, "")
        _finite_in("markers.lateral_shift_per_slope_mm", self.lateral_shift_per_slope_mm, 0.0, 5.0, "mm")

    def apply(
        self, image: np.ndarray, gel_depth_mm: np.ndarray, pixel_pitch_mm: tuple[float, float], rng: np.random.Generator
    ) -> np.ndarray:
        h, w = gel_depth_mm.shape
        pitch_row, pitch_col = pixel_pitch_mm
        slope_row, slope_col = np.gradient(gel_depth_mm.astype(np.float32), pitch_row, pitch_col)
        # Pixel positions in mm from the gel centre, so the grid is centred on the gel.
        row_mm = (np.arange(h, dtype=np.float32) - (h - 1) / 2.0)[:, None] * pitch_row
        col_mm = (np.arange(w, dtype=np.float32) - (w - 1) / 2.0)[None, :] * pitch_col
        # The gel depth grows towards the contact, so -slope points away from it.
        rest_row = row_mm + self.lateral_shift_per_slope_mm * slope_row
        rest_col = col_mm + self.lateral_shift_per_slope_mm * slope_col
        d_row = rest_row - self.pitch_mm * np.round(rest_row / self.pitch_mm)
        d_col = rest_col - self.pitch_mm * np.round(rest_col / self.pitch_mm)
        dist_mm = np.hypot(d_row, d_col)
        # Anti-aliased disc edge, about one pixel wide.
        coverage = np.clip((self.dot_radius_mm - dist_mm) / max(pitch_row, pitch_col) + 0.5, 0.0, 1.0)
        return image * (1.0 - np.float32(self.darkness) * coverage)[:, :, None]


@dataclasses.dataclass
class LightingDrift:
    """Slow change of the LED brightness, per channel, as a bounded random walk.

    The real ball-press frames show it: away from the touch the green channel falls by about
    5 levels (4 %) over 30 frames. The walk's state lives in the effect, so successive
    renders drift; ``step_fraction`` is the standard deviation of the gain change per frame.
    Being a process over frames, the walk draws its steps from a stream of its own (started
    from the first frame's generator), not from each frame's: a simulated sensor keys a frame's
    generator on what the frame shows (``sim.seeding``), which would make every step of a still
    gel the same.
    """

    step_fraction: float = 0.002
    max_fraction: float = 0.05
    carries_state: ClassVar[bool] = True

    def __post_init__(self) -> None:
        _finite_in("lighting_drift.step_fraction", self.step_fraction, 0.0, 0.1, "")
        _finite_in("lighting_drift.max_fraction", self.max_fraction, 0.0, 0.5, "")
        self.gain = np.ones(3, np.float32)  # state, not a parameter
        self._steps: np.random.Generator | None = None

    def apply(
        self, image: np.ndarray, gel_depth_mm: np.ndarray, pixel_pitch_mm: tuple[float, float], rng: np.random.Generator
    ) -> np.ndarray:
        if self._steps is None:
            self._steps = np.random.default_rng(rng.integers(0, 2**63))
        step = self._steps.normal(0.0, self.step_fraction, 3).astype(np.float32)
        self.gain = np.clip(self.gain + step, 1.0 - self.max_fraction, 1.0 + self.max_fraction)
        return image * self.gain


# Name -> effect class, as a scene file names them (sim.effects reads the defaults from it).
EFFECTS: dict[str, type] = {
    "sensor_noise": SensorNoise,
    "markers": Markers,
    "lighting_drift": LightingDrift,
}


def make_effect(name: str, params: dict | None = None) -> SensorNoise | Markers | LightingDrift:
    """Build the effect called ``name`` from a scene's parameter mapping (msgs.config)."""
    _require(name in EFFECTS, f"unknown GelSight effect {name!r} (allowed: {sorted(EFFECTS)})")
    try:
        return config_from_dict(EFFECTS[name], params or {})
    except ConfigError as exc:
        raise GelSightRenderError(f"GelSight effect {name!r}: {exc}") from None
