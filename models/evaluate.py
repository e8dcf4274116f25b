"""Evaluate a trained generator like the paper (``dtx evaluate CHECKPOINT DATASET``).

* SSIM (perception.ssim) of every estimate against its ground truth, and the baseline: the
  same estimate against ``baseline_draws`` (15) random other ground-truth images of the
  evaluated set, averaged per estimate. Mean +- standard error of both, paired Wilcoxon
  signed-rank and paired t-test p-values (two-sided), and the dissimilarity ratio
  (1 - SSIM_model) / (1 - SSIM_baseline) (paper: 0.16 / 0.20 = 0.80).
* Template matching (OpenCV TM_CCOEFF_NORMED; models.template_match): the template is the
  ground truth's most deformed ``template_px`` square (largest summed |change| of the
  background-subtracted copy), searched for in the estimate; score and distance (px) from the
  template's place.
* Density table: the same SSIM on datasets whose depth-maps were made from clouds
  downsampled to given densities (points/cm^3) - inputs from the collection session.

The figures (``--figures``) are models.figures'.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.redepth import depth_map_params, depth_maps_made_beside
from models.data import reader_for_model, select_records
from models.networks import ModelConfigError, UNetGenerator
from models.predictions import Predictions, predict_records
from models.serving import predict
from models.template_match import template_match
from models.uncertainty import served_uncertainty_statistics, uncertainty_table
from msgs.progress import Progress
from perception.density import voxel_size_for_density
from perception.depthmap import surface_bins
from perception.errors import ImageComparisonError, PerceptionError
from perception.ssim import WINDOW, psnr_rgb, ssim_pairs_rgb, ssim_rgb

PAPER = {
    "ssim_model_mean": 0.84,
    "ssim_model_se": 0.0056,
    "ssim_baseline_mean": 0.80,
    "ssim_baseline_se": 0.0036,
    "dissimilarity_ratio": 0.80,
}
# The paper's mean SSIM at each point-cloud density (points/cm³).
PAPER_DENSITY_SSIM: dict[float, float] = {1: 0.8238, 10: 0.8278, 20: 0.8478, 40: 0.8480, 80: 0.8476}


def predict_dataset(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    root: str | os.PathLike[str],
    split: str = "test",
    hold_out_object: str = "",
) -> Predictions:
    """Estimates for one split of a dataset (``split="all"``: every sample)."""
    reader = reader_for_model(root, depth_range_m)
    records = evaluated_records(reader, split, hold_out_object)
    return predict_records(generator, depth_range_m, reader, records, f"the {split} set of {root}")


def evaluated_records(reader: DatasetReader, split: str, hold_out_object: str = "") -> list[SampleRecord]:
    """The samples an evaluation of ``split`` scores (``"all"``: every sample)."""
    return reader.records if split == "all" else select_records(reader, split, hold_out_object)


# Most random truths per estimate in the baseline (the paper draws 15); each draw costs one SSIM.
MAX_BASELINE_DRAWS = 1000


def _baseline(n: int, baseline_draws: int, seed: int, score: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Per estimate i, the mean of its scores against ``baseline_draws`` random other truths,
    drawn the same way for every metric and seed; ``score`` scores every (truth, estimate) row
    of a K x 2 index array at once."""
    rng = np.random.default_rng(seed)
    draws = np.empty((n, baseline_draws), np.int64)
    for i in range(n):
        # Random *other* ground truths: the estimate's own would favour the baseline.
        others = np.delete(np.arange(n), i)
        draws[i] = rng.choice(others, size=baseline_draws, replace=len(others) < baseline_draws)
    pairs = np.stack([draws.ravel(), np.repeat(np.arange(n), baseline_draws)], axis=1)
    return score(pairs).reshape(n, baseline_draws).mean(axis=1)


def _mean_se(values: np.ndarray) -> tuple[float, float]:
    return float(np.mean(values)), float(np.std(values, ddof=1) / np.sqrt(len(values)))


