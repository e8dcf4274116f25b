"""What a checkpoint serves, and the uncertainty served with it (``dtx train`` fits both at
its end; ``dtx fit-serving CHECKPOINT`` fits them for a checkpoint trained before).

- ``serves``: ``network`` (the generator's image) or ``prior`` (the physics prior's image, as
  the generator draws it with no correction). A generator held to its prior can return the
  prior's image on nearly every pixel (the demo's model: 99.989 %) at three quarters of the
  inference node's time. The network is served where it measurably helps: its validation SSIM
  above the prior's by more than two standard errors of the paired difference. A generator
  without a prior (the paper's configuration) always serves the network.
- ``uncertainty``: models.uncertainty, fitted on the training split's residuals of what is
  served and calibrated on the validation split's.

Both are checkpoint entries; a checkpoint without them serves its network, its uncertainty
absent (never zeros passed off as certain). :func:`predict_served` answers depth-maps as the
inference node does, for the evaluations (``dtx evaluate``, the real presses, the reports).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.checkpoint import SERVES, load_checkpoint, load_generator, save_atomic
from models.data import network_input, to_uint8_rgb
from models.errors import ModelConfigError
from models.networks import UNetGenerator
from models.pairs import PairCache, PairSet
from models.sessions import Session, checkpoint_sessions, open_sessions, session_paths, session_sources
from models.uncertainty import UncertaintyConfig, fit_uncertainty, pixel_error_levels
from perception.ssim import ssim_rgb

# The checkpoint entries fit_serving writes: without them a checkpoint is one trained before.
SERVING_ENTRIES = ("serves", "serving_figures", "uncertainty")
# How many standard errors of the paired SSIM difference the network must lead the prior by on
# the validation split to be served.
NETWORK_LEAD_SE = 2.0
# The most pairs of each split the fit holds at once (drawn seeded where a lab's sessions have
# more): a demo-size session's train and validation splits, so such a session fits on all of its
# pairs and ten sessions in the same memory (at 2,048 and 1,024, ten sessions' dtx train peaked
# 1,146 MiB above one's: dtx bench train).
FIT_TRAIN_PAIRS = 1680
FIT_VAL_PAIRS = 360
BATCH = 64


def prior_images(generator: UNetGenerator, network_input: torch.Tensor) -> torch.Tensor:
    """The physics prior's images (N x 3 x H x W, [-1, 1]) carried in ``network_input``, as the
    generator draws them where its correction is zero (its output adds the correction to the
    prior's atanh of the same clamp)."""
    if not generator.config.prior:
        raise ModelConfigError("this generator has no physics prior to serve")
    return network_input[:, generator.config.in_channels :].clamp(-0.99, 0.99)


@torch.no_grad()
def served_images(generator: UNetGenerator, network_input: torch.Tensor, serves: str) -> torch.Tensor:
    """What a checkpoint serving ``serves`` answers for ``network_input``: N x 3 x H x W in [-1, 1]."""
    if serves == "prior":
        return prior_images(generator, network_input)
    if serves != "network":
        raise ModelConfigError(f"serves must be one of {', '.join(SERVES)}, got {serves!r}")
    generator.eval()
    return torch.cat([generator(network_input[i : i + BATCH]) for i in range(0, len(network_input), BATCH)])


# Most regions one forward pass of predict takes: as many as the inference node takes in one
# request (its max_regions), so that evaluation needs no more memory than serving.
MAX_PREDICT_BATCH = 256


def predict(
    generator: UNetGenerator,
    depth_maps_m: np.ndarray,
    depth_range_m: tuple[float, float],
    batch: int = 64,
    pose_sigma_mm: float | None = None,
) -> np.ndarray:
    """N x H x W depth-maps (m) -> N x H x W x 3 uint8 estimates: :func:`predict_served`'s images."""
    return predict_served(generator, depth_maps_m, depth_range_m, batch, pose_sigma_mm)[0]


@torch.no_grad()
def predict_served(
    generator: UNetGenerator,
    depth_maps_m: np.ndarray,
    depth_range_m: tuple[float, float],
    batch: int = 64,
    pose_sigma_mm: float | None = None,
    sensor_floor: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """N x H x W depth-maps (m) -> what the checkpoint serves (``generator.serves``: its
    network's or its prior's image), N x H x W x 3 uint8, and the uncertainty served beside it (N x H x W
    float32, image levels; None when the checkpoint has none). ``pose_sigma_mm``: the maps'
    in-plane pose error for a physics prior (None: the model's default, its training session's).
    ``batch``: regions a forward pass, an integer in [1, MAX_PREDICT_BATCH]; otherwise
    ModelConfigError. ``sensor_floor`` False: the checkpoint's own u, without the floor of a lab's
    sensor (models.sensor_floor) that it may carry."""
    if not (isinstance(batch, (int, np.integer)) and not isinstance(batch, bool) and 1 <= batch <= MAX_PREDICT_BATCH):
        raise ModelConfigError(f"batch must be an integer in [1, {MAX_PREDICT_BATCH}], got {batch!r}")
    generator.eval()
    x = network_input(depth_maps_m, depth_range_m, generator.config, generator.prior, pose_sigma_mm)
    images, uncertainty = [], []
    for i in range(0, len(x), batch):
        estimate = served_images(generator, x[i : i + batch], generator.serves)
        images.append(to_uint8_rgb(estimate))
        if generator.uncertainty is not None:
            uncertainty.append(generator.uncertainty.levels(x[i : i + batch], estimate, sensor_floor))
    return np.concatenate(images), (np.concatenate(uncertainty) if uncertainty else None)


def choose_served(
    generator: UNetGenerator, x_val: torch.Tensor, y_val: torch.Tensor
) -> tuple[str, dict[str, float], torch.Tensor]:
    """``network`` where it leads the prior on the validation pairs by more than NETWORK_LEAD_SE
    standard errors of the paired SSIM difference, else ``prior``; the figures that decided; and
    the chosen form's images of the validation pairs."""
    if len(y_val) < 2:
        raise ModelConfigError(f"choosing what is served needs at least 2 validation pairs, got {len(y_val)}")
    network_images = served_images(generator, x_val, "network")
    if not generator.config.prior:
        return "network", {}, network_images
    prior_images_val = prior_images(generator, x_val)
    truth = to_uint8_rgb(y_val)
    network = ssim_rgb(truth, to_uint8_rgb(network_images))
    prior = ssim_rgb(truth, to_uint8_rgb(prior_images_val))
    lead = network - prior
    se = float(lead.std(ddof=1) / np.sqrt(len(lead)))
    figures = {
        "val_ssim_network": float(network.mean()),
        "val_ssim_prior": float(prior.mean()),
        "network_lead": float(lead.mean()),
        "network_lead_se": se,
    }
    if lead.mean() > NETWORK_LEAD_SE * se:
        return "network", figures, network_images
    return "prior", figures, prior_images_val


def _fit_pairs(
    sessions: Sequence[Session],
    split: str,
    hold_out: str,
    generator: UNetGenerator,
    most: int,
    pose_sigmas_mm: Sequence[float | None],
) -> tuple[torch.Tensor, torch.Tensor]:
    """At most ``most`` pairs of ``split`` over ``sessions`` (seeded), at once."""
    sources = session_sources(sessions, split, hold_out, generator.config, generator.prior, pose_sigmas_mm)
    return PairSet(sources, generator.config.in_channels, PairCache(0)).subset(most, seed=0).tensors()


def fit_serving(
    checkpoint: str | os.PathLike[str],
    dataset: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None = None,
    config: UncertaintyConfig = UncertaintyConfig(),
    log: Callable[[str], None] = lambda line: print(line, file=sys.stderr),
) -> dict[str, Any]:
    """Choose what ``checkpoint`` serves and fit its uncertainty on ``dataset`` (one session or
        several; default: the sessions it was trained on, or the single ``dataset`` a checkpoint from
        before sessions names; their train split fits, their validation split chooses and calibrates:
    at most FIT_TRAIN_PAIRS and FIT_VAL_PAIRS of them, drawn seeded), and
        write both into the checkpoint (atomically: a failure leaves it as it was). Returns the
        figures that decided."""
    path = Path(checkpoint)
    state = load_checkpoint(path)
    generator, depth_range_m = load_generator(path)
    roots = checkpoint_sessions(state) if dataset is None else session_paths(dataset)
    if not roots:
        raise ModelConfigError(f"{path} does not name its dataset: give the dataset to fit on")
    sessions = open_sessions(roots, depth_range_m)
    hold_out = state["train_config"].get("hold_out_object", "")
    # The sessions it was trained on, each with the pose error its prior was blurred by.
    sigmas = [entry.get("pose_sigma_mm") for entry in state.get("sessions", [])] if dataset is None else []
    x_train, y_train = _fit_pairs(sessions, "train", hold_out, generator, FIT_TRAIN_PAIRS, sigmas)
    x_val, y_val = _fit_pairs(sessions, "val", hold_out, generator, FIT_VAL_PAIRS, sigmas)
    serves, figures, estimate_val = choose_served(generator, x_val, y_val)
    log(f"serves the {serves}: {', '.join(f'{k} {v:.4f}' for k, v in figures.items())}")
    estimate_train = served_images(generator, x_train, serves)
    error_train = pixel_error_levels(to_uint8_rgb(estimate_train), to_uint8_rgb(y_train))
    error_val = pixel_error_levels(to_uint8_rgb(estimate_val), to_uint8_rgb(y_val))
    uncertainty = fit_uncertainty(
        x_train, estimate_train, torch.from_numpy(error_train), x_val, estimate_val, error_val, config, log
    )
    if "sensor_floor" in state.get("uncertainty", {}):
        log("the lab's sensor floor goes with the u it was fitted beside: dtx calibrate uncertainty fits it again")
    state |= {"serves": serves, "serving_figures": figures, "uncertainty": uncertainty.to_state()}
    save_atomic(state, path)
    return {"serves": serves, **figures}
