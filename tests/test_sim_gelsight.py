"""GelSight renderer: shapes, exactness without effects, physics properties, bad input, effects."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from perception.ssim import ssim_rgb
from sim.gelsight import (
    EFFECTS,
    GelSightConfig,
    GelSightRenderer,
    GelSightRenderError,
    LightingDrift,
    Markers,
    SensorNoise,
    gel_surface_depth_mm,
    indentation_mm,
    make_effect,
)
from sim.gelsight_check import ball_gap_map
from sim.gelsight_shading import slope_bin, slope_bin_edges

RENDERER = GelSightRenderer()
H, W = RENDERER.config.shape


def ball(depth_mm: float, config: GelSightConfig = RENDERER.config, center_mm=(0.0, 0.0)) -> np.ndarray:
    """Gap map of the 4 mm ball pressed ``depth_mm`` in, ``center_mm`` (x, y) from the gel centre."""
    h, w = config.shape
    center_px = ((w - 1) / 2 + center_mm[0] / config.mm_per_px, (h - 1) / 2 + center_mm[1] / config.mm_per_px)
    return ball_gap_map((h, w), center_px, depth_mm, config.mm_per_px)


def upsampled(small: np.ndarray) -> np.ndarray:
    """A small gap map blown up to the image size, keeping +inf (no interpolation across it)."""
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_NEAREST)


# Gap maps of any finite or +inf values, at the image's aspect ratio (3x4 cells).
gap_cells = hnp.arrays(
    np.float32,
    (6, 8),
    elements=st.one_of(
        st.floats(width=32, allow_nan=False, allow_infinity=False),
        st.floats(-3.0, 3.0, width=32),
        st.just(np.float32(np.inf)),
    ),
)


@settings(max_examples=40, deadline=None)
@given(gap_cells)
def test_render_is_valid_for_any_finite_or_inf_gap_map(cells):
    depth = RENDERER.gel_depth_mm(upsampled(cells))
    assert np.all(np.isfinite(depth)) and depth.min() >= 0.0
    assert depth.max() <= RENDERER.config.elastomer_thickness_mm + 1e-4
    image = RENDERER.render(upsampled(cells))
    assert image.shape == (H, W, 3) and image.dtype == np.uint8


@settings(max_examples=40, deadline=None)
@given(gap_cells)
def test_gap_map_at_another_size_is_resampled(cells):
    assert RENDERER.render(cells).shape == (H, W, 3)


@settings(max_examples=30, deadline=None)
@given(hnp.arrays(np.float64, (3, 4), elements=st.one_of(st.floats(0.0, 1e30), st.just(np.inf))))
def test_gel_not_touched_renders_the_background_exactly(cells):
    assert np.array_equal(RENDERER.render(upsampled(cells)), RENDERER.background())


@settings(max_examples=25, deadline=None)
@given(st.floats(0.05, 1.9), st.floats(0.05, 1.9))
def test_deeper_press_pushes_the_gel_further_and_changes_the_image_more(d1, d2):
    shallow, deep = sorted((d1, d2))
    depth_shallow, depth_deep = RENDERER.gel_depth_mm(ball(shallow)), RENDERER.gel_depth_mm(ball(deep))
    assert np.all(depth_deep >= depth_shallow - 1e-5)
    background = RENDERER.background().astype(int)
    change = [np.abs(RENDERER.render(ball(d)).astype(int) - background).sum() for d in (shallow, deep)]
    assert change[1] >= change[0]


def test_gel_spreads_around_the_contact_and_lies_on_the_object_inside_it():
    depth_mm = 1.0
    gap = ball(depth_mm)
    indentation = indentation_mm(gap, 3.0)
    surface = RENDERER.gel_depth_mm(gap)
    centre = (H // 2, W // 2)
    assert surface[centre] == pytest.approx(depth_mm, abs=0.05)
    beyond = (indentation == 0) & (surface > 0.01)  # pressed in where the ball does not reach
    assert beyond.sum() > 0.5 * (indentation > 0).sum()


def test_spreading_keeps_the_contact():
    indentation = np.zeros((40, 40), np.float32)
    indentation[15:25, 15:25] = 0.5
    surface = gel_surface_depth_mm(indentation, spreading_sigma_px=(4.0, 3.0), blur_sigma_px=(1e-3, 1e-3))
    assert np.all(surface >= indentation - 1e-6)


def test_no_effects_is_deterministic_and_pressing_changes_the_touch_only():
    image = RENDERER.render(ball(1.0, center_mm=(3.0, 1.0)))
    assert np.array_equal(image, GelSightRenderer().render(ball(1.0, center_mm=(3.0, 1.0))))
    diff = np.abs(image.astype(int) - RENDERER.background().astype(int)).sum(axis=2)
    assert diff[:, :10].max() == 0  # far from the ball the gel is untouched
    assert diff.max() > 30


@pytest.mark.parametrize(("height", "width"), [(100, 100), (480, 640)])
def test_other_sizes_render_the_same_gel(height, width):
    config = GelSightConfig(image_height=height, image_width=width, mm_per_px=0.1245 * 160 / width)
    renderer = GelSightRenderer(config)
    gap = ball(1.2, center_mm=(2.0, -1.0))  # at the native size: resampled to the image size
    image = renderer.render(gap)
    assert image.shape == (height, width, 3) and image.dtype == np.uint8
    assert renderer.pixel_pitch_mm == pytest.approx((0.1245 * 120 / height, 0.1245 * 160 / width))
    # The same field of view: the native rendering resized to this size looks the same.
    reference = cv2.resize(RENDERER.render(gap), (width, height), interpolation=cv2.INTER_LINEAR)
    assert ssim_rgb(image, reference) > 0.98
    assert np.array_equal(renderer.render(np.full((7, 9), np.inf)), renderer.background())


@pytest.mark.parametrize(
    "gap",
    [
        np.zeros((H, W), np.int32),
        np.zeros((H, W, 1), np.float32),
        np.zeros((2, 2), np.float32),
        np.full((H, W), np.nan, np.float32),
        np.full((H, W), -np.inf, np.float32),
        [[0.0] * 4] * 3,
    ],
)
def test_bad_gap_map_is_rejected(gap):
    with pytest.raises(GelSightRenderError):
        RENDERER.render(gap)


@pytest.mark.parametrize(
    "change",
    [
        {"image_height": 0},
        {"image_width": 2.5},
        {"mm_per_px": 0.0},
        {"spreading_length_mm": -1.0},
        {"shading_gain": float("nan")},
        {"compression_saturation_mm": 0.0},
        {"shading_gain": 5.0},
    ],
)
def test_bad_config_is_rejected(change):
    with pytest.raises(GelSightRenderError):
        GelSightConfig(**change)


def test_bad_calibration_dir_and_background_are_rejected(tmp_path):
    with pytest.raises(GelSightRenderError, match="missing"):
        GelSightRenderer(GelSightConfig(calibration_dir=str(tmp_path)))
    with pytest.raises(GelSightRenderError, match="background"):
        GelSightRenderer(background=np.zeros((H, W, 3), np.float32))
    with pytest.raises(GelSightRenderError, match="apply"):
        GelSightRenderer(effects=(object(),))
    mini = GelSightConfig(image_height=240, image_width=320, mm_per_px=0.0623)
    with pytest.raises(GelSightRenderError, match=r"\(120, 160, 3\) or \(240, 320, 3\), got \(100, 100, 3\)"):
        GelSightRenderer(mini, background=np.zeros((100, 100, 3), np.uint8))


def test_a_background_of_the_images_size_is_that_cameras_own_frame_smoothed():
    """Another sensor's no-contact frame (a press file at 240 x 320) is rendered against as it is,
    smoothed by the config's millimetres at that camera's pitch, not resampled from the calibration's."""
    config = GelSightConfig(image_height=240, image_width=320, mm_per_px=0.0623, background_smoothing_mm=0.1246)
    frame = np.zeros((240, 320, 3), np.uint8)
    frame[120, 160] = 255
    levels = GelSightRenderer(config, background=frame).background_levels
    assert levels.shape == (240, 320, 3) and levels.sum() == pytest.approx(3 * 255, rel=1e-3)
    # Two pixels' sigma: the point's spread falls to e^-1/2 of its peak two pixels away.
    assert levels[120, 162, 0] / levels[120, 160, 0] == pytest.approx(np.exp(-0.5), rel=0.02)