def ssim_statistics(
    truth: np.ndarray, estimate: np.ndarray, baseline_draws: int = 15, seed: int = 0, windows: np.ndarray | None = None
) -> dict[str, Any]:
    """Model vs baseline SSIM statistics (see module docstring) for N >= 2 image pairs.
    ``windows`` (N x H x W bool) restricts each SSIM to the windows centred on a truth's True
    pixels (perception.ssim.ssim_rgb); the baseline then uses each random truth's own windows.

    Contract: ``truth`` and ``estimate`` N x H x W x 3 uint8 (perception.ssim.ssim_rgb), N >= 2;
    ``baseline_draws`` an integer in [1, MAX_BASELINE_DRAWS]; every truth's ``windows`` must hold
    a window inside the 5-pixel border. Otherwise ModelConfigError. Every statistic is then
    finite except ``dissimilarity_ratio``, which is NaN when the baseline's mean dissimilarity
    1 - SSIM is 0 (every truth the same frame, and the estimates too): the ratio is undefined, and
    ``dissimilarity_ratio_undefined`` says why (the key is present only then)."""
    n = len(truth)
    _check_statistics_input(truth, estimate, baseline_draws)
    try:
        model = ssim_rgb(truth, estimate, windows)
    except ImageComparisonError as err:  # the contract above names the models' error
        raise ModelConfigError(str(err)) from err
    if not np.all(np.isfinite(model)):
        raise ModelConfigError(
            f"pairs {np.flatnonzero(~np.isfinite(model)).tolist()} have no SSIM window inside "
            f"the {WINDOW // 2}-pixel border (empty windows mask)"
        )
    baseline = _baseline(n, baseline_draws, seed, lambda pairs: ssim_pairs_rgb(truth, estimate, pairs, windows))
    return {
        "n": n,
        **_model_against_baseline(model, baseline),
        "ssim_model": model.tolist(),
        "ssim_baseline": baseline.tolist(),
    }


def _check_statistics_input(truth: np.ndarray, estimate: np.ndarray, baseline_draws: int) -> None:
    """ModelConfigError unless there are 2 pairs of one shape and ``baseline_draws`` is an
    integer in [1, MAX_BASELINE_DRAWS]."""
    shape, other = np.shape(truth), np.shape(estimate)
    if not shape or shape[0] < 2 or shape != other:
        raise ModelConfigError(
            f"need at least 2 pairs of equal shape (the baseline scores each estimate against other "
            f"truths), got {shape} and {other}"
        )
    if not (
        isinstance(baseline_draws, (int, np.integer))
        and not isinstance(baseline_draws, bool)
        and 1 <= baseline_draws <= MAX_BASELINE_DRAWS
    ):
        raise ModelConfigError(
            f"baseline_draws must be an integer in [1, {MAX_BASELINE_DRAWS}], got {baseline_draws!r}"
        )


def _model_against_baseline(model: np.ndarray, baseline: np.ndarray) -> dict[str, Any]:
    """Means and standard errors of the model's and the baseline's SSIM, paired Wilcoxon and
    t-test p-values and the dissimilarity ratio (with why it is undefined, when it is)."""
    model_mean, model_se = _mean_se(model)
    base_mean, base_se = _mean_se(baseline)
    diff = model - baseline
    # Degenerate differences have no test statistic: all zero means no evidence (p = 1),
    # a constant non-zero difference is as certain as it gets (p = 0).
    p_wilcoxon = float(stats.wilcoxon(model, baseline).pvalue) if np.any(diff != 0) else 1.0
    p_t = float(stats.ttest_rel(model, baseline).pvalue) if np.std(diff) > 0 else float(np.all(diff == 0))
    # The ratio of dissimilarities needs a baseline that is dissimilar at all (SSIM can exceed 1
    # by rounding, so "at all" is more than a few ulps).
    base_dissimilarity = 1.0 - base_mean
    undefined = (
        {}
        if base_dissimilarity > 1e-12
        else {
            "dissimilarity_ratio_undefined": f"the baseline's mean SSIM is {base_mean!r}: every estimate equals the "
            "other truths it is compared with (every truth the same frame, "
            "estimated exactly), so there is no dissimilarity to compare with"
        }
    )
    return {
        "ssim_model_mean": model_mean,
        "ssim_model_se": model_se,
        "ssim_baseline_mean": base_mean,
        "ssim_baseline_se": base_se,
        "p_value_wilcoxon": p_wilcoxon,
        "p_value_t": p_t,
        "dissimilarity_ratio": (1.0 - model_mean) / base_dissimilarity if not undefined else float("nan"),
        **undefined,
    }


