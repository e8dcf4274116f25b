"""Evaluation: SSIM statistics, baseline, template matching, figures and the CLI."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dataset.synth import write_synthetic_dataset
from models.checkpoint import TrainConfig
from models.cli import add_commands
from models.evaluate import CONTACT_LEVELS, contact_ssim_statistics, ssim_statistics
from models.networks import GeneratorConfig, ModelConfigError
from models.template_match import most_deformed_box, template_match
from models.train import train

sys.path.insert(0, str(Path(__file__).parent))
from test_dataset_format import ShadingRenderer
from test_json_output import strict_loads


def blob_images(n: int, seed: int) -> np.ndarray:
    """n distinct smooth RGB images: a bright Gaussian blob at a random place."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:64, 0:64]
    images = []
    for _ in range(n):
        cy, cx = rng.uniform(12, 52, size=2)
        blob = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * rng.uniform(3, 8) ** 2))
        images.append(np.stack([60 + 180 * blob, 90 + 120 * blob, 120 - 80 * blob], axis=-1))
    return np.round(images).astype(np.uint8)


def test_good_estimates_beat_the_random_baseline_significantly() -> None:
    truth = blob_images(40, seed=0)
    noise = np.random.default_rng(1).integers(-6, 7, truth.shape)
    estimate = np.clip(truth.astype(int) + noise, 0, 255).astype(np.uint8)
    result = ssim_statistics(truth, estimate, baseline_draws=15, seed=0)
    assert result["ssim_model_mean"] > result["ssim_baseline_mean"] + 0.05
    assert result["p_value_wilcoxon"] < 1e-6 and result["p_value_t"] < 1e-6
    assert result["dissimilarity_ratio"] == pytest.approx(
        (1 - result["ssim_model_mean"]) / (1 - result["ssim_baseline_mean"])
    )
    assert result["ssim_model_se"] > 0 and len(result["ssim_baseline"]) == 40


def test_estimates_unrelated_to_their_truth_are_not_better_than_baseline() -> None:
    truth = blob_images(40, seed=0)
    shuffled = truth[np.roll(np.arange(40), 7)]
    result = ssim_statistics(truth, shuffled, seed=0)
    assert result["dissimilarity_ratio"] > 0.8 and result["p_value_t"] > 1e-3


@settings(max_examples=20, deadline=None)
@given(dy=st.integers(-6, 6), dx=st.integers(-6, 6), seed=st.integers(0, 1000))
def test_template_is_the_most_deformed_region_and_is_found_where_it_moved(dy: int, dx: int, seed: int) -> None:
    truth = blob_images(1, seed)
    background = np.array([60, 90, 120])
    deformation = np.abs(truth[0].astype(float) - background).sum(axis=2)
    x, y = most_deformed_box(deformation, 16)
    peak_y, peak_x = np.unravel_index(np.argmax(deformation), deformation.shape)
    assert x <= peak_x < x + 16 and y <= peak_y < y + 16
    moved = np.roll(truth, (dy, dx), axis=(1, 2))
    match = template_match(truth, deformation[None], moved, size_px=16)[0]
    inside = 0 <= x + dx <= 64 - 16 and 0 <= y + dy <= 64 - 16
    if inside:
        assert match["score"] > 0.99 and match["distance_px"] == pytest.approx(np.hypot(dx, dy))


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ModelConfigError, match="at least 2"):
        ssim_statistics(blob_images(1, 0), blob_images(1, 0))
    with pytest.raises(ModelConfigError, match="does not fit"):
        most_deformed_box(np.zeros((10, 10)), 32)


