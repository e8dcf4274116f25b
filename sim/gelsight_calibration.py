"""The photometric calibration of the simulated GelSight (Taxim, assets/gelsight/ATTRIBUTION.md):
per slope bin, a polynomial in pixel position giving the colour change, and the sensor's
no-contact frame, read from a calibration directory and checked (every problem is a
:class:`GelSightRenderError`). The renderer (``sim.gelsight``) shades with it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import cv2
import numpy as np

from sim.gelsight_effects import GelSightRenderError

REPO_ROOT = Path(__file__).resolve().parent.parent
POLYNOMIAL_FILE = "polycalib_small.npz"
# A real no-contact frame of the calibrated sensor (not real_bg_small.npy: that is Taxim's
# base image with its gel-dome shading removed, values up to 369, not a camera frame).
BACKGROUND_FILE = "ball_presses.npz"
# The renderer's physical parameters fitted with the tables (``dtx calibrate gelsight``); a
# directory without it (the shipped one) renders with GelSightConfig's defaults.
PARAMETERS_FILE = "renderer.json"
PARAMETER_NAMES = (
    "calibration_mm_per_px",
    "spreading_length_mm",
    "optical_blur_mm",
    "compression_saturation_mm",
    "shading_gain",
    "background_smoothing_mm",
)
# The calibration's slope bins are split in this many, interpolated (a finer split changes
# the gelsight-check SSIMs by less than 0.001).
BIN_REFINEMENT = 2


@dataclasses.dataclass(frozen=True)
class PolyCalibration:
    """The photometric calibration of one sensor.

    ``coeffs[i_mag, i_dir, channel]`` are the 6 coefficients of the colour change, in 8-bit
    levels, as a polynomial ``[x^2, y^2, xy, x, y, 1]`` of the pixel position (x column,
    y row) in the ``native_shape`` image, for ``n_bins`` equal bins of the slope magnitude
    ``atan|grad h|`` over [0, pi/2) and of its direction over [-pi, pi). ``background`` is
    that sensor's no-contact frame.
    """

    coeffs: np.ndarray  # (n_bins, n_bins, 3, 6) float32
    background: np.ndarray  # native_shape + (3,) uint8

    @property
    def n_bins(self) -> int:
        return self.coeffs.shape[0]

    @property
    def native_shape(self) -> tuple[int, int]:
        return self.background.shape[0], self.background.shape[1]


def _repo_path(path: str | Path) -> Path:
    path = Path(path)
    return path if path.is_absolute() else REPO_ROOT / path


def load_calibration(calibration_dir: str | Path) -> PolyCalibration:
    """Read the per-slope-bin polynomials and the no-contact frame from ``calibration_dir``
    (relative paths are from the repository root). Read once per directory; the arrays are
    read-only."""
    return _load_calibration(str(_repo_path(calibration_dir).resolve()))


def renderer_parameters(calibration_dir: str | Path) -> dict[str, float]:
    """The renderer's physical parameters a calibration directory holds (PARAMETERS_FILE, names
    of PARAMETER_NAMES, each a finite number; GelSightConfig checks their ranges); none for a
    directory without the file."""
    path = _repo_path(calibration_dir) / PARAMETERS_FILE
    if not path.is_file():
        return {}
    try:
        values = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise GelSightRenderError(f"{path}: not readable JSON ({exc})") from exc
    if not isinstance(values, dict) or set(values) - set(PARAMETER_NAMES):
        raise GelSightRenderError(f"{path}: must map some of {list(PARAMETER_NAMES)} to numbers, got {values!r}")
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise GelSightRenderError(f"{path}: {name} must be a finite number, got {value!r}")
    return {name: float(value) for name, value in values.items()}


@functools.lru_cache(maxsize=8)
def _load_calibration(directory_name: str) -> PolyCalibration:
    directory = Path(directory_name)
    poly_path, bg_path = directory / POLYNOMIAL_FILE, directory / BACKGROUND_FILE
    for path in (poly_path, bg_path):
        if not path.is_file():
            raise GelSightRenderError(f"GelSight calibration file missing: {path}")
    with np.load(poly_path) as poly:
        missing = sorted({"bins", "grad_r", "grad_g", "grad_b"} - set(poly.files))
        if missing:
            raise GelSightRenderError(f"{poly_path}: missing keys {missing}")
        n = int(poly["bins"])
        tables = [np.asarray(poly[k], np.float64) for k in ("grad_r", "grad_g", "grad_b")]
    for table in tables:
        if table.shape != (n, n, 6) or not np.all(np.isfinite(table)):
            raise GelSightRenderError(
                f"{poly_path}: each grad_* must be a finite ({n}, {n}, 6) array, got shape {table.shape}"
            )
    with np.load(bg_path) as data:
        if "background" not in data.files:
            raise GelSightRenderError(f"{bg_path}: missing key 'background'")
        background = np.asarray(data["background"])
    if background.ndim != 3 or background.shape[2] != 3 or background.dtype != np.uint8:
        raise GelSightRenderError(
            f"{bg_path}: background must be HxWx3 uint8, got {background.shape} {background.dtype}"
        )
    return calibration_from_tables(np.stack(tables, axis=2), background)


def calibration_from_tables(tables: np.ndarray, background: np.ndarray) -> PolyCalibration:
    """The calibration the renderer shades with, from the tables as the file stores them
    ((n, n, 3, 6): magnitude bin, direction bin, channel, coefficient) and the no-contact frame."""
    n = tables.shape[0]
    # Taxim's n bins are n - 1 bins of width range / (n - 1) plus one for the range's end
    # point alone; keep the n - 1 (the end point falls in the last of them).
    coeffs = np.array(tables[: n - 1, : n - 1], np.float64)  # (n - 1, n - 1, 3, 6)
    # The calibration saw almost no pixels at zero slope (only each press's centre), so the
    # direction bins of magnitude 0 disagree by noise; a flat gel has no direction, so use
    # their mean: the colour is then continuous at zero slope and the same for every flat pixel.
    coeffs[0] = coeffs[0].mean(axis=0, keepdims=True)
    coeffs = _refine_bins(coeffs.astype(np.float32), BIN_REFINEMENT)
    background = np.array(background)
    coeffs.flags.writeable = False
    background.flags.writeable = False
    return PolyCalibration(coeffs, background)


def _refine_bins(coeffs: np.ndarray, factor: int) -> np.ndarray:
    """The table on bins ``factor`` times narrower, linearly interpolated between the
    calibration's bin centres: the colour is a continuous function of the surface normal, and
    a nearest-bin look-up would print the bins' steps into the image. The direction wraps
    around; below the first magnitude bin centre the zero-slope bin is kept."""
    n_mag, n_dir = coeffs.shape[:2]
    table = coeffs.reshape(n_mag, n_dir, -1)
    wrapped = np.concatenate([table[:, -1:], table, table[:, :1]], axis=1)
    # cv2.resize samples at pixel centres, so fine bin centres interpolate coarse bin centres.
    fine = cv2.resize(wrapped, ((n_dir + 2) * factor, n_mag * factor), interpolation=cv2.INTER_LINEAR)
    fine = fine[:, factor : (n_dir + 1) * factor]
    return np.ascontiguousarray(fine.reshape(n_mag * factor, n_dir * factor, *coeffs.shape[2:]))
