"""``dtx sim gelsight-check``: how close the renderer comes to real GelSight frames.

The file holds real frames of a 4 mm-diameter ball pressed into the gel (layout of
assets/gelsight/ball_presses.npz: ``background``, ``frames``, ``touch_center`` (x, y px),
``touch_radius`` (px); 0.1245 mm per pixel). Each press is rendered from its annotated centre
and radius against the file's own background, and compared by SSIM (perception.ssim:
Gaussian window sigma 1.5, data range 255, per channel) on the full frame and on a 48x48 crop
centred on the touch, next to two baselines computed the same way: the background alone, and
the mean over 15 random other real frames (seeded), as in the paper's evaluation.

``--holdout`` refits the renderer's physical parameters on the even frames and reports the
odd frames, with the fitted and with the default parameters: the defaults should hold there.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from perception.ssim import WINDOW, ssim_rgb
from sim.gelsight import MAX_LENGTH_MM, GelSightConfig, GelSightRenderer, GelSightRenderError
from sim.gelsight_calibration import renderer_parameters
from sim.press_annotation import BALL_RADIUS_RANGE_MM, MM_PER_PX_RANGE, checked_number, find_checked_presses

BALL_RADIUS_MM = 2.0
FILE_MM_PER_PX = 0.1245
CROP_PX = 48  # the touch crop on the shipped 120 x 160 frames: 6 mm of gel
CROP_MM = CROP_PX * FILE_MM_PER_PX
N_RANDOM_FRAMES = 15
KEYS = ("crop", "full", "background_crop", "background_full", "random_crop", "random_full")
# The renderer's fitted parameters and where a fit starts: neutral, physically plausible
# values (spread and blur of the order of the gel's features, no gain, light smoothing), not
# the defaults, so that a holdout fit shows what the data alone determine.
FIT_START = {
    "spreading_length_mm": 1.0,
    "optical_blur_mm": 0.25,
    "compression_saturation_mm": 1.0,
    "shading_gain": 1.0,
    "background_smoothing_mm": 0.3,
}


@dataclasses.dataclass(frozen=True)
class BallPresses:
    background: np.ndarray  # HxWx3 uint8
    frames: np.ndarray  # NxHxWx3 uint8
    centers_xy_px: np.ndarray  # Nx2 (x column, y row)
    radii_px: np.ndarray  # N
    mm_per_px: float  # the frames' scale
    ball_radius_mm: float  # the pressed ball's
    file_indices: tuple[int, ...]  # each press's frame in the file
    left_out: dict[int, str]  # frames the press finder could not trust, and why
    annotations: str  # where the centres and radii come from: "file" or "finder"


def read_press_file(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Every array of a press file (.npz, no pickles) by key, its frames and its background;
    GelSightRenderError when the file is missing or unreadable, or its background is not an
    H x W x 3 uint8 frame (H, W >= 16) with N frames like it."""
    path = Path(path)
    if not path.is_file():
        raise GelSightRenderError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            contents = {key: np.asarray(data[key]) for key in data.files}
    except (OSError, ValueError) as exc:
        raise GelSightRenderError(f"{path}: not a readable .npz file ({exc})") from exc
    missing = sorted({"background", "frames"} - set(contents))
    if missing:
        raise GelSightRenderError(f"{path}: missing keys {missing}")
    background, frames = contents["background"], contents["frames"]
    if (
        background.ndim != 3
        or background.shape[2] != 3
        or background.dtype != np.uint8
        or min(background.shape[:2]) < 16
    ):
        raise GelSightRenderError(
            f"{path}: background must be HxWx3 uint8 (H, W >= 16), got {background.shape} {background.dtype}"
        )
    if frames.ndim != 4 or frames.shape[1:] != background.shape or frames.dtype != np.uint8:
        raise GelSightRenderError(
            f"{path}: frames must be N x {' x '.join(map(str, background.shape))} uint8 like the background, "
            f"got {frames.shape} {frames.dtype}"
        )
    return contents, frames, background


