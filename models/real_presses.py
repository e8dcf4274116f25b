"""A model judged on real GelSight frames of contacts it never saw (``dtx evaluate --real-presses``).

The file (layout of assets/gelsight/ball_presses.npz, read by ``sim.gelsight_check``) holds real
frames of a ball pressed into the gel, each with its annotated centre (x column, y row, px) and
contact radius (px). For each press the system sees what it would see at a grasp:

* **the contact**: the ball in the gel frame (workcell.kinematics; x along image columns, z
  along image rows, y out of the gel), centred under the annotated pixel, its lowest point
  ``press_depth_mm`` into the gel (the sphere-cap depth that gives the annotated radius);
* **the depth-map**: the ball's surface sampled uniformly at ``MODEL_POINT_SPACING_M``, as a
  model cloud is, and binned by ``perception.depthmap.contact_depth_map`` with the inference
  node's parameters (the scene's gripper geometry, its margin, the checkpoint's depth range);
* **the truth**: the real frame brought to the model's grid as the collector brings a sensor
  frame (``dataset.images.resize_rgb``).

Estimates scored against the truth, each by SSIM (Gaussian sigma 1.5, data range 255, per
channel; perception.ssim) and PSNR, over the whole image and over the press window — the box of
side ``WINDOW_RADII`` contact radii around the press, cut from both images:

* ``model`` — the model fed the press's depth-map; ``model_empty`` — fed an empty map;
* ``background`` — the file's no-contact frame; ``random`` — ``RANDOM_FRAMES`` random other
  presses of the file (seeded), averaged;
* ``renderer`` — the simulated GelSight (the scene's, effects off) fed the same contact, exact
  (the ball's gap at every pixel of the file's frame), then brought to the grid as the truth is;
* ``renderer_depth_map`` — the renderer fed what the model is fed, the press's depth-map: the
  model's own physics prior (sharp: the press's geometry is exact), the image its correction
  starts from; for a model without a prior the scene's renderer at the grid, as a prior draws it.
  The model scoring below this row is a correction making physics worse; the gap between this
  row and ``renderer`` is what the depth-map (0.24 x 0.19 mm bins, each its nearest point) and
  the grid-size rendering cost before any learning.

Location: the truth's press window is searched for in each estimate (OpenCV TM_CCOEFF_NORMED)
and the distance from the match to the annotated place is given in mm.

The real frames are for evaluation only: nothing here fits anything to them. The uncertainty a
lab's own presses would give the checkpoint (models.sensor_floor) is scored press by press with
the floor fitted on the other presses only.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dataset.images import resize_rgb
from models.errors import ModelConfigError
from models.networks import UNetGenerator
from models.sensor_floor import press_uncertainty_statistics, presses_digest
from models.serving import predict, predict_served
from models.uncertainty import uncertainty_table
from perception.depthmap import MODEL_POINT_SPACING_M, DepthMapParams, contact_depth_map, crop_bounds
from perception.errors import DepthMapError
from perception.ssim import WINDOW, psnr_rgb, ssim_rgb
from sim.gelsight import (
    PIXEL_PITCH_RANGE_MM,
    GelSightRenderer,
    GelSightRenderError,
    render_depth_maps,
    scene_renderer,
)
from sim.gelsight_check import BallPresses, ball_gap_map, load_ball_presses, press_depth_mm
from workcell.kinematics import GripperGeometry
from workcell.scene import Scene, SceneError, load_scene

WINDOW_RADII = 3.0
RANDOM_FRAMES = 15
ESTIMATES = ("model", "model_empty", "background", "renderer", "renderer_depth_map", "random")
DEFAULT_SCENE = "scenes/ycb_three.yaml"
# Sizes a pressed ball may have (mm radius): from a ball 0.1 mm across, about one pixel of the
# sensor, to one 50 mm across, as wide as the 24.9 mm gel (a larger one presses a nearly flat cap
# into it). Its cloud at the model spacing (0.1 mm) has 0.8 M points (19 MB).
BALL_RADIUS_RANGE_MM = (0.05, 25.0)
# Most points of a ball's cloud (24 MB of float64 points, twice that while it is drawn).
MAX_BALL_POINTS = 1_000_000
# Widest crop margin (m) the evaluation bins with: the calibration offset it absorbs is a few
# mm, and 10 mm is more than the gel's half-width.
MAX_MARGIN_M = 0.01


def _check_press_settings(ball_radius_mm: float, mm_per_px: float) -> None:
    """ModelConfigError naming the argument unless the ball radius is in BALL_RADIUS_RANGE_MM
    and the pixel pitch in sim.gelsight.PIXEL_PITCH_RANGE_MM (NaN and inf fail both)."""
    low, high = BALL_RADIUS_RANGE_MM
    if not (_is_real(ball_radius_mm) and low <= ball_radius_mm <= high):
        raise ModelConfigError(f"--ball-radius-mm must be in [{low:g}, {high:g}] mm, got {ball_radius_mm!r}")
    low, high = PIXEL_PITCH_RANGE_MM
    if not (_is_real(mm_per_px) and low <= mm_per_px <= high):
        raise ModelConfigError(f"--mm-per-px must be in [{low:g}, {high:g}] mm, got {mm_per_px!r}")


def _is_real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


@dataclasses.dataclass(frozen=True)
class PressGeometry:
    """One press in the gel frame and on the model's grid."""

    centre_x_mm: float  # gel x of the ball's centre (along image columns)
    centre_z_mm: float  # gel z (along image rows)
    depth_mm: float  # lowest point of the ball below the gel surface
    contact_radius_mm: float
    window: tuple[int, int, int, int]  # rows r0:r1, columns c0:c1 of the press box on the grid


