"""Depth-map normalisation for learning, and its inverse.

A depth-map holds, per x-z bin of the gel frame, the minimum y in metres (y > 0: the surface
is that far from the gel, y < 0: it indents the gel). The network sees values in [-1, 1]:
``depth_range_m = (y_near, y_far)`` maps y_near -> -1 and y_far -> +1, values outside are
clipped. Empty bins are stored as y_far (nothing within reach), so they read as "no contact".
"""

from __future__ import annotations

import numpy as np


class NormalisationError(ValueError):
    """The depth range cannot define a normalisation."""


def _check_range(depth_range_m: tuple[float, float]) -> tuple[float, float]:
    """(y_near, y_far) as floats: two numbers finite in float32 (the depth-maps' dtype; a wider
    range, e.g. +-1e308, would map every depth to -1), y_far > y_near, resolvable in float32."""
    try:
        y_near, y_far = (float(v) for v in depth_range_m)
    except (TypeError, ValueError) as err:
        raise NormalisationError(
            f"depth_range_m must be two numbers (y_near, y_far), got {depth_range_m!r}: {err}"
        ) from None
    if not (np.isfinite(y_near) and np.isfinite(y_far)):
        raise NormalisationError(f"depth range must be finite, got {depth_range_m}")
    if not max(abs(y_near), abs(y_far)) <= float(np.finfo(np.float32).max):
        raise NormalisationError(f"depth range {depth_range_m} is beyond float32, the depth-maps' dtype")
    if not y_far > y_near:
        raise NormalisationError(f"depth range must have y_far > y_near, got {depth_range_m}")
    if not np.float32(y_far) > np.float32(y_near):
        raise NormalisationError(f"depth range {depth_range_m} is below float32 resolution")
    return y_near, y_far


def normalise_depth_map(depth_map_m: np.ndarray, depth_range_m: tuple[float, float]) -> np.ndarray:
    """Metres in the gel frame -> float32 in [-1, 1], same shape; NaN (empty bin) -> +1 (far),
    +-inf and values beyond the range clip to +-1. ``depth_map_m``: any real dtype and shape.
    A range that is not two finite numbers with y_far > y_near (see ``_check_range``) raises
    NormalisationError."""
    y_near, y_far = _check_range(depth_range_m)
    # Clipped to the range before scaling: a value near float64's largest would overflow to inf.
    inside = np.clip(np.asarray(depth_map_m, dtype=np.float64), y_near, y_far)
    scaled = (inside - y_near) * (2.0 / (y_far - y_near)) - 1.0
    scaled = np.where(np.isnan(scaled), 1.0, scaled)
    return np.clip(scaled, -1.0, 1.0).astype(np.float32)


def denormalise_depth_map(normalised: np.ndarray, depth_range_m: tuple[float, float]) -> np.ndarray:
    """Inverse of :func:`normalise_depth_map` for values inside the range (metres, float32)."""
    y_near, y_far = _check_range(depth_range_m)
    values = np.asarray(normalised, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise NormalisationError("normalised depth-map contains NaN or inf")
    return ((values + 1.0) * 0.5 * (y_far - y_near) + y_near).astype(np.float32)
