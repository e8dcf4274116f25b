"""dtx calibrate gelsight: the press finder, the photometric fit and bad input, on press files
rendered here by the renderer with known truth (and the shipped file where it is cheap)."""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_json_output import strict_loads

from dtx.calibrate import add_commands
from sim.gelsight import GelSightConfig, GelSightRenderer, GelSightRenderError, scene_renderer
from sim.gelsight_calibrate import calibrate_presses
from sim.gelsight_calibration import renderer_parameters
from sim.gelsight_check import ball_gap_map, press_depth_mm, run_check
from sim.gelsight_fit import Presses, fit_background, fit_with_parameters, press_scores, render_fit
from sim.press_annotation import change_extent_px, check_background, find_presses, ring_edge_px

MM_PER_PX = 0.1245
BALL_MM = 2.0
TRUTH_PARAMETERS: dict[str, Any] = {
    "spreading_length_mm": 0.8,
    "optical_blur_mm": 0.25,
    "compression_saturation_mm": 1.2,
    "background_smoothing_mm": 0.3,
}


def synthetic_presses(
    n: int,
    seed: int = 0,
    contact_mm: float = 1.9,
    margin_px: float = 30.0,
    shape: tuple[int, int] = (120, 160),
    mm_per_px: float = MM_PER_PX,
):
    """Frames of ``n`` presses of the 4 mm ball rendered by the shipped renderer (with camera
    noise) at random centres, the background, and the true centres; frames of ``shape`` at ``mm_per_px``."""
    rng = np.random.default_rng(seed)
    h, w = shape
    config = GelSightConfig(image_height=h, image_width=w, mm_per_px=mm_per_px, **TRUTH_PARAMETERS, shading_gain=1.0)
    renderer = GelSightRenderer(config)
    centers = np.column_stack([rng.uniform(margin_px, w - margin_px, n), rng.uniform(margin_px, h - margin_px, n)])
    depth = press_depth_mm(contact_mm, BALL_MM)
    frames = []
    for center in centers:
        clean = renderer.render(ball_gap_map((h, w), center, depth, mm_per_px, BALL_MM)).astype(np.float32)
        frames.append(np.clip(np.rint(clean + rng.normal(0.0, 1.5, clean.shape)), 0, 255).astype(np.uint8))
    background = np.clip(np.rint(renderer.background() + rng.normal(0.0, 1.5, (h, w, 3))), 0, 255).astype(np.uint8)
    return np.stack(frames), background, centers


def write_press_file(path, frames, background, mm_per_px=MM_PER_PX, **extra):
    np.savez(path, frames=frames, background=background, mm_per_px=mm_per_px, ball_radius_mm=BALL_MM, **extra)
    return path


@pytest.fixture(scope="module")
def synthetic():
    return synthetic_presses(24)


def test_finder_recovers_the_true_centres_of_rendered_presses(synthetic):
    frames, background, centers = synthetic
    found = find_presses(frames, background, BALL_MM / MM_PER_PX)
    assert found.trusted.all(), found.reasons
    error_px = np.hypot(*(found.centers_xy_px - centers).T)
    # The shading differs across the gel, so a press matches the mean press to about half a pixel.
    assert np.median(error_px) < 0.5 and np.max(error_px) < 1.5, error_px
    # One depth for all: the rings are one size, near the contact's edge.
    assert np.ptp(found.radii_px) < 1.5 and np.all(np.abs(found.radii_px - 1.9 / MM_PER_PX) < 1.5)


def test_fit_of_rendered_presses_renders_presses_it_never_saw():
    frames, background, centers = synthetic_presses(20, seed=2)
    radii = np.full(len(frames), 1.9 / MM_PER_PX)
    presses = Presses(frames, background, centers, radii, MM_PER_PX, BALL_MM)
    fit = fit_with_parameters(presses.subset(range(0, 20, 2)), TRUTH_PARAMETERS)
    unseen = presses.subset(range(1, 20, 2))
    scores = press_scores(render_fit(fit, unseen), unseen)
    # The renderer that made them scores 0.98 / 0.97 (the camera noise); ten presses leave some
    # slope bins to their neighbours.
    assert np.mean(scores["crop"]) > 0.93 and np.mean(scores["full"]) > 0.95, scores


