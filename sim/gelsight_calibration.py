"""The photometric calibration of the simulated GelSight (Taxim, assets/gelsight/ATTRIBUTION.md):
per slope bin, a polynomial in pixel position giving the colour change, and the sensor's
no-contact frame, read from a calibration directory and checked (every problem is a
:class:`GelSightRenderError`). The renderer (``sim.gelsight``) shades with it.

A calibration directory is trusted no more than any file: each array's .npy header is read and
checked before its data (a small file claiming a huge array is refused, not allocated), and the
parameters file is read within a size.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import zipfile
import zlib
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
# A file's slope bins (Taxim's n, the range's end point included): at least one bin and its end,
# at most 256 (the shipped file has 80; the refined table then stays under 20 MB).
TABLE_BINS_RANGE = (2, 256)
# The no-contact frame's sides, as the renderer's images (sim.gelsight.GelSightConfig).
BACKGROUND_PX_RANGE = (3, 4096)
MAX_PARAMETERS_BYTES = 64 * 1024  # a few names and numbers; more is not a parameters file


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

    def __post_init__(self) -> None:
        coeffs = self.coeffs
        if not (
            isinstance(coeffs, np.ndarray)
            and coeffs.ndim == 4
            and coeffs.shape[0] == coeffs.shape[1] >= 1
            and coeffs.shape[2:] == (3, 6)
            and coeffs.dtype.kind == "f"
            and np.all(np.isfinite(coeffs))
        ):
            raise GelSightRenderError(
                f"PolyCalibration.coeffs must be a finite (n, n, 3, 6) float array, got "
                f"{getattr(coeffs, 'shape', type(coeffs).__name__)} {getattr(coeffs, 'dtype', '')}"
            )
        _check_background(self.background, "PolyCalibration.background")

    @property
    def n_bins(self) -> int:
        return self.coeffs.shape[0]

    @property
    def native_shape(self) -> tuple[int, int]:
        return self.background.shape[0], self.background.shape[1]


def _check_background(background: object, name: str) -> None:
    low, high = BACKGROUND_PX_RANGE
    if not (
        isinstance(background, np.ndarray)
        and background.dtype == np.uint8
        and background.ndim == 3
        and background.shape[2] == 3
        and low <= min(background.shape[:2])
        and max(background.shape[:2]) <= high
    ):
        raise GelSightRenderError(
            f"{name} must be an H x W x 3 uint8 frame, H and W in [{low}, {high}], got "
            f"{getattr(background, 'shape', type(background).__name__)} {getattr(background, 'dtype', '')}"
        )


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
        if path.stat().st_size > MAX_PARAMETERS_BYTES:
            raise GelSightRenderError(f"{path}: more than {MAX_PARAMETERS_BYTES} bytes: not a parameters file")
        # Every number as a float, which is what the renderer takes: an integer of 400 digits is then
        # inf (refused below), not an int no float can hold.
        values = json.loads(path.read_text(), parse_int=float)
    except GelSightRenderError:
        raise
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: arrays nested thousands deep
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
    low, high = TABLE_BINS_RANGE
    bins = read_npz_arrays(poly_path, {"bins": 1})["bins"]
    if bins.shape != () or bins.dtype.kind not in "iu" or not low <= int(bins) <= high:
        raise GelSightRenderError(f"{poly_path}: bins must be an integer in [{low}, {high}], got {bins!r:.60}")
    n = int(bins)
    tables = read_npz_arrays(poly_path, dict.fromkeys(("grad_r", "grad_g", "grad_b"), n * n * 6))
    for name, table in tables.items():
        if table.shape != (n, n, 6):
            raise GelSightRenderError(f"{poly_path}: {name} must be an ({n}, {n}, 6) array, got shape {table.shape}")
    side = BACKGROUND_PX_RANGE[1]
    background = read_npz_arrays(bg_path, {"background": side * side * 3})["background"]
    stacked = np.stack([tables[name] for name in ("grad_r", "grad_g", "grad_b")], axis=2)
    try:
        return calibration_from_tables(stacked, background)
    except GelSightRenderError as exc:
        raise GelSightRenderError(f"{directory}: {exc}") from exc


def read_npz_arrays(path: Path, most_elements: dict[str, int]) -> dict[str, np.ndarray]:
    """The arrays ``most_elements`` names from the .npz at ``path``, each .npy header read before
    its data: GelSightRenderError for a file that is not a readable .npz, a missing key, an object
    array or one of more elements than its entry."""
    try:
        with zipfile.ZipFile(path) as archive:
            missing = sorted(key for key in most_elements if f"{key}.npy" not in archive.namelist())
            if missing:
                raise GelSightRenderError(f"missing keys {missing}")
            return {key: _read_member(archive, key, most) for key, most in most_elements.items()}
    except GelSightRenderError as exc:
        raise GelSightRenderError(f"{path}: {exc}") from exc
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError) as exc:
        raise GelSightRenderError(f"{path}: not a readable .npz file ({exc})") from exc


def _read_member(archive: zipfile.ZipFile, key: str, most_elements: int) -> np.ndarray:
    headers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with archive.open(f"{key}.npy") as member:
        version = np.lib.format.read_magic(member)
        if version not in headers:
            raise GelSightRenderError(f"{key}: .npy format version {version} is not one this reader takes")
        shape, _, dtype = headers[version](member, max_header_size=4096)
    if dtype.hasobject or math.prod(shape) > most_elements:
        what = "an object array" if dtype.hasobject else f"more than {most_elements} numbers"
        raise GelSightRenderError(f"{key}: its header says {shape} {dtype}, {what}")
    with archive.open(f"{key}.npy") as member:
        return np.asarray(np.lib.format.read_array(member, allow_pickle=False, max_header_size=4096))


def calibration_from_tables(tables: np.ndarray, background: np.ndarray) -> PolyCalibration:
    """The calibration the renderer shades with, from the tables as the file stores them
    ((n, n, 3, 6): magnitude bin, direction bin, channel, coefficient) and the no-contact frame.

    Contract: ``tables`` a finite real (n, n, 3, 6) array, n in TABLE_BINS_RANGE; ``background`` as
    :class:`PolyCalibration` takes it; otherwise GelSightRenderError naming the argument."""
    low, high = TABLE_BINS_RANGE
    real = isinstance(tables, np.ndarray) and tables.dtype.kind in "iuf"
    if not (
        real
        and tables.ndim == 4
        and tables.shape[0] == tables.shape[1]
        and low <= tables.shape[0] <= high
        and tables.shape[2:] == (3, 6)
    ):
        raise GelSightRenderError(
            f"tables must be a real (n, n, 3, 6) array, n in [{low}, {high}], got "
            f"{getattr(tables, 'shape', type(tables).__name__)} {getattr(tables, 'dtype', '')}"
        )
    if not np.all(np.isfinite(tables)):
        raise GelSightRenderError(f"tables must be finite, got {np.count_nonzero(~np.isfinite(tables))} NaN or inf")
    _check_background(background, "background")
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