def load_ball_presses(
    path: str | os.PathLike[str], mm_per_px: float | None = None, ball_radius_mm: float | None = None
) -> BallPresses:
    """Read and check a ball-press file; every problem raises :class:`GelSightRenderError`. The
    scale and the ball are the arguments, else the file's, else the shipped file's. A file without
    ``touch_center`` and ``touch_radius`` (a lab's raw presses) has its presses found by
    ``sim.press_annotation``; those it cannot trust are left out and named."""
    path = Path(path)
    contents, frames, background = read_press_file(path)
    scale = press_scalar(path, contents, "mm_per_px", mm_per_px, FILE_MM_PER_PX, MM_PER_PX_RANGE)
    ball = press_scalar(path, contents, "ball_radius_mm", ball_radius_mm, BALL_RADIUS_MM, BALL_RADIUS_RANGE_MM)
    annotated = {"touch_center", "touch_radius"} & set(contents)
    if len(annotated) == 1:
        raise GelSightRenderError(
            f"{path}: {annotated.pop()} without its pair: give touch_center and touch_radius, or neither "
            "for the press finder"
        )
    if annotated:
        indices, left_out = np.arange(len(frames)), {}
        centers, radii = _checked_annotations(path, contents, background.shape[:2])
    else:
        found = find_checked_presses(frames, background, scale, ball)
        indices = np.flatnonzero(found.trusted)
        left_out = {int(i): reason for i, reason in enumerate(found.reasons) if reason}
        frames, centers, radii = frames[indices], found.centers_xy_px[indices], found.radii_px[indices]
    if len(frames) < 2:
        raise GelSightRenderError(
            f"{path}: needs at least 2 presses for the random-frame baseline, got {len(frames)} "
            f"({'; '.join(f'press {i}: {r}' for i, r in left_out.items()) or 'none left out'})"
        )
    source = "file" if annotated else "finder"
    return BallPresses(background, frames, centers, radii, scale, ball, tuple(indices.tolist()), left_out, source)


