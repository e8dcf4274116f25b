"""What the report's sweeps share: timing, SSIM against a session's truth, standard errors."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from dataset.images import resize_rgb
from models.evaluate import contact_ssim, contact_windows, ssim_statistics
from models.networks import UNetGenerator
from models.serving import predict
from perception.ssim import ssim_rgb
from report.ceiling import depth_map_images
from report.specs import PER_SESSION
from report.workspace import REFERENCE_SIZE, SessionTest, epoch_cpu_s
from workcell.scene import Scene


def median_cpu_ms(function: Callable[[], object], runs: int) -> float:
    """The median of ``runs`` calls' process CPU time (ms, every thread of the work counted):
    the report's time. On cores that other work shares, a wall clock times the sharing as much
    as the setting; the CPU a call spends is what it costs a machine that serves or collects."""
    spent = []
    for _ in range(runs):
        started = time.process_time()
        function()
        spent.append((time.process_time() - started) * 1e3)
    return statistics.median(spent)


def resize(images: np.ndarray, size: int) -> np.ndarray:
    return np.stack([resize_rgb(image, size, size) for image in images])


def session_scores(test: SessionTest, estimate: np.ndarray, no_contact: np.ndarray) -> dict[str, Any]:
    """SSIM of 100 x 100 estimates against the sessions' test truth on the contact windows
    (models.evaluate.contact_ssim: the accuracy these sweeps rank by) and over the whole
    image (the paper's figure, which a no-contact estimate scores well on). ``no_contact`` is
    the same model's estimate from an empty depth-map: a setting whose estimates do not beat
    it on the contact windows (one-sided Wilcoxon over the pairs, ``p_vs_no_contact``) gives
    the model nothing it uses. Of several sessions, each one's contact SSIM too (PER_SESSION,
    in the workspace's order)."""
    contact = contact_ssim(test.truth, test.deformation, estimate)
    floor = contact_ssim(test.truth, test.deformation, np.repeat(no_contact[None], len(test.truth), axis=0))
    whole = ssim_rgb(test.truth, estimate)
    better = stats.wilcoxon(contact, floor, alternative="greater").pvalue if np.any(contact != floor) else 1.0
    scores: dict[str, Any] = {
        "contact_ssim": float(contact.mean()),
        "contact_ssim_se": standard_error(contact),
        "contact_pairs": len(contact),
        "no_contact_ssim": round(float(floor.mean()), 4),
        "p_vs_no_contact": float(better),
        "ssim": round(float(whole.mean()), 4),
        "ssim_se": standard_error(whole),
    }
    if len(np.unique(test.session_of)) > 1:
        session_of = test.session_of[contact_windows(test.deformation)[0]]  # of the pairs that show contact
        of_each = [contact[session_of == s] for s in range(test.session_of.max() + 1)]
        scores[PER_SESSION] = " / ".join(f"{c.mean():.4f}" if len(c) else "no contact" for c in of_each)
    return scores


def no_contact_estimate(
    generator: UNetGenerator, depth_range: tuple[float, float], size: int, pose_sigma_mm: float | None = None
) -> np.ndarray:
    """The model's estimate (resized to 100 x 100) from a depth-map with nothing in reach,
    served with ``pose_sigma_mm`` (mm; None: the model's default)."""
    empty = np.full((1, size, size), depth_range[1], np.float32)
    return resize(predict(generator, empty, depth_range, pose_sigma_mm=pose_sigma_mm), REFERENCE_SIZE)[0]


def dissimilarity_ratio(test: SessionTest, estimate: np.ndarray) -> float:
    """The estimates' mean 1 - SSIM over a random pairing's, against the session's test truth
    (models.evaluate.ssim_statistics: how ``dtx evaluate`` scores a model; below 1 is better)."""
    return round(float(ssim_statistics(test.truth, estimate)["dissimilarity_ratio"]), 4)


def renderer_ratio(
    test: SessionTest, scene: Scene, depth_crop_m: Sequence[float] | None, depth_maps_m: np.ndarray
) -> dict[str, float]:
    """The test split's ``depth_maps_m`` (m) through the GelSight renderer, scored against the
    session's images as a model is (models.evaluate.ssim_statistics)."""
    assert depth_crop_m is not None  # a session records its crop (dataset.json)
    images = depth_map_images(scene, depth_maps_m, depth_crop_m, test.truth.shape[1:3])
    scores = ssim_statistics(test.truth, images)
    return {
        "renderer_ratio": round(float(scores["dissimilarity_ratio"]), 4),
        "renderer_ssim": round(float(scores["ssim_model_mean"]), 4),
    }


def epoch_s(model: Path) -> float:
    """The median epoch's CPU seconds: the first training of a process also pays start-up."""
    return float(statistics.median(epoch_cpu_s(model)))


def standard_error(values: np.ndarray) -> float:
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else float("nan")
