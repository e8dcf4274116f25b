"""``dtx bench serve --forms``: one trained checkpoint served in each of its forms, side by side
in one run (issue 49: what the estimate's cost buys). Each form runs the whole benchmark
(benchmarks.serve) through its own node; with ``--dataset`` each form's accuracy is measured on
the test split through models.serving.predict_served, the path the node serves."""

from __future__ import annotations

import argparse
import statistics
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.checkpoint import load_generator
from models.evaluate import contact_ssim_statistics, predict_dataset, ssim_statistics
from models.serving import SERVING_ENTRIES
from models.uncertainty import served_uncertainty_statistics

# What a checkpoint can be served as, side by side in one run (``--forms``): ``before``, the
# checkpoint as one trained before issue 49 serves it (its network, no uncertainty: its serving
# entries removed); ``network``, its network with the uncertainty; ``served``, the checkpoint's own choice.
FORMS = ("before", "network", "served")


def run_forms(
    args: argparse.Namespace, run_form: Callable[[argparse.Namespace, dict[str, Any]], dict[str, Any]]
) -> dict[str, Any]:
    """``run_form`` (the benchmark with these node params) once per form of ``args.forms``, with
    each form's accuracy on ``args.dataset`` where given, and the side-by-side table."""
    if not args.checkpoint:
        raise SystemExit("dtx bench serve: --forms compares what a trained --checkpoint serves")
    forms: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="dtxforms") as tmp:
        state = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
        before = Path(tmp) / "before.pt"
        torch.save({k: v for k, v in state.items() if k not in SERVING_ENTRIES}, before)
        for form in args.forms:
            checkpoint = str(before) if form == "before" else args.checkpoint
            params = {"serves": "network"} if form == "network" else {}
            form_args = argparse.Namespace(**{**vars(args), "checkpoint": checkpoint})
            forms[form] = run_form(form_args, params)
            if args.dataset:
                forms[form]["accuracy"] = _form_accuracy(Path(checkpoint), params.get("serves", ""), args.dataset)
    return {"forms": forms, "side_by_side": _side_by_side(forms)}


def _form_accuracy(checkpoint: Path, serves: str, dataset: str) -> dict[str, Any]:
    """The served estimates' figures on ``dataset``'s test split, as the node serving ``checkpoint``
    (``serves``: "" for its own choice) answers them: models.serving.predict_served."""
    generator, depth_range_m = load_generator(checkpoint)
    generator.serves = serves or generator.serves
    predictions = predict_dataset(generator, depth_range_m, dataset)
    whole = ssim_statistics(predictions.truth, predictions.estimate)
    contact = contact_ssim_statistics(predictions.truth, predictions.truth_deformation, predictions.estimate)
    accuracy = {
        "serves": generator.serves,
        "n": whole["n"],
        "ssim_mean": round(whole["ssim_model_mean"], 5),
        "dissimilarity_ratio": round(whole["dissimilarity_ratio"], 5),
        "contact_dissimilarity_ratio": round(contact.get("dissimilarity_ratio", float("nan")), 5),
    }
    figures = served_uncertainty_statistics(
        predictions.uncertainty, predictions.estimate, predictions.truth, 1.0 - np.asarray(whole["ssim_model"])
    )
    kept = ("pearson_pixel", "pearson_region", "decile_ratio_min", "decile_ratio_max")
    return accuracy | {k: figures[k] for k in kept if k in figures}


def _side_by_side(forms: dict[str, Any]) -> dict[str, Any]:
    """Per form its cloud-form rate (the median over the points rows), its server CPU a region and
    its accuracy; and each form's rate over ``before``'s, measured in the same run."""
    table: dict[str, Any] = {}
    for form, result in forms.items():
        rows = result.get("points", [])
        table[form] = {
            "model": result["model"],
            "handle_regions_per_s": statistics.median(r["handle_regions_per_s"] for r in rows) if rows else None,
            "handle_server_cpu_ms_per_region": (
                statistics.median(r["handle_server_cpu_ms_per_region"] for r in rows) if rows else None
            ),
            "regions_per_s": result["regions_per_s"],
            **{k: v for k, v in result.get("accuracy", {}).items() if k != "n"},
        }
    if "before" in table and table["before"]["handle_regions_per_s"]:
        for row in table.values():
            if row["handle_regions_per_s"]:
                row["handle_over_before"] = round(
                    row["handle_regions_per_s"] / table["before"]["handle_regions_per_s"], 2
                )
    return table
