"""The JSON every ``dtx`` command prints: strict RFC 8259 text that ``JSON.parse``, ``jq`` and
other non-Python readers accept.

JSON has no NaN or infinity. A figure that is undefined (a ratio over a zero baseline, say)
is written as ``null``, and only where the producer says why: beside key ``name`` a key
``name_undefined`` holds the reason (``models.evaluate.ssim_statistics`` writes
``dissimilarity_ratio_undefined``). A non-finite number without its reason is a bug in the
producer, and :func:`dumps` raises ValueError on it rather than print text a reader refuses.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

UNDEFINED_SUFFIX = "_undefined"


def dumps(value: Any, indent: int | None = None) -> str:
    """``value`` as strict JSON text; ValueError names the first non-finite number that has
    no ``<key>_undefined`` reason beside it."""
    return json.dumps(_strict(value, explained=False, path="$"), indent=indent, allow_nan=False)


def _strict(value: Any, explained: bool, path: str) -> Any:
    """A copy with numpy scalars and arrays as Python numbers and lists and, under an explained key, every
    non-finite number as None."""
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        if explained:
            return None
        raise ValueError(f"{path} is {value} with no {UNDEFINED_SUFFIX!r} reason beside it: JSON has no such number")
    if isinstance(value, dict):
        return {
            key: _strict(item, explained or f"{key}{UNDEFINED_SUFFIX}" in value, f"{path}.{key}")
            for key, item in value.items()
        }
    if isinstance(value, (list, tuple)):
        return [_strict(item, explained, f"{path}[{index}]") for index, item in enumerate(value)]
    return value