def press_geometry(
    presses: BallPresses, index: int, mm_per_px: float, ball_radius_mm: float, grid: tuple[int, int]
) -> PressGeometry:
    """Where press ``index`` is: in the gel frame from the file's pixels, and on the model's
    ``grid`` (rows, columns), which shows the same camera field as the file's frames. Ball and
    pitch as :func:`evaluate_real_presses` takes them; otherwise ModelConfigError."""
    _check_press_settings(ball_radius_mm, mm_per_px)
    height, width = presses.background.shape[:2]
    col_px, row_px = presses.centers_xy_px[index]
    contact_mm = float(presses.radii_px[index]) * mm_per_px
    # Pixel j's centre is at (j - (n - 1) / 2) * pitch from the gel centre (sim.grasp_contact.gel_grid).
    x_mm = (col_px - (width - 1) / 2) * mm_per_px
    z_mm = (row_px - (height - 1) / 2) * mm_per_px
    rows, cols = grid
    col_grid = (col_px + 0.5) * cols / width - 0.5
    row_grid = (row_px + 0.5) * rows / height - 0.5
    half_cols = 0.5 * WINDOW_RADII * contact_mm / (mm_per_px * width / cols)
    half_rows = 0.5 * WINDOW_RADII * contact_mm / (mm_per_px * height / rows)
    window = (
        max(0, int(round(row_grid - half_rows))),
        min(rows, int(round(row_grid + half_rows)) + 1),
        max(0, int(round(col_grid - half_cols))),
        min(cols, int(round(col_grid + half_cols)) + 1),
    )
    return PressGeometry(x_mm, z_mm, press_depth_mm(contact_mm, ball_radius_mm), contact_mm, window)


def ball_cloud_m(ball_radius_mm: float, spacing_m: float = MODEL_POINT_SPACING_M, seed: int = 0) -> np.ndarray:
    """Points uniformly on a sphere of ``ball_radius_mm`` about the origin (N x 3 m), one per
    ``spacing_m``² of surface, as ``perception.registration.sample_model_cloud`` samples a mesh.
    ``ball_radius_mm`` in BALL_RADIUS_RANGE_MM, ``spacing_m`` positive and at most
    MAX_BALL_POINTS points; otherwise ModelConfigError, before any point is drawn."""
    low, high = BALL_RADIUS_RANGE_MM
    if not (_is_real(ball_radius_mm) and low <= ball_radius_mm <= high):
        raise ModelConfigError(f"ball_radius_mm must be in [{low:g}, {high:g}] mm, got {ball_radius_mm!r}")
    radius_m = ball_radius_mm * 1e-3
    if not (
        _is_real(spacing_m) and spacing_m > 0 and 4 * np.pi * radius_m**2 / MAX_BALL_POINTS <= spacing_m**2 < np.inf
    ):
        raise ModelConfigError(
            f"spacing_m {spacing_m!r} must be finite, positive and leave at most {MAX_BALL_POINTS} points on a "
            f"{ball_radius_mm:g} mm ball"
        )
    count = max(int(4 * np.pi * radius_m**2 / spacing_m**2), 100)
    directions = np.random.default_rng(seed).standard_normal((count, 3))
    return radius_m * directions / np.linalg.norm(directions, axis=1, keepdims=True)


