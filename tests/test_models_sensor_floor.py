"""A lab's own GelSight in the served uncertainty (models.sensor_floor, ``dtx calibrate
uncertainty``): the floor's arithmetic, the held-out figures equal to what the served path gives,
and bad input refused with nothing written."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from test_json_output import strict_loads

from benchmarks.serve import write_checkpoint
from dtx.calibrate import add_commands as add_calibrate_commands
from models.checkpoint import load_generator
from models.cli import add_commands as add_model_commands
from models.errors import ModelConfigError
from models.real_presses import evaluate_real_presses
from models.sensor_floor import MIN_PRESSES, fit_sensor_floor, leave_one_out_uncertainty
from models.serving import predict_served
from models.uncertainty import Calibration, SensorFloor, ServedUncertainty, UncertaintyConfig, UncertaintyNet

REPO = Path(__file__).resolve().parent.parent
PRESSES = REPO / "assets" / "gelsight" / "ball_presses.npz"
SCENE = REPO / "scenes" / "ycb_three.yaml"

levels = st.floats(0.0, 300.0, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(
    error=hnp.arrays(np.float32, st.tuples(st.integers(2, 6), st.integers(1, 4), st.integers(1, 4)), elements=levels),
    data=st.data(),
)
def test_the_floor_makes_each_pixel_calibrated_in_quadrature_and_is_never_negative(
    error: np.ndarray, data: st.DataObject
) -> None:
    own = data.draw(hnp.arrays(np.float32, error.shape, elements=levels))
    floor = fit_sensor_floor(error, own)
    assert floor.shape == error.shape[1:] and floor.dtype == np.float32 and np.all(floor >= 0)
    excess = np.mean(error.astype(np.float64) ** 2, axis=0) - np.mean(own.astype(np.float64) ** 2, axis=0)
    served = SensorFloor(floor, {}).added(own).astype(np.float64)
    # Where the error exceeds what u says, the served u's mean square is the error's there.
    rises = excess > 0
    np.testing.assert_allclose(
        np.mean(served**2, axis=0)[rises], np.mean(error.astype(np.float64) ** 2, axis=0)[rises], rtol=1e-5, atol=1e-3
    )
    # Where u already says as much, the floor adds nothing.
    assert np.all(floor[~rises] == 0) and np.array_equal(served[:, ~rises], own[:, ~rises].astype(np.float64))


@settings(max_examples=40, deadline=None)
@given(u=hnp.arrays(np.float32, (3, 5, 4), elements=levels), floor=hnp.arrays(np.float32, (5, 4), elements=levels))
def test_the_floor_adds_to_the_same_bits_on_the_host_and_as_tensor_operations(u: np.ndarray, floor: np.ndarray) -> None:
    sensor = SensorFloor(floor, {})
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        on_device = sensor.added_on_device(torch.from_numpy(u).to(device)).cpu().numpy()
        assert np.array_equal(on_device, sensor.added(u))


@pytest.mark.parametrize(
    ("error", "own", "message"),
    [
        (np.ones((1, 4, 4), np.float32), np.ones((1, 4, 4), np.float32), f"at least {MIN_PRESSES} presses"),
        (np.ones((3, 4, 4), np.float32), np.ones((3, 4, 5), np.float32), "same N x H x W"),
        (np.ones((3, 4), np.float32), np.ones((3, 4), np.float32), "same N x H x W"),
        (np.full((3, 4, 4), np.nan, np.float32), np.ones((3, 4, 4), np.float32), "not all finite"),
        (np.ones((3, 4, 4), np.float32), np.full((3, 4, 4), np.inf, np.float32), "not all finite"),
    ],
)
def test_a_floor_is_refused_bad_presses(error: np.ndarray, own: np.ndarray, message: str) -> None:
    with pytest.raises(ModelConfigError, match=message):
        fit_sensor_floor(error, own)


@pytest.mark.parametrize(
    "levels_map",
    [
        np.full((4, 4), -1.0, np.float32),
        np.full((4, 4), np.nan, np.float32),
        np.ones((4, 4), np.float64),
        np.ones((2, 4, 4), np.float32),
        np.ones((0, 0), np.float32),
    ],
)
def test_a_damaged_floor_is_refused(levels_map: np.ndarray) -> None:
    with pytest.raises(ModelConfigError, match="sensor floor"):
        SensorFloor(levels_map, {})


def test_each_held_out_press_gets_what_a_checkpoint_fitted_on_the_others_serves_it() -> None:
    """Judge the path the user calls: the evaluation's held-out u of press i is, to the bit, the
    u a ServedUncertainty carrying the floor of the other presses serves for press i."""
    torch.manual_seed(0)
    net = UncertaintyNet(2, 4)
    plain = ServedUncertainty(net, Calibration((0.5, 1.0), (2.0, 3.0)), UncertaintyConfig(width=4))
    x, estimate = torch.rand(5, 2, 16, 16), torch.rand(5, 3, 16, 16) * 2 - 1
    own = plain.levels(x, estimate)
    error = np.random.default_rng(1).gamma(2.0, 3.0, size=own.shape).astype(np.float32)
    held_out = leave_one_out_uncertainty(error, own)
    for i in range(len(own)):
        others = np.delete(np.arange(len(own)), i)
        floored = ServedUncertainty(
            net, plain.calibration, plain.config, SensorFloor(fit_sensor_floor(error[others], own[others]), {})
        )
        # The same batch as the evaluation's: a convolution's last bit may depend on it.
        assert np.array_equal(floored.levels(x, estimate)[i], held_out[i])
        assert np.array_equal(floored.levels(x, estimate, sensor_floor=False), own)
    assert floored.reply_note().endswith("floor of the sensor of unnamed presses)") and plain.reply_note() == ""
    again = ServedUncertainty.from_state(floored.to_state())
    assert again.floor is not None and np.array_equal(again.levels(x, estimate), floored.levels(x, estimate))


@pytest.fixture(scope="module")
def checkpoint_with_uncertainty(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh small checkpoint with an uncertainty entry (its net untrained, its calibration a
    plain one): what dtx calibrate uncertainty needs of a checkpoint, at a test's cost."""
    path = write_checkpoint(tmp_path_factory.mktemp("floor") / "fresh.pt", width=8)
    generator, _ = load_generator(path)
    torch.manual_seed(0)
    served = ServedUncertainty(
        UncertaintyNet(generator.config.in_channels, 4), Calibration((0.5, 1.0), (1.0, 1.0)), UncertaintyConfig(width=4)
    )
    state = torch.load(path, weights_only=True)
    state["uncertainty"] = served.to_state()
    torch.save(state, path)
    return path