def test_calibrate_command_writes_a_directory_scenes_and_the_check_read(tmp_path, synthetic, monkeypatch, capsys):
    frames, background, _ = synthetic
    path = write_press_file(tmp_path / "presses.npz", frames, background)
    monkeypatch.setattr("sim.gelsight_fit.FIT_EVALUATIONS", 1)  # the search's first simplex only
    out = tmp_path / "calibration"
    assert _calibrate(path, out, "--folds", "2", "--json") == 0
    report = strict_loads((out / "report.json").read_text())
    printed = capsys.readouterr()
    assert strict_loads(printed.out) == report  # --json: strict, the file's
    assert "calibrate gelsight: 4/4 fits (100 %)" in printed.err  # 2 folds, the half, all: progress on stderr
    assert report["used"] == list(range(24)) and report["left_out"] == {}
    assert report["k_fold"]["crop"] > report["k_fold"]["background_crop"]
    parameters = renderer_parameters(out)
    assert parameters["calibration_mm_per_px"] == MM_PER_PX and parameters["shading_gain"] == 1.0
    check = run_check(out / "ball_presses.npz", calibration_dir=out)
    assert check["mean"]["crop"] > 0.9 and check["calibration"] == str(out)
    scene_file = tmp_path / "scene.yaml"
    scene_file.write_text(_scene_with_calibration(out))
    from workcell.scene import load_scene

    config = scene_renderer(load_scene(scene_file), effects=False).config
    assert config.calibration_dir == str(out)
    assert config.spreading_length_mm == parameters["spreading_length_mm"]


def _scene_with_calibration(directory) -> str:
    text = open("scenes/ideal.yaml").read()
    return text.replace("gelsight:\n", f"gelsight:\n  calibration_dir: {directory}\n", 1)


def _calibrate(path, out, *options: str) -> int:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["calibrate", "gelsight", str(path), "--out", str(out), *options])
    return args.func(args)


def _refused(tmp_path, capsys, monkeypatch, frames, background, *options: str, **extra) -> str:
    """The command's error for a press file; an existing calibration directory stays as it was.
    (Its fit is cut to one rendering: were the file accepted, the test fails quickly.)"""
    monkeypatch.setattr("sim.gelsight_fit.FIT_EVALUATIONS", 1)
    path = write_press_file(tmp_path / "bad.npz", frames, background, **extra)
    out = tmp_path / "existing"
    out.mkdir(exist_ok=True)
    (out / "kept.txt").write_text("an earlier calibration")
    assert _calibrate(path, out, "--force", *options) == 1
    assert [p.name for p in out.iterdir()] == ["kept.txt"] and (
        out / "kept.txt"
    ).read_text() == "an earlier calibration"
    return capsys.readouterr().err


def test_too_few_presses_are_refused(tmp_path, capsys, monkeypatch, synthetic):
    frames, background, _ = synthetic
    assert "too few presses" in _refused(tmp_path, capsys, monkeypatch, frames[:12], background)


def test_saturating_presses_are_left_out_and_named(tmp_path, capsys, monkeypatch, synthetic):
    frames, background, _ = synthetic
    saturated = frames.copy()
    ring = np.abs(frames[:6].astype(int) - background).sum(axis=3) > 30
    saturated[:6][ring] = 255
    error = _refused(tmp_path, capsys, monkeypatch, saturated, background)
    assert "too few presses" in error and all(f"press {i}: saturated" in error for i in range(6)), error


def test_presses_leaving_the_frame_are_left_out_and_named(tmp_path, capsys, monkeypatch):
    frames, background, _ = synthetic_presses(24, seed=1, margin_px=2.0)
    found = find_presses(frames, background, BALL_MM / MM_PER_PX)
    out_of_frame = [i for i, reason in enumerate(found.reasons) if reason == "the ring leaves the frame"]
    assert out_of_frame, found.reasons
    error = _refused(tmp_path, capsys, monkeypatch, frames, background)
    assert all(f"press {i}: the ring leaves the frame" in error for i in out_of_frame), error


def test_a_background_of_another_sensor_is_refused(tmp_path, capsys, monkeypatch, synthetic):
    frames, background, _ = synthetic
    error = _refused(tmp_path, capsys, monkeypatch, frames, 255 - background)
    assert "background does not match the frames" in error and "presses [0, 1, 2" in error


@pytest.mark.parametrize(("option", "value"), [("--ball-radius-mm", "6"), ("--mm-per-px", "0.05")])
def test_a_ball_or_scale_that_cannot_explain_the_rings_is_refused(
    tmp_path, capsys, monkeypatch, synthetic, option, value
):
    frames, background, _ = synthetic
    error = _refused(tmp_path, capsys, monkeypatch, frames, background, option, value)
    assert "cannot explain the rings of presses [0, 1, 2" in error, error


