"""Hard cases, round three (issue 52), family "press finder and GelSight fit": the press finder,
the photometric fit, the touch crop and the calibration files give the right answer or a
GelSightRenderError naming the argument, for frames with no press, bad or unchecked inputs, no
presses, NaN tables, a zero evaluation budget, frames smaller than the crop and hostile
calibration files. The presses are rendered here by the project's own renderer, with known
truth. Hypothesis runs derandomized, so every run draws the same examples."""

from __future__ import annotations

import json
import math
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import sim.gelsight_fit as gelsight_fit
from sim.gelsight import GelSightConfig, GelSightRenderer, GelSightRenderError
from sim.gelsight_calibration import (
    POLYNOMIAL_FILE,
    PolyCalibration,
    calibration_from_tables,
    read_npz_arrays,
    renderer_parameters,
)
from sim.gelsight_check import ball_gap_map, crop_px, press_depth_mm, press_ssim, touch_crop
from sim.gelsight_fit import (
    FITTED,
    MAX_FIT_EVALUATIONS,
    Presses,
    fit_presses,
    fit_tables,
    fit_with_parameters,
)
from sim.press_annotation import (
    check_background,
    find_checked_presses,
    find_presses,
    shows_a_change,
    template_center_offset,
)

pytestmark = pytest.mark.filterwarnings("error")  # a RuntimeWarning on the way fails the case

REPO = Path(__file__).resolve().parent.parent
SHIPPED = REPO / "assets" / "gelsight"
MM_PER_PX = 0.1245
BALL_MM = 2.0
BALL_PX = BALL_MM / MM_PER_PX
SHAPE = (120, 160)
# The renderer's parameters the presses are made with (as tests/test_sim_gelsight_fit.py's).
TRUTH: dict[str, Any] = {
    "spreading_length_mm": 0.8,
    "optical_blur_mm": 0.25,
    "compression_saturation_mm": 1.2,
    "background_smoothing_mm": 0.3,
}
RENDERED = settings(max_examples=8, deadline=None, derandomize=True)
CHEAP = settings(max_examples=40, deadline=None, derandomize=True)
# Values no number argument takes: non-finite, huge (an int no float holds), bools, text.
NOT_A_NUMBER: list[object] = [math.nan, math.inf, -math.inf, 10**400, True, "2", None, [2.0]]


@pytest.fixture(scope="module")
def renderer() -> GelSightRenderer:
    return GelSightRenderer(GelSightConfig(**TRUTH, shading_gain=1.0))