def _calibrate(args: list[str]) -> int:
    parser = argparse.ArgumentParser()
    add_calibrate_commands(parser.add_subparsers())
    parsed = parser.parse_args(["calibrate", "uncertainty", *args])
    return int(parsed.func(parsed))


def test_dtx_calibrate_uncertainty_writes_a_checkpoint_that_serves_the_floor(
    checkpoint_with_uncertainty: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = checkpoint_with_uncertainty.read_bytes()
    out = tmp_path / "floored.pt"
    assert _calibrate([str(checkpoint_with_uncertainty), str(PRESSES), "--out", str(out), "--json"]) == 0
    report = strict_loads(capsys.readouterr().out)  # strict JSON: no NaN
    assert checkpoint_with_uncertainty.read_bytes() == before  # the input is left as it is
    assert report["presses"]["presses"] == 30 and report["presses"]["file"] == PRESSES.name
    assert report["leave_one_out"]["n"] == 30 and len(report["leave_one_out"]["deciles"]) == 10
    generator, depth_range_m = load_generator(out)
    assert generator.uncertainty is not None and generator.uncertainty.floor is not None
    assert generator.uncertainty.floor.levels.shape == (100, 100)
    # Served: the checkpoint's own u with the floor added, in every reply, asked for nothing.
    result, images = evaluate_real_presses(generator, depth_range_m, PRESSES, SCENE)
    _, served = predict_served(generator, images["depth_maps_m"], depth_range_m, pose_sigma_mm=0.0)
    assert served is not None
    assert np.array_equal(served, generator.uncertainty.floor.added(images["uncertainty_own"]))
    assert result["uncertainty"]["fitted_on_these_presses"] is True
    assert result["uncertainty"]["sensor_floor"]["sha256"] == report["presses"]["sha256"]
    # Its held-out figures are the input checkpoint's: the floor is fitted again without the press.
    assert result["uncertainty_lab_floor"] == report["leave_one_out"]
    # Asked again without --force, nothing is replaced.
    written = out.read_bytes()
    assert _calibrate([str(checkpoint_with_uncertainty), str(PRESSES), "--out", str(out)]) == 1
    assert "exists" in capsys.readouterr().err and out.read_bytes() == written


def test_a_real_press_evaluation_prints_the_held_out_floors_table(
    checkpoint_with_uncertainty: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    add_model_commands(parser.add_subparsers())
    args = parser.parse_args(["evaluate", str(checkpoint_with_uncertainty), "--real-presses", str(PRESSES)])
    assert args.func(args) == 0
    assert "fitted on the other presses" in capsys.readouterr().out


def test_a_checkpoint_without_an_uncertainty_or_bad_presses_get_a_clear_error(
    checkpoint_with_uncertainty: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    state = torch.load(checkpoint_with_uncertainty, weights_only=True)
    del state["uncertainty"]
    plain = tmp_path / "plain.pt"
    torch.save(state, plain)
    out = tmp_path / "out.pt"
    assert _calibrate([str(plain), str(PRESSES), "--out", str(out)]) == 1
    assert "serves no uncertainty" in capsys.readouterr().err and not out.exists()
    assert _calibrate([str(checkpoint_with_uncertainty), str(tmp_path / "none.npz"), "--out", str(out)]) == 1
    assert "none.npz" in capsys.readouterr().err and not out.exists()
    assert _calibrate([str(checkpoint_with_uncertainty), str(PRESSES), "--out", str(out), "--scene", "none.yaml"]) == 1
    assert "none.yaml" in capsys.readouterr().err and not out.exists()
    other_sensor = tmp_path / "other_sensor.npz"
    with np.load(PRESSES) as data:
        twice = {key: np.repeat(np.repeat(data[key], 2, -3), 2, -2) for key in ("background", "frames")}
        np.savez(other_sensor, background=twice["background"], frames=twice["frames"][:4])
    half_pitch = ["--mm-per-px", "0.06225"]  # a sensor of twice the pixels over the same gel
    assert _calibrate([str(checkpoint_with_uncertainty), str(other_sensor), "--out", str(out), *half_pitch]) == 1
    assert "the scene's GelSight" in capsys.readouterr().err and not out.exists()
    one = tmp_path / "one.npz"
    with np.load(PRESSES) as data:
        np.savez(one, **{key: data[key][:1] if data[key].ndim and len(data[key]) == 30 else data[key] for key in data})
    assert _calibrate([str(checkpoint_with_uncertainty), str(one), "--out", str(out)]) == 1
    assert f"at least {MIN_PRESSES} presses" in capsys.readouterr().err and not out.exists()


def test_a_floor_of_another_size_than_the_images_is_refused_on_load(
    checkpoint_with_uncertainty: Path, tmp_path: Path
) -> None:
    state = torch.load(checkpoint_with_uncertainty, weights_only=True)
    state["uncertainty"]["sensor_floor"] = {"levels": torch.ones(50, 50), "source": {"file": "x.npz"}}
    bad = tmp_path / "bad.pt"
    torch.save(state, bad)
    with pytest.raises(ModelConfigError, match="sensor floor is \\(50, 50\\)"):
        load_generator(bad)


def test_a_sessions_predictions_name_the_sensor_floor_their_u_carries(
    checkpoint_with_uncertainty: Path, tmp_path: Path
) -> None:
    from dataset.contact_library import write_contact_library
    from dataset.reader import DatasetReader
    from models.predictions import predict_records

    library = write_contact_library(tmp_path / "library", 4, seed=3, scene=SCENE, depth_range_m=(-0.005, 0.01)).root
    reader = DatasetReader(library)
    floored = tmp_path / "floored.pt"
    assert _calibrate([str(checkpoint_with_uncertainty), str(PRESSES), "--out", str(floored)]) == 0
    for path, source in ((checkpoint_with_uncertainty, None), (floored, PRESSES.name)):
        generator, depth_range_m = load_generator(path)
        predictions = predict_records(generator, depth_range_m, reader, reader.records, "the library")
        assert (predictions.sensor_floor or {}).get("file") == source
