"""Pareto front of (time, accuracy) points and the recommended default among them."""

from __future__ import annotations

import math
from collections.abc import Sequence


def dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """``a`` = (time, score) is at least as fast and as good as ``b`` and better in one."""
    return a[0] <= b[0] and a[1] >= b[1] and (a[0] < b[0] or a[1] > b[1])


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (time, score) point (lower time, higher score is better): True when no other
    point dominates it. Equal points do not dominate each other, so both stay on the front.
    Points with a NaN coordinate are never on it (a failed measurement is no option)."""
    valid = [not (math.isnan(t) or math.isnan(s)) for t, s in points]
    return [
        valid[i] and not any(valid[j] and dominates(points[j], p) for j in range(len(points)))
        for i, p in enumerate(points)
    ]


def recommend(points: Sequence[tuple[float, float]], tolerance: float) -> int | None:
    """Index of the fastest front point whose score is within ``tolerance`` of the best score:
    beyond that margin a lab pays time for a difference it would not see. None if no point
    is valid."""
    front = [i for i, on in enumerate(pareto_front(points)) if on]
    if not front:
        return None
    best = max(points[i][1] for i in front)
    return min((i for i in front if points[i][1] >= best - tolerance), key=lambda i: points[i][0])
