"""The physics prior's image expected over a pose error (models.prior): the sensor's background
stays, the contact's change spreads as the offsets do, and a bad uncertainty is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.checkpoint import TrainConfig
from models.errors import ModelConfigError
from models.networks import GeneratorConfig
from models.prior import PhysicsPrior, PriorSpec
from sim.gelsight import render_depth_maps

REPO = Path(__file__).resolve().parent.parent
SCENE = str(REPO / "scenes" / "ycb_three.yaml")
BINS = 100
CROP_M = (0.024, 0.015, 0.019)  # wider than the GelSight's 16 x 12 mm field, as a session's crop
FAR_M = 0.01


@pytest.fixture(scope="module")
def prior() -> PhysicsPrior:
    return PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=1.0), BINS)


def ball_press(centre_mm: tuple[float, float], radius_mm: float = 2.0, depth_mm: float = 0.6) -> np.ndarray:
    """A 1 x BINS x BINS depth-map (m) of a ball pressed into the gel at ``centre_mm`` (x, z)
    from the crop's centre; elsewhere nothing within reach."""
    x = (np.arange(BINS) + 0.5) / BINS * CROP_M[0] * 1e3 - CROP_M[0] * 1e3 / 2
    z = (np.arange(BINS) + 0.5) / BINS * CROP_M[2] * 1e3 - CROP_M[2] * 1e3 / 2
    r2 = (x[None, :] - centre_mm[0]) ** 2 + (z[:, None] - centre_mm[1]) ** 2
    gap_mm = np.where(r2 < radius_mm**2, radius_mm - depth_mm - np.sqrt(np.maximum(radius_mm**2 - r2, 0)), np.inf)
    return np.minimum(gap_mm * 1e-3, FAR_M).astype(np.float32)[None]


def test_zero_uncertainty_is_the_renderers_image(prior: PhysicsPrior) -> None:
    press = ball_press((1.0, -0.5))
    sharp = prior.images(press, pose_sigma_mm=0.0)
    renderer = PhysicsPrior(PriorSpec(SCENE, CROP_M), BINS)  # the spec's default, 0
    np.testing.assert_array_equal(sharp, renderer.images(press))
    assert np.abs(sharp.astype(int) - prior.images(press).astype(int)).max() > 10  # the default, 1 mm, differs


@settings(max_examples=8, deadline=None)
@given(sigma_mm=st.floats(0.1, 3.0))
def test_nothing_in_reach_is_the_background_at_any_uncertainty(prior: PhysicsPrior, sigma_mm: float) -> None:
    empty = np.full((1, BINS, BINS), FAR_M, np.float32)
    np.testing.assert_array_equal(prior.images(empty, sigma_mm)[0], prior.renderer.background())


@pytest.mark.parametrize("sigma_mm", [0.0, 1.0])
def test_maps_nothing_presses_into_are_what_the_renderer_draws_for_them_beside_pressed_ones(
    prior: PhysicsPrior, sigma_mm: float
) -> None:
    """The prior skips the renderer for a map with no bin below 0 (its background); each map of
    a mixed batch is what the renderer's public function draws for it alone, so a renderer that
    one day draws something for an object near the gel but not in it fails here."""
    rng = np.random.default_rng(3)
    untouched = np.stack(
        [
            np.zeros((BINS, BINS)),  # touching everywhere, pressing nowhere
            np.full((BINS, BINS), FAR_M),
            np.where(rng.random((BINS, BINS)) < 0.3, np.nan, rng.uniform(0.0, 0.002, (BINS, BINS))),
            np.full((BINS, BINS), np.inf),
        ]
    ).astype(np.float32)
    batch = np.concatenate([ball_press((1.0, 0.5)), untouched, ball_press((-3.0, 1.0))])
    images = prior.images(batch, sigma_mm)
    crop_xz = (CROP_M[0], CROP_M[2])
    np.testing.assert_array_equal(images[1:5], render_depth_maps(prior.renderer, untouched, crop_xz))
    for i in (0, 5):
        np.testing.assert_array_equal(images[i], prior.images(batch[i : i + 1], sigma_mm)[0])
    assert np.abs(images[0].astype(int) - images[1]).max() > 10  # the presses are drawn