def test_evaluate_cli_writes_json_and_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dataset = tmp_path / "ds"
    write_synthetic_dataset(dataset, 32, seed=2, renderer=ShadingRenderer(), pixel_pitch_mm=(0.15, 0.2))
    config = TrainConfig(
        epochs=1, epochs_decay=0, batch_size=8, ndf=8, threads=1, max_steps=2, generator=GeneratorConfig(ngf=8)
    )
    checkpoint = train(dataset, config, tmp_path / "run", progress=False)
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(
        [
            "evaluate",
            str(checkpoint),
            str(dataset),
            "--json",
            "--figures",
            str(tmp_path / "fig"),
        ]
    )
    assert args.func(args) == 0
    result = strict_loads(capsys.readouterr().out)  # strict JSON only
    for key in (
        "ssim_model_mean",
        "ssim_model_se",
        "ssim_baseline_mean",
        "ssim_baseline_se",
        "p_value_wilcoxon",
        "p_value_t",
        "dissimilarity_ratio",
    ):
        assert np.isfinite(result[key])
    assert set(result["template_match"]) >= {"score_mean", "distance_px_median"}
    assert result["contact"]["contact_levels"] == CONTACT_LEVELS
    assert sum(stats["n"] for stats in result["objects"].values()) <= result["n"]
    assert all(np.isfinite(stats["dissimilarity_ratio"]) for stats in result["objects"].values())
    assert result["density"] == []
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == ["qualitative.png", "ssim_bars.png"]
    args = parser.parse_args(["evaluate", str(tmp_path / "missing.pt"), str(dataset)])
    assert args.func(args) == 1 and "does not exist" in capsys.readouterr().err
    # A density table needs depth-maps made again from the models, which a synthetic dataset lacks.
    args = parser.parse_args(["evaluate", str(checkpoint), str(dataset), "--density", "20"])
    assert args.func(args) == 1 and "records no depth-map crop" in capsys.readouterr().err
    args = parser.parse_args(["evaluate", str(checkpoint), str(dataset), "--density", "0"])
    assert args.func(args) == 1 and "--density" in capsys.readouterr().err


def test_contact_ssim_does_not_reward_drawing_no_contact() -> None:
    """On images that are mostly a shared background, the no-contact image scores well on the
    whole-image SSIM; over the contact windows it loses to the true contacts."""
    background = np.full((64, 64, 3), 120, np.uint8)
    contacts = blob_images(8, 9)
    truth = np.where(contacts.astype(int).sum(axis=-1, keepdims=True) > 400, contacts, background).astype(np.uint8)
    deformation = np.abs(truth.astype(np.float32) - background).sum(axis=-1)
    no_contact = np.repeat(background[None], len(truth), axis=0)
    whole = ssim_statistics(truth, no_contact)
    assert whole["ssim_model_mean"] > 0.5
    perfect = contact_ssim_statistics(truth, deformation, truth)
    assert perfect["ssim_model_mean"] == pytest.approx(1.0) and perfect["n"] == 8
    assert contact_ssim_statistics(truth, deformation, no_contact)["ssim_model_mean"] < whole["ssim_model_mean"]
    assert contact_ssim_statistics(truth, np.zeros_like(deformation), truth) == {
        "n": 0,
        "contact_levels": CONTACT_LEVELS,
    }


def test_the_demo_table_sets_the_paper_beside_each_figure_and_gives_each_object() -> None:
    from dtx.demo import paper_table

    stats = {
        "n": 10,
        "ssim_model_mean": 0.95,
        "ssim_model_se": 0.01,
        "ssim_baseline_mean": 0.9,
        "ssim_baseline_se": 0.01,
        "p_value_wilcoxon": 1e-3,
        "dissimilarity_ratio": 0.5,
    }
    evaluation = {
        **stats,
        "p_value_t": 1e-3,
        "template_match": {"score_mean": 0.9, "distance_px_median": 2.0},
        "objects": {"mustard_bottle": stats},
        "density": [{"points_per_cm3": 20.0, "ssim_mean": 0.94, "ssim_se": 0.01}],
    }
    table = paper_table(evaluation)
    assert "mustard_bottle (10 pairs)" in table and "0.950 / 0.900, 0.50" in table
    assert "0.84 ± 0.0056" in table and "0.8478" in table
