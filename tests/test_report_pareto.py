"""report.pareto: the front holds exactly the undominated points; the default is on it."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from report.pareto import dominates, pareto_front, recommend

values = st.floats(min_value=0.0, max_value=1e3, allow_nan=False) | st.sampled_from([0.0, 1.0, 2.0])
points = st.lists(st.tuples(values, values), max_size=30)


@given(points)
def test_no_point_on_the_front_is_dominated(pts: list[tuple[float, float]]) -> None:
    front = pareto_front(pts)
    for i, on in enumerate(front):
        if on:
            assert not any(dominates(q, pts[i]) for q in pts)


@given(points)
def test_every_dominated_point_is_off_the_front(pts: list[tuple[float, float]]) -> None:
    front = pareto_front(pts)
    for i, p in enumerate(pts):
        if any(dominates(q, p) for q in pts):
            assert not front[i]
        else:
            assert front[i]


@given(points, st.floats(min_value=0.0, max_value=10.0))
def test_recommended_is_fastest_front_point_near_the_best(pts: list[tuple[float, float]], tolerance: float) -> None:
    chosen = recommend(pts, tolerance)
    if not pts:
        assert chosen is None
        return
    assert chosen is not None and pareto_front(pts)[chosen]
    best = max(s for _, s in pts)
    assert pts[chosen][1] >= best - tolerance
    assert all(t >= pts[chosen][0] for t, s in pts if s >= best - tolerance)


def test_equal_points_stay_on_the_front_and_nan_is_never_on_it() -> None:
    assert pareto_front([(1.0, 0.5), (1.0, 0.5), (2.0, 0.4)]) == [True, True, False]
    assert pareto_front([(1.0, math.nan), (2.0, 0.4)]) == [False, True]
    assert recommend([(1.0, math.nan)], 0.1) is None


def test_tolerance_trades_accuracy_for_time() -> None:
    pts = [(10.0, 0.90), (2.0, 0.895), (1.0, 0.80)]
    assert recommend(pts, 0.01) == 1
    assert recommend(pts, 0.0) == 0
    assert recommend(pts, 0.2) == 2