def press_depth_map(
    press: PressGeometry,
    ball_radius_mm: float,
    geometry: GripperGeometry,
    params: DepthMapParams,
    cloud_m: np.ndarray | None = None,
) -> np.ndarray:
    """The depth-map (m) the system would make of the press: the ball's cloud placed in the gel
    frame and binned as the inference node bins a region."""
    cloud = ball_cloud_m(ball_radius_mm) if cloud_m is None else cloud_m
    ball_to_gel = np.eye(4)
    ball_to_gel[:3, 3] = [press.centre_x_mm * 1e-3, (ball_radius_mm - press.depth_mm) * 1e-3, press.centre_z_mm * 1e-3]
    return contact_depth_map(cloud, ball_to_gel, np.eye(4), geometry, params).depth_map_m


LOCATION_UNDEFINED = "the estimate has no structure: the press's template matches it nowhere"


def location_error_mm(
    truth: np.ndarray, estimate: np.ndarray, press: PressGeometry, field_mm: tuple[float, float]
) -> float:
    """Distance (mm) between the press box's place in the truth and its best match
    (TM_CCOEFF_NORMED) in the estimate; ``field_mm`` is the grid's (height, width) in mm. An
    estimate with no structure matches nowhere: the distance is then NaN."""
    r0, r1, c0, c1 = press.window
    template = np.ascontiguousarray(truth[r0:r1, c0:c1])
    scores = cv2.matchTemplate(np.ascontiguousarray(estimate), template, cv2.TM_CCOEFF_NORMED)
    if not np.all(np.isfinite(scores)) or np.ptp(scores) == 0:
        return float("nan")
    _, _, _, (col, row) = cv2.minMaxLoc(scores)
    rows, cols = truth.shape[:2]
    return float(np.hypot((col - c0) * field_mm[1] / cols, (row - r0) * field_mm[0] / rows))


