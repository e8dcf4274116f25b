"""Numerical contracts of SSIM and the evaluation statistics (issue 20): a right finite answer
or ModelConfigError, for every dtype, layout and degenerate data set; ``dtx evaluate`` reports
what it can and says what it cannot."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import models.checkpoint
import models.evaluate as evaluate_module
from models.cli import add_commands
from models.errors import ModelConfigError
from models.evaluate import Predictions, ssim_statistics, summary_table
from models.template_match import template_match
from perception.errors import ImageComparisonError
from perception.ssim import PSNR_MAX_DB, psnr_rgb, ssim_pairs_rgb, ssim_rgb, ssim_torch

FAST = settings(max_examples=25, deadline=None)


def images(n: int, seed: int, size: int = 24) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, size, size, 3), dtype=np.uint8)


def as_batch(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x)).permute(0, 3, 1, 2)


# --- family 1: ssim_torch dtypes --------------------------------------------------------------


@FAST
@given(
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from(
        [
            torch.uint8,
            torch.int16,
            torch.int32,
            torch.int64,
            torch.float16,
            torch.bfloat16,
            torch.float32,
            torch.float64,
        ]
    ),
)
def test_property_ssim_is_the_float64_ssim_in_every_dtype(seed: int, dtype: torch.dtype) -> None:
    a, b = images(2, seed), images(2, seed + 1)
    reference = ssim_torch(as_batch(a).double(), as_batch(b).double())
    got = ssim_torch(as_batch(a).to(dtype), as_batch(b).to(dtype))
    assert torch.all(torch.isfinite(got))
    # 8-bit levels are exact in every dtype here; only float32 arithmetic differs.
    torch.testing.assert_close(got.double(), reference, atol=1e-4, rtol=0)
    assert torch.all(reference < 0.5)  # unrelated noise images: far from 1
    torch.testing.assert_close(
        ssim_torch(as_batch(a).to(dtype), as_batch(a).to(dtype)).double(),
        torch.ones(2, dtype=torch.float64),
        atol=1e-5,
        rtol=0,
    )


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int32, torch.int64])
def test_integer_inputs_of_unrelated_images_are_not_scored_1(dtype: torch.dtype) -> None:
    a, b = images(1, 0), images(1, 1)
    assert ssim_torch(as_batch(a).to(dtype), as_batch(b).to(dtype)).item() < 0.1


def test_float16_ssim_is_not_nan() -> None:
    a, b = images(1, 0), images(1, 1)
    value = ssim_torch(as_batch(a).half(), as_batch(b).half())
    assert torch.isfinite(value).all() and value.item() == pytest.approx(
        ssim_torch(as_batch(a).double(), as_batch(b).double()).item(), abs=1e-4
    )


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0, 255.5, 1e300])
def test_ssim_refuses_values_outside_the_8_bit_range(value: float) -> None:
    a = torch.zeros(1, 3, 16, 16, dtype=torch.float64)
    a[0, 1, 3, 4] = value
    with pytest.raises(ImageComparisonError, match=r"\[0, 255\]"):
        ssim_torch(a, torch.zeros_like(a))


def test_ssim_refuses_bad_shapes_and_complex() -> None:
    with pytest.raises(ImageComparisonError, match="C >= 1"):
        ssim_torch(torch.zeros(1, 0, 16, 16), torch.zeros(1, 0, 16, 16))
    with pytest.raises(ImageComparisonError, match="at least 11"):
        ssim_torch(torch.zeros(1, 3, 10, 16), torch.zeros(1, 3, 10, 16))
    with pytest.raises(ImageComparisonError, match="real images"):
        ssim_torch(torch.zeros(1, 3, 16, 16, dtype=torch.complex64), torch.zeros(1, 3, 16, 16, dtype=torch.complex64))
    assert ssim_torch(torch.zeros(0, 3, 16, 16), torch.zeros(0, 3, 16, 16)).shape == (0,)


# --- family 9: ssim_rgb views ------------------------------------------------------------------


@FAST
@given(seed=st.integers(0, 2**16), view=st.sampled_from(["flip_x", "flip_y", "flip_c", "step", "fortran"]))
def test_property_ssim_rgb_of_a_view_is_the_ssim_of_its_copy(seed: int, view: str) -> None:
    a, b = images(2, seed, 30), images(2, seed + 1, 30)
    make = {
        "flip_x": lambda x: x[:, :, ::-1],
        "flip_y": lambda x: x[:, ::-1],
        "flip_c": lambda x: x[..., ::-1],
        "step": lambda x: x[:, ::2, ::2],
        "fortran": np.asfortranarray,
    }[view]
    va, vb = make(a), make(b)
    np.testing.assert_array_equal(ssim_rgb(va, vb), ssim_rgb(va.copy(), vb.copy()))
    windows = np.ones(va.shape[:-1], bool)[:, ::-1]
    np.testing.assert_allclose(ssim_rgb(va, vb, windows), ssim_rgb(va.copy(), vb.copy()), atol=1e-12)


@FAST
@given(
    seed=st.integers(0, 2**16),
    counts=st.tuples(st.integers(1, 4), st.integers(1, 4), st.integers(0, 9)),
    masked=st.booleans(),
)
def test_property_ssim_of_pairs_is_ssim_rgb_of_each_pair(seed: int, counts: tuple[int, int, int], masked: bool) -> None:
    """The baseline's pairwise SSIM (each image blurred once) is ssim_rgb's, pair by pair."""
    n, m, k = counts
    rng = np.random.default_rng(seed)
    a, b = images(n, seed, 17), images(m, seed + 1, 17)
    pairs = np.stack([rng.integers(0, n, k), rng.integers(0, m, k)], axis=1)
    windows = rng.random((n, 17, 17)) < 0.3 if masked else None
    expected = [ssim_rgb(a[i], b[j], None if windows is None else windows[i]) for i, j in pairs]
    np.testing.assert_allclose(ssim_pairs_rgb(a, b, pairs, windows), expected, atol=1e-12, equal_nan=True)


def test_ssim_of_pairs_refuses_what_it_cannot_pair() -> None:
    a = images(2, 0)
    good = np.array([[0, 1]])
    for bad_a, bad_b, pairs, match in (
        (a.astype(np.float32), a, good, "uint8"),
        (a, a[:, :20], good, "one image size"),
        (a[:, :8, :8], a[:, :8, :8], good, "at least 11"),
        (a, a, good.astype(float), "integer indices"),
        (a, a, np.array([0, 1]), "integer indices"),
        (a, a, np.array([[0, 2]]), "not there"),
        (a, a, np.array([[-1, 0]]), "not there"),
    ):
        with pytest.raises(ImageComparisonError, match=match):
            ssim_pairs_rgb(bad_a, bad_b, pairs)
    assert ssim_pairs_rgb(a, a, np.empty((0, 2), int)).shape == (0,)


def test_ssim_rgb_refuses_windows_of_another_shape_or_dtype() -> None:
    a = images(2, 0)
    with pytest.raises(ImageComparisonError, match="windows"):
        ssim_rgb(a, a, np.ones((2, 23, 24), bool))
    with pytest.raises(ImageComparisonError, match="windows"):
        ssim_rgb(a, a, np.ones((2, 24, 24), np.float32))


@FAST
@given(seed=st.integers(0, 2**16), level=st.integers(1, 40))
def test_property_psnr_is_the_8_bit_formula_and_capped(seed: int, level: int) -> None:
    a = images(2, seed).astype(np.int16)
    b = np.clip(a + level, 0, 255)
    mse = ((a - b) ** 2).reshape(2, -1).mean(axis=1)
    np.testing.assert_allclose(
        psnr_rgb(a.astype(np.uint8), b.astype(np.uint8)), 10 * np.log10(255.0**2 / mse), rtol=1e-12
    )
    assert psnr_rgb(a[0].astype(np.uint8), a[0].astype(np.uint8)) == PSNR_MAX_DB


def test_psnr_refuses_what_ssim_refuses() -> None:
    a = images(2, 0)
    with pytest.raises(ImageComparisonError, match="psnr_rgb"):
        psnr_rgb(a, a[:1])
    with pytest.raises(ImageComparisonError, match="psnr_rgb"):
        psnr_rgb(a.astype(np.float32), a.astype(np.float32))


# --- family 3: template_match ------------------------------------------------------------------


def test_flat_template_scores_0_and_has_no_match() -> None:
    truth = np.full((1, 40, 40, 3), 90, np.uint8)
    truth[0, ..., 1] = 30  # flat in every channel, channels differ
    estimate = images(1, 5, 40)
    match = template_match(truth, np.random.default_rng(0).random((1, 40, 40)), estimate, size_px=8)[0]
    assert match["score"] == 0.0 and match["match_xy"] is None and match["distance_px"] is None


def test_flat_estimate_scores_0_against_a_textured_template() -> None:
    truth = images(1, 3, 40)
    estimate = np.full((1, 40, 40, 3), 7, np.uint8)
    match = template_match(truth, np.zeros((1, 40, 40)), estimate, size_px=8)[0]
    assert match["score"] == 0.0


@FAST
@given(seed=st.integers(0, 2**16), flat_fraction=st.floats(0.0, 1.0))
def test_property_template_scores_are_finite_correlations(seed: int, flat_fraction: float) -> None:
    rng = np.random.default_rng(seed)
    truth, estimate = images(2, seed, 32), images(2, seed + 7, 32)
    cut = int(flat_fraction * 32)
    estimate[:, :cut] = 100
    truth[1] = estimate[1]
    for m in template_match(truth, rng.random((2, 32, 32)), estimate, size_px=8):
        assert -1.0 - 1e-6 <= m["score"] <= 1.0 + 1e-6
    assert template_match(truth, np.zeros((2, 32, 32)), truth, size_px=8)[0]["score"] == pytest.approx(1.0, abs=1e-5)


def test_template_match_refuses_mismatched_inputs() -> None:
    with pytest.raises(ModelConfigError, match="template matching"):
        template_match(images(2, 0), np.zeros((2, 24, 24)), images(3, 0))
    with pytest.raises(ModelConfigError, match="template matching"):
        template_match(images(2, 0).astype(np.int32), np.zeros((2, 24, 24)), images(2, 0).astype(np.int32))


# --- family 4: ssim_statistics and dtx evaluate on degenerate data ------------------------------


def test_identical_truths_give_an_undefined_ratio_with_its_reason() -> None:
    truth = np.repeat(images(1, 0), 4, axis=0)
    result = ssim_statistics(truth, truth.copy())  # was ZeroDivisionError
    assert math.isnan(result["dissimilarity_ratio"]) and "same frame" in result["dissimilarity_ratio_undefined"]
    for key in (
        "ssim_model_mean",
        "ssim_model_se",
        "ssim_baseline_mean",
        "ssim_baseline_se",
        "p_value_wilcoxon",
        "p_value_t",
    ):
        assert math.isfinite(result[key])


@pytest.mark.parametrize("draws", [0, -1, 1001, 2.5, True, "15"])
def test_baseline_draws_out_of_range_are_refused(draws: object) -> None:
    with pytest.raises(ModelConfigError, match="baseline_draws"):
        ssim_statistics(images(3, 0), images(3, 1), baseline_draws=draws)


def test_an_empty_window_mask_is_refused_not_nan() -> None:
    windows = np.ones((3, 24, 24), bool)
    windows[1] = False
    windows[2, 5:-5, 5:-5] = False  # only border pixels: no whole window either
    with pytest.raises(ModelConfigError, match=r"pairs \[1, 2\]"):
        ssim_statistics(images(3, 0), images(3, 1), windows=windows)


@FAST
@given(
    seed=st.integers(0, 2**16),
    n=st.integers(2, 5),
    draws=st.integers(1, 20),
    same=st.sampled_from(["none", "truths", "pairs", "estimates"]),
)
def test_property_statistics_are_finite_or_explained(seed: int, n: int, draws: int, same: str) -> None:
    truth, estimate = images(n, seed, 16), images(n, seed + 1, 16)
    if same == "truths":
        truth[:] = truth[0]
    elif same == "pairs":
        estimate = truth.copy()
    elif same == "estimates":
        estimate[:] = estimate[0]
    result = ssim_statistics(truth, estimate, baseline_draws=draws, seed=seed)
    for key, value in result.items():
        if isinstance(value, float) and not math.isfinite(value):
            assert key == "dissimilarity_ratio" and "dissimilarity_ratio_undefined" in result
    assert 0.0 <= result["p_value_t"] <= 1.0 and 0.0 <= result["p_value_wilcoxon"] <= 1.0


def _degenerate_predictions(n: int, identical: bool) -> Predictions:
    """``identical``: every truth the same flat frame, estimated exactly (undefined ratio, flat
    templates); otherwise random truths and flat estimates."""
    flat = np.full((n, 40, 40, 3), 120, np.uint8)
    truth = flat.copy() if identical else images(n, 0, 40)
    return Predictions(
        sample_ids=[f"s{i}" for i in range(n)],
        objects=["only"] * n,
        depth_maps_m=np.zeros((n, 40, 40), np.float32),
        truth=truth,
        truth_deformation=np.zeros(truth.shape[:-1], np.float32),
        estimate=flat,
    )


@pytest.mark.parametrize("n, identical", [(1, False), (2, True), (3, True), (3, False)])
def test_dtx_evaluate_reports_degenerate_data_without_a_traceback(
    n: int, identical: bool, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """One object, identical (flat) truths, a single pair: the table says what it cannot give."""
    predictions = _degenerate_predictions(n, identical)

    def predict_dataset(
        generator: object, depth_range_m: object, root: object, split: str = "test", hold_out_object: str = ""
    ) -> Predictions:
        if n < 2:
            raise ModelConfigError(f"the {split} set of {root} has {n} sample(s); need at least 2")
        return predictions

    monkeypatch.setattr(evaluate_module, "predict_dataset", predict_dataset)
    monkeypatch.setattr(models.checkpoint, "load_generator", lambda path: (None, (-0.002, 0.002)))
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    for extra in ([], ["--json"]):
        args = parser.parse_args(["evaluate", "checkpoint.pt", "dataset", *extra])
        code = args.func(args)
        out, err = capsys.readouterr()
        if n < 2:
            assert code == 1 and "need at least 2" in err
            continue
        assert code == 0
        if extra:
            result = json.loads(out)  # strict JSON: an undefined ratio is null beside its reason
            assert (result["dissimilarity_ratio"] is None) == identical
            assert ("dissimilarity_ratio_undefined" in result) == identical
        else:
            assert ("ratio undefined (all pairs)" in out) == identical
            assert ("ratio undefined (object only)" in out) == identical
            assert ("every template is flat" in out) == identical


def test_summary_table_prints_every_undefined_figure() -> None:
    predictions = _degenerate_predictions(3, True)
    result = ssim_statistics(predictions.truth, predictions.estimate)
    result.update(
        template_match={
            "template_px": 8,
            "score_mean": 0.0,
            "distance_px_median": float("nan"),
            "per_sample": template_match(predictions.truth, predictions.truth_deformation, predictions.estimate, 8),
        },
        contact={"n": 0},
        objects={},
        density=[],
    )
    table = summary_table(result)
    assert "ratio undefined (all pairs)" in table and "every template is flat" in table
    assert "no object has 2 pairs" in table
