"""The served uncertainty (models.uncertainty) and what a checkpoint serves (models.serving)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_json_output import strict_loads

from dataset.records import DatasetError
from models.checkpoint import TrainConfig, load_generator
from models.cli import add_commands
from models.errors import ModelConfigError
from models.networks import GeneratorConfig
from models.serving import fit_serving, predict_served, prior_images, served_images
from models.train import train
from models.uncertainty import (
    UNCERTAINTY_ABSENT,
    Calibration,
    ServedUncertainty,
    UncertaintyConfig,
    UncertaintyNet,
    decile_groups,
    fit_uncertainty,
    served_uncertainty_statistics,
    uncertainty_statistics,
)
from msgs import strict_json

REPO = Path(__file__).resolve().parent.parent


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 500), seed=st.integers(0, 2**31 - 1))
def test_deciles_partition_the_values_lowest_first(n: int, seed: int) -> None:
    values = np.random.default_rng(seed).normal(size=n).round(1)  # ties too
    groups = decile_groups(values)
    assert sorted(np.concatenate(groups).tolist()) == list(range(n))
    assert max(len(g) for g in groups) - min(len(g) for g in groups) <= 1
    for low, high in zip(groups, groups[1:]):
        assert values[low].max() <= values[high].min()


@settings(max_examples=100, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    spread=st.floats(0.0, 3.0),
    scale=st.floats(0.1, 10.0),
)
def test_a_calibration_makes_each_decile_of_its_own_fit_close_to_calibrated(
    seed: int, spread: float, scale: float
) -> None:
    """Raw sigmas off by a factor that varies with sigma: after the calibration fitted on the same
    pixels, every decile's RMS(e) / mean(u) is near 1, and every u is finite and positive."""
    rng = np.random.default_rng(seed)
    raw = np.exp(rng.normal(0.0, spread, 5000)).astype(np.float32) + 0.1
    error = np.abs(rng.normal(size=5000)) * raw * scale * (1 + 0.5 * np.tanh(raw - 1))
    calibrated = Calibration.fit(raw, error).apply(raw)
    assert np.all(np.isfinite(calibrated)) and np.all(calibrated > 0)
    for group in decile_groups(calibrated):
        ratio = np.sqrt(np.mean(error[group] ** 2)) / calibrated[group].mean()
        assert 0.7 < ratio < 1.4


@settings(max_examples=200, deadline=None)
@given(
    knots=st.lists(st.floats(0.01, 100.0), min_size=1, max_size=12),
    scale=st.lists(st.floats(0.05, 20.0), min_size=12, max_size=12),
    seed=st.integers(0, 2**31 - 1),
    float64=st.booleans(),
)
def test_a_calibration_is_np_interp_to_the_bit(
    knots: list[float], scale: list[float], seed: int, float64: bool
) -> None:
    """apply is (raw * np.interp(raw, levels, scale)).astype(float32) exactly: on the knots (equal
    ones too), a float's step either side of them, between them, outside them, at 0, inf and NaN;
    so is its tensor form, on the CPU and on a GPU where there is one."""
    levels = sorted(knots)
    calibration = Calibration(tuple(levels), tuple(scale[: len(levels)]))
    rng = np.random.default_rng(seed)
    dtype = np.float64 if float64 else np.float32
    on = np.asarray(levels, dtype)
    raw = np.concatenate(
        [
            on,
            np.nextafter(on, dtype(np.inf)),
            np.nextafter(on, dtype(0)),
            rng.uniform(0.0, 120.0, 500).astype(dtype),
            np.array([0.0, np.inf, np.nan], dtype),
        ]
    ).reshape(-1, 1)
    expected = (raw * np.interp(raw, calibration.raw_levels, calibration.scale)).astype(np.float32)
    np.testing.assert_array_equal(calibration.apply(raw), expected)
    for device in ["cpu"] + (["cuda"] if torch.cuda.is_available() else []):
        on_device = calibration.apply_on_device(torch.from_numpy(raw).to(device))
        assert on_device.dtype == torch.float32 and on_device.device.type == device
        np.testing.assert_array_equal(on_device.cpu().numpy(), expected)


def test_a_constant_sigma_is_calibrated_to_the_rms_error() -> None:
    error = np.abs(np.random.default_rng(0).normal(size=1000)) * 3
    calibration = Calibration.fit(np.ones(1000, np.float32), error)
    assert calibration.raw_levels == (1.0,)
    assert calibration.apply(np.array([1.0], np.float32))[0] == pytest.approx(np.sqrt(np.mean(error**2)), rel=1e-5)


