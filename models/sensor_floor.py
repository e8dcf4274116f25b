"""A lab's own GelSight in the served uncertainty (``dtx calibrate uncertainty CHECKPOINT
PRESSES.npz --out NEW.pt``, models.calibrate_uncertainty).

A checkpoint's u (models.uncertainty) is calibrated on its session's simulated frames. On a real
sensor most of the error is the sensor's own light, which changes from frame to frame (the shipped
no-contact frame is 8.3 levels from the presses on average) and which no depth-map holds: on the
30 shipped presses the demo checkpoint's u is 10-14 x too small and uncorrelated with the error.
The lab's ball presses (the file ``dtx calibrate gelsight`` fits the renderer from) measure where
on the image that light varies: per pixel, the mean square of the served estimate's error beyond
the mean square of u there. That is the sensor's floor (models.uncertainty.SensorFloor), served as
sqrt(u^2 + floor^2) in every reply of the checkpoint written with it.

It is a property of one sensor under one checkpoint: the checkpoint written with it serves that
sensor (its u on simulated frames is then the sensor's, too wide for the simulation). How it
scores on presses it was not fitted on, ``dtx evaluate --real-presses`` says: each press's u with
the floor fitted on the other presses (:func:`leave_one_out_uncertainty`), the same arithmetic the
served path runs.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from models.errors import ModelConfigError
from models.uncertainty import (
    SensorFloor,
    ServedUncertainty,
    pixel_error_levels,
    served_uncertainty_statistics,
    uncertainty_statistics,
)

# Presses a floor is fitted on, at least: one press's error is its own light, not the sensor's.
MIN_PRESSES = 2
# Why the held-out u's per-region r is no figure of the served u's.
HELD_OUT_REGION_NOTE = (
    "held out, a press's own error leaves its floor's fit: the presses that miss most get the lowest floor, "
    "so per region r is negative by construction; the served floor is one map for every region"
)


def fit_sensor_floor(error_levels: np.ndarray, uncertainty_levels: np.ndarray) -> np.ndarray:
    """The floor, H x W float32 image levels: per pixel sqrt(max(mean e^2 - mean u^2, 0)) over
    the presses, of their errors e and the checkpoint's own u (both N x H x W, image levels,
    N >= MIN_PRESSES). ModelConfigError for fewer presses, unequal shapes or values that are not
    finite."""
    if error_levels.shape != uncertainty_levels.shape or error_levels.ndim != 3:
        raise ModelConfigError(
            f"errors {error_levels.shape} and uncertainties {uncertainty_levels.shape} must be the same N x H x W"
        )
    if len(error_levels) < MIN_PRESSES:
        raise ModelConfigError(f"a sensor floor needs at least {MIN_PRESSES} presses, got {len(error_levels)}")
    if not (np.all(np.isfinite(error_levels)) and np.all(np.isfinite(uncertainty_levels))):
        raise ModelConfigError("the presses' errors or uncertainties are not all finite")
    error, own = error_levels.astype(np.float64), uncertainty_levels.astype(np.float64)
    excess = np.mean(error * error, axis=0) - np.mean(own * own, axis=0)
    return np.sqrt(np.maximum(excess, 0.0)).astype(np.float32)


def leave_one_out_uncertainty(error_levels: np.ndarray, uncertainty_levels: np.ndarray) -> np.ndarray:
    """Each press's u served with the floor fitted on the other presses (N x H x W float32):
    what a lab that calibrated on all but that press would be served on it."""
    n = len(error_levels)
    return np.stack(
        [
            SensorFloor(fit_sensor_floor(np.delete(error_levels, i, 0), np.delete(uncertainty_levels, i, 0)), {}).added(
                uncertainty_levels[i : i + 1]
            )[0]
            for i in range(n)
        ]
    )


def presses_digest(path: str | os.PathLike[str]) -> str:
    """The presses file's SHA-256: a floor names the file it was fitted on, so that an evaluation
    on the same file can say its figures are the fit's own."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def press_uncertainty_statistics(
    served: ServedUncertainty | None,
    own_levels: np.ndarray | None,
    estimate: np.ndarray,
    truth: np.ndarray,
    region_dissimilarity: np.ndarray,
    presses_sha256: str,
) -> dict[str, Any]:
    """The real presses' uncertainty figures: ``uncertainty``, u as the checkpoint serves it (its
    own u, ``own_levels``, with its sensor floor where it has one; ``fitted_on_these_presses`` when
    that floor was fitted on this very file), and ``uncertainty_lab_floor``, u with a floor fitted
    on the other presses (:func:`leave_one_out_uncertainty`)."""
    if served is None or own_levels is None:
        return {"uncertainty": served_uncertainty_statistics(None, estimate, truth, region_dissimilarity)}
    floor = served.floor
    figures = uncertainty_statistics(
        own_levels if floor is None else floor.added(own_levels), estimate, truth, region_dissimilarity
    )
    source = served.floor_source()
    if source is not None:
        figures["sensor_floor"] = source
        figures["fitted_on_these_presses"] = source.get("sha256") == presses_sha256
    out = {"uncertainty": figures}
    if len(own_levels) > MIN_PRESSES:
        error = pixel_error_levels(estimate, truth)
        held_out = leave_one_out_uncertainty(error, own_levels)
        held_out_figures = uncertainty_statistics(held_out, estimate, truth, region_dissimilarity)
        held_out_figures["pearson_region_note"] = HELD_OUT_REGION_NOTE
        out["uncertainty_lab_floor"] = held_out_figures
    return out
