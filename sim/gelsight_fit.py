"""The GelSight renderer's photometric model fitted from ball presses of the lab's own sensor.

A press of a ball of known radius, at a known centre and contact radius, gives the gel's
surface everywhere (``sim.gelsight_check.ball_gap_map`` through the renderer's deformation,
``sim.gelsight.gel_surface_depth_mm``), so every pixel near the press pairs a surface slope
with the colour change the camera saw there. This is Taxim's example-based calibration (Si and
Yuan, RA-L 2022, assets/gelsight/ATTRIBUTION.md), fitted in the form the renderer reads:

1. Background: the mean of every frame where no press reaches (farther than
   :data:`FAR_RADII` contact radii from its centre) and of the no-contact frame: the camera's
   noise and the frame-to-frame fringes average out, the fixed pattern stays.
2. Flat pressed gel: the colour change where the gel is pressed but not tilted, a polynomial
   in pixel position times the compression (the renderer's step 3).
3. Tilted gel: per bin of slope magnitude and direction (:data:`N_BINS` each), the colour change
   as a polynomial ``[x^2, y^2, xy, x, y, 1]`` of pixel position, by least squares. Neighbouring
   bins share their samples through a Gaussian of :data:`BIN_SMOOTHING` bins (the colour is a
   smooth function of the surface normal), a ridge keeps sparse bins near a constant, and bins no
   press reached take their nearest fitted neighbour's colour.
4. The renderer's physical parameters (spread, optical blur, compression saturation, background
   smoothing) by Nelder-Mead on the mean crop + full-frame SSIM of the fitted presses, the table
   fitted again at every step (SSIM is not differentiable through the bin look-up).

Plain functions on arrays; lengths in mm, positions in pixels (x column, y row). Presses are
checked where they enter (:class:`Presses`), the rest where each public function takes it; bad
input is a GelSightRenderError naming the argument.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

from sim.gelsight import MAX_LENGTH_MM, GelSightConfig, GelSightRenderer, gel_surface_depth_mm, indentation_mm
from sim.gelsight_calibration import PolyCalibration, calibration_from_tables
from sim.gelsight_check import ball_gap_map, press_depth_mm, press_ssim
from sim.gelsight_effects import GelSightRenderError
from sim.press_annotation import BALL_RADIUS_RANGE_MM, MM_PER_PX_RANGE, checked_frames, checked_number

N_BINS = 60  # slope magnitude bins over [0, pi/2) and direction bins over [-pi, pi)
BIN_SMOOTHING = 1.0  # sigma, in bins, of the sharing between neighbouring bins
FLAT_RIDGE = 1.0  # the same for the flat pressed gel's colour
RIDGE = 0.05  # weight, per sample, pulling a bin's position terms towards a constant colour
FAR_RADII = 2.5  # a pixel this many ball radii from a press is untouched by it
NEAR_RADII = 2.0  # pixels this many ball radii from a press carry its shading
FITTED = ("spreading_length_mm", "optical_blur_mm", "compression_saturation_mm", "background_smoothing_mm")
FIT_EVALUATIONS = 40
# The most renderings one fit may take: 25 times the default, an hour or more on the largest frames.
MAX_FIT_EVALUATIONS = 1000


@dataclasses.dataclass(frozen=True)
class PressFit:
    """A fitted photometric model: the tables as the calibration file stores them
    ((N_BINS + 1)^2 x 3 x 6, ``sim.gelsight_calibration``), the background (HxWx3 uint8) and
    the renderer's parameters."""

    tables: np.ndarray
    background: np.ndarray
    parameters: dict[str, float]

    def calibration(self) -> PolyCalibration:
        return calibration_from_tables(self.tables, self.background)


def fit_background(frames: np.ndarray, background: np.ndarray, centers_xy_px: np.ndarray, ball_radius_px: float):
    """The no-contact frame (HxWx3 float32): the mean of ``background`` and of every frame's
    pixels farther than FAR_RADII ball radii from its press."""
    h, w = background.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    total = background.astype(np.float64)
    count = np.ones((h, w))
    for frame, (x, y) in zip(frames, centers_xy_px):
        free = np.hypot(cols - x, rows - y) > FAR_RADII * ball_radius_px
        total += frame * free[:, :, None]
        count += free
    return (total / count[:, :, None]).astype(np.float32)