def test_the_statistics_of_an_uncertainty_that_is_the_error() -> None:
    rng = np.random.default_rng(1)
    truth = rng.integers(0, 256, (20, 16, 16, 3), dtype=np.uint8)
    noise = rng.integers(-30, 31, (20, 16, 16, 1)) * rng.integers(0, 2, (20, 16, 16, 1))
    estimate = np.clip(truth.astype(int) + noise, 0, 255).astype(np.uint8)
    error = np.abs(estimate.astype(float) - truth).mean(axis=-1)
    figures = uncertainty_statistics(error + 1e-3, estimate, truth, error.mean(axis=(1, 2)))
    assert figures["pearson_pixel"] == pytest.approx(1.0) and figures["pearson_region"] == pytest.approx(1.0)
    assert len(figures["deciles"]) == 10
    flat = uncertainty_statistics(np.ones((20, 16, 16)), estimate, truth, error.mean(axis=(1, 2)))
    assert np.isnan(flat["pearson_pixel"])  # a constant u predicts nothing: no correlation to give


def test_per_object_figures_show_one_u_given_to_objects_that_miss_by_much_and_by_little() -> None:
    """Four pairs each of a rough and a smooth object; u is 6 levels at each pair's contact (5 x 9
    of its 10 x 10 pixels: together the set's top three deciles) and 0.5 elsewhere, on both. The
    rough object misses by 8 levels there, the smooth by 1; a third object's u is low everywhere."""
    rng = np.random.default_rng(2)
    truth = rng.integers(60, 200, (12, 10, 10, 3), dtype=np.uint8)
    miss = np.zeros((12, 10, 10, 1), int)
    miss[:4, 2:7, :9] = 8
    miss[4:8, 2:7, :9] = 1
    estimate = (truth + miss).astype(np.uint8)
    u = np.full((12, 10, 10), 0.5)
    u[:8, 2:7, :9] = 6.0
    objects = ["rough"] * 4 + ["smooth"] * 4 + ["flat"] * 4
    figures = uncertainty_statistics(u, estimate, truth, np.zeros(12), objects)["objects"]
    assert list(figures) == ["flat", "rough", "smooth"]
    rough, smooth = figures["rough"], figures["smooth"]
    assert rough["high_u_mean"] == smooth["high_u_mean"] == pytest.approx(6.0)
    assert rough["high_e_rms"] == pytest.approx(8.0) and smooth["high_e_rms"] == pytest.approx(1.0)
    assert rough["high_u_share"] == smooth["high_u_share"] == pytest.approx(0.5)
    assert rough["pearson_pixel"] == pytest.approx(1.0) and rough["n"] == 4
    # The flat object's u is never high, and its error and u are the same everywhere: both said, in strict JSON.
    flat = strict_loads(strict_json.dumps(figures))["flat"]
    assert flat["high_u_share"] == 0.0 and flat["high_u_mean"] is None and flat["high_e_rms"] is None
    assert flat["pearson_pixel"] is None and "pearson_pixel_undefined" in flat and "high_u_mean_undefined" in flat
    with pytest.raises(ModelConfigError, match="11 object names for 12"):
        uncertainty_statistics(u, estimate, truth, np.zeros(12), objects[:-1])


def test_the_network_learns_where_the_error_is() -> None:
    """Pairs whose error is large where the input's first channel is high (patches of 8 x 8
    pixels, as contacts are patches): the fitted u follows it."""
    rng = np.random.default_rng(2)
    cells = torch.from_numpy(rng.choice([-1.0, 1.0], (128, 2, 3, 3)).astype(np.float32))
    x = torch.nn.functional.interpolate(cells, scale_factor=8, mode="nearest")
    estimate = torch.zeros(128, 3, 24, 24)
    scale = 0.5 + 8.0 * (x[:, 0] > 0).float()
    error = (torch.from_numpy(rng.normal(size=(128, 24, 24)).astype(np.float32)) * scale).abs()
    served = fit_uncertainty(
        x[:96],
        estimate[:96],
        error[:96],
        x[96:],
        estimate[96:],
        error[96:].numpy(),
        UncertaintyConfig(width=8, epochs=60, batch_size=16, lr=1e-2),
    )
    u = served.levels(x[96:], estimate[96:])
    # The ideal u (the scale itself) reaches r = 0.66 on these errors, half-normal at each scale.
    assert np.corrcoef(u.ravel(), error[96:].numpy().ravel())[0, 1] > 0.5
    assert np.all(u > 0)


def test_a_served_uncertainty_round_trips_and_a_damaged_one_is_refused() -> None:
    served = ServedUncertainty(UncertaintyNet(4, 4), Calibration((1.0, 2.0), (1.0, 0.5)), UncertaintyConfig(width=4))
    again = ServedUncertainty.from_state(served.to_state())
    x, estimate = torch.zeros(2, 4, 100, 100), torch.zeros(2, 3, 100, 100)
    assert np.array_equal(served.levels(x, estimate), again.levels(x, estimate))
    state = served.to_state()
    state["calibration"]["scale"] = [1.0]
    with pytest.raises(ModelConfigError, match="calibration"):
        ServedUncertainty.from_state(state)
    del state["weights"]
    with pytest.raises(ModelConfigError, match="not readable"):
        ServedUncertainty.from_state(state)