def test_the_prior_is_the_sharp_image_averaged_over_gaussian_offsets(prior: PhysicsPrior) -> None:
    """Monte Carlo over in-plane offsets drawn with the prior's sigma: the mean of the sharp
    images of the shifted press is the prior's image, far closer than the sharp image is."""
    offsets = np.random.default_rng(0).normal(0.0, 1.0, size=(400, 2))
    mean = np.mean([prior.images(ball_press((dx, dz)), 0.0)[0].astype(np.float64) for dx, dz in offsets], axis=0)
    expected = prior.images(ball_press((0.0, 0.0)))[0].astype(np.float64)
    sharp = prior.images(ball_press((0.0, 0.0)), 0.0)[0].astype(np.float64)
    assert np.abs(mean - expected).mean() < 0.25 * np.abs(mean - sharp).mean()


def test_an_off_centre_press_spreads_about_its_own_place(prior: PhysicsPrior) -> None:
    background = prior.renderer.background().astype(np.float64)
    change = np.abs(prior.images(ball_press((4.0, 2.0)))[0].astype(np.float64) - background).sum(axis=-1)
    rows, cols = np.nonzero(change > 0.2 * change.max())
    h, w = change.shape
    pitch_rows_mm, pitch_cols_mm = prior.renderer.pixel_pitch_mm
    assert abs((cols.mean() - (w - 1) / 2) * pitch_cols_mm - 4.0) < 0.5
    assert abs((rows.mean() - (h - 1) / 2) * pitch_rows_mm - 2.0) < 0.5


@pytest.mark.parametrize("sigma_mm", [-0.5, float("nan"), float("inf")])
def test_a_bad_uncertainty_is_refused(prior: PhysicsPrior, sigma_mm: float) -> None:
    with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
        prior.images(ball_press((0.0, 0.0)), sigma_mm)
    with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
        PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=sigma_mm), BINS)
    with pytest.raises(ModelConfigError, match="session_pose_sigma_mm"):
        TrainConfig(session_pose_sigma_mm=sigma_mm).validate()


def test_the_spec_round_trips_and_an_older_checkpoints_prior_is_sharp() -> None:
    spec = PriorSpec(SCENE, CROP_M, pose_sigma_mm=1.25)
    assert PriorSpec.from_dict(spec.to_dict()) == spec
    assert PriorSpec.from_dict({"scene": SCENE, "depth_crop_m": list(CROP_M)}).pose_sigma_mm == 0.0