def _noisy(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``image`` as a camera with ``sigma`` levels of noise records it."""
    return np.clip(np.rint(image + rng.normal(0.0, sigma, image.shape)), 0, 255).astype(np.uint8)


def _pressed(
    renderer: GelSightRenderer, centres: np.ndarray, seed: int, contact_mm: float = 1.9
) -> tuple[np.ndarray, np.ndarray]:
    """Frames of the ball pressed at ``centres`` (rows with NaN: nothing pressed) and the
    no-contact frame, all with camera noise."""
    rng = np.random.default_rng(seed)
    depth = press_depth_mm(contact_mm, BALL_MM)
    frames = []
    for centre in centres:
        if np.isnan(centre).any():
            clean = renderer.background().astype(np.float32)
        else:
            clean = renderer.render(ball_gap_map(SHAPE, centre, depth, MM_PER_PX, BALL_MM)).astype(np.float32)
        frames.append(_noisy(clean, 1.5, rng))
    return np.stack(frames), _noisy(renderer.background().astype(np.float32), 1.5, rng)


@pytest.fixture(scope="module")
def presses(renderer: GelSightRenderer) -> Presses:
    centres = np.array([[50.0, 40.0], [110.0, 45.0], [60.0, 80.0], [100.0, 75.0]])
    frames, background = _pressed(renderer, centres, seed=0)
    return Presses(frames, background, centres, np.full(4, 1.9 / MM_PER_PX), MM_PER_PX, BALL_MM)


# --- the press finder --------------------------------------------------------------------------


CENTRE = st.tuples(st.floats(30.0, SHAPE[1] - 30.0), st.floats(30.0, SHAPE[0] - 30.0))


@RENDERED
@given(
    st.lists(CENTRE, min_size=3, max_size=5),
    st.lists(st.integers(0, 5), max_size=2),
    st.floats(1.5, 1.9),
    st.integers(0, 2**16),
)
def test_presses_of_a_known_ball_are_found_where_they_are(
    renderer: GelSightRenderer, centres: list[tuple[float, float]], blanks: list[int], contact_mm: float, seed: int
) -> None:
    """Three or more presses (the finder centres them on their mean press: one or two alone carry
    their own shading's asymmetry, 1-3 px at the frame's corners), frames with nothing pressed
    among them, 1.5 to 1.9 mm contacts anywhere their rings and halo fit in the frame."""
    truth = [(x, y) for x, y in centres]
    for index in blanks:
        truth.insert(index, (math.nan, math.nan))
    frames, background = _pressed(renderer, np.array(truth), seed, contact_mm)
    found = find_checked_presses(frames, background, MM_PER_PX, BALL_MM)
    blank = np.isnan(np.array(truth)[:, 0])
    assert np.array_equal(found.trusted, ~blank), found.reasons
    assert all(found.reasons[i].startswith("no press") for i in np.flatnonzero(blank))
    error_px = np.hypot(*(found.centers_xy_px[~blank] - np.array(truth)[~blank]).T)
    # A press matches the mean press to about half a pixel (the shading differs across the gel).
    assert np.max(error_px) < 1.5, error_px
    # Each ring is one this ball makes (half to one and a half of its radius).
    assert np.all(np.abs(found.radii_px[~blank] / BALL_PX - 1.0) <= 0.5), found.radii_px


@CHEAP
@given(st.integers(1, 4), st.floats(0.0, 16.0), st.integers(0, 2**16))
def test_frames_with_no_press_are_all_no_press(renderer: GelSightRenderer, n: int, sigma: float, seed: int) -> None:
    """Before: blank frames crashed with numpy's AxisError (no template to centre) and a single
    noisy frame came out a trusted press."""
    rng = np.random.default_rng(seed)
    clean = renderer.background().astype(np.float32)
    frames = np.stack([_noisy(clean, sigma, rng) for _ in range(n)])
    background = _noisy(clean, sigma, rng)
    for found in (find_presses(frames, background, BALL_PX), find_checked_presses(frames, background, MM_PER_PX, 2.0)):
        assert not found.pressed.any() and not found.trusted.any(), found.reasons
        assert np.isnan(found.radii_px).all() and found.centers_xy_px.shape == (n, 2)
    exact = find_presses(np.repeat(background[None], n, axis=0), background, BALL_PX)
    assert all(reason.startswith("no press") for reason in exact.reasons)


def test_no_frames_are_no_presses() -> None:
    background = np.zeros((*SHAPE, 3), np.uint8)
    frames = np.zeros((0, *SHAPE, 3), np.uint8)
    for found in (find_presses(frames, background, BALL_PX), find_checked_presses(frames, background, 0.1245, 2.0)):
        assert found.centers_xy_px.shape == (0, 2) and found.radii_px.shape == (0,) and found.reasons == []
    check_background(frames, background)


@CHEAP
@given(st.floats(4.0, 30.0), st.floats(0.5, 3.0), st.floats(20.0, 200.0), st.integers(0, 2**16))
def test_a_change_stands_out_of_the_noise_when_a_press_is_there(
    radius_px: float, noise: float, height: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    floor = np.abs(rng.normal(0.0, noise, (*SHAPE, 3))).sum(axis=2)
    assert not shows_a_change(floor)
    ring = np.exp(-0.5 * ((np.hypot(cols - 80, rows - 60) - radius_px) / 1.5) ** 2)
    assert shows_a_change(floor + height * ring)


@CHEAP
@given(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(6.0, 12.0))
def test_template_centre_is_its_rings_centre_and_a_flat_template_its_middle(
    dx: float, dy: float, radius_px: float
) -> None:
    size = 41
    rows, cols = np.mgrid[0:size, 0:size]
    ring = np.exp(-0.5 * ((np.hypot(cols - 20 - dx, rows - 20 - dy) - radius_px) / 1.5) ** 2)
    template = np.repeat(ring[:, :, None], 3, axis=2).astype(np.float32)
    assert np.allclose(template_center_offset(template), (dx, dy), atol=0.3)
    for level in (0.0, 5.0):  # before: AxisError, no edge to fit a circle to
        assert np.array_equal(template_center_offset(np.full((size, size, 3), level, np.float32)), (0.0, 0.0))


def _frames_and_background(h: int = SHAPE[0], w: int = SHAPE[1]) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((2, h, w, 3), np.uint8), np.zeros((h, w, 3), np.uint8)


BAD_FRAMES = [
    ("frames", np.zeros((2, 0, 0, 3), np.uint8), np.zeros((0, 0, 3), np.uint8)),  # 0 x 0
    ("frames", np.full((2, *SHAPE, 3), np.nan, np.float32), np.zeros((*SHAPE, 3), np.uint8)),  # NaN floats
    ("frames", np.zeros((2, *SHAPE, 3), np.float64), np.zeros((*SHAPE, 3), np.uint8)),  # floats
    ("frames", np.zeros((2, 15, 15, 3), np.uint8), np.zeros((15, 15, 3), np.uint8)),  # too small a frame
    ("frames", np.zeros((1, 16, 5000, 3), np.uint8), np.zeros((16, 5000, 3), np.uint8)),  # too wide
    ("frames", np.zeros((*SHAPE, 3), np.uint8), np.zeros((*SHAPE, 3), np.uint8)),  # one frame, no N
    ("frames", [np.zeros((*SHAPE, 3), np.uint8)], np.zeros((*SHAPE, 3), np.uint8)),  # a list
    ("background", np.zeros((2, *SHAPE, 3), np.uint8), np.zeros((100, 160, 3), np.uint8)),  # another size
    ("background", np.zeros((2, *SHAPE, 3), np.uint8), np.zeros(SHAPE, np.uint8)),  # grey
    ("background", np.zeros((2, *SHAPE, 3), np.uint8), np.zeros((*SHAPE, 3), np.float32)),
]


@pytest.mark.parametrize(("name", "frames", "background"), BAD_FRAMES)
def test_bad_frames_and_backgrounds_are_refused_naming_them(name: str, frames: Any, background: Any) -> None:
    """Before: a background of another size broadcast-failed, 0 x 0 frames and NaN float frames
    went through the work first."""
    for call in (
        lambda: find_presses(frames, background, 8.0),
        lambda: find_checked_presses(frames, background, MM_PER_PX, BALL_MM),
        lambda: check_background(frames, background),
    ):
        with pytest.raises(GelSightRenderError, match=f"^{name} must be"):
            call()


@CHEAP
@given(st.one_of(st.sampled_from(NOT_A_NUMBER), st.floats(-100.0, 100.0), st.integers(-(10**6), 10**6)))
def test_find_presses_takes_a_ball_radius_it_can_see_or_names_it(ball_radius_px: Any) -> None:
    """Before: any value went in; 10**6 px ran OpenCV out of memory, -5 px crashed the process."""
    frames, background = _frames_and_background()
    number = isinstance(ball_radius_px, (int, float)) and not isinstance(ball_radius_px, bool)
    if number and 4.0 <= ball_radius_px <= 60.0:
        assert len(find_presses(frames[:1], background, ball_radius_px).reasons) == 1
    else:
        with pytest.raises(GelSightRenderError, match=r"^ball_radius_px must be a number in \[4, 60\]"):
            find_presses(frames, background, ball_radius_px)


@pytest.mark.parametrize("value", [0.0, -0.1245, 1e-9, 11.0, *NOT_A_NUMBER])
@pytest.mark.parametrize("name", ["mm_per_px", "ball_radius_mm"])
def test_find_checked_presses_names_a_bad_scale_or_ball(name: str, value: object) -> None:
    """Before: 0 mm/px divided by zero."""
    frames, background = _frames_and_background()
    arguments = {"mm_per_px": MM_PER_PX, "ball_radius_mm": BALL_MM, name: value}
    if name == "ball_radius_mm" and value == 11.0:
        arguments[name] = 60.0  # 11 mm is a ball it takes; 60 mm is not
    with pytest.raises(GelSightRenderError, match=f"^{name} must be a number"):
        find_checked_presses(frames, background, **arguments)


# --- the touch crop and its SSIM ---------------------------------------------------------------


@CHEAP
@given(
    st.integers(1, 40),
    st.integers(1, 40),
    st.data(),
    st.floats(-1e6, 1e6),
    st.floats(-1e6, 1e6),
)
def test_touch_crop_is_a_window_of_the_frame_holding_the_touch(
    h: int, w: int, data: st.DataObject, x: float, y: float
) -> None:
    image = np.arange(h * w).reshape(h, w)
    size = data.draw(st.integers(1, min(h, w)))
    crop = touch_crop(image, (x, y), size)
    assert crop.shape == (size, size)
    y0, x0 = divmod(int(crop[0, 0]), w)
    assert np.array_equal(crop, image[y0 : y0 + size, x0 : x0 + size])
    # The window holds the touch's pixel, or the frame's edge nearest it.
    touch_x, touch_y = min(max(round(x), 0), w - 1), min(max(round(y), 0), h - 1)
    assert x0 <= touch_x < x0 + size and y0 <= touch_y < y0 + size


@pytest.mark.parametrize(
    ("arguments", "name"),
    [
        ((np.zeros((10, 10)), (5, 5), 16), "size"),  # before: the wrong pixels, from a negative start
        ((np.zeros((10, 10)), (5, 5), 0), "size"),
        ((np.zeros((10, 10)), (5, 5), True), "size"),
        ((np.zeros((10, 10)), (5, 5), 4.0), "size"),
        ((np.zeros((10, 10)), (math.nan, 5), 4), "center_xy_px"),
        ((np.zeros((10, 10)), (5,), 4), "center_xy_px"),
        ((np.zeros((10, 10)), "ab", 4), "center_xy_px"),
        ((np.zeros(10), (5, 5), 4), "image"),
    ],
)
def test_touch_crop_names_what_it_cannot_take(arguments: tuple[Any, Any, Any], name: str) -> None:
    with pytest.raises(GelSightRenderError, match=f"^{name} must be"):
        touch_crop(*arguments)


@CHEAP
@given(st.integers(11, 47), st.integers(11, 47), st.data(), st.integers(0, 2**16))
def test_the_crop_ssim_of_a_frame_narrower_than_the_crop_is_on_the_pixels_about_the_touch(
    h: int, w: int, data: st.DataObject, seed: int
) -> None:
    """At 0.1245 mm/px the crop is 48 px: a smaller frame's crop is the square of its smaller side
    about the touch. A change at the touch lowers the crop's SSIM; one farther from the touch than
    that side (outside every such square holding it) does not."""
    rng = np.random.default_rng(seed)
    frame = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    x, y = data.draw(st.integers(0, w - 1)), data.draw(st.integers(0, h - 1))
    side = min(h, w)
    at_touch = frame.copy()
    at_touch[y, x] = (at_touch[y, x].astype(int) + 128) % 256  # half the range away
    scores = press_ssim([at_touch], [frame], np.array([[x, y]]), MM_PER_PX)
    # At the crop's corner the pixel is in one SSIM window, at its edge weight: a drop of 1e-6.
    assert scores["crop"][0] < 1.0 and scores["full"][0] < 1.0
    far = [(col, row) for col, row in ((x + side, y), (x - side, y), (x, y + side), (x, y - side)) if 0 <= col < w]
    far = [(col, row) for col, row in far if 0 <= row < h]
    for col, row in far:
        elsewhere = frame.copy()
        elsewhere[row, col] = (elsewhere[row, col].astype(int) + 128) % 256
        scores = press_ssim([elsewhere], [frame], np.array([[x, y]]), MM_PER_PX)
        assert scores["crop"][0] == pytest.approx(1.0, abs=1e-9) and scores["full"][0] < 1.0


def test_press_ssim_of_no_presses_is_empty_and_bad_arguments_are_named() -> None:
    frames = np.zeros((2, 20, 20, 3), np.uint8)
    centres = np.full((2, 2), 10.0)
    empty = press_ssim([], np.zeros((0, 20, 20, 3), np.uint8), np.zeros((0, 2)), MM_PER_PX)
    assert empty["crop"].shape == empty["full"].shape == (0,)
    assert np.allclose(press_ssim(frames, frames, centres, MM_PER_PX)["crop"], 1.0)
    for arguments, name in [
        ((frames[:, :10, :10], frames[:, :10, :10], centres, MM_PER_PX), "images"),  # below SSIM's window
        ((frames, frames.astype(np.float32), centres, MM_PER_PX), "frames"),
        ((frames, [frames[0], frames[0, :15]], centres, MM_PER_PX), "frames"),
        ((frames, frames[:1], centres, MM_PER_PX), "images, frames and centers_xy_px"),
        ((frames, frames, np.full((2, 2), np.nan), MM_PER_PX), "images, frames and centers_xy_px"),
        ((frames, frames, centres, 0.0), "mm_per_px"),
        ((frames, frames, centres, math.nan), "mm_per_px"),
    ]:
        with pytest.raises(GelSightRenderError, match=f"^{name} must be"):
            press_ssim(*arguments)
    with pytest.raises(GelSightRenderError, match="^mm_per_px must be"):
        crop_px(10**400)


# --- the photometric fit -----------------------------------------------------------------------


def test_presses_are_checked_where_they_enter(presses: Presses) -> None:
    """Before: NaN centres reached the fit, which said "the presses show no ball"."""
    good = {name: getattr(presses, name) for name in presses.__dataclass_fields__}
    for field, value in [
        ("frames", presses.frames.astype(np.float32)),
        ("background", presses.background[:100]),
        ("centers_xy_px", np.full((4, 2), np.nan)),
        ("centers_xy_px", presses.centers_xy_px[:3]),
        ("centers_xy_px", presses.centers_xy_px + [[200.0, 0.0]]),
        ("radii_px", np.zeros(4)),
        ("radii_px", np.full(4, np.inf)),
        ("radii_px", presses.radii_px.astype(complex)),
        ("mm_per_px", 0.0),
        ("ball_radius_mm", math.nan),
    ]:
        with pytest.raises(GelSightRenderError, match=f"^{field} must"):
            Presses(**{**good, field: value})


def test_zero_presses_cannot_be_fitted(presses: Presses) -> None:
    """Before: an IndexError."""
    none = presses.subset([])
    for call in (lambda: fit_with_parameters(none, TRUTH), lambda: fit_presses(none)):
        with pytest.raises(GelSightRenderError, match="^presses must be Presses holding one or more presses, got 0"):
            call()
    with pytest.raises(GelSightRenderError, match="^gel_depths_mm, colour_changes and near_masks"):
        fit_tables([], [], [], MM_PER_PX, 1.0)


@pytest.mark.parametrize(
    ("parameters", "message"),
    [
        ({"shading_gain": 1.0}, "^parameters must map some of"),  # not one the fit varies (before: a TypeError)
        ({"spreading": 1.0}, "^parameters must map some of"),
        ([0.8, 0.25], "^parameters must map some of"),
        ({"optical_blur_mm": math.nan}, r"^GelSightConfig\.optical_blur_mm must be a finite number"),
        ({"spreading_length_mm": -1.0}, r"^GelSightConfig\.spreading_length_mm must be in"),
    ],
)
def test_fit_with_parameters_names_parameters_it_cannot_take(presses: Presses, parameters: Any, message: str) -> None:
    with pytest.raises(GelSightRenderError, match=message):
        fit_with_parameters(presses, parameters)


def test_fit_tables_names_what_it_cannot_take() -> None:
    depth, change, near = np.zeros(SHAPE, np.float32), np.zeros((*SHAPE, 3), np.float32), np.ones(SHAPE, bool)
    for arguments, name in [
        (([depth, depth], [change], [near, near], MM_PER_PX, 1.0), "gel_depths_mm, colour_changes and near_masks"),
        (([np.full(SHAPE, np.nan, np.float32)], [change], [near], MM_PER_PX, 1.0), "gel_depths_mm"),
        (([depth, depth[:10]], [change] * 2, [near] * 2, MM_PER_PX, 1.0), "gel_depths_mm"),
        (([depth], [change[:, :, :2]], [near], MM_PER_PX, 1.0), "colour_changes"),
        (([depth], [change], [near.astype(np.uint8)], MM_PER_PX, 1.0), "near_masks"),
        (([depth], [change], [near], 0.0, 1.0), "mm_per_px"),
        (([depth], [change], [near], MM_PER_PX, 0.0), "compression_saturation_mm"),
        (([depth], [change], [near], MM_PER_PX, math.inf), "compression_saturation_mm"),
    ]:
        with pytest.raises(GelSightRenderError, match=f"^{name} must"):
            fit_tables(*arguments)


@pytest.mark.parametrize("evaluations", [0, 1, 2])
def test_a_fit_renders_the_presses_as_many_times_as_it_is_given(
    presses: Presses, evaluations: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: ``evaluations=0`` ran FIT_EVALUATIONS (40). Zero is no search: the defaults' fit."""
    rendered: list[int] = []
    real_render = gelsight_fit.render_fit
    monkeypatch.setattr(gelsight_fit, "render_fit", lambda *a: rendered.append(1) or real_render(*a))
    fit = fit_presses(presses.subset([0, 1]), evaluations=evaluations)
    assert len(rendered) == evaluations
    if evaluations == 0:
        defaults = {name: getattr(GelSightConfig(), name) for name in FITTED}
        assert fit.parameters == pytest.approx(defaults)


@pytest.mark.parametrize("evaluations", [-1, MAX_FIT_EVALUATIONS + 1, 10**400, 2.5, True, "3", math.nan])
def test_a_fit_names_an_evaluation_budget_it_cannot_take(presses: Presses, evaluations: Any) -> None:
    with pytest.raises(GelSightRenderError, match="^evaluations must be"):
        fit_presses(presses, evaluations=evaluations)


# --- calibration tables and files --------------------------------------------------------------


@CHEAP
@given(
    st.integers(0, 5),
    st.sampled_from(["none", "nan", "inf", "complex", "text"]),
    st.sampled_from([(12, 16), (3, 3), (2, 16), (0, 0)]),
)
def test_calibration_from_tables_takes_finite_tables_of_two_bins_or_more(n: int, bad: str, size: tuple) -> None:
    """Before: NaN tables were accepted (the renderer drew NaN), a one-bin table IndexError'd and a
    0 x 0 background divided by zero in the renderer."""
    rng = np.random.default_rng(n)
    tables: np.ndarray = rng.normal(0.0, 1.0, (n, n, 3, 6))
    if bad in ("nan", "inf") and n:
        tables[-1, 0, 1, 2] = math.nan if bad == "nan" else math.inf
    elif bad == "complex":
        tables = tables.astype(complex)
    elif bad == "text":
        tables = tables.astype(str)
    background = np.full((*size, 3), 128, np.uint8)
    if n >= 2 and bad == "none" and min(size) >= 3:
        calibration = calibration_from_tables(tables, background)
        image = GelSightRenderer(GelSightConfig(image_height=12, image_width=16), calibration=calibration).render(
            ball_gap_map((12, 16), (8.0, 6.0), 0.3, MM_PER_PX)
        )
        assert image.shape == (12, 16, 3) and calibration.n_bins == 2 * (n - 1)
        return
    name = "tables" if n < 2 or bad != "none" else "background"
    with pytest.raises(GelSightRenderError, match=f"^{name} must be"):
        calibration_from_tables(tables, background)


def test_a_calibration_made_directly_is_checked_too() -> None:
    coeffs, background = np.zeros((4, 4, 3, 6), np.float32), np.zeros((12, 16, 3), np.uint8)
    for bad_coeffs in (np.full((4, 4, 3, 6), np.nan, np.float32), np.zeros((0, 0, 3, 6), np.float32), [[0.0]]):
        with pytest.raises(GelSightRenderError, match=r"^PolyCalibration\.coeffs must be"):
            PolyCalibration(bad_coeffs, background)  # type: ignore[arg-type]
    with pytest.raises(GelSightRenderError, match=r"^PolyCalibration\.background must be"):
        PolyCalibration(coeffs, np.zeros((0, 0, 3), np.uint8))


def _calibration_dir(root: Path, name: str, poly: dict[str, Any], background: Any = None) -> Path:
    """A calibration directory: the shipped tables with ``poly``'s keys replaced (None: removed)."""
    directory = root / name
    directory.mkdir()
    with np.load(SHIPPED / POLYNOMIAL_FILE) as shipped:
        arrays = {key: shipped[key] for key in shipped.files}
    arrays.update(poly)
    np.savez(directory / POLYNOMIAL_FILE, **{k: v for k, v in arrays.items() if v is not None})
    with np.load(SHIPPED / "ball_presses.npz") as shipped:
        frame = shipped["background"] if background is None else background
    np.savez(directory / "ball_presses.npz", background=frame)
    return directory


def _huge_header_npz(path: Path, key: str, shape: tuple[int, ...]) -> None:
    """An .npz whose ``key`` claims ``shape`` (uint8) and holds a few bytes."""
    header = {"descr": "|u1", "fortran_order": False, "shape": shape}
    with zipfile.ZipFile(path, "w") as archive, archive.open(f"{key}.npy", "w") as member:
        np.lib.format.write_array_header_1_0(member, header)
        member.write(b"\0" * 64)


def test_hostile_calibration_files_are_refused_naming_the_file(tmp_path: Path) -> None:
    """Before: a bins of inf or of two numbers, a one-bin table, a 0 x 0 background and an object
    array crashed with OverflowError, TypeError, IndexError, ZeroDivisionError and ValueError."""
    tables = ("grad_r", "grad_g", "grad_b")
    cases: list[tuple[str, dict[str, Any], Any, str]] = [
        ("bins_400_digits", {"bins": np.array("9" * 400)}, None, "bins must be an integer in"),
        ("bins_inf", {"bins": np.array(math.inf)}, None, "bins must be an integer in"),
        ("bins_two", {"bins": np.array([80, 80])}, None, "bins: its header says"),
        ("bins_object", {"bins": np.array([None], dtype=object)}, None, "an object array"),
        ("one_bin", {"bins": np.int64(1), **{k: np.zeros((1, 1, 6)) for k in tables}}, None, "bins must be"),
        ("tables_nan", {"grad_g": np.full((80, 80, 6), np.nan)}, None, "tables must be finite"),
        ("tables_text", {"grad_b": np.full((80, 80, 6), "a")}, None, "tables must be a real"),
        ("tables_short", {"grad_r": np.zeros((80, 79, 6))}, None, r"grad_r must be an \(80, 80, 6\) array"),
        ("no_tables", {"grad_r": None}, None, r"missing keys \['grad_r'\]"),
        ("background_0x0", {}, np.zeros((0, 0, 3), np.uint8), "background must be an H x W x 3 uint8 frame"),
        ("background_float", {}, np.zeros((12, 16, 3)), "background must be an H x W x 3 uint8 frame"),
    ]
    for name, poly, background, message in cases:
        directory = _calibration_dir(tmp_path, name, poly, background)
        with pytest.raises(GelSightRenderError, match=f"{re.escape(str(directory))}.*{message}"):
            GelSightRenderer(GelSightConfig(calibration_dir=str(directory)))
    garbage = _calibration_dir(tmp_path, "garbage", {})
    (garbage / POLYNOMIAL_FILE).write_bytes(b"not a zip file at all")
    with pytest.raises(GelSightRenderError, match="not a readable .npz file"):
        GelSightRenderer(GelSightConfig(calibration_dir=str(garbage)))


def test_an_npz_claiming_a_huge_array_is_refused_before_it_is_read(tmp_path: Path) -> None:
    _huge_header_npz(tmp_path / "huge.npz", "background", (100_000, 100_000, 3))  # 30 GB claimed
    with pytest.raises(GelSightRenderError, match=r"background: its header says \(100000, 100000, 3\)"):
        read_npz_arrays(tmp_path / "huge.npz", {"background": 4096 * 4096 * 3})
    _huge_header_npz(tmp_path / "short.npz", "background", (10, 10, 3))  # claims 300 bytes, holds 64
    with pytest.raises(GelSightRenderError, match="not a readable .npz file"):
        read_npz_arrays(tmp_path / "short.npz", {"background": 4096 * 4096 * 3})


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"spreading_length_mm": ' + "9" * 400 + "}", "spreading_length_mm must be a finite number"),
        ('{"spreading_length_mm": ' + "9" * 5000 + "}", "spreading_length_mm must be a finite number"),
        ('{"optical_blur_mm": NaN}', "optical_blur_mm must be a finite number"),
        ('{"shading_gain": true}', "shading_gain must be a finite number"),
        ('{"shading_gain": "1"}', "shading_gain must be a finite number"),
        ("[" * 30_000, "not readable JSON"),  # nested past Python's recursion limit
        ('{"shading_gain": 1.0, "x": 1}', "must map some of"),
        (" " * 70_000 + "{}", "more than 65536 bytes: not a parameters file"),
    ],
)
def test_hostile_renderer_parameters_are_refused_naming_the_file(tmp_path: Path, text: str, message: str) -> None:
    """Before: an integer of 400 digits was an OverflowError, deep nesting a RecursionError."""
    (tmp_path / "renderer.json").write_text(text)
    with pytest.raises(GelSightRenderError, match=f"renderer.json: {message}"):
        renderer_parameters(tmp_path)


def test_the_shipped_calibration_and_a_fitted_one_still_load(tmp_path: Path, presses: Presses) -> None:
    fit = fit_with_parameters(presses, TRUTH)
    directory = _calibration_dir(
        tmp_path,
        "fitted",
        {"bins": np.int64(fit.tables.shape[0]), **{f"grad_{k}": fit.tables[:, :, i] for i, k in enumerate("rgb")}},
    )
    (directory / "renderer.json").write_text(json.dumps({**TRUTH, "calibration_mm_per_px": 0.1245}))
    for calibration_dir in (str(SHIPPED), str(directory)):
        renderer = GelSightRenderer(
            GelSightConfig(calibration_dir=calibration_dir, **renderer_parameters(calibration_dir))
        )
        assert renderer.render(ball_gap_map(SHAPE, (80.0, 60.0), 0.3, MM_PER_PX)).shape == (*SHAPE, 3)
