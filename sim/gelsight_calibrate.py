"""``dtx calibrate gelsight PRESSES.npz --out DIR``: the renderer calibrated from the lab's own
ball presses, checked on presses the fit never saw.

The press file has the layout of assets/gelsight/ball_presses.npz (``background``, ``frames``)
plus the frame's ``mm_per_px`` and the ball's ``ball_radius_mm`` (keys, or given on the command
line); ``touch_center`` and ``touch_radius``, when the file has them, are only compared with
what the finder (``sim.press_annotation``) sees. Presses the finder cannot trust are left out
and named; the rest are fitted (``sim.gelsight_fit``) in ``folds`` ways (fit on all folds but
one, score the one), with the shipped calibration and the background alone scored on the same
presses beside, and on the two halves (fit on the even presses, score the odd ones, next to the
fit of all scored there), then once on all. Bad input is a GelSightRenderError naming the cause
and the presses involved, raised before anything is written.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from msgs.progress import Progress
from sim.gelsight import GelSightConfig
from sim.gelsight_calibration import BACKGROUND_FILE, PARAMETERS_FILE, POLYNOMIAL_FILE
from sim.gelsight_check import (
    BALL_RADIUS_RANGE_MM,
    MM_PER_PX_RANGE,
    ball_gap_map,
    press_depth_mm,
    press_scalar,
    read_press_file,
)
from sim.gelsight_effects import GelSightRenderError
from sim.gelsight_fit import Presses, PressFit, fit_presses, press_scores, render_fit
from sim.press_annotation import FoundPresses, find_checked_presses

# Usable presses needed: the half-against-all check fits a half, and below about a dozen presses a
# fit leaves too many slope bins to too few positions on the gel (on rendered presses: six score a
# crop SSIM of 0.47 on presses they never saw, twelve 0.95).
MIN_PRESSES = 24


def load_press_file(
    path: str | Path, mm_per_px: float | None = None, ball_radius_mm: float | None = None
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], float, float]:
    """Frames, background, the file's own annotations (may be empty), scale and ball radius;
    the arguments override the file's keys."""
    path = Path(path)
    contents, frames, background = read_press_file(path)
    scale = press_scalar(path, contents, "mm_per_px", mm_per_px, None, MM_PER_PX_RANGE)
    ball = press_scalar(path, contents, "ball_radius_mm", ball_radius_mm, None, BALL_RADIUS_RANGE_MM)
    annotations: dict[str, np.ndarray] = {
        k: contents[k].astype(np.float64) for k in ("touch_center", "touch_radius") if k in contents
    }
    return frames, background, annotations, scale, ball


def annotate(frames: np.ndarray, background: np.ndarray, mm_per_px: float, ball_radius_mm: float) -> FoundPresses:
    """The finder's presses (``find_checked_presses``); refuses too few trusted presses."""
    found = find_checked_presses(frames, background, mm_per_px, ball_radius_mm)
    trusted = found.trusted
    if trusted.sum() < MIN_PRESSES:
        left_out = "; ".join(f"press {i}: {r}" for i, r in enumerate(found.reasons) if r)
        raise GelSightRenderError(
            f"too few presses to calibrate: {int(trusted.sum())} usable of {len(frames)}, at least {MIN_PRESSES} "
            f"needed ({left_out or 'none left out'})"
        )
    return found


def _references(presses: Presses) -> dict[str, list[float]]:
    """The shipped calibration (against the file's background) and the background alone, on ``presses``."""
    from sim.gelsight import GelSightRenderer  # noqa: PLC0415

    h, w = presses.shape
    renderer = GelSightRenderer(
        GelSightConfig(image_height=h, image_width=w, mm_per_px=presses.mm_per_px), background=presses.background
    )
    shipped = [
        renderer.render(
            ball_gap_map(
                (h, w),
                c,
                press_depth_mm(r * presses.mm_per_px, presses.ball_radius_mm),
                presses.mm_per_px,
                presses.ball_radius_mm,
            )
        )
        for c, r in zip(presses.centers_xy_px, presses.radii_px)
    ]
    scores = press_scores(shipped, presses)
    alone = press_scores([presses.background] * len(presses.frames), presses)
    return {
        "shipped_crop": scores["crop"],
        "shipped_full": scores["full"],
        "background_crop": alone["crop"],
        "background_full": alone["full"],
    }


