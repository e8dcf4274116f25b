"""The accuracy-time report's depth-map rule and pose-uncertainty sweeps on a short collected
session, with the models trained and served as the report trains them (one epoch each)."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dataset.reader import DatasetReader
from dataset.redepth import model_index
from models.checkpoint import TrainConfig, load_checkpoint, load_generator
from models.evaluate import contact_ssim
from models.serving import predict
from report.plan import QUICK
from report.specs import Point
from report.sweeps.session import _cut_again, _cutters, _objects, depth_map, pose_sigma
from report.workspace import REFERENCE_SIZE, Workspace

REPO = Path(__file__).resolve().parent.parent
POSE_SIGMAS_MM = (0.0, 1.0, 2.0)  # 1.0: configs/quick.yaml's session_pose_sigma_mm, the model's own


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    """A 10-grasp simulated session (as tests/test_touch_calibration.py collects it) in a
    workspace whose models train one epoch beside an 8-pair contact library."""
    root = tmp_path_factory.mktemp("session_sweeps")
    session = root / "session"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "dtx.cli",
            "launch",
            "launch/collect_sim.yaml",
            f"out:={session}",
            "grasps:=10",
            "seed:=5",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, "DTX_DOMAIN": f"sweeps{id(root) % 100000}"},  # a bus of its own
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    plan = dataclasses.replace(QUICK, epochs=1, library_samples=8, pose_sigmas_mm=POSE_SIGMAS_MM)
    return Workspace(root / "work", plan, [session])


@pytest.fixture(scope="module")
def rules(workspace: Workspace) -> list[Point]:
    return depth_map(workspace)


@pytest.fixture(scope="module")
def sigmas(workspace: Workspace, rules: list[Point]) -> list[Point]:
    """After the rules: their surface model is the session model served here."""
    return pose_sigma(workspace)


def _test_maps(dataset: Path, workspace: Workspace) -> np.ndarray:
    reader = DatasetReader(dataset)
    return np.stack([reader.load(r.sample_id).depth_map_m for r in workspace.session_test.records])


def test_each_rule_gives_a_scored_row(rules: list[Point]) -> None:
    assert [p["setting"] for p in rules] == ["surface", "nearest_point"]
    for row in rules:
        assert 0 < row["accuracy"] <= 1 and 0 <= row["p_vs_no_contact"] <= 1
        assert row["dissimilarity_ratio"] > 0 and row["renderer_ratio"] > 0
        assert row["training_s_per_epoch"] > 0 and row["time"] > 0


def test_the_nearest_point_model_trains_on_its_rule_and_the_default_keeps_its_place(
    workspace: Workspace, rules: list[Point]
) -> None:
    nearest = load_checkpoint(workspace.session_model(REFERENCE_SIZE, "nearest_point") / "checkpoint.pt")
    assert nearest["depth_map_method"] == "nearest_point"
    assert TrainConfig.from_dict(nearest["train_config"]).depth_map == "nearest_point"
    # The default rule's model and datasets keep the names an earlier workspace gave them.
    surface = workspace.session_model()
    assert surface == workspace.root / f"train_session_{REFERENCE_SIZE}"
    assert load_checkpoint(surface / "checkpoint.pt")["depth_map_method"] == "surface"
    assert workspace.session_at(REFERENCE_SIZE) == (workspace.session,)
    assert DatasetReader(workspace.library_at(REFERENCE_SIZE)).info.depth_map_method == "surface"


def test_the_two_rules_cut_different_maps_of_the_same_contacts(workspace: Workspace, rules: list[Point]) -> None:
    (recut,) = workspace.session_at(REFERENCE_SIZE, "nearest_point")
    assert DatasetReader(recut).info.depth_map_method == "nearest_point"
    surface, nearest = _test_maps(workspace.session, workspace), _test_maps(recut, workspace)
    assert surface.shape == nearest.shape
    assert not np.array_equal(surface, nearest)
    y_far = max(surface.max(), nearest.max())
    assert (surface < y_far).any() and (nearest < y_far).any()  # both hold the objects in reach


def test_the_pose_sigma_rows_hold_the_models_default_once(sigmas: list[Point], rules: list[Point]) -> None:
    assert [p["setting"] for p in sigmas] == ["0 mm", "1 mm", "2 mm"]
    assert [p["model_default"] for p in sigmas] == [False, True, False]
    # The same model on the same maps: the surface rule's cut from the recorded poses gives back
    # the collected maps bit for bit (dataset.redepth).
    assert sigmas[1]["accuracy"] == rules[0]["accuracy"]
    for row in sigmas:
        assert 0 < row["accuracy"] <= 1 and 0 <= row["p_vs_no_contact"] <= 1 and row["contact_ssim_se"] >= 0


def test_a_sharp_prior_row_is_the_served_estimate_at_zero_scored_directly(
    workspace: Workspace, sigmas: list[Point]
) -> None:
    generator, depth_range = load_generator(workspace.session_model() / "checkpoint.pt")
    test, depth = workspace.session_test, _test_maps(workspace.session, workspace)
    sharp = predict(generator, depth, depth_range, pose_sigma_mm=0.0)
    assert sigmas[0]["accuracy"] == pytest.approx(contact_ssim(test.truth, test.deformation, sharp).mean())
    # The request's sigma reaches the served estimate: the model's default blurs its prior.
    assert not np.array_equal(sharp, predict(generator, depth, depth_range))


def test_each_session_is_cut_again_by_its_own_patch_extractors_rule(workspace: Workspace) -> None:
    """Two sessions whose patch extractors cut by different rules (the collected one and its maps
    cut again by the nearest point): the sweeps cut each test map again as its own session did,
    from its own scene's object model at its recorded pose."""
    (nearest,) = workspace.session_at(REFERENCE_SIZE, "nearest_point")
    both = Workspace(workspace.root / "both", workspace.plan, [workspace.session, nearest])
    test = both.session_test
    assert test.session_of.tolist() == [0] * (len(test.records) // 2) + [1] * (len(test.records) // 2)
    cutters = _cutters(both)
    clouds = {key: model_index(scene, key[1]) for key, scene in _objects(test, cutters).items()}
    maps, cut_ms = _cut_again(test, clouds, cutters)
    assert np.array_equal(maps, test.depth_maps(both.sessions)) and cut_ms > 0
    assert not np.array_equal(maps[test.session_of == 0], maps[test.session_of == 1])