def _checked_annotations(
    path: Path, contents: dict[str, np.ndarray], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The file's touch_center (N x 2) and touch_radius (N) as float64, checked against its frames."""
    n, (h, w) = len(contents["frames"]), shape
    centers, radii = contents["touch_center"], contents["touch_radius"]
    if centers.shape != (n, 2) or radii.shape != (n,):
        raise GelSightRenderError(
            f"{path}: touch_center must be {n}x2 and touch_radius {n}, got {centers.shape} and {radii.shape}"
        )
    centers, radii = centers.astype(np.float64), radii.astype(np.float64)
    if not (np.all(np.isfinite(centers)) and np.all(np.isfinite(radii))):
        raise GelSightRenderError(f"{path}: touch_center and touch_radius must be finite")
    if np.any(radii <= 0):
        raise GelSightRenderError(f"{path}: touch_radius must be > 0 px, got {radii[radii <= 0].tolist()}")
    outside = (centers[:, 0] < 0) | (centers[:, 0] > w - 1) | (centers[:, 1] < 0) | (centers[:, 1] > h - 1)
    if np.any(outside):
        raise GelSightRenderError(
            f"{path}: touch_center outside the {w}x{h} frame for frames {np.flatnonzero(outside).tolist()}"
        )
    return centers, radii


def press_scalar(
    path: str | Path,
    contents: dict[str, np.ndarray],
    key: str,
    given: float | None,
    default: float | None,
    limits: tuple[float, float],
) -> float:
    """``given``, else the press file's ``key`` (``dtx calibrate gelsight``'s files hold their scale
    and ball), else ``default`` (the shipped file's; None: the value is needed); GelSightRenderError
    when there is none or it is not a number within ``limits``."""
    option = f"--{key.replace('_', '-')}"
    if given is None and key not in contents and default is None:
        raise GelSightRenderError(f"{path}: no {key}: store it in the file or give {option}")
    value = np.asarray(given if given is not None else contents.get(key, default))
    if value.shape != () or value.dtype.kind not in "iuf" or not limits[0] <= float(value) <= limits[1]:
        source = option if given is not None else f"{path}: {key}"
        raise GelSightRenderError(f"{source} must be a number in [{limits[0]:g}, {limits[1]:g}], got {value!r}")
    return float(value)


def press_depth_mm(contact_radius_mm: float, ball_radius_mm: float = BALL_RADIUS_MM) -> float:
    """Depth of a sphere pressed into a plane until the contact has radius ``a``:
    ``R - sqrt(R^2 - a^2)``. An annotated radius larger than the ball (the annotation traced
    the edge of the visible imprint, which the gel's spread widens) means the ball is in up
    to its equator, so ``a`` is capped at ``R``. Both radii finite and > 0 mm, the ball's at most
    MAX_LENGTH_MM (a length on the gel); otherwise GelSightRenderError (NaN and inf too)."""
    if not (0 < contact_radius_mm < math.inf and 0 < ball_radius_mm <= MAX_LENGTH_MM):
        raise GelSightRenderError(
            f"contact radius must be finite > 0 mm and ball radius in (0, {MAX_LENGTH_MM:g}] mm, "
            f"got {contact_radius_mm!r}, {ball_radius_mm!r}"
        )
    a = min(contact_radius_mm, ball_radius_mm)
    return ball_radius_mm - math.sqrt(ball_radius_mm**2 - a**2)


def ball_gap_map(
    shape: tuple[int, int],
    center_xy_px: Sequence[float],
    depth_mm: float,
    mm_per_px: float,
    ball_radius_mm: float = BALL_RADIUS_MM,
) -> np.ndarray:
    """Gel gap map (HxW float32 mm) of a ball whose lowest point is ``depth_mm`` into the gel."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    r2 = ((cols - center_xy_px[0]) ** 2 + (rows - center_xy_px[1]) ** 2) * mm_per_px**2
    under_ball = r2 < ball_radius_mm**2
    gap = np.full(shape, np.inf)
    gap[under_ball] = ball_radius_mm - np.sqrt(ball_radius_mm**2 - r2[under_ball]) - depth_mm
    return gap.astype(np.float32)


def crop_px(mm_per_px: float) -> int:
    """The side of the touch crop at ``mm_per_px`` (in MM_PER_PX_RANGE, else GelSightRenderError):
    the same CROP_MM of gel at any frame size."""
    return max(16, round(CROP_MM / checked_number("mm_per_px", mm_per_px, *MM_PER_PX_RANGE)))


def touch_crop(image: np.ndarray, center_xy_px: Sequence[float], size: int) -> np.ndarray:
    """The size x size window centred on the touch, shifted inside the frame at its edges.

    Contract: ``image`` at least 2-D, ``size`` an integer from 1 to its height and width (a larger
    window has no place in it), ``center_xy_px`` two finite numbers; otherwise GelSightRenderError
    naming the argument."""
    if not isinstance(image, np.ndarray) or image.ndim < 2:
        raise GelSightRenderError(f"image must be an H x W (x C) array, got {getattr(image, 'shape', type(image))}")
    h, w = image.shape[:2]
    if isinstance(size, (bool, np.bool_)) or not isinstance(size, (int, np.integer)) or not 1 <= size <= min(h, w):
        raise GelSightRenderError(f"size must be an integer from 1 to the image's {h} x {w}, got {size!r}")
    x, y = _checked_centre(center_xy_px)
    x0 = int(np.clip(round(x) - size // 2, 0, w - size))
    y0 = int(np.clip(round(y) - size // 2, 0, h - size))
    return image[y0 : y0 + size, x0 : x0 + size]


def _real_array(value: object) -> np.ndarray:
    """``value`` as an array when it is a sequence of real numbers (an empty array otherwise, which no
    contract's shape takes)."""
    try:
        array = np.asarray(value) if isinstance(value, (Sequence, np.ndarray)) else np.zeros(0)
    except (TypeError, ValueError):  # a ragged sequence
        return np.zeros(0)
    return array if array.dtype.kind in "iuf" else np.zeros(0)


def _checked_centre(center_xy_px: object) -> tuple[float, float]:
    centre = _real_array(center_xy_px)
    if centre.shape != (2,) or not np.all(np.isfinite(centre)):
        raise GelSightRenderError(f"center_xy_px must be two finite numbers (x, y px), got {center_xy_px!r}")
    return float(centre[0]), float(centre[1])


def _stacked(name: str, images: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """``images`` as one N x H x W x 3 uint8 array, H and W at least SSIM's window."""
    try:
        # list(): np.stack takes a sequence of arrays; an N x ... array is one, row by row.
        stack = np.stack(list(images)) if len(images) else np.zeros((0, WINDOW, WINDOW, 3), np.uint8)
    except (TypeError, ValueError) as exc:
        raise GelSightRenderError(f"{name} must be H x W x 3 uint8 images of one size ({exc})") from exc
    if stack.ndim != 4 or stack.shape[3] != 3 or stack.dtype != np.uint8 or min(stack.shape[1:3]) < WINDOW:
        raise GelSightRenderError(
            f"{name} must be H x W x 3 uint8 images, H and W at least {WINDOW} (SSIM's window), "
            f"got {stack.shape} {stack.dtype}"
        )
    return stack


def press_ssim(
    images: Sequence[np.ndarray] | np.ndarray,
    frames: Sequence[np.ndarray] | np.ndarray,
    centers_xy_px: np.ndarray,
    mm_per_px: float,
) -> dict[str, np.ndarray]:
    """SSIM of each image against its real frame: the touch crop (:func:`crop_px` at
    ``mm_per_px``, around each centre; a frame narrower than that crop gives a square of its
    smaller side) and the full frame, one batch each (SSIM's set-up costs more than a frame).

    Contract: ``images`` and ``frames`` N >= 0 H x W x 3 uint8 images of one size (H, W >= SSIM's
    window), ``centers_xy_px`` N x 2 finite, ``mm_per_px`` in MM_PER_PX_RANGE; otherwise
    GelSightRenderError naming the argument."""
    size = crop_px(mm_per_px)
    image_stack, frame_stack = _stacked("images", images), _stacked("frames", frames)
    centres, n = _real_array(centers_xy_px), len(frame_stack)
    if image_stack.shape != frame_stack.shape or centres.shape != (n, 2) or not np.all(np.isfinite(centres)):
        raise GelSightRenderError(
            f"images, frames and centers_xy_px must be N images of one size and N x 2 finite centres, got "
            f"{image_stack.shape}, {frame_stack.shape} and {centres.shape} {centres.dtype}"
        )
    if not n:
        return {"crop": np.zeros(0), "full": np.zeros(0)}
    size = min(size, *frame_stack.shape[1:3])
    crops = np.stack([touch_crop(i, c, size) for i, c in zip(image_stack, centres)])
    real_crops = np.stack([touch_crop(r, c, size) for r, c in zip(frame_stack, centres)])
    return {"crop": ssim_rgb(crops, real_crops), "full": ssim_rgb(image_stack, frame_stack)}


def render_presses(
    presses: BallPresses, indices: Sequence[int], config: GelSightConfig, file_background: bool = True
) -> list[np.ndarray]:
    """Render the presses ``indices`` with ``config`` against the file's background (or, without
    ``file_background``, the calibration's: a fitted calibration's is the sensor's mean no-contact frame)."""
    renderer = GelSightRenderer(config, background=presses.background if file_background else None)
    images = []
    ball_mm = presses.ball_radius_mm
    for i in indices:
        depth = press_depth_mm(presses.radii_px[i] * config.mm_per_px, ball_mm)
        gap = ball_gap_map(config.shape, presses.centers_xy_px[i], depth, config.mm_per_px, ball_mm)
        images.append(renderer.render(gap))
    return images


def _file_config(presses: BallPresses, **params: float | str) -> GelSightConfig:
    h, w = presses.background.shape[:2]
    return GelSightConfig(image_height=h, image_width=w, mm_per_px=presses.mm_per_px, **params)  # type: ignore[arg-type]


def calibration_config(presses: BallPresses, calibration_dir: str | Path) -> GelSightConfig:
    """The renderer of ``calibration_dir`` (its tables and physical parameters) at the file's size and scale."""
    return _file_config(presses, calibration_dir=str(calibration_dir), **renderer_parameters(calibration_dir))


def _mean_ssim(presses: BallPresses, indices: Sequence[int], config: GelSightConfig) -> dict[str, float]:
    indices = list(indices)
    scores = press_ssim(
        render_presses(presses, indices, config),
        presses.frames[indices],
        presses.centers_xy_px[indices],
        presses.mm_per_px,
    )
    return {key: float(np.mean(values)) for key, values in scores.items()}


def fit_parameters(presses: BallPresses, indices: Sequence[int], max_evaluations: int = 300) -> dict[str, float]:
    """The parameters of :data:`FIT_START` maximising mean crop + full SSIM on ``indices``
    (Nelder-Mead: SSIM is not differentiable through the slope-bin look-up)."""
    names = list(FIT_START)
    start = np.array(list(FIT_START.values()))
    # First simplex: each parameter moved by half its start value.
    simplex = np.vstack([start] + [start + 0.5 * start[k] * np.eye(len(names))[k] for k in range(len(names))])

    def loss(values: np.ndarray) -> float:
        try:
            config = _file_config(presses, **dict(zip(names, map(float, values))))
        except GelSightRenderError:
            return 2.0  # outside the physical range: worse than any SSIM sum
        score = _mean_ssim(presses, indices, config)
        return -(score["crop"] + score["full"])

    result = minimize(
        loss, start, method="Nelder-Mead", options={"maxfev": max_evaluations, "initial_simplex": simplex}
    )
    return dict(zip(names, map(float, result.x)))


def _frame_scores(presses: BallPresses, renders: Sequence[np.ndarray], seed: int) -> list[dict[str, float]]:
    """Each press's SSIM (full frame, touch crop) of its rendering, the background and the mean
    of N_RANDOM_FRAMES other frames (seeded), named by its frame in the file."""
    n, real, centers = len(presses.frames), presses.frames, presses.centers_xy_px
    rng = np.random.default_rng(seed)
    rendered = press_ssim(renders, real, centers, presses.mm_per_px)
    background = press_ssim([presses.background] * n, real, centers, presses.mm_per_px)
    frames = []
    for i in range(n):
        others = rng.choice(np.delete(np.arange(n), i), size=min(N_RANDOM_FRAMES, n - 1), replace=False)
        random = press_ssim(real[others], [real[i]] * len(others), centers[[i] * len(others)], presses.mm_per_px)
        frames.append(
            {
                "index": presses.file_indices[i],
                "crop": float(rendered["crop"][i]),
                "full": float(rendered["full"][i]),
                "background_crop": float(background["crop"][i]),
                "background_full": float(background["full"][i]),
                "random_crop": float(random["crop"].mean()),
                "random_full": float(random["full"].mean()),
            }
        )
    return frames


def run_check(
    npz_path: str | Path,
    seed: int = 0,
    holdout: bool = False,
    calibration_dir: str | Path | None = None,
    mm_per_px: float | None = None,
    ball_radius_mm: float | None = None,
) -> dict:
    """SSIM of the renderings and of the two baselines, per frame and on average (the JSON of
    ``dtx sim gelsight-check``); with ``holdout`` also the even/odd refit figures. With
    ``calibration_dir`` the renderer is that calibration's, its background included. Scale and
    ball as :func:`load_ball_presses` reads them; frames are named by their index in the file."""
    presses = load_ball_presses(npz_path, mm_per_px, ball_radius_mm)
    n = presses.frames.shape[0]
    if calibration_dir is None:
        renders = render_presses(presses, range(n), _file_config(presses))
    else:
        config = calibration_config(presses, calibration_dir)
        renders = render_presses(presses, range(n), config, file_background=False)
    frames = _frame_scores(presses, renders, seed)
    result = {
        "file": str(npz_path),
        "calibration": str(calibration_dir or GelSightConfig().calibration_dir),
        "seed": seed,
        "mm_per_px": presses.mm_per_px,
        "ball_radius_mm": presses.ball_radius_mm,
        "n_frames": n,
        "annotations": presses.annotations,
        "left_out": presses.left_out,
        "mean": {key: float(np.mean([f[key] for f in frames])) for key in KEYS},
        "frames": frames,
    }
    if holdout:
        train, test = list(range(0, n, 2)), list(range(1, n, 2))
        fitted = fit_parameters(presses, train)
        result["holdout"] = {
            "fit_frames": [presses.file_indices[i] for i in train],
            "test_frames": [presses.file_indices[i] for i in test],
            "fitted_parameters": fitted,
            "test_default": _mean_ssim(presses, test, _file_config(presses)),
            "test_fitted": _mean_ssim(presses, test, _file_config(presses, **fitted)),
            "train_fitted": _mean_ssim(presses, train, _file_config(presses, **fitted)),
        }
    return result


def format_table(result: dict) -> str:
    """The check's result as a readable table."""
    header = f"{'frame':>6} " + " ".join(f"{key:>16}" for key in KEYS)
    lines = [
        f"gelsight-check {result['file']} ({result['n_frames']} frames, {result['mm_per_px']:g} mm/px, ball radius "
        f"{result['ball_radius_mm']:g} mm, centres and radii from the {result['annotations']}, seed {result['seed']})",
        *(f"  left out: press {i}: {reason}" for i, reason in result["left_out"].items()),
        "SSIM",
        header,
    ]
    for f in result["frames"]:
        lines.append(f"{f['index']:>6} " + " ".join(f"{f[key]:>16.4f}" for key in KEYS))
    lines.append(f"{'mean':>6} " + " ".join(f"{result['mean'][key]:>16.4f}" for key in KEYS))
    if "holdout" in result:
        h = result["holdout"]
        lines.append("holdout: fitted on even frames, scored on odd frames")
        for name in ("train_fitted", "test_fitted", "test_default"):
            lines.append(f"  {name:>13}: crop {h[name]['crop']:.4f}  full {h[name]['full']:.4f}")
        lines.append("  fitted: " + ", ".join(f"{k}={v:.3f}" for k, v in h["fitted_parameters"].items()))
    return "\n".join(lines)