def psnr_statistics(truth: np.ndarray, estimate: np.ndarray, baseline_draws: int = 15, seed: int = 0) -> dict[str, Any]:
    """PSNR (dB, perception.ssim.psnr_rgb) of every estimate against its truth and against the same
    random other truths as the SSIM baseline (same draws for the same seed): mean and standard
    error of each. Cross-modal benchmarks report PSNR beside SSIM; PSNR weighs every pixel's
    error, SSIM the local structure.

    Contract as :func:`ssim_statistics` without windows (N >= 2 pairs of uint8 N x H x W x 3
    images of one shape, at least one pixel); otherwise ModelConfigError."""
    n = len(truth)
    _check_statistics_input(truth, estimate, baseline_draws)
    try:
        model = psnr_rgb(truth, estimate)
    except ImageComparisonError as err:  # the contract above names the models' error
        raise ModelConfigError(str(err)) from err
    baseline = _baseline(
        n,
        baseline_draws,
        seed,
        lambda pairs: np.concatenate(
            [
                psnr_rgb(truth[chunk[:, 0]], estimate[chunk[:, 1]])
                for chunk in np.array_split(pairs, -(-len(pairs) // 256))
            ]
        ),
    )
    model_mean, model_se = _mean_se(model)
    base_mean, base_se = _mean_se(baseline)
    return {
        "psnr_db_model_mean": model_mean,
        "psnr_db_model_se": model_se,
        "psnr_db_baseline_mean": base_mean,
        "psnr_db_baseline_se": base_se,
    }


SUMMARY_KEYS = (
    "n",
    "ssim_model_mean",
    "ssim_model_se",
    "ssim_baseline_mean",
    "ssim_baseline_se",
    "p_value_wilcoxon",
    "dissimilarity_ratio",
    "dissimilarity_ratio_undefined",
)


def per_object_statistics(
    truth: np.ndarray, estimate: np.ndarray, objects: Sequence[str], baseline_draws: int = 15, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """:func:`ssim_statistics` (its summary: :data:`SUMMARY_KEYS`) of each object with at
    least 2 pairs, the baseline drawn from that object's own ground truths."""
    names = np.asarray(objects)
    return {
        name: {
            k: v
            for k, v in ssim_statistics(truth[names == name], estimate[names == name], baseline_draws, seed).items()
            if k in SUMMARY_KEYS
        }
        for name in sorted(set(names.tolist()))
        if np.sum(names == name) >= 2
    }


# Summed |change| over RGB (8-bit levels) from which a pixel counts as contact: well above the
# simulated sensor noise (1 level per channel) and the real camera's frame-to-frame fringes.
CONTACT_LEVELS = 15.0


def contact_windows(truth_deformation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the pairs whose truth shows contact, N x H x W bool contact pixels): the
    SSIM windows centred on those pixels are the contact windows (``truth_deformation`` >=
    CONTACT_LEVELS). A pair counts only if a contact pixel is far enough inside the image for
    a whole window."""
    contact = truth_deformation >= CONTACT_LEVELS
    inner = contact[:, WINDOW // 2 : -(WINDOW // 2), WINDOW // 2 : -(WINDOW // 2)]
    return np.flatnonzero(inner.any(axis=(1, 2))), contact


def contact_ssim(truth: np.ndarray, truth_deformation: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """SSIM of each pair whose truth shows contact, over its contact windows only
    (:func:`contact_windows`); pairs without contact are left out."""
    keep, contact = contact_windows(truth_deformation)
    return ssim_rgb(truth[keep], estimate[keep], contact[keep]) if len(keep) else np.empty(0)


def contact_ssim_statistics(
    truth: np.ndarray, truth_deformation: np.ndarray, estimate: np.ndarray, baseline_draws: int = 15, seed: int = 0
) -> dict[str, Any]:
    """The paper's comparison with SSIM taken only over the contact windows
    (:func:`contact_windows`). The whole-image SSIM of these images is mostly the sensor's own
    background, which a no-contact estimate gets right; here only the contact counts. Pairs
    whose truth shows no contact are left out; the baseline scores an estimate on each random
    truth's own contact windows."""
    keep, contact = contact_windows(truth_deformation)
    if len(keep) < 2:
        return {"n": int(len(keep)), "contact_levels": CONTACT_LEVELS}
    result = ssim_statistics(truth[keep], estimate[keep], baseline_draws, seed, windows=contact[keep])
    return {
        "contact_levels": CONTACT_LEVELS,
        **{k: v for k, v in result.items() if k not in ("ssim_model", "ssim_baseline")},
    }


def evaluate(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    root: str | os.PathLike[str],
    split: str = "test",
    hold_out_object: str = "",
    density: Sequence[float] = (),
    baseline_draws: int = 15,
    template_px: int = 32,
    seed: int = 0,
    progress: bool = True,
) -> tuple[dict[str, Any], Predictions]:
    """The paper's analysis on one split, plus the density table: the same pairs with their
    depth-maps made again from the model cloud thinned to each of ``density`` (points/cm^3,
    ``dataset.redepth.depth_maps_at_density``, in a process beside the analysis; the dataset
    must record its models' poses)."""
    density_ids = []
    if density:
        density_reader = _density_reader(root, depth_range_m, density)
        density_ids = [r.sample_id for r in evaluated_records(density_reader, split, hold_out_object)]
    shown = Progress("evaluate", 1 + len(density), "depth-map sets", enabled=progress)
    with depth_maps_made_beside(root, density_ids, sorted(density)) as density_maps:
        predictions = predict_dataset(generator, depth_range_m, root, split, hold_out_object)
        result = full_analysis(predictions, baseline_draws, template_px, seed)
        shown.note(f"last: the {split} split")
        shown.update()
        result["density"] = []
        full_contact = contact_ssim(predictions.truth, predictions.truth_deformation, predictions.estimate)
        empty_contact = _empty_map_contact(generator, depth_range_m, predictions) if density else None
        result["surface_bins_mean"] = float(surface_bins(predictions.depth_maps_m, depth_range_m[1]).mean())
        for points_per_cm3, depth in density_maps.items():
            maps = depth.result()
            estimate = predict(generator, maps, depth_range_m)
            bins = surface_bins(maps, depth_range_m[1])
            result["density"].append(
                _density_row(points_per_cm3, predictions, estimate, bins, full_contact, empty_contact)
            )
            shown.note(f"last: {points_per_cm3:g} points/cm³")
            shown.update()
    shown.close()
    result.update({"split": split, "hold_out_object": hold_out_object, "sample_ids": predictions.sample_ids})
    return result, predictions


def full_analysis(predictions: Predictions, baseline_draws: int, template_px: int, seed: int) -> dict[str, Any]:
    """The paper's analysis of ``predictions``: SSIM against the baseline, template match, PSNR,
    and the contact windows' and each object's SSIM."""
    result = ssim_statistics(predictions.truth, predictions.estimate, baseline_draws, seed)
    matches = template_match(predictions.truth, predictions.truth_deformation, predictions.estimate, template_px)
    distances = [m["distance_px"] for m in matches if m["distance_px"] is not None]
    result["template_match"] = {
        "template_px": template_px,
        "score_mean": float(np.mean([m["score"] for m in matches])),
        # Over the pairs whose template is not flat; NaN, with the reason, when every template is.
        "distance_px_median": float(np.median(distances)) if distances else float("nan"),
        **({} if distances else {"distance_px_median_undefined": "every truth's template is flat: nothing to locate"}),
        "per_sample": matches,
    }
    result["psnr"] = psnr_statistics(predictions.truth, predictions.estimate, baseline_draws, seed)
    result["contact"] = contact_ssim_statistics(
        predictions.truth, predictions.truth_deformation, predictions.estimate, baseline_draws, seed
    )
    result["objects"] = per_object_statistics(
        predictions.truth, predictions.estimate, predictions.objects, baseline_draws, seed
    )
    result["uncertainty"] = served_uncertainty_statistics(
        predictions.uncertainty,
        predictions.estimate,
        predictions.truth,
        1.0 - np.asarray(result["ssim_model"]),
        predictions.objects,
    )
    if predictions.sensor_floor is not None:  # u then carries a real sensor's light, wider than a session's error
        result["uncertainty"]["sensor_floor"] = predictions.sensor_floor
    return result


def _density_reader(
    root: str | os.PathLike[str], depth_range_m: tuple[float, float], density: Sequence[float]
) -> DatasetReader:
    """The dataset the density table's depth-maps are made again from, checked before the
    evaluation starts: ModelConfigError for a density no voxel grid gives, DatasetError for a
    dataset that records no crop to make them in."""
    for points_per_cm3 in density:
        try:
            voxel_size_for_density(points_per_cm3)
        except PerceptionError as err:
            raise ModelConfigError(f"--density: {err}") from err
    reader = reader_for_model(root, depth_range_m)
    depth_map_params(reader)
    return reader


def _empty_map_contact(
    generator: UNetGenerator, depth_range_m: tuple[float, float], predictions: Predictions
) -> np.ndarray:
    """The contact-window SSIM of an empty map's estimate (no surface in reach) on each pair: the
    reference a thinned cloud must beat."""
    empty_map = np.full((1, *predictions.truth.shape[1:3]), depth_range_m[1], np.float32)
    empty = np.repeat(predict(generator, empty_map, depth_range_m), len(predictions.truth), axis=0)
    return contact_ssim(predictions.truth, predictions.truth_deformation, empty)


def _density_row(
    points_per_cm3: float,
    full: Predictions,
    estimate: np.ndarray,
    bins: np.ndarray,
    full_contact: np.ndarray,
    empty: np.ndarray | None,
) -> dict[str, Any]:
    """The density table's row for ``estimate``, the estimates of ``full``'s pairs from their
    depth-maps at ``points_per_cm3``, whose bins holding a surface are ``bins`` (one count a map);
    the full cloud's contact-window SSIM (``full_contact``) for the test of what the density
    costs, an empty map's (``empty``) for what the cloud is worth."""
    mean, se = _mean_se(ssim_rgb(full.truth, estimate))
    psnr_mean, psnr_se = _mean_se(psnr_rgb(full.truth, estimate))
    row = {
        "points_per_cm3": float(points_per_cm3),
        "ssim_mean": mean,
        "ssim_se": se,
        "psnr_db_mean": psnr_mean,
        "psnr_db_se": psnr_se,
        "paper_ssim_mean": PAPER_DENSITY_SSIM.get(points_per_cm3),
        "surface_bins_mean": float(np.mean(bins)),
    }
    contact = contact_ssim(full.truth, full.truth_deformation, estimate)
    if len(contact) >= 2:
        row["contact_ssim_mean"], row["contact_ssim_se"] = _mean_se(contact)
        # What this density costs: the full cloud's estimates better on the same pairs'
        # contact windows (one-sided Wilcoxon).
        if np.any(contact != full_contact):
            row["contact_p_full_better"] = float(stats.wilcoxon(full_contact, contact, alternative="greater").pvalue)
        if empty is not None:  # what the thinned cloud is worth: its estimates better than an empty map's
            row["empty_contact_ssim_mean"] = float(np.mean(empty))
            if np.any(contact != empty):
                row["contact_p_better_than_empty"] = float(stats.wilcoxon(contact, empty, alternative="greater").pvalue)
    return row


def summary_table(result: dict[str, Any]) -> str:
    """The paper-style table, beside the paper's numbers. A figure the data cannot give (NaN)
    prints as nan, and a line at the end says why."""
    lines = [
        f"{'':28s}{'this model':>22s}{'paper':>18s}",
        f"{'SSIM model':28s}{result['ssim_model_mean']:>13.4f} ± {result['ssim_model_se']:.4f}"
        f"{PAPER['ssim_model_mean']:>11.2f} ± {PAPER['ssim_model_se']}",
        f"{'SSIM baseline (15 random)':28s}{result['ssim_baseline_mean']:>13.4f} ± {result['ssim_baseline_se']:.4f}"
        f"{PAPER['ssim_baseline_mean']:>11.2f} ± {PAPER['ssim_baseline_se']}",
        f"{'dissimilarity ratio':28s}{result['dissimilarity_ratio']:>22.3f}{PAPER['dissimilarity_ratio']:>18.2f}",
        f"{'p (Wilcoxon / t)':28s}{result['p_value_wilcoxon']:>12.2e} / {result['p_value_t']:.2e}",
        f"{'template match score':28s}{result['template_match']['score_mean']:>22.3f}",
        f"{'template distance (px, med)':28s}{result['template_match']['distance_px_median']:>22.1f}",
        f"samples evaluated: {result['n']}",
    ]
    if "psnr" in result:
        lines.insert(
            4,
            f"{'PSNR model / baseline (dB)':28s}{result['psnr']['psnr_db_model_mean']:>13.2f} / "
            f"{result['psnr']['psnr_db_baseline_mean']:.2f}",
        )
    contact = result["contact"]
    if "ssim_model_mean" in contact:
        lines.insert(
            -1,
            f"{'contact SSIM model / base':28s}{contact['ssim_model_mean']:>13.4f} / "
            f"{contact['ssim_baseline_mean']:.4f}  ratio {contact['dissimilarity_ratio']:.3f}, "
            f"p {contact['p_value_wilcoxon']:.1e}, {contact['n']} pairs",
        )
    for name, row in result["objects"].items():
        lines.insert(
            -1,
            f"{'  ' + name:28s}{row['ssim_model_mean']:>13.4f} / {row['ssim_baseline_mean']:.4f}  "
            f"ratio {row['dissimilarity_ratio']:.3f}, {row['n']} pairs",
        )
    undefined = [
        ("all pairs", result),
        ("contact windows", contact),
        *((f"object {name}", row) for name, row in result["objects"].items()),
    ]
    lines += [
        f"ratio undefined ({where}): {stats['dissimilarity_ratio_undefined']}"
        for where, stats in undefined
        if "dissimilarity_ratio_undefined" in stats
    ]
    if not any(m["distance_px"] is not None for m in result["template_match"]["per_sample"]):
        lines.append("template distance undefined: every template is flat (no correlation to locate)")
    if not result["objects"]:
        lines.append("per-object statistics: no object has 2 pairs")
    lines += uncertainty_table(result["uncertainty"]) if "uncertainty" in result else []
    lines += _density_lines(result)
    return "\n".join(lines)


def _density_lines(result: dict[str, Any]) -> list[str]:
    """The summary table's density rows: SSIM beside the paper's, PSNR, the contact windows and
    the bins holding a surface, then the full cloud's bins."""
    lines = []
    for row in result["density"]:
        paper = row["paper_ssim_mean"]
        lines.append(
            f"{'density ' + format(row['points_per_cm3'], 'g') + ' pts/cm3':28s}"
            f"{row['ssim_mean']:>13.4f} ± {row['ssim_se']:.4f}{'' if paper is None else format(paper, '>18.4f')}"
            + (f"   PSNR {row['psnr_db_mean']:.2f} dB" if "psnr_db_mean" in row else "")
            + (f"   contact {row['contact_ssim_mean']:.4f}" if "contact_ssim_mean" in row else "")
            + (f" (full cloud better: p {row['contact_p_full_better']:.1e})" if "contact_p_full_better" in row else "")
            + f"   surface bins {row['surface_bins_mean']:.0f}"
        )
    if result["density"]:  # evaluate() counts the full cloud's bins wherever it made density rows
        lines.append(f"{'surface bins, full cloud':28s}{result['surface_bins_mean']:>13.0f}")
    return lines
