"""The sweeps on what the session model serves, through the path a planner calls
(models.serving.predict_served) on the collected session's test split: the uncertainty served
beside the estimate (the checkpoint's learned one against dropout sampling: how well it predicts
the error, and what it adds to the time), and the forms that could serve (the physics prior
alone, the network), each with and without that uncertainty."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.errors import ModelConfigError
from models.networks import UNetGenerator
from models.runtime import sampling_copy
from models.serving import predict_served, served_images
from models.uncertainty import LEVELS_PER_TANH_UNIT, UNCERTAINTY_ABSENT, uncertainty_statistics
from perception.ssim import ssim_rgb
from report.specs import Point, point
from report.sweeps.common import dissimilarity_ratio, median_cpu_ms, no_contact_estimate, session_scores
from report.workspace import REFERENCE_SIZE, SessionTest, Workspace

# Regions a forward pass: predict_served's default, as the inference node batches a request.
SERVING_BATCH = 64
TIMED_RUNS = 3
LEARNED = "learned (served)"
FORMS = {"prior": "prior alone", "network": "network"}


@contextlib.contextmanager
def serving_as(generator: UNetGenerator, serves: str, uncertainty: Any) -> Iterator[UNetGenerator]:
    """``generator`` serving ``serves`` with ``uncertainty`` beside it (None: without), as
    models.serving.predict_served reads them; what the checkpoint set is restored after."""
    saved = generator.serves, generator.uncertainty
    generator.serves, generator.uncertainty = serves, uncertainty
    try:
        yield generator
    finally:
        generator.serves, generator.uncertainty = saved


class DropoutSpread:
    """The uncertainty the inference node served before protocol v4, answered as a
    models.uncertainty.ServedUncertainty is (:meth:`levels`), so that predict_served times and
    serves it the same way: per pixel, the standard deviation of ``samples`` passes of the
    generator's sampling copy (models.runtime.sampling_copy), image levels, the channels' mean."""

    def __init__(self, generator: UNetGenerator, samples: int) -> None:
        self.sampled, self.samples = sampling_copy(generator), samples

    @torch.inference_mode()
    def levels(self, network_input: torch.Tensor, estimate: torch.Tensor, sensor_floor: bool = True) -> np.ndarray:
        """N x H x W float32 spread (levels) for ``network_input``; ``estimate`` is not needed, nor
        ``sensor_floor``: the spread had no sensor's floor."""
        passes = torch.stack([self.sampled(network_input) for _ in range(self.samples)])
        return (passes.std(dim=0).mean(dim=1) * LEVELS_PER_TANH_UNIT).float().numpy()


def uncertainty(ws: Workspace) -> list[Point]:
    """The session model's served estimate and, beside it, its learned uncertainty u (what a
    planner receives) or the spread of S dropout passes -> accuracy = Pearson r(u, e) per pixel,
    e = |estimate - truth| (levels, the channels' mean); time = ms per region of the uncertainty's
    own pass over the served estimate's input and image (timed alone: the difference of two timed
    estimates is noise on a loaded machine, even below zero)."""
    test = ws.session_test
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    depth = test.depth_maps(ws.sessions)
    learned = generator.uncertainty
    with serving_as(generator, generator.serves, None):
        estimate_ms = median_cpu_ms(lambda: predict_served(generator, depth, depth_range, SERVING_BATCH), TIMED_RUNS)
    x = network_input(depth, depth_range, generator.config, generator.prior)
    batches = [slice(i, i + SERVING_BATCH) for i in range(0, len(x), SERVING_BATCH)]
    with torch.inference_mode():
        served = [served_images(generator, x[b], generator.serves) for b in batches]
    # The served estimate as predict_served answers it: the same batches, to uint8 one by one.
    estimate = np.concatenate([to_uint8_rgb(image) for image in served])
    dissimilarity = 1.0 - ssim_rgb(test.truth, estimate)
    points = []
    if learned is None:
        points.append(point("uncertainty", LEARNED, math.nan, None, refused=UNCERTAINTY_ABSENT))
    spreads = [(LEARNED, learned)] if learned is not None else []
    spreads += [(f"dropout {s} samples", DropoutSpread(generator, s)) for s in ws.plan.dropout_samples]
    for setting, spread in spreads:
        torch.manual_seed(ws.plan.seed)  # the dropout passes draw their masks from torch's generator
        with serving_as(generator, generator.serves, spread):
            levels = predict_served(generator, depth, depth_range, SERVING_BATCH)[1]
        assert levels is not None  # served beside the estimate: the spread was set just above
        with torch.inference_mode():
            spread_ms = median_cpu_ms(lambda: [spread.levels(x[b], im) for b, im in zip(batches, served)], TIMED_RUNS)
        figures = uncertainty_statistics(levels, estimate, test.truth, dissimilarity)
        points.append(
            point(
                "uncertainty",
                setting,
                spread_ms / len(depth),
                figures["pearson_pixel"],
                region_r=round(figures["pearson_region"], 4),
                decile_ratio_min=round(figures["decile_ratio_min"], 3),
                decile_ratio_max=round(figures["decile_ratio_max"], 3),
                u_mean_levels=round(figures["u_mean_levels"], 3),
                estimate_ms=round(estimate_ms / len(depth), 3),
            )
        )
    return points


def serving(ws: Workspace) -> list[Point]:
    """The forms that could serve the session model's estimate (the physics prior alone, its
    network), each with the checkpoint's uncertainty and without -> contact SSIM on the session's
    test split; time = ms per region from the depth-maps through predict_served, 64 regions a
    pass, on torch's current threads. ``served`` marks what the checkpoint serves."""
    test = ws.session_test
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    depth = test.depth_maps(ws.sessions)
    learned = generator.uncertainty
    points = []
    for serves, form in FORMS.items():
        for with_uncertainty in (True, False):
            setting = f"{form} {'with' if with_uncertainty else 'without'} uncertainty"
            served = serves == generator.serves and with_uncertainty == (learned is not None)
            if with_uncertainty and learned is None:
                points.append(point("serving", setting, math.nan, None, served=served, refused=UNCERTAINTY_ABSENT))
                continue
            with serving_as(generator, serves, learned if with_uncertainty else None):
                points.append(_form_point(test, generator, depth, depth_range, setting, served))
    return points


def _form_point(
    test: SessionTest,
    generator: UNetGenerator,
    depth: np.ndarray,
    depth_range: tuple[float, float],
    setting: str,
    served: bool,
) -> Point:
    """The serving sweep's point for ``generator`` as it serves now; refused (accuracy NaN, the
    reason given) where it cannot serve that form (a prior it does not have)."""
    try:
        estimate = predict_served(generator, depth, depth_range, SERVING_BATCH)[0]
    except ModelConfigError as err:
        return point("serving", setting, math.nan, None, served=served, refused=str(err))
    ms = median_cpu_ms(lambda: predict_served(generator, depth, depth_range, SERVING_BATCH), TIMED_RUNS) / len(depth)
    scores = session_scores(test, estimate, no_contact_estimate(generator, depth_range, REFERENCE_SIZE))
    return point(
        "serving",
        setting,
        ms,
        scores.pop("contact_ssim"),
        dissimilarity_ratio=dissimilarity_ratio(test, estimate),
        regions_per_s=round(1e3 / ms, 1),
        threads=torch.get_num_threads(),
        served=served,
        **scores,
    )
