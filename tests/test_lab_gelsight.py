"""A lab's own GelSight through the whole system, as a lab with a GelSight Mini (240 x 320 frames
at 0.0634 mm/px) meets it: its ball presses calibrated, the scene block the command prints, a
session collected with that sensor, a model trained on the session and scored on the lab's raw
presses (the finder's centres). The presses are rendered here with known truth."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_json_output import strict_loads
from test_sim_gelsight_fit import _calibrate, synthetic_presses, write_press_file

from models.checkpoint import TrainConfig, load_generator
from models.networks import GeneratorConfig
from models.real_presses import evaluate_real_presses
from models.train import train
from sim.gelsight import scene_renderer
from sim.gelsight_check import run_check
from workcell.scene import load_scene

REPO = Path(__file__).resolve().parent.parent
MINI_MM_PER_PX = 0.0634
SHIPPED_SENSOR = "gelsight:\n  image_height: 120\n  image_width: 160\n  mm_per_px: 0.1245\n"


@dataclasses.dataclass(frozen=True)
class Lab:
    root: Path
    presses: Path  # the lab's raw presses: background, frames, mm_per_px, ball_radius_mm
    calibration: Path
    block: str  # the scene block `dtx calibrate gelsight` printed
    scene: Path  # ycb_three with that block


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    """The lab's raw presses, its calibration directory (the fit cut to its first simplex), the
    command's printed scene block and a scene file that carries it."""
    root = tmp_path_factory.mktemp("lab")
    frames, background, _ = synthetic_presses(24, seed=3, margin_px=50.0, shape=(240, 320), mm_per_px=MINI_MM_PER_PX)
    presses = write_press_file(root / "presses.npz", frames, background, mm_per_px=MINI_MM_PER_PX)
    calibration = root / "gelsight_cal"
    printed = io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setattr("sim.gelsight_fit.FIT_EVALUATIONS", 1)
        assert _calibrate(presses, calibration, "--folds", "2") == 0
    block = printed.getvalue().strip().splitlines()[-1].split("gelsight: ", 1)[1]
    scene = root / "scene.yaml"
    lines = "".join(f"  {item.strip()}\n" for item in block.strip("{}").split(","))
    scene.write_text((REPO / "scenes" / "ycb_three.yaml").read_text().replace(SHIPPED_SENSOR, "gelsight:\n" + lines))
    return Lab(root, presses, calibration, block, scene)


def test_the_calibration_of_another_frame_size_and_the_scene_it_prints(lab: Lab) -> None:
    assert lab.block == (
        f"{{image_height: 240, image_width: 320, mm_per_px: 0.0634, calibration_dir: {lab.calibration}}}"
    )
    report = strict_loads((lab.calibration / "report.json").read_text())
    assert report["frame_shape"] == [240, 320] and report["used"] == list(range(24))
    k_fold = report["k_fold"]
    # The shipped tables rendered against this sensor's own background are a reference too.
    assert k_fold["crop"] > k_fold["background_crop"] and k_fold["shipped_crop"] > k_fold["background_crop"]
    check = run_check(lab.calibration / "ball_presses.npz", calibration_dir=lab.calibration)
    assert check["mean"]["crop"] > 0.9 and check["mean"]["crop"] > check["mean"]["background_crop"]
    scene = load_scene(lab.scene)
    assert scene_renderer(scene, effects=False).render(np.full((240, 320), np.inf, np.float32)).shape == (240, 320, 3)
    assert scene_renderer(scene, size=(100, 100), effects=False).pixel_pitch_mm == pytest.approx(
        (0.0634 * 240 / 100, 0.0634 * 320 / 100)
    )


def test_a_session_with_the_labs_sensor_trains_a_model_scored_on_its_raw_presses(lab: Lab) -> None:
    session = lab.root / "session"
    command = ["launch", "launch/collect_sim.yaml", f"scene:={lab.scene}", f"out:={session}", "grasps:=4"]
    result = subprocess.run(
        [sys.executable, "-m", "dtx.cli", *command],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "DTX_DOMAIN": f"labgel{os.getpid()}"},
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    config = TrainConfig(
        epochs=1, epochs_decay=0, batch_size=4, ndf=8, threads=1, generator=GeneratorConfig(ngf=8, prior=True)
    )
    checkpoint = train(session, config, lab.root / "train", progress=False)
    generator, depth_range_m = load_generator(checkpoint)
    assert generator.prior.spec.scene == str(lab.scene)
    with np.load(lab.presses) as data:  # the lab's raw file: no annotations
        assert "touch_center" not in data.files
    real, images = evaluate_real_presses(generator, depth_range_m, lab.presses, lab.scene)
    assert real["annotations"] == "finder" and real["n"] == 24 and real["mm_per_px"] == MINI_MM_PER_PX
    assert images["truth"].shape[1:] == (100, 100, 3)
    # The prior draws this sensor: even an untrained correction is near the renderer, far from its background.
    ssim = real["window_ssim"]
    assert ssim["renderer_depth_map"] > ssim["background"] + 0.3 and ssim["model"] > ssim["background"]
