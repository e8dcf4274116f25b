"""The gel's give under a grasp (workcell.compliance): the Winkler balance it solves."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from workcell.compliance import indentation_for_force_mm

K = 0.125  # N/mm per mm² of contact: 0.25 MPa over 2 mm
CELL_MM2 = 0.09

gap_lists = st.lists(st.floats(0.0, 3.0, allow_nan=False), min_size=1, max_size=200)


@settings(max_examples=200, deadline=None)
@given(gap_lists, st.floats(0.01, 200.0))
def test_property_the_press_carries_the_force_unless_the_elastomer_is_used_up(gaps, force_n):
    gaps_mm = np.array(gaps)
    d, area, saturated = indentation_for_force_mm(gaps_mm, CELL_MM2, force_n, K, 2.0)
    carried = K * CELL_MM2 * np.maximum(0.0, d - gaps_mm).sum()
    assert 0.0 <= d <= 2.0
    assert area == pytest.approx(np.count_nonzero(gaps_mm < d) * CELL_MM2)
    if saturated:
        assert d == 2.0 and carried <= force_n * (1 + 1e-9)
    else:
        assert carried == pytest.approx(force_n, rel=1e-9)


@settings(max_examples=100, deadline=None)
@given(gap_lists, st.floats(0.01, 100.0), st.floats(1.01, 3.0))
def test_property_more_force_presses_no_less(gaps, force_n, factor):
    gaps_mm = np.array(gaps)
    less = indentation_for_force_mm(gaps_mm, CELL_MM2, force_n, K, 2.0)[0]
    assert indentation_for_force_mm(gaps_mm, CELL_MM2, force_n * factor, K, 2.0)[0] >= less


def test_a_flat_face_over_the_whole_gel_presses_force_over_stiffness_and_area():
    gaps_mm = np.zeros(62 * 83)
    d, area, saturated = indentation_for_force_mm(gaps_mm, 18.6 * 24.9 / gaps_mm.size, 10.0, K, 2.0)
    assert d == pytest.approx(10.0 / (K * 18.6 * 24.9)) and area == pytest.approx(18.6 * 24.9) and not saturated


def test_nothing_in_front_or_no_force_presses_nothing():
    assert indentation_for_force_mm(np.full(4, np.inf), CELL_MM2, 10.0, K, 2.0) == (0.0, 0.0, False)
    assert indentation_for_force_mm(np.zeros(4), CELL_MM2, 0.0, K, 2.0) == (0.0, 0.0, False)