@pytest.fixture(scope="module")
def prior_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from dataset.contact_library import write_contact_library

    tmp = tmp_path_factory.mktemp("serving")
    library = write_contact_library(tmp / "library", 40, seed=3, scene=REPO / "scenes" / "ycb_three.yaml").root
    config = TrainConfig(
        epochs=1,
        epochs_decay=0,
        batch_size=8,
        ndf=8,
        threads=1,
        max_steps=1,
        generator=GeneratorConfig(ngf=8, prior=True, background=False),
    )
    return train(library, config, tmp / "run", progress=False), library


def test_a_checkpoint_trained_before_serves_its_network_and_says_its_uncertainty_is_absent(
    prior_checkpoint: tuple[Path, Path],
) -> None:
    checkpoint, library = prior_checkpoint
    generator, depth_range = load_generator(checkpoint)
    assert generator.serves == "network" and generator.uncertainty is None
    from dataset.reader import DatasetReader

    reader = DatasetReader(library)
    depth = np.stack([reader.load(r).depth_map_m for r in reader.records[:3]])
    images, uncertainty = predict_served(generator, depth, depth_range)
    assert images.shape == (3, 100, 100, 3) and uncertainty is None
    # The evaluation says so with its reason, and scores nothing as if it were certain.
    assert served_uncertainty_statistics(uncertainty, images, images, np.zeros(3)) == {"absent": UNCERTAINTY_ABSENT}


def test_fit_serving_writes_what_is_served_and_its_uncertainty(
    prior_checkpoint: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    checkpoint, library = prior_checkpoint
    fitted = tmp_path / "fitted.pt"
    fitted.write_bytes(checkpoint.read_bytes())
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["fit-serving", str(fitted), str(library), "--json"])
    assert args.func(args) == 0
    # Strict JSON alone on stdout (tests/test_json_output.py): the fit's progress goes to stderr.
    figures = strict_loads(capsys.readouterr().out)
    assert figures["serves"] in ("network", "prior")
    generator, depth_range = load_generator(fitted)
    assert generator.serves == figures["serves"] and isinstance(generator.uncertainty, ServedUncertainty)
    from dataset.reader import DatasetReader

    reader = DatasetReader(library)
    depth = np.stack([reader.load(r).depth_map_m for r in reader.records[:3]])
    images, uncertainty = predict_served(generator, depth, depth_range)
    assert uncertainty is not None and uncertainty.shape == (3, 100, 100)
    assert np.all(np.isfinite(uncertainty)) and np.all(uncertainty > 0)
    # The prior, served, is the prior's image as the generator draws it with no correction.
    from models.data import network_input, to_uint8_rgb

    x = network_input(depth, depth_range, generator.config, generator.prior)
    assert np.array_equal(to_uint8_rgb(served_images(generator, x, "prior")), to_uint8_rgb(prior_images(generator, x)))
    # Fitted again, a lab sensor's floor goes with the u it was fitted beside, and the log says so.
    state = torch.load(fitted, weights_only=True)
    state["uncertainty"]["sensor_floor"] = {"levels": torch.ones(100, 100), "source": {"file": "lab.npz"}}
    torch.save(state, fitted)
    capsys.readouterr()
    assert args.func(args) == 0
    assert "sensor floor goes with the u" in capsys.readouterr().err
    refitted, _ = load_generator(fitted)
    assert refitted.uncertainty is not None and refitted.uncertainty.floor is None
    # A checkpoint that says it serves a prior it does not have is refused on load.
    state = torch.load(fitted, weights_only=True)
    state["serves"] = "oracle"
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(ModelConfigError, match="serves 'oracle'"):
        load_generator(tmp_path / "bad.pt")


def test_fit_serving_refuses_a_dataset_it_cannot_fit_on(prior_checkpoint: tuple[Path, Path], tmp_path: Path) -> None:
    checkpoint, _ = prior_checkpoint
    before = checkpoint.read_bytes()
    with pytest.raises(DatasetError, match="does not exist"):
        fit_serving(checkpoint, tmp_path / "missing")
    assert checkpoint.read_bytes() == before  # nothing already written is lost


def test_dtx_train_ends_with_what_is_served_and_its_uncertainty(
    prior_checkpoint: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command make demo runs: its checkpoint serves the uncertainty with no further step."""
    _, library = prior_checkpoint
    config = tmp_path / "tiny.yaml"
    config.write_text(
        "epochs: 1\nepochs_decay: 0\nbatch_size: 8\nndf: 8\nthreads: 1\nmax_steps: 1\n"
        "generator: {ngf: 8, prior: true, background: false}\n"
    )
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    args = parser.parse_args(["train", str(library), "--config", str(config), "--out", str(tmp_path / "run")])
    assert args.func(args) == 0
    generator, _ = load_generator(tmp_path / "run" / "checkpoint.pt")
    assert generator.serves in ("network", "prior") and isinstance(generator.uncertainty, ServedUncertainty)
