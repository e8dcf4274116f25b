"""Template matching of the paper's evaluation: the ground truth's most deformed square
(``most_deformed_box``), searched for in the estimate with OpenCV's TM_CCOEFF_NORMED."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from models.errors import ModelConfigError


def most_deformed_box(deformation: np.ndarray, size_px: int) -> tuple[int, int]:
    """Top-left (x, y) of the size_px square with the largest summed deformation (ties: the
    first in row-major order).

    Contract: ``deformation`` an H x W array of finite real numbers (bool, integer or float;
    the sums are taken in float64 and never overflow), ``size_px`` an integer in [1, min(H, W)].
    Otherwise ModelConfigError naming the argument: a NaN or an infinite pixel has no sum to rank."""
    values = np.asarray(deformation)
    if values.ndim != 2 or values.dtype.kind not in "biuf":
        raise ModelConfigError(f"deformation must be an H x W real array, got {values.shape} {values.dtype}")
    h, w = values.shape
    whole = isinstance(size_px, (int, np.integer)) and not isinstance(size_px, bool)
    if not (whole and 0 < size_px <= min(h, w)):
        raise ModelConfigError(f"template size {size_px!r} px does not fit a {h} x {w} image (size_px)")
    values = values.astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise ModelConfigError("deformation contains NaN or inf: no box has a largest sum")
    # Scaled to at most 1, so that no sum of size_px² values overflows; the ranking is the same.
    peak = float(np.abs(values).max())
    if peak > 0:
        values /= peak
    sums = cv2.boxFilter(
        values, -1, (size_px, size_px), normalize=False, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT
    )[: h - size_px + 1, : w - size_px + 1]
    y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(x), int(y)


def template_match(
    truth: np.ndarray, truth_deformation: np.ndarray, estimate: np.ndarray, size_px: int = 32
) -> list[dict[str, Any]]:
    """Per pair: the template box in the truth, the best match in the estimate, its score
    (TM_CCOEFF_NORMED, -1..1) and the distance between the two boxes in pixels.

    ``truth`` and ``estimate``: N x H x W x 3 uint8 of one shape, ``truth_deformation``
    N x H x W; otherwise ModelConfigError. A flat template (every channel one value) or a flat
    estimate window has no correlation coefficient (OpenCV 5 scores a flat template 1.0, older
    versions NaN): it scores 0. A pair with a flat template has no match: ``match_xy`` and
    ``distance_px`` are None."""
    truth, estimate = np.asarray(truth), np.asarray(estimate)
    if (
        truth.dtype != np.uint8
        or truth.shape != estimate.shape
        or estimate.dtype != np.uint8
        or truth.ndim != 4
        or truth.shape[-1] != 3
        or np.shape(truth_deformation) != truth.shape[:-1]
    ):
        raise ModelConfigError(
            f"template matching needs uint8 N x H x W x 3 truth and estimate and an N x H x W "
            f"deformation, got {truth.dtype} {truth.shape}, {estimate.dtype} {estimate.shape}, "
            f"{np.shape(truth_deformation)}"
        )
    results = []
    for gt, deform, est in zip(truth, truth_deformation, estimate):
        x, y = most_deformed_box(deform, size_px)
        template = np.ascontiguousarray(gt[y : y + size_px, x : x + size_px])
        if np.all(template == template[:1, :1]):
            results.append({"template_xy": [x, y], "match_xy": None, "score": 0.0, "distance_px": None})
            continue
        est = np.ascontiguousarray(est)
        scores = cv2.matchTemplate(est, template, cv2.TM_CCOEFF_NORMED)
        # Summed per-channel variance of each estimate window; zero (to rounding) where it is flat.
        levels = est.astype(np.float64)
        window = (size_px, size_px)
        mean = cv2.boxFilter(levels, -1, window, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)
        mean_sq = cv2.boxFilter(levels * levels, -1, window, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)
        variance = (mean_sq - mean * mean).sum(axis=-1)[: scores.shape[0], : scores.shape[1]]
        scores = np.where((variance > 1e-6) & np.isfinite(scores), scores, 0.0).astype(np.float32)
        _, score, _, (mx, my) = cv2.minMaxLoc(scores)
        results.append(
            {
                "template_xy": [x, y],
                "match_xy": [int(mx), int(my)],
                "score": float(score),
                "distance_px": float(np.hypot(mx - x, my - y)),
            }
        )
    return results