@pytest.mark.parametrize(("option", "value"), [("--ball-radius-mm", "0.8"), ("--mm-per-px", "0.3")])
def test_a_ball_too_small_for_how_far_the_presses_reach_is_refused(
    tmp_path, capsys, monkeypatch, synthetic, option, value
):
    frames, background, _ = synthetic
    error = _refused(tmp_path, capsys, monkeypatch, frames, background, option, value)
    assert "the presses change the frame out to" in error and "the ball radius is too small" in error, error


@settings(max_examples=40, deadline=None)
@given(
    st.floats(4.0, 40.0),
    st.floats(0.0, 1.0),
    st.floats(0.0, 1.0),
    st.floats(20.0, 300.0),
    st.floats(0.0, 20.0),
    st.booleans(),
)
def test_change_extent_is_the_radius_of_a_press_whatever_its_place_and_levels(
    radius_px, x_share, y_share, height, floor, ring_only
):
    """A disc (or a ring with a flat inside, as a ball's press) of ``radius_px`` anywhere in the
    frame, on any floor: the reach is its radius to a pixel, clipped where the frame ends."""
    h, w = 120, 160
    rows, cols = np.mgrid[0:h, 0:w]
    center = (radius_px + x_share * (w - 2 * radius_px), radius_px + y_share * (h - 2 * radius_px))
    distance = np.hypot(cols - center[0], rows - center[1])
    press = distance <= radius_px
    if ring_only:
        press &= distance >= 0.6 * radius_px
    magnitude = np.where(press, floor + height, floor).astype(np.float32)
    assert abs(change_extent_px(magnitude) - radius_px) <= 1.0


def test_a_file_without_scale_and_an_existing_directory_without_force_are_refused(tmp_path, capsys, synthetic):
    frames, background, _ = synthetic
    np.savez(tmp_path / "no_scale.npz", frames=frames, background=background)
    with pytest.raises(GelSightRenderError, match="no mm_per_px"):
        calibrate_presses(tmp_path / "no_scale.npz")
    out = tmp_path / "existing"
    out.mkdir()
    assert _calibrate(write_press_file(tmp_path / "p.npz", frames, background), out) == 1
    assert "exists; give --force" in capsys.readouterr().err and not any(out.iterdir())


def test_shipped_presses_background_matches_and_finder_trusts_them():
    data = np.load("assets/gelsight/ball_presses.npz")
    check_background(data["frames"], data["background"])
    found = find_presses(data["frames"][:8], data["background"], BALL_MM / MM_PER_PX)
    assert found.trusted.all(), found.reasons
    assert np.all(np.abs(found.radii_px - data["touch_radius"][:8]) <= 2.0)


@settings(max_examples=40, deadline=None)
@given(st.floats(4.0, 30.0), st.floats(1.0, 6.0), st.floats(5.0, 100.0), st.floats(0.0, 20.0))
def test_ring_edge_is_where_the_profile_has_fallen_its_fraction(peak_px, width_px, height, far):
    from sim.press_annotation import RING_EDGE_FRACTION

    radii = np.arange(0.125, 4 * peak_px + 20, 0.25)
    # Rises to the peak, then falls as a Gaussian of width_px to the far level.
    profile = far + height * np.exp(-0.5 * (np.maximum(radii - peak_px, 0.0) / width_px) ** 2) * np.minimum(
        radii / peak_px, 1.0
    )
    edge = ring_edge_px(radii, profile, 2 * peak_px)
    expected = peak_px + width_px * math.sqrt(-2.0 * math.log(1.0 - RING_EDGE_FRACTION))
    assert abs(edge - expected) < 0.05


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 6))
def test_fitted_background_is_the_frames_mean_away_from_the_presses(seed, n):
    rng = np.random.default_rng(seed)
    background = rng.integers(0, 256, (40, 50, 3)).astype(np.uint8)
    centers = rng.uniform(0, 50, (n, 2))
    frames = np.repeat(background[None], n, axis=0)
    rows, cols = np.mgrid[0:40, 0:50]
    for frame, (x, y) in zip(frames, centers):
        frame[np.hypot(cols - x, rows - y) < 5.0] = 255 - frame[np.hypot(cols - x, rows - y) < 5.0]
    fitted = fit_background(frames, background, centers, ball_radius_px=2.0)
    assert np.allclose(fitted, background, atol=1e-3)
