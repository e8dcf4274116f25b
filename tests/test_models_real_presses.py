"""Real-frame evaluation (``dtx evaluate --real-presses``): the press seen as the system sees a
contact, every estimate scored the same way, and a bad presses file refused clearly."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch

from dataset.contact_library import write_contact_library
from models.checkpoint import TrainConfig, load_generator
from models.cli import add_commands
from models.networks import GeneratorConfig, UNetGenerator
from models.prior import PhysicsPrior, PriorSpec
from models.real_presses import (
    ESTIMATES,
    evaluate_real_presses,
    press_depth_map,
    press_geometry,
    write_real_press_figure,
)
from models.serving import predict
from models.train import train
from perception.depthmap import DepthMapParams, crop_bounds
from sim.gelsight import scene_renderer
from sim.gelsight_check import ball_gap_map, load_ball_presses
from workcell.scene import load_scene

REPO = Path(__file__).resolve().parent.parent
PRESSES = REPO / "assets" / "gelsight" / "ball_presses.npz"
SCENE = REPO / "scenes" / "ycb_three.yaml"
DEPTH_RANGE_M = (-0.005, 0.01)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small generator trained on spheres of a contact library: enough to draw a press where
    its depth-map puts it."""
    root = tmp_path_factory.mktemp("real")
    write_contact_library(root / "library", 96, seed=3, scene=SCENE, depth_range_m=DEPTH_RANGE_M)
    config = TrainConfig(
        epochs=8,
        epochs_decay=4,
        batch_size=8,
        ndf=8,
        threads=1,
        lambda_l1=1000.0,
        contact_weight=4.0,
        generator=GeneratorConfig(ngf=8, background=True, dropout=0.0),
    )
    return train(root / "library", config, root / "train", progress=False)


def _offset_from_centre(image_change: np.ndarray) -> np.ndarray:
    """(row, column) of the change-weighted centroid, relative to the image centre."""
    weights = image_change / image_change.sum()
    rows, cols = np.indices(image_change.shape)
    centre = (np.array(image_change.shape) - 1) / 2
    return np.array([(weights * rows).sum(), (weights * cols).sum()]) - centre


def test_an_off_centre_press_lands_on_the_same_side_in_depth_map_render_and_prediction(checkpoint: Path) -> None:
    presses = load_ball_presses(PRESSES)
    scene = load_scene(SCENE)
    generator, depth_range_m = load_generator(checkpoint)
    # The press farthest from the frame's centre, in both axes.
    offsets = presses.centers_xy_px - (np.array(presses.background.shape[1::-1]) - 1) / 2
    index = int(np.argmax(np.abs(offsets).min(axis=1)))
    expected = np.sign(offsets[index][::-1])  # (row, column) side
    press = press_geometry(presses, index, 0.1245, 2.0, (100, 100))
    params = DepthMapParams(shape=(100, 100), margin_m=0.002, y_range_m=depth_range_m)
    depth_map = press_depth_map(press, 2.0, scene.gripper_geometry(), params)
    pressed = np.clip(-depth_map, 0, None)
    assert np.array_equal(np.sign(_offset_from_centre(pressed)), expected)

    renderer = scene_renderer(scene, effects=False)
    image = renderer.render(ball_gap_map(renderer.config.shape, presses.centers_xy_px[index], press.depth_mm, 0.1245))
    change = np.abs(image.astype(float) - renderer.background().astype(float)).sum(axis=2)
    assert np.array_equal(np.sign(_offset_from_centre(change)), expected)

    estimate, empty = predict(
        generator, np.stack([depth_map, np.full_like(depth_map, depth_range_m[1])]), depth_range_m
    )
    predicted_change = np.abs(estimate.astype(float) - empty.astype(float)).sum(axis=2)
    assert np.array_equal(np.sign(_offset_from_centre(predicted_change)), expected)


def test_every_estimate_is_scored_on_window_and_full_image(checkpoint: Path, tmp_path: Path) -> None:
    generator, depth_range_m = load_generator(checkpoint)
    result, images = evaluate_real_presses(generator, depth_range_m, PRESSES, SCENE)
    assert write_real_press_figure(result, images, tmp_path).stat().st_size > 0
    assert result["n"] == 30
    for key in ("window_ssim", "full_ssim", "window_psnr_db", "full_psnr_db"):
        assert set(result[key]) == set(ESTIMATES)
    # The renderer fed the true contact is the strong reference; the background sees no press.
    assert result["window_ssim"]["renderer"] > 0.85 > result["window_ssim"]["background"]
    assert result["window_ssim"]["renderer"] > result["window_ssim"]["random"]
    assert result["location_error_mm_median_of"]["renderer"] < 0.5
    assert images["truth"].shape == images["model"].shape == images["renderer_depth_map"].shape == (30, 100, 100, 3)