def press_config(shape: tuple[int, int], mm_per_px: float, parameters: dict[str, Any]) -> GelSightConfig:
    """The renderer's configuration for frames of ``shape`` at ``mm_per_px`` calibrated at that size."""
    return GelSightConfig(
        image_height=shape[0],
        image_width=shape[1],
        mm_per_px=mm_per_px,
        calibration_mm_per_px=mm_per_px,
        shading_gain=1.0,
        **parameters,
    )


def press_gaps_mm(
    shape: tuple[int, int], centers_xy_px: np.ndarray, radii_px: np.ndarray, mm_per_px: float, ball_radius_mm: float
) -> list[np.ndarray]:
    """The gel gap map of each press (mm), its depth from its contact radius."""
    return [
        ball_gap_map(shape, center, press_depth_mm(radius * mm_per_px, ball_radius_mm), mm_per_px, ball_radius_mm)
        for center, radius in zip(centers_xy_px, radii_px)
    ]


def _position_terms(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The polynomial terms of every pixel, divided by their scale (pixels x 6), and that scale."""
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = cols.ravel(), rows.ravel()
    scale = np.array([w * w, h * h, w * h, w, h, 1.0])
    return np.stack([x * x, y * y, x * y, x, y, np.ones_like(x)], axis=1) / scale, scale


def _per_bin_sums(bins: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (samples x k) per slope bin, shared with the neighbouring bins
    (N_BINS x N_BINS x k; the direction wraps)."""
    sums = np.stack([np.bincount(bins, column, N_BINS * N_BINS) for column in values.T], axis=-1)
    sums = sums.reshape(N_BINS, N_BINS, -1)
    return ndimage.gaussian_filter(sums, (BIN_SMOOTHING, BIN_SMOOTHING, 0), mode=("nearest", "wrap", "nearest"))


def _ridge_solve(gram: np.ndarray, moment: np.ndarray, ridge: float = RIDGE) -> np.ndarray:
    """Per bin, the coefficients (bins x 6 x 3) with the ridge on the position terms, scaled by
    the bin's sample weight so that a bin of few samples stays near a constant."""
    weight = gram[:, 5, 5]
    penalty = np.zeros((gram.shape[0], 6, 6))
    penalty[:, np.arange(5), np.arange(5)] = ridge * weight[:, None] + 1e-9
    penalty[:, 5, 5] = 1e-9
    return np.linalg.solve(gram + penalty, moment)


def _fill_empty_bins(coeffs: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Bins with no sample take the coefficients of the nearest bin with some (direction wraps)."""
    empty = weight < 1e-6
    if not empty.any():
        return coeffs
    if empty.all():
        raise GelSightRenderError("no pixel of any press is tilted: the presses show no ball")
    n_dir = empty.shape[1]
    tiled = np.concatenate([empty, empty, empty], axis=1)
    _, (i_mag, i_dir) = ndimage.distance_transform_edt(tiled, return_indices=True)
    i_mag, i_dir = i_mag[:, n_dir : 2 * n_dir], i_dir[:, n_dir : 2 * n_dir] % n_dir
    return coeffs[i_mag, i_dir]


def fit_tables(
    gel_depths_mm: Sequence[np.ndarray],
    colour_changes: Sequence[np.ndarray],
    near_masks: Sequence[np.ndarray],
    mm_per_px: float,
    compression_saturation_mm: float,
) -> np.ndarray:
    """The shading tables ((N_BINS + 1)^2 x 3 x 6, the file's layout: polynomial coefficients in
    pixel position, 8-bit levels) that best explain ``colour_changes`` (frame minus background,
    HxWx3) from the gel surfaces ``gel_depths_mm`` (HxW), on the pixels of ``near_masks``.

    Contract: one or more presses, each an HxW finite float depth, an HxWx3 real change and an HxW
    bool mask of one size; ``mm_per_px`` in MM_PER_PX_RANGE, ``compression_saturation_mm`` finite > 0
    (at most MAX_LENGTH_MM, the renderer's longest length); otherwise GelSightRenderError naming the argument."""
    _check_table_input(gel_depths_mm, colour_changes, near_masks)
    checked_number("mm_per_px", mm_per_px, *MM_PER_PX_RANGE)
    if not 0 < checked_number("compression_saturation_mm", compression_saturation_mm, 0.0, MAX_LENGTH_MM):
        raise GelSightRenderError(f"compression_saturation_mm must be > 0 mm, got {compression_saturation_mm!r}")
    shape = gel_depths_mm[0].shape
    terms, scale = _position_terms(shape)
    mag_step, dir_step = 0.5 * math.pi / N_BINS, 2.0 * math.pi / N_BINS
    # The renderer's "tilted" threshold: its table is refined twice (sim.gelsight_calibration).
    tilted_tan = math.tan(0.5 * mag_step)
    flat_x, flat_y, tilt_rows, tilt_bins, tilt_y, tilt_c = [], [], [], [], [], []
    for depth, change, near in zip(gel_depths_mm, colour_changes, near_masks):
        slope_x = cv2.Sobel(depth, cv2.CV_32F, 1, 0, ksize=1, scale=0.5 / mm_per_px, borderType=cv2.BORDER_REPLICATE)
        slope_y = cv2.Sobel(depth, cv2.CV_32F, 0, 1, ksize=1, scale=0.5 / mm_per_px, borderType=cv2.BORDER_REPLICATE)
        compression = np.minimum(depth / compression_saturation_mm, 1.0).ravel()
        magnitude = np.arctan(np.hypot(slope_x, slope_y)).ravel()
        near, change = near.ravel(), change.reshape(-1, 3)
        flat = near & (magnitude < math.atan(tilted_tan))
        flat_x.append(terms[flat] * compression[flat, None])
        flat_y.append(change[flat])
        tilted = np.flatnonzero(near & ~flat)
        i_mag = np.minimum(magnitude[tilted] / mag_step, N_BINS - 1).astype(np.intp)
        direction = np.arctan2(slope_y.ravel()[tilted], slope_x.ravel()[tilted])
        i_dir = np.minimum((direction + math.pi) / dir_step, N_BINS - 1).astype(np.intp)
        tilt_rows.append(tilted)
        tilt_bins.append(i_mag * N_BINS + i_dir)
        tilt_y.append(change[tilted])
        tilt_c.append(compression[tilted])
    x, y = np.concatenate(flat_x), np.concatenate(flat_y)
    # Flat pressed pixels lie only at the presses' centres, a few clusters: a strong ridge.
    flat_coeffs = _ridge_solve((x.T @ x)[None], (x.T @ y)[None], FLAT_RIDGE)[0]  # 6 x 3, scaled terms
    rows, bins = np.concatenate(tilt_rows), np.concatenate(tilt_bins)
    a = terms[rows]
    # The renderer adds the flat colour times (compression - 1) to a tilted pixel's bin colour.
    target = np.concatenate(tilt_y) - (a @ flat_coeffs) * (np.concatenate(tilt_c) - 1.0)[:, None]
    gram = _per_bin_sums(bins, (a[:, :, None] * a[:, None, :]).reshape(-1, 36))
    moment = _per_bin_sums(bins, (a[:, :, None] * target[:, None, :]).reshape(-1, 18))
    coeffs = _ridge_solve(gram.reshape(-1, 6, 6), moment.reshape(-1, 6, 3)).reshape(N_BINS, N_BINS, 6, 3)
    coeffs = _fill_empty_bins(coeffs, gram[:, :, 35])
    coeffs[0] = flat_coeffs  # the zero-slope bin is the flat pressed gel's colour
    coeffs = np.transpose(coeffs, (0, 1, 3, 2)) / scale  # (mag, dir, channel, 6) per pixel unit
    # The file's layout: one more bin for the range's end point, a copy of the last.
    return np.pad(coeffs, ((0, 1), (0, 1), (0, 0), (0, 0)), mode="edge").astype(np.float32)


def _check_table_input(
    gel_depths_mm: Sequence[np.ndarray], colour_changes: Sequence[np.ndarray], near_masks: Sequence[np.ndarray]
) -> None:
    n = len(gel_depths_mm)
    if n == 0 or len(colour_changes) != n or len(near_masks) != n:
        raise GelSightRenderError(
            "gel_depths_mm, colour_changes and near_masks must hold one or more presses each, as many, got "
            f"{n}, {len(colour_changes)} and {len(near_masks)}"
        )
    shape = np.shape(gel_depths_mm[0])
    for depth, change, near in zip(gel_depths_mm, colour_changes, near_masks):
        if not (isinstance(depth, np.ndarray) and depth.ndim == 2 and depth.shape == shape):
            raise GelSightRenderError(f"gel_depths_mm must be H x W arrays of one size, got {np.shape(depth)}")
        if depth.dtype.kind != "f" or not np.all(np.isfinite(depth)):
            raise GelSightRenderError(f"gel_depths_mm must be finite floats, got {depth.dtype} with NaN or inf")
        if not (isinstance(change, np.ndarray) and change.shape == shape + (3,) and change.dtype.kind in "iuf"):
            raise GelSightRenderError(f"colour_changes must be {shape + (3,)} real arrays, got {np.shape(change)}")
        if not (isinstance(near, np.ndarray) and near.shape == shape and near.dtype == bool):
            raise GelSightRenderError(f"near_masks must be {shape} bool arrays, got {np.shape(near)}")


@dataclasses.dataclass(frozen=True)
class Presses:
    """Ball presses of one sensor: frames (N x H x W x 3 uint8), its no-contact frame, each press's
    centre (N x 2, x column and y row, px) and contact radius (N, px), the frame's scale and the ball's radius.

    Contract, checked on construction: frames and background as
    ``sim.press_annotation.checked_frames`` takes them (N >= 0); centres N x 2 finite, inside the
    frame; radii N finite > 0 px; ``mm_per_px`` in MM_PER_PX_RANGE and ``ball_radius_mm`` in
    BALL_RADIUS_RANGE_MM. Otherwise GelSightRenderError naming the field."""

    frames: np.ndarray
    background: np.ndarray
    centers_xy_px: np.ndarray
    radii_px: np.ndarray
    mm_per_px: float
    ball_radius_mm: float

    def __post_init__(self) -> None:
        checked_frames(self.frames, self.background)
        n, (h, w) = len(self.frames), self.background.shape[:2]
        centers, radii = self.centers_xy_px, self.radii_px
        if not (isinstance(centers, np.ndarray) and centers.shape == (n, 2) and centers.dtype.kind in "iuf"):
            raise GelSightRenderError(f"centers_xy_px must be {n} x 2 numbers, got {np.shape(centers)}")
        inside = (centers[:, 0] >= 0) & (centers[:, 0] <= w - 1) & (centers[:, 1] >= 0) & (centers[:, 1] <= h - 1)
        if not inside.all():  # NaN is not inside either
            raise GelSightRenderError(
                f"centers_xy_px must lie in the {w} x {h} frame, presses {np.flatnonzero(~inside).tolist()} do not"
            )
        if not (isinstance(radii, np.ndarray) and radii.shape == (n,) and radii.dtype.kind in "iuf"):
            raise GelSightRenderError(f"radii_px must be {n} numbers, got {np.shape(radii)}")
        if not np.all((radii > 0) & (radii < np.inf)):
            raise GelSightRenderError(f"radii_px must be finite > 0 px, got {radii[~((radii > 0) & (radii < np.inf))]}")
        checked_number("mm_per_px", self.mm_per_px, *MM_PER_PX_RANGE)
        checked_number("ball_radius_mm", self.ball_radius_mm, *BALL_RADIUS_RANGE_MM)

    def subset(self, indices: Sequence[int]) -> Presses:
        keep = list(indices)
        return dataclasses.replace(
            self, frames=self.frames[keep], centers_xy_px=self.centers_xy_px[keep], radii_px=self.radii_px[keep]
        )

    @property
    def ball_radius_px(self) -> float:
        return self.ball_radius_mm / self.mm_per_px

    @property
    def shape(self) -> tuple[int, int]:
        return self.background.shape[0], self.background.shape[1]


def _distance_px(shape: tuple[int, int], center_xy_px: Sequence[float]) -> np.ndarray:
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    return np.hypot(cols - center_xy_px[0], rows - center_xy_px[1])


def _smoothed(background: np.ndarray, sigma_px: float) -> np.ndarray:
    """The background as the renderer draws it at its calibration's own size."""
    return cv2.GaussianBlur(background.astype(np.float32), (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)


def _require_presses(presses: Presses) -> None:
    if not isinstance(presses, Presses) or not len(presses.frames):
        got = f"{len(presses.frames)}" if isinstance(presses, Presses) else type(presses).__name__
        raise GelSightRenderError(f"presses must be Presses holding one or more presses, got {got}")


def fit_with_parameters(presses: Presses, parameters: dict[str, float]) -> PressFit:
    """The background and the tables fitted to ``presses`` (one or more) with the renderer's
    ``parameters`` fixed: some of FITTED, by name, each in GelSightConfig's range; otherwise
    GelSightRenderError naming the argument."""
    _require_presses(presses)
    if not isinstance(parameters, dict) or not set(parameters) <= set(FITTED):
        raise GelSightRenderError(f"parameters must map some of {list(FITTED)} to numbers, got {parameters!r:.120}")
    background = np.rint(
        np.clip(
            fit_background(presses.frames, presses.background, presses.centers_xy_px, presses.ball_radius_px), 0, 255
        )
    ).astype(np.uint8)
    config = press_config(presses.shape, presses.mm_per_px, parameters)
    pitch = presses.mm_per_px
    base = _smoothed(background, config.background_smoothing_mm / pitch)
    gaps = press_gaps_mm(presses.shape, presses.centers_xy_px, presses.radii_px, pitch, presses.ball_radius_mm)
    depths = [
        gel_surface_depth_mm(
            indentation_mm(gap, config.elastomer_thickness_mm),
            (config.spreading_length_mm / pitch,) * 2,
            (config.optical_blur_mm / pitch,) * 2,
        )
        for gap in gaps
    ]
    changes = [frame.astype(np.float32) - base for frame in presses.frames]
    near = [_distance_px(presses.shape, c) < NEAR_RADII * presses.ball_radius_px for c in presses.centers_xy_px]
    tables = fit_tables(depths, changes, near, pitch, config.compression_saturation_mm)
    return PressFit(tables, background, dict(parameters))


def render_fit(fit: PressFit, presses: Presses) -> list[np.ndarray]:
    """The fitted renderer's image of each press (against the fit's own background)."""
    renderer = GelSightRenderer(
        press_config(presses.shape, presses.mm_per_px, fit.parameters), calibration=fit.calibration()
    )
    gaps = press_gaps_mm(
        presses.shape, presses.centers_xy_px, presses.radii_px, presses.mm_per_px, presses.ball_radius_mm
    )
    return [renderer.render(gap) for gap in gaps]


def press_scores(images: Sequence[np.ndarray], presses: Presses) -> dict[str, list[float]]:
    """SSIM of each image against its real press: the touch crop and the full frame (one
    batch each: SSIM's set-up costs more than a frame)."""
    scores = press_ssim(images, presses.frames, presses.centers_xy_px, presses.mm_per_px)
    return {key: values.tolist() for key, values in scores.items()}


def fit_presses(presses: Presses, evaluations: int | None = None) -> PressFit:
    """The photometric model and the renderer's parameters that best render ``presses``
    (the mean of crop and full-frame SSIM), searched in log space from the renderer's defaults
    in ``evaluations`` renderings of them (default FIT_EVALUATIONS; 0: no search, the defaults').

    Contract: ``presses`` one or more; ``evaluations`` None or an integer in [0,
    MAX_FIT_EVALUATIONS]; otherwise GelSightRenderError naming the argument."""
    _require_presses(presses)
    if evaluations is None:
        evaluations = FIT_EVALUATIONS
    if isinstance(evaluations, (bool, np.bool_)) or not isinstance(evaluations, (int, np.integer)):
        raise GelSightRenderError(f"evaluations must be an integer, got {evaluations!r:.40}")
    if not 0 <= evaluations <= MAX_FIT_EVALUATIONS:
        raise GelSightRenderError(f"evaluations must be in [0, {MAX_FIT_EVALUATIONS}], got {evaluations!r:.40}")
    default = GelSightConfig()
    start = np.log([getattr(default, name) for name in FITTED])

    def fit_at(log_values: np.ndarray) -> PressFit:
        return fit_with_parameters(presses, dict(zip(FITTED, np.exp(log_values).tolist())))

    def loss(log_values: np.ndarray) -> float:
        try:
            fit = fit_at(log_values)
        except GelSightRenderError:
            return 2.0  # outside the renderer's range: worse than any SSIM
        scores = press_scores(render_fit(fit, presses), presses)
        return -float(np.mean(scores["crop"]) + np.mean(scores["full"])) / 2.0

    if evaluations == 0:
        return fit_at(start)
    simplex = np.vstack([start] + [start + 0.4 * np.eye(len(FITTED))[k] for k in range(len(FITTED))])
    result = minimize(
        loss, start, method="Nelder-Mead", options={"maxfev": evaluations, "initial_simplex": simplex, "xatol": 0.02}
    )
    return fit_at(result.x)
