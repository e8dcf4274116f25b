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
# Deeper than any report nests (a few levels): a producer's bug, refused with its place before
# Python's recursion limit turns it into a RecursionError with none.
MAX_DEPTH = 100


def dumps(value: Any, indent: int | None = None) -> str:
    """``value`` as strict JSON text. ValueError names the place (``$`` the value itself) of the
    first non-finite number that has no ``<key>_undefined`` reason beside it, long double beyond
    float64's range, key JSON cannot hold (numpy scalar keys are written as their Python value),
    value JSON has no form for, container inside itself (a cycle) or nesting deeper than
    MAX_DEPTH."""
    return json.dumps(_strict(value, explained=False, path="$", inside=set()), indent=indent, allow_nan=False)


def _strict(value: Any, explained: bool, path: str, inside: set[int]) -> Any:
    """A copy with numpy scalars and arrays as Python numbers and lists and, under an explained key, every
    non-finite number as None. ``inside``: the ids of the containers ``path`` runs through."""
    if isinstance(value, (np.generic, np.ndarray)):
        value = _python(value, path)
    if isinstance(value, float) and not math.isfinite(value):
        if explained:
            return None
        raise ValueError(f"{path} is {value} with no {UNDEFINED_SUFFIX!r} reason beside it: JSON has no such number")
    if value is None or isinstance(value, (str, int, float)):
        return value
    if not isinstance(value, (dict, list, tuple)):
        raise ValueError(f"{path} is a {type(value).__name__}, which JSON has no form for")
    if id(value) in inside:
        raise ValueError(f"{path} is a cycle: the container holds itself")
    if len(inside) >= MAX_DEPTH:
        raise ValueError(f"{path} nests deeper than {MAX_DEPTH} levels")
    inside.add(id(value))
    try:
        if isinstance(value, dict):
            return {
                _key(key, path): _strict(
                    item, explained or f"{key}{UNDEFINED_SUFFIX}" in value, f"{path}.{key}", inside
                )
                for key, item in value.items()
            }
        return [_strict(item, explained, f"{path}[{index}]", inside) for index, item in enumerate(value)]
    finally:
        inside.discard(id(value))


def _python(value: np.generic | np.ndarray, path: str) -> Any:
    """A numpy scalar as the Python value JSON writes, an array as nested lists of its scalars."""
    if isinstance(value, np.ndarray):
        return value.tolist()  # a long double array's items stay long doubles: each comes back here
    if not isinstance(value, np.floating):
        return value.item()
    number = float(value)  # a long double's item() is itself, no float
    if math.isinf(number) and np.isfinite(value):
        raise ValueError(
            f"{path} is {value} (a {value.dtype}), beyond float64's range: JSON readers hold no such number"
        )
    return number


def _key(key: Any, path: str) -> Any:
    """``key`` as json.dumps takes a key (and writes as text), or ValueError naming it."""
    if isinstance(key, np.generic):
        key = float(key) if isinstance(key, np.floating) else key.item()
    if not (key is None or isinstance(key, (str, int, float))) or (isinstance(key, float) and not math.isfinite(key)):
        raise ValueError(f"{path} has a key {key!r:.80} that JSON cannot hold (text, a number or null)")
    return key