def test_a_correction_that_adds_nothing_scores_as_the_renderer_fed_the_same_depth_map(tmp_path: Path) -> None:
    """The model is judged against the physics it starts from: its prior fed the press's
    depth-map. A generator whose correction is zero draws that prior, so the two rows agree;
    and the depth-map itself (0.24 x 0.19 mm bins, each its nearest point) costs the renderer
    against the exact contact, before any learning (docs/measurements.md, issue 30 part 3)."""
    scene = load_scene(SCENE)
    half_x, half_z, y_near, y_far = crop_bounds(
        scene.gripper_geometry(), DepthMapParams(shape=(100, 100), margin_m=0.002, y_range_m=DEPTH_RANGE_M)
    )
    generator = UNetGenerator(GeneratorConfig(ngf=4, dropout=0.0, prior=True))
    last = generator.output[1]
    assert isinstance(last, torch.nn.ConvTranspose2d) and last.bias is not None
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    generator.prior = PhysicsPrior(PriorSpec(str(SCENE), (2 * half_x, y_far - y_near, 2 * half_z)), 100)
    with np.load(PRESSES) as data:  # eight presses, of both depths the file holds
        np.savez(
            tmp_path / "eight.npz",
            background=data["background"],
            **{key: data[key][:8] for key in ("frames", "touch_center", "touch_radius")},
        )
    result, images = evaluate_real_presses(generator, DEPTH_RANGE_M, tmp_path / "eight.npz", scene)
    assert np.abs(images["model"].astype(int) - images["renderer_depth_map"].astype(int)).max() <= 1
    assert np.array_equal(images["renderer_depth_map"], generator.prior.images(images["depth_maps_m"], 0.0))
    window = result["window_ssim"]
    assert window["model"] == pytest.approx(window["renderer_depth_map"], abs=2e-3)
    assert window["renderer_depth_map"] < window["renderer"]


def _bad_file(tmp_path: Path, **changes: object) -> Path:
    with np.load(PRESSES) as data:
        contents = {key: data[key] for key in data.files}
    for key, value in changes.items():
        if value is None:
            contents.pop(key)
        else:
            contents[key] = value
    path = tmp_path / "bad.npz"
    np.savez(path, **contents)
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"touch_radius": None}, "touch_center without its pair"),
        ({"frames": np.zeros((30, 120, 159, 3), np.uint8)}, "frames must be"),
        ({"frames": np.zeros((30, 120, 160, 3), np.float32)}, "frames must be"),
        ({"touch_center": np.full((30, 2), np.nan)}, "finite"),
        ({"touch_center": np.full((30, 2), 500.0)}, "outside"),
        ({"touch_radius": np.zeros(30, np.int64)}, "> 0"),
    ],
)
def test_a_bad_presses_file_gets_a_clear_error_and_exit_2(
    checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture, changes: dict, message: str
) -> None:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["evaluate", str(checkpoint), "--real-presses", str(_bad_file(tmp_path, **changes))])
    assert args.func(args) == 2
    assert message in capsys.readouterr().err


def test_a_files_own_ball_and_scale_are_used_unless_given(checkpoint: Path, tmp_path: Path) -> None:
    """A press file that says its ball and scale (``dtx calibrate gelsight``'s copies do) is read
    with them; the options override them."""
    generator, depth_range_m = load_generator(checkpoint)
    path = _bad_file(tmp_path, ball_radius_mm=np.float64(2.5), mm_per_px=np.float64(0.1245))
    own, _ = evaluate_real_presses(generator, depth_range_m, path, SCENE)
    given, _ = evaluate_real_presses(generator, depth_range_m, path, SCENE, ball_radius_mm=2.0)
    shipped, _ = evaluate_real_presses(generator, depth_range_m, PRESSES, SCENE)
    assert (own["ball_radius_mm"], given["ball_radius_mm"], shipped["ball_radius_mm"]) == (2.5, 2.0, 2.0)
    assert given["window_ssim"] == shipped["window_ssim"] and own["window_ssim"] != shipped["window_ssim"]


def test_a_labs_raw_presses_are_evaluated_at_the_finders_centres(checkpoint: Path, tmp_path: Path) -> None:
    generator, depth_range_m = load_generator(checkpoint)
    with np.load(PRESSES) as data:
        np.savez(tmp_path / "raw.npz", background=data["background"], frames=data["frames"][:8])
    result, images = evaluate_real_presses(generator, depth_range_m, tmp_path / "raw.npz", SCENE)
    assert result["annotations"] == "finder" and result["left_out"] == {} and result["n"] == 8
    assert [press["index"] for press in result["per_press"]] == list(range(8)) and len(images["model"]) == 8


def test_bad_options_and_a_missing_file_get_exit_2(checkpoint: Path, tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    for extra in (["--ball-radius-mm", "0"], ["--mm-per-px", "nan"], ["--scene", str(tmp_path / "none.yaml")]):
        args = parser.parse_args(["evaluate", str(checkpoint), "--real-presses", str(PRESSES), *extra])
        assert args.func(args) == 2
    args = parser.parse_args(["evaluate", str(checkpoint), "--real-presses", str(tmp_path / "none.npz")])
    assert args.func(args) == 2
    args = parser.parse_args(["evaluate", str(checkpoint)])
    assert args.func(args) == 2
