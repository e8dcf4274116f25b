"""Numerical contracts of the GelSight renderer and its config (issue 20): a finite uint8 image
or GelSightRenderError, never cv2.error or an unbounded Gaussian kernel."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.gelsight import (
    MAX_BACKGROUND_SIGMA_PX,
    MAX_LENGTH_MM,
    PIXEL_PITCH_RANGE_MM,
    GelSightConfig,
    GelSightRenderer,
    GelSightRenderError,
)

LENGTHS = (
    "elastomer_thickness_mm",
    "spreading_length_mm",
    "optical_blur_mm",
    "compression_saturation_mm",
    "background_smoothing_mm",
)


@pytest.mark.parametrize(
    "change",
    [
        {"background_smoothing_mm": 1e8},
        {"optical_blur_mm": 1e9},
        {"mm_per_px": 1e-12},
        {"calibration_mm_per_px": 1e-12},
        {"spreading_length_mm": 1e300},
        {"mm_per_px": 1e3},
    ],
)
def test_lengths_opencv_cannot_blur_with_are_refused_at_construction(change: dict) -> None:
    started = time.monotonic()
    with pytest.raises(GelSightRenderError, match=next(iter(change))):
        GelSightConfig(**change)
    assert time.monotonic() - started < 0.1


@pytest.mark.parametrize("name", LENGTHS)
def test_length_bound_is_inclusive_to_the_ulp(name: str) -> None:
    if name == "background_smoothing_mm":  # bound by calibration pixels first
        GelSightConfig(**{name: MAX_BACKGROUND_SIGMA_PX * 0.1245})
        with pytest.raises(GelSightRenderError, match=name):
            GelSightConfig(**{name: np.nextafter(MAX_BACKGROUND_SIGMA_PX * 0.1245, np.inf)})
        return
    GelSightConfig(**{name: MAX_LENGTH_MM})
    with pytest.raises(GelSightRenderError, match=name):
        GelSightConfig(**{name: np.nextafter(MAX_LENGTH_MM, np.inf)})
    with pytest.raises(GelSightRenderError, match=name):
        GelSightConfig(**{name: 0.0})


def test_pitch_bounds_are_inclusive_to_the_ulp() -> None:
    low, high = PIXEL_PITCH_RANGE_MM
    GelSightConfig(mm_per_px=low)
    GelSightConfig(mm_per_px=high)
    for value in (np.nextafter(low, 0.0), np.nextafter(high, np.inf)):
        with pytest.raises(GelSightRenderError, match="mm_per_px"):
            GelSightConfig(mm_per_px=value)


@settings(max_examples=12, deadline=None)
@given(
    length=st.sampled_from(LENGTHS),
    value=st.floats(1e-3, MAX_LENGTH_MM),
    pitch=st.floats(*PIXEL_PITCH_RANGE_MM),
    size=st.sampled_from([(3, 4), (30, 40), (120, 160)]),
)
def test_property_every_accepted_config_renders_a_finite_image_quickly(
    length: str, value: float, pitch: float, size: tuple[int, int]
) -> None:
    if length == "background_smoothing_mm":
        value = min(value, MAX_BACKGROUND_SIGMA_PX * 0.1245)
    config = GelSightConfig(image_height=size[0], image_width=size[1], mm_per_px=pitch, **{length: value})
    started = time.monotonic()
    renderer = GelSightRenderer(config)
    gap = np.full(size, np.inf)
    gap[size[0] // 3 :, : size[1] // 2] = -0.5
    image = renderer.render(gap)
    assert image.dtype == np.uint8 and image.shape == size + (3,)
    assert time.monotonic() - started < 5.0


@settings(max_examples=20, deadline=None)
@given(
    dtype=st.sampled_from([np.float16, np.float32, np.float64, ">f8", ">f4"]),
    layout=st.sampled_from(["c", "f", "flipped", "strided"]),
    fill=st.sampled_from([np.inf, 1e300, -1e300, 0.0, -0.0, 5e-324, -3.0, np.finfo(np.float32).max]),
)
def test_property_gap_maps_of_any_float_dtype_and_layout_render(dtype: str, layout: str, fill: float) -> None:
    renderer = GelSightRenderer(GelSightConfig(image_height=30, image_width=40, mm_per_px=0.1245 * 4))
    with np.errstate(over="ignore"):  # 1e300 in float32 is +inf: "nothing there", as meant
        gap = np.full((60, 80), fill).astype(dtype)
    gap[20:40, 30:50] = -1.0
    view = {
        "c": gap,
        "f": np.asfortranarray(gap),
        "flipped": gap[::-1, ::-1],
        "strided": np.repeat(gap, 2, axis=1)[:, ::2],
    }[layout]
    if np.isneginf(gap).any():  # -1e300 in float16/32: an infinitely deep object, refused
        with pytest.raises(GelSightRenderError, match="-inf"):
            renderer.render(view)
        return
    image = renderer.render(view)
    np.testing.assert_array_equal(image, renderer.render(np.ascontiguousarray(view, dtype=np.float64)))


@pytest.mark.parametrize(
    "gap",
    [
        np.full((30, 40), np.nan),
        np.full((30, 40), -np.inf),
        np.zeros((30, 40), np.int32),
        np.zeros((2, 40)),
        np.zeros((30, 40, 1)),
        [[0.0] * 40] * 30,
    ],
)
def test_gap_maps_without_a_rendering_are_refused(gap: object) -> None:
    with pytest.raises(GelSightRenderError, match="gel gap map"):
        GelSightRenderer(GelSightConfig(image_height=30, image_width=40, mm_per_px=0.1245 * 4)).render(gap)