def test_a_dataset_larger_than_one_rendering_call_is_drawn_in_calls(
    prior: PhysicsPrior, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Training loads a whole split through network_input; past the renderer's pixel limit a call
    (1,680 maps at 200 x 200) the prior is drawn in several calls, the same images."""
    import models.data

    maps = np.concatenate([ball_press((x, 0.0)) for x in (-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, -3.0)])
    config = GeneratorConfig(prior=True, image_size=BINS)
    whole = models.data.network_input(maps, (-0.0015, FAR_M), config, prior)
    monkeypatch.setattr(models.data, "MAX_RENDERED_PIXELS", 3 * BINS * BINS)  # 3 maps a call
    with pytest.raises(ModelConfigError, match="pixels a call"):
        prior.channels(np.broadcast_to(maps[:1], (7000, BINS, BINS)))  # one call still refuses past the limit
    np.testing.assert_array_equal(models.data.network_input(maps, (-0.0015, FAR_M), config, prior), whole)


def test_a_prior_drawn_at_the_sensors_pixels_is_the_scene_renderers_image_area_averaged() -> None:
    """``drawn_at="sensor"``: each image is the scene's GelSight (its own 120 x 160 pixels) fed
    the depth-map, then brought to the grid as every target image is (dataset.images.resize_rgb);
    a spec that names no place was drawn at the grid (every checkpoint before it)."""
    from dataset.images import resize_rgb
    from sim.gelsight import scene_renderer
    from workcell.scene import load_scene

    spec = PriorSpec(SCENE, CROP_M, drawn_at="sensor")
    sensor = PhysicsPrior(spec, BINS)
    presses = np.concatenate([ball_press((1.0, -0.5)), ball_press((-2.0, 1.5), radius_mm=3.0, depth_mm=1.2)])
    drawn = render_depth_maps(scene_renderer(load_scene(SCENE), effects=False), presses, (CROP_M[0], CROP_M[2]))
    expected = np.stack([resize_rgb(image, BINS, BINS) for image in drawn])
    np.testing.assert_array_equal(sensor.images(presses), expected)
    grid = PhysicsPrior(PriorSpec(SCENE, CROP_M), BINS)
    assert np.abs(grid.images(presses).astype(int) - expected.astype(int)).max() > 5  # the grid's differ
    assert PriorSpec.from_dict(spec.to_dict()) == spec
    old = spec.to_dict()
    del old["drawn_at"]
    assert PriorSpec.from_dict(old).drawn_at == "grid"


def test_a_prior_drawn_on_fewer_square_pixels_is_that_renderers_image_area_averaged() -> None:
    """``drawn_rows``: the sensor's 14.9 x 19.9 mm field drawn on 84 x 112 square pixels by the
    scene's GelSight at that size, then brought to the grid as the sensor's own would be; a spec
    that names no rows was drawn on the sensor's own (every checkpoint before it)."""
    from dataset.images import resize_rgb
    from sim.gelsight import scene_renderer
    from workcell.scene import load_scene

    spec = PriorSpec(SCENE, CROP_M, drawn_at="sensor", drawn_rows=84)
    prior = PhysicsPrior(spec, BINS)
    assert prior.renderer.config.shape == (84, 112)
    assert prior.renderer.pixel_pitch_mm[0] == pytest.approx(prior.renderer.pixel_pitch_mm[1])
    presses = np.concatenate([ball_press((1.0, -0.5)), ball_press((-2.0, 1.5), radius_mm=3.0, depth_mm=1.2)])
    renderer = scene_renderer(load_scene(SCENE), size=(84, 112), effects=False)
    drawn = render_depth_maps(renderer, presses, (CROP_M[0], CROP_M[2]))
    images = prior.images(presses)
    np.testing.assert_array_equal(images, np.stack([resize_rgb(image, BINS, BINS) for image in drawn]))
    sensor = PhysicsPrior(PriorSpec(SCENE, CROP_M, drawn_at="sensor"), BINS).images(presses)
    assert np.abs(images.astype(int) - sensor.astype(int)).mean() < 1.0  # the same contact
    assert PriorSpec.from_dict(spec.to_dict()) == spec
    old = spec.to_dict()
    del old["drawn_rows"]
    assert PriorSpec.from_dict(old).drawn_rows == 0


@pytest.mark.parametrize("rows", [85, 2, 0.5, 123, -3, True, "84"])
def test_drawn_rows_that_do_not_make_square_pixels_of_the_field_are_refused(rows: object) -> None:
    with pytest.raises(ModelConfigError, match="drawn rows must be 0 .* or a multiple of 3 from 3 to 120"):
        PhysicsPrior(PriorSpec(SCENE, CROP_M, drawn_at="sensor", drawn_rows=rows), BINS)  # type: ignore[arg-type]


def test_drawn_rows_at_the_grid_are_refused() -> None:
    with pytest.raises(ModelConfigError, match="not the grid"):
        PhysicsPrior(PriorSpec(SCENE, CROP_M, drawn_at="grid", drawn_rows=84), BINS)
    with pytest.raises(ModelConfigError, match="needs prior_drawn_at 'sensor'"):
        GeneratorConfig(prior=True, prior_drawn_rows=84).validate()
    for rows in (-1, True, 1.5):
        with pytest.raises(ModelConfigError, match="prior_drawn_rows must be an integer"):
            GeneratorConfig(prior=True, prior_drawn_at="sensor", prior_drawn_rows=rows).validate()  # type: ignore[arg-type]


@pytest.mark.parametrize("drawn_at", ["camera", "", "GRID"])
def test_a_prior_drawn_anywhere_else_is_refused(drawn_at: str) -> None:
    with pytest.raises(ModelConfigError, match="drawn at"):
        PhysicsPrior(PriorSpec(SCENE, CROP_M, drawn_at=drawn_at), BINS)
    with pytest.raises(ModelConfigError, match="prior_drawn_at"):
        GeneratorConfig(prior=True, prior_drawn_at=drawn_at).validate()