def evaluate_real_presses(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    path: str | os.PathLike[str],
    scene: Scene | str = DEFAULT_SCENE,
    ball_radius_mm: float | None = None,
    mm_per_px: float | None = None,
    margin_m: float = 0.002,
    seed: int = 0,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Scores of every estimate on every press (module docstring): the JSON of ``dtx evaluate
    --real-presses`` and the images behind it (for figures; ``uncertainty_own``: the checkpoint's
    u without a sensor floor, where it has a u). The ball and the scale are the file's own (``sim.gelsight_check.load_ball_presses``) unless given.

    Contract: ``ball_radius_mm`` in BALL_RADIUS_RANGE_MM, ``mm_per_px`` in
    sim.gelsight.PIXEL_PITCH_RANGE_MM, ``margin_m`` in [0, MAX_MARGIN_M], ``seed`` an integer >= 0,
    ``depth_range_m`` as perception.depthmap.crop_bounds takes it. Bad input raises
    ModelConfigError naming it, before any depth-map is cut."""
    if not (_is_real(margin_m) and 0 <= margin_m <= MAX_MARGIN_M):
        raise ModelConfigError(f"margin_m must be in [0, {MAX_MARGIN_M:g}] m, got {margin_m!r}")
    if not (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0):
        raise ModelConfigError(f"seed must be an integer >= 0, got {seed!r}")
    presses, scene, renderer = _load_presses(path, scene, mm_per_px, ball_radius_mm)
    ball_radius_mm, mm_per_px = presses.ball_radius_mm, presses.mm_per_px
    _check_press_settings(ball_radius_mm, mm_per_px)
    grid = (generator.config.image_size, generator.config.image_size)
    n = len(presses.frames)
    geometries = [press_geometry(presses, i, mm_per_px, ball_radius_mm, grid) for i in range(n)]
    _check_windows(path, geometries, grid)
    geometry = scene.gripper_geometry()
    params = DepthMapParams(shape=grid, margin_m=margin_m, y_range_m=depth_range_m, method=generator.depth_map_method)
    try:
        crop_bounds(geometry, params)
    except DepthMapError as err:
        raise ModelConfigError(f"depth_range_m {depth_range_m!r}: {err}") from err
    cloud = ball_cloud_m(ball_radius_mm)
    depth_maps = np.stack([press_depth_map(g, ball_radius_mm, geometry, params, cloud) for g in geometries])
    empty = np.full((1, *grid), depth_range_m[1], dtype=np.float32)
    # The press is placed by its annotation, not by a registration: its geometry is exact.
    model, own_uncertainty = predict_served(generator, depth_maps, depth_range_m, pose_sigma_mm=0.0, sensor_floor=False)
    images = {
        "truth": np.stack([resize_rgb(f, *grid) for f in presses.frames]),
        "depth_maps_m": depth_maps,
        "model": model,
        "model_empty": np.repeat(predict(generator, empty, depth_range_m, pose_sigma_mm=0.0), n, axis=0),
        "background": np.repeat(resize_rgb(presses.background, *grid)[None], n, axis=0),
        "renderer": _renderer_images(renderer, presses, geometries, grid, mm_per_px, ball_radius_mm),
        "renderer_depth_map": _renderer_of_depth_maps(generator, scene, depth_maps, geometry, params),
    }
    rng = np.random.default_rng(seed)
    others = [rng.choice(np.delete(np.arange(n), i), size=min(RANDOM_FRAMES, n - 1), replace=False) for i in range(n)]
    height, width = presses.background.shape[:2]
    scores = _score_presses(images, geometries, others, (height * mm_per_px, width * mm_per_px))
    settings = {"ball_radius_mm": ball_radius_mm, "mm_per_px": mm_per_px, "window_radii": WINDOW_RADII, "seed": seed}
    dissimilarity = 1.0 - np.asarray(scores["full_ssim"]["model"])
    summary = _summary(scores, geometries, presses) | press_uncertainty_statistics(
        generator.uncertainty, own_uncertainty, model, images["truth"], dissimilarity, presses_digest(path)
    )
    images |= {} if own_uncertainty is None else {"uncertainty_own": own_uncertainty}
    return {"n": n, "file": str(path), **settings, **summary}, images


def _check_windows(path: str | os.PathLike[str], geometries: list[PressGeometry], grid: tuple[int, int]) -> None:
    """ModelConfigError naming the presses whose window is too small for SSIM on ``grid``."""
    small = [i for i, g in enumerate(geometries) if min(g.window[1] - g.window[0], g.window[3] - g.window[2]) < WINDOW]
    if small:
        raise ModelConfigError(
            f"{path}: presses {small} have a window under {WINDOW} px on the {grid} grid "
            "(contact radius too small for SSIM)"
        )


def _load_presses(
    path: str | os.PathLike[str], scene: Scene | str, mm_per_px: float | None, ball_radius_mm: float | None
) -> tuple[BallPresses, Scene, GelSightRenderer]:
    """The presses file (its presses found where it has no annotations), the scene and its
    GelSight renderer (effects off), which must draw frames of the file's size; ModelConfigError
    otherwise."""
    try:
        presses = load_ball_presses(path, mm_per_px, ball_radius_mm)
        scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
        renderer = scene_renderer(scene, effects=False)
    except (GelSightRenderError, SceneError) as err:
        raise ModelConfigError(str(err)) from err
    height, width = presses.background.shape[:2]
    if renderer.config.shape != (height, width):
        raise ModelConfigError(f"{path}: frames are {height} x {width}, the scene's GelSight {renderer.config.shape}")
    return presses, scene, renderer


def _renderer_images(
    renderer: GelSightRenderer,
    presses: BallPresses,
    geometries: list[PressGeometry],
    grid: tuple[int, int],
    mm_per_px: float,
    ball_radius_mm: float,
) -> np.ndarray:
    """The simulated GelSight's image of every press, rendered at the file's size and brought
    to the model's grid."""
    shape = presses.background.shape[:2]
    return np.stack(
        [
            resize_rgb(
                renderer.render(ball_gap_map(shape, presses.centers_xy_px[i], g.depth_mm, mm_per_px, ball_radius_mm)),
                *grid,
            )
            for i, g in enumerate(geometries)
        ]
    )


def _renderer_of_depth_maps(
    generator: UNetGenerator, scene: Scene, depth_maps_m: np.ndarray, geometry: GripperGeometry, params: DepthMapParams
) -> np.ndarray:
    """The GelSight renderer fed the depth-maps the model is fed (module docstring,
    ``renderer_depth_map``): the model's own prior at pose sigma 0, or without one the scene's
    renderer at the grid reading the maps over their crop."""
    if generator.prior is not None:
        return generator.prior.images(depth_maps_m, 0.0)
    half_x, half_z, _, _ = crop_bounds(geometry, params)
    grid_renderer = scene_renderer(scene, size=params.shape, effects=False)
    return render_depth_maps(grid_renderer, depth_maps_m, (2 * half_x, 2 * half_z))


def _score_presses(
    images: dict[str, np.ndarray],
    geometries: list[PressGeometry],
    others: list[np.ndarray],
    field_mm: tuple[float, float],
) -> dict[str, dict[str, list[float]]]:
    """Per score and estimate, the value on every press: SSIM and PSNR over the whole image
    and over the press window, and the location error; ``random`` averages over ``others``."""
    scores: dict[str, dict[str, list[float]]] = {
        key: {e: [] for e in ESTIMATES}
        for key in ("window_ssim", "full_ssim", "window_psnr_db", "full_psnr_db", "location_error_mm")
    }
    truth = images["truth"]
    for i, geometry in enumerate(geometries):
        for name in ESTIMATES:
            candidates = truth[others[i]] if name == "random" else images[name][i : i + 1]
            reference = np.repeat(truth[i : i + 1], len(candidates), axis=0)
            r0, r1, c0, c1 = geometry.window
            reference_window = np.ascontiguousarray(reference[:, r0:r1, c0:c1])
            candidates_window = np.ascontiguousarray(candidates[:, r0:r1, c0:c1])
            scores["full_ssim"][name].append(float(ssim_rgb(reference, candidates).mean()))
            scores["window_ssim"][name].append(float(ssim_rgb(reference_window, candidates_window).mean()))
            scores["full_psnr_db"][name].append(float(psnr_rgb(reference, candidates).mean()))
            scores["window_psnr_db"][name].append(float(psnr_rgb(reference_window, candidates_window).mean()))
            scores["location_error_mm"][name].append(
                _finite_mean([location_error_mm(truth[i], c, geometry, field_mm) for c in candidates])
            )
    return scores


# The estimates every press's own scores are given for.
PER_PRESS = ("model", "renderer", "renderer_depth_map")


def _summary(
    scores: dict[str, dict[str, list[float]]], geometries: list[PressGeometry], presses: BallPresses
) -> dict[str, Any]:
    """The result's scores: each estimate's mean (location: median) over the presses, and the
    model's and the renderers' scores on every press (named by its frame in the file); where the
    centres and radii came from and the presses the finder left out."""
    result: dict[str, Any] = {"annotations": presses.annotations, "left_out": presses.left_out}
    result |= {
        key: {name: float(np.mean(values)) for name, values in scores[key].items()}
        for key in ("window_ssim", "full_ssim", "window_psnr_db", "full_psnr_db")
    }
    location = scores["location_error_mm"]
    result["location_error_mm_median"] = _nan_median(location["model"])
    result["location_error_mm_median_of"] = {name: _nan_median(values) for name, values in location.items()}
    result["per_press"] = [
        {
            "index": presses.file_indices[i],
            "depth_mm": g.depth_mm,
            "contact_radius_mm": g.contact_radius_mm,
            "window": list(g.window),
            **{f"{key}_{name}": scores[key][name][i] for key in scores for name in PER_PRESS},
            **{
                f"location_error_mm_{name}_undefined": LOCATION_UNDEFINED
                for name in PER_PRESS
                if not np.isfinite(scores["location_error_mm"][name][i])
            },
        }
        for i, g in enumerate(geometries)
    ]
    return result


def _finite_mean(values: list[float]) -> float:
    """Mean of the finite values; NaN when there is none (an estimate that matched nowhere)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _nan_median(values: list[float]) -> float | None:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.median(finite)) if finite else None


def real_press_table(result: dict[str, Any]) -> str:
    """The real-press scores of each estimate, one row each."""
    names = {
        "model": "the model, fed the press's depth-map",
        "model_empty": "the model, fed an empty depth-map",
        "background": "the real no-contact frame",
        "renderer": "the GelSight renderer, fed the exact contact",
        "renderer_depth_map": "the GelSight renderer, fed the same depth-map (the model's prior)",
        "random": f"{RANDOM_FRAMES} random other real frames",
    }
    width = max(len(v) for v in names.values())
    lines = [
        f"real presses: {result['file']} ({result['n']} frames; window of {result['window_radii']:g} contact "
        "radii around each press)",
        f"{'estimate':{width}}  {'window SSIM':>11}  {'full SSIM':>9}  {'window PSNR':>11}  {'full PSNR':>9}  "
        f"{'location (mm, median)':>21}",
    ]
    for key, label in names.items():
        location = result["location_error_mm_median_of"][key]
        lines.append(
            f"{label:{width}}  {result['window_ssim'][key]:>11.3f}  {result['full_ssim'][key]:>9.3f}  "
            f"{result['window_psnr_db'][key]:>8.1f} dB  {result['full_psnr_db'][key]:>6.1f} dB  "
            f"{'—' if location is None else format(location, '.2f'):>21}"
        )
    served = result.get("uncertainty", {})
    if served.get("fitted_on_these_presses"):
        lines.append(
            "as served, with a sensor floor fitted on these very presses (its own fit, not a held-out figure):"
        )
    lines += uncertainty_table(served) if served else []
    if "uncertainty_lab_floor" in result:
        lines.append("with a floor of this sensor's light fitted on the other presses (dtx calibrate uncertainty):")
        lines += uncertainty_table(result["uncertainty_lab_floor"])
        lines.append(f"  ({result['uncertainty_lab_floor']['pearson_region_note']})")
    return "\n".join(lines)


def write_real_press_figure(
    result: dict[str, Any], images: dict[str, np.ndarray], out: str | os.PathLike[str], rows: int = 6
) -> Path:
    """real_presses.png: per press the depth-map, the real frame, the model's and the
    renderer's images, the press window drawn on each image."""
    import matplotlib  # noqa: PLC0415 (only evaluation with --figures needs it)

    matplotlib.use("Agg")
    from matplotlib import patches  # noqa: PLC0415 - matplotlib loads only to draw a figure
    from matplotlib import pyplot as plt  # noqa: PLC0415 - matplotlib loads only to draw a figure

    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    count = min(rows, result["n"])
    fig, axes = plt.subplots(count, 4, figsize=(8, 2 * count), squeeze=False)
    for row, ax in enumerate(axes):
        press = result["per_press"][row]
        r0, r1, c0, c1 = press["window"]
        ax[0].imshow(images["depth_maps_m"][row] * 1e3, cmap="viridis")
        for a, key in zip(ax[1:], ("truth", "model", "renderer")):
            a.imshow(images[key][row])
            # The window is on the image grid; the depth-map's bins cover a wider crop.
            a.add_patch(
                patches.Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0, r1 - r0, fill=False, color="red", linewidth=0.8)
            )
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
        ax[2].set_xlabel(f"window SSIM {press['window_ssim_model']:.2f}", fontsize=7)
        ax[3].set_xlabel(f"window SSIM {press['window_ssim_renderer']:.2f}", fontsize=7)
    for a, title in zip(axes[0], ("depth-map (mm)", "real frame", "model", "renderer")):
        a.set_title(title, fontsize=9)
    fig.tight_layout()
    path = out_dir / "real_presses.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