def _means(scores: dict[str, list[float]]) -> dict[str, float]:
    return {key: float(np.mean(values)) for key, values in scores.items()}


def _held_out(
    presses: Presses, train: list[int], test: list[int], **budget: int
) -> tuple[PressFit, dict[str, list[float]]]:
    fit = fit_presses(presses.subset(train), **budget)
    return fit, press_scores(render_fit(fit, presses.subset(test)), presses.subset(test))


def _k_fold(
    presses: Presses, folds: int, shown: Progress, **budget: int
) -> tuple[dict[str, list[float]], list[dict[str, float]]]:
    """Each press's crop and full SSIM from the fit of the other folds (press i in fold i % folds),
    and each fold's fitted parameters; ``shown`` counts the fits."""
    n = len(presses.frames)
    held = {key: [math.nan] * n for key in ("crop", "full")}
    fold_parameters = []
    for k in range(folds):
        test = list(range(k, n, folds))
        fit, scores = _held_out(presses, [i for i in range(n) if i % folds != k], test, **budget)
        fold_parameters.append(fit.parameters)
        shown.update()
        for key in held:
            for i, value in zip(test, scores[key]):
                held[key][i] = value
    return held, fold_parameters


def annotation_agreement(found: FoundPresses, annotations: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """How far the finder's centres and radii are from the file's own annotations (px), per press and in sum."""
    if (
        set(annotations) != {"touch_center", "touch_radius"}
        or annotations["touch_radius"].shape != found.radii_px.shape
    ):
        return None
    center_px = np.hypot(*(found.centers_xy_px - annotations["touch_center"]).T)
    radius_px = found.radii_px - annotations["touch_radius"]
    both = (center_px <= 1.0) & (np.abs(radius_px) <= 1.0)
    return {
        "center_px": center_px.tolist(),
        "radius_px": radius_px.tolist(),
        "mean_center_offset_xy_px": (found.centers_xy_px - annotations["touch_center"]).mean(axis=0).tolist(),
        "median_center_px": float(np.median(center_px)),
        "center_within_1px": float(np.mean(center_px <= 1.0)),
        "radius_within_1px": float(np.mean(np.abs(radius_px) <= 1.0)),
        "both_within_1px": float(np.mean(both)),
    }


def calibrate_presses(
    path: str | Path,
    folds: int = 3,
    mm_per_px: float | None = None,
    ball_radius_mm: float | None = None,
    evaluations: int | None = None,
    progress: bool = True,
) -> tuple[PressFit, Presses, dict[str, Any]]:
    """The fit of all usable presses, those presses (found centres and radii) and the report;
    with ``progress`` a line on stderr as each of the folds + 2 fits ends (a fit takes 5 s to
    minutes with the frame's size)."""
    frames, background, annotations, scale, ball = load_press_file(path, mm_per_px, ball_radius_mm)
    found = annotate(frames, background, scale, ball)
    used = np.flatnonzero(found.trusted)
    if not 2 <= folds <= len(used) // 2:
        raise GelSightRenderError(
            f"--folds must be in [2, {len(used) // 2}] for {len(used)} usable presses, got {folds}"
        )
    presses = Presses(frames[used], background, found.centers_xy_px[used], found.radii_px[used], scale, ball)
    budget = {} if evaluations is None else {"evaluations": evaluations}
    with Progress("calibrate gelsight", folds + 2, "fits", enabled=progress) as shown:
        held, fold_parameters = _k_fold(presses, folds, shown, **budget)
        n = len(used)
        even, odd = list(range(0, n, 2)), list(range(1, n, 2))
        _, half = _held_out(presses, even, odd, **budget)
        shown.update()
        full = fit_presses(presses, **budget)
        shown.update()
    full_on_odd = press_scores(render_fit(full, presses.subset(odd)), presses.subset(odd))
    references = _references(presses)
    report = {
        "file": str(path),
        "mm_per_px": scale,
        "ball_radius_mm": ball,
        "frame_shape": list(background.shape[:2]),
        "presses": int(len(frames)),
        "used": used.tolist(),
        "left_out": {int(i): reason for i, reason in enumerate(found.reasons) if reason},
        "found": {"touch_center": found.centers_xy_px.tolist(), "touch_radius": found.radii_px.tolist()},
        "annotation_agreement": annotation_agreement(found, annotations),
        "folds": folds,
        "k_fold": {**_means({"crop": held["crop"], "full": held["full"]}), **_means(references)},
        "k_fold_per_press": {**held, **references},
        "fold_parameters": fold_parameters,
        "half": {"fit_even_score_odd": _means(half), "fit_all_score_odd": _means(full_on_odd)},
        "parameters": full.parameters,
    }
    return full, presses, report


def _npz_bytes(**arrays: Any) -> bytes:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def calibration_files(fit: PressFit, presses: Presses) -> dict[str, bytes]:
    """The calibration directory's files: the tables and the background in the layout of
    assets/gelsight (the background beside the presses fitted, with their found centres and radii
    and the scale), and the renderer's physical parameters (sim.gelsight_calibration)."""
    tables = {f"grad_{c}": fit.tables[:, :, i] for i, c in enumerate("rgb")}
    parameters = {"calibration_mm_per_px": presses.mm_per_px, "shading_gain": 1.0, **fit.parameters}
    return {
        POLYNOMIAL_FILE: _npz_bytes(bins=np.int64(fit.tables.shape[0]), **tables),
        BACKGROUND_FILE: _npz_bytes(
            background=fit.background,
            frames=presses.frames,
            touch_center=presses.centers_xy_px,
            touch_radius=presses.radii_px,
            mm_per_px=presses.mm_per_px,
            ball_radius_mm=presses.ball_radius_mm,
        ),
        PARAMETERS_FILE: (json.dumps(parameters, indent=1) + "\n").encode(),
    }


def format_report(report: dict[str, Any]) -> str:
    """The report for a person."""
    k, half = report["k_fold"], report["half"]
    lines = [
        f"{report['file']}: {len(report['used'])} of {report['presses']} presses used "
        f"({report['mm_per_px']:g} mm/px, ball radius {report['ball_radius_mm']:g} mm)",
        *(f"  left out: press {i}: {reason}" for i, reason in report["left_out"].items()),
        f"{report['folds']}-fold, on presses each fit never saw (SSIM crop / full):",
        f"  fitted calibration  {k['crop']:.4f} / {k['full']:.4f}",
        f"  shipped calibration {k['shipped_crop']:.4f} / {k['shipped_full']:.4f}",
        f"  background alone    {k['background_crop']:.4f} / {k['background_full']:.4f}",
        "odd presses: fitted on the even half {:.4f} / {:.4f}, fitted on all {:.4f} / {:.4f}".format(
            half["fit_even_score_odd"]["crop"],
            half["fit_even_score_odd"]["full"],
            half["fit_all_score_odd"]["crop"],
            half["fit_all_score_odd"]["full"],
        ),
        "parameters: " + ", ".join(f"{name} {value:.3f}" for name, value in report["parameters"].items()),
    ]
    agreement = report["annotation_agreement"]
    if agreement is not None:
        lines.append(
            "found vs the file's annotations: centre within 1 px {:.0%} (median {:.2f} px, mean offset x {:+.2f} "
            "y {:+.2f} px), radius within 1 px {:.0%}, both {:.0%}".format(
                agreement["center_within_1px"],
                agreement["median_center_px"],
                *agreement["mean_center_offset_xy_px"],
                agreement["radius_within_1px"],
                agreement["both_within_1px"],
            )
        )
    return "\n".join(lines)