def test_sensor_noise_is_seeded_zero_mean_and_of_its_size():
    clean = RENDERER.render(ball(1.0)).astype(float)
    noisy = [
        GelSightRenderer(effects=(SensorNoise(3.0),), rng=np.random.default_rng(s)).render(ball(1.0)) for s in (1, 1, 2)
    ]
    assert np.array_equal(noisy[0], noisy[1]) and not np.array_equal(noisy[0], noisy[2])
    residual = noisy[0] - clean
    assert abs(residual.mean()) < 0.2 and 2.5 < residual.std() < 3.5


def test_markers_are_dark_dots_that_move_with_the_gel():
    markers = Markers(pitch_mm=1.2, dot_radius_mm=0.2, darkness=0.7, lateral_shift_per_slope_mm=0.3)
    renderer = GelSightRenderer(effects=(markers,))
    flat = renderer.render(ball(-1.0))  # nothing touches
    background = RENDERER.background()
    assert np.all(flat <= background)
    dark = flat.astype(int).sum(axis=2) < 0.6 * background.astype(int).sum(axis=2)
    assert dark[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].any()  # a dot at the gel centre
    pitch_px = markers.pitch_mm / RENDERER.config.mm_per_px
    assert 0.5 * (W * H) / pitch_px**2 < cv2.connectedComponents(dark.astype(np.uint8))[0] - 1
    pressed = renderer.render(ball(1.5))
    without = RENDERER.render(ball(1.5))
    moved = (pressed < without).any(axis=2) != (flat < background).any(axis=2)
    assert moved[H // 2 - 20 : H // 2 + 20, W // 2 - 20 : W // 2 + 20].any()
    assert not moved[:, :15].any()  # far from the contact the dots stay put


def test_lighting_drift_changes_successive_frames_within_its_bound():
    drift = LightingDrift(step_fraction=0.01, max_fraction=0.03)
    renderer = GelSightRenderer(effects=(drift,), rng=np.random.default_rng(3))
    frames = [renderer.render(ball(1.0)).astype(float) for _ in range(30)]
    assert not np.array_equal(frames[0], frames[-1])
    assert np.all(np.abs(drift.gain - 1.0) <= 0.03 + 1e-6)


def test_effects_are_built_by_name_with_checked_parameters():
    assert set(EFFECTS) == {"sensor_noise", "markers", "lighting_drift"}
    assert make_effect("sensor_noise", {"sigma_levels": 2.0}) == SensorNoise(2.0)
    for name, cls in EFFECTS.items():
        assert isinstance(make_effect(name), cls)
        assert dataclasses.is_dataclass(cls)
    with pytest.raises(GelSightRenderError, match="unknown GelSight effect"):
        make_effect("shadows")
    with pytest.raises(GelSightRenderError, match=r"unknown parameter\(s\) \['pitch'\]"):
        make_effect("markers", {"pitch": 1.0})
    with pytest.raises(GelSightRenderError, match="sigma_levels"):
        make_effect("sensor_noise", {"sigma_levels": -1.0})
    with pytest.raises(GelSightRenderError, match="dot_radius_mm"):
        Markers(pitch_mm=1.0, dot_radius_mm=0.6)


def test_refined_calibration_interpolates_between_bin_centres_and_wraps_direction():
    from sim.gelsight_calibration import _refine_bins

    n, factor = 32, 2
    mag = (np.arange(n) + 0.5) * (0.5 * np.pi / n)  # bin centres
    direction = -np.pi + (np.arange(n) + 0.5) * (2 * np.pi / n)
    table = (100 * mag[:, None] + np.sin(direction)[None, :]).astype(np.float32)[:, :, None, None]
    fine = _refine_bins(np.broadcast_to(table, (n, n, 3, 6)).copy(), factor)[:, :, 0, 0]
    assert fine.shape == (n * factor, n * factor)
    fine_mag = (np.arange(n * factor) + 0.5) * (0.5 * np.pi / (n * factor))
    fine_dir = -np.pi + (np.arange(n * factor) + 0.5) * (2 * np.pi / (n * factor))
    # Linear in magnitude: exact between the first and last coarse centres.
    inner = (fine_mag > mag[0]) & (fine_mag < mag[-1])
    expected_mag_part = 100 * fine_mag[inner][:, None]
    residual = fine[inner] - expected_mag_part
    # The direction part is interpolated across the -pi/pi seam too, where sin changes sign.
    assert np.abs(residual - np.sin(fine_dir)[None, :]).max() < 0.01


def test_large_images_computed_on_the_coarser_working_grid_match_the_full_computation(monkeypatch):
    import sim.gelsight as gelsight

    config = GelSightConfig(image_height=480, image_width=640, mm_per_px=0.1245 / 4)
    coarse = GelSightRenderer(config)
    monkeypatch.setattr(gelsight, "SHADING_GRID_PER_SIGMA", float("inf"))  # work on the image grid
    full = GelSightRenderer(config)
    gap = ball(1.2, config, center_mm=(2.0, -1.0))
    assert coarse.gel_depth_mm(gap).shape == full.gel_depth_mm(gap).shape == (480, 640)
    assert ssim_rgb(coarse.render(gap), full.render(gap)) > 0.99


# Slopes a gel under a press has (mm per mm), both signs, from flat to near vertical.
slopes = st.floats(-50.0, 50.0, allow_nan=False).filter(lambda v: v == 0.0 or abs(v) > 1e-6)


def float_bins(x: np.ndarray, y: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The slopes' bin positions in float64 as the renderer's NumPy form wrote them (floor of
    these, at most n - 1): magnitude atan|slope| / (pi/2/n), direction (atan2 + pi) / (2 pi/n)."""
    return np.arctan(np.hypot(x, y)) / (0.5 * np.pi / n_bins), (np.arctan2(y, x) + np.pi) / (2 * np.pi / n_bins)


def away_from_an_edge(position: np.ndarray) -> np.ndarray:
    return np.abs(position - np.rint(position)) > 1e-9


@settings(max_examples=300, deadline=None)
@given(slopes, slopes, st.sampled_from([7, 32, 158]))
def test_property_a_slopes_bin_is_its_angles_floor_without_a_transcendental(x, y, n_bins):
    """The polynomial's guess corrected by the bin edges gives the bin arctan and arctan2 give,
    wherever the slope is not within rounding of an edge."""
    if x == 0.0 and y == 0.0:
        return
    tan_edges, direction_edges = slope_bin_edges(n_bins)
    i_mag, i_dir = slope_bin(x, y, tan_edges, direction_edges)
    magnitude, direction = float_bins(np.float64(x), np.float64(y), n_bins)
    assert 0 <= i_mag < n_bins and 0 <= i_dir < n_bins
    if away_from_an_edge(magnitude):
        assert i_mag == min(int(magnitude), n_bins - 1)
    if away_from_an_edge(direction):
        assert i_dir == min(int(direction), n_bins - 1)


@settings(max_examples=20, deadline=None)
@given(st.floats(0.05, 1.4), st.floats(-3.0, 3.0), st.floats(-2.0, 2.0))
def test_the_compiled_colour_change_is_the_numpy_form_it_replaced(press_mm, centre_x_mm, centre_y_mm):
    """Flat colour by compression, the tilt threshold, each tilted pixel's bin and polynomial (summed
    in the stated order): equal to the renderer's NumPy form, written out here, on every pixel
    whose slope is not within rounding of a bin edge."""
    renderer, grid, config = RENDERER, RENDERER.grid, RENDERER.config
    depth = renderer._work_depth(ball(press_mm, center_mm=(centre_x_mm, centre_y_mm)))
    change = renderer._colour_change(depth)

    row_mm, col_mm = grid.pitch_mm
    padded = np.pad(depth, 1, mode="edge")
    slope_x = (padded[1:-1, 2:] - padded[1:-1, :-2]) * np.float32(0.5 / col_mm)
    slope_y = (padded[2:, 1:-1] - padded[:-2, 1:-1]) * np.float32(0.5 / row_mm)
    compression = np.minimum(depth * np.float32(1.0 / config.compression_saturation_mm), np.float32(1.0))
    want = grid.flat_change * compression[:, :, None]
    tilted = np.flatnonzero(np.sqrt(slope_x * slope_x + slope_y * slope_y) >= grid.tilted_tan)
    assert tilted.size > 0
    x, y = slope_x.ravel()[tilted].astype(np.float64), slope_y.ravel()[tilted].astype(np.float64)
    magnitude, direction = float_bins(x, y, grid.n_bins)
    bins = np.minimum(magnitude.astype(int), grid.n_bins - 1) * grid.n_bins + np.minimum(
        direction.astype(int), grid.n_bins - 1
    )
    t = [grid.coeffs[bins][:, :, k] * grid.terms[tilted][:, None, k] for k in range(6)]
    colour = ((t[0] + t[4]) + (t[1] + t[5])) + (t[2] + t[3])
    want.reshape(-1, 3)[tilted] += np.float32(config.shading_gain) * (colour - grid.flat_colour[tilted])
    exact = np.ones(depth.size, bool)
    exact[tilted] = away_from_an_edge(magnitude) & away_from_an_edge(direction)
    assert np.array_equal(change.reshape(-1, 3)[exact], want.reshape(-1, 3)[exact])
    assert exact.mean() > 0.999
