"""``pose_sigma_mm``: a planner says how sure the geometry it asks about is, and the inference
node renders the physics prior's image for that uncertainty — the image ``dtx evaluate``
gives the same depth-maps at the same uncertainty, the real presses included.

Weights: fresh seeded generators (ngf 8) in models/train.py's checkpoint format, correcting the
default scene's prior with a default uncertainty of 1 mm, as the demo's model does."""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from test_inference_node import fit_for_serving, planner, serving

from benchmarks.serve import depth_maps, write_checkpoint
from bus.inference_client import SERVICE, InferenceError
from bus.pubsub import Bus
from bus.registry import Registry
from bus.services import ServiceCallError
from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.prior import MAX_POSE_SIGMA_MM
from models.real_presses import evaluate_real_presses
from models.serving import prior_images
from msgs.inference import TactileEstimateReply, TactileEstimateRequest

PRESSES = Path(__file__).resolve().parent.parent / "assets" / "gelsight" / "ball_presses.npz"
DEFAULT_SIGMA_MM = 1.0


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A prior-correcting checkpoint whose depth-maps were, by default, 1 mm off in the gel plane."""
    path = tmp_path_factory.mktemp("sigma") / "prior.pt"
    return write_checkpoint(path, width=8, prior=True, pose_sigma_mm=DEFAULT_SIGMA_MM)


def reference(checkpoint: Path, maps: np.ndarray, pose_sigma_mm: float | None) -> np.ndarray:
    """The generator's own estimate (eager PyTorch, dropout off) at that uncertainty."""
    generator, depth_range_m = load_generator(checkpoint)
    with torch.inference_mode():
        x = network_input(maps, depth_range_m, generator.config, generator.prior, pose_sigma_mm)
        return to_uint8_rgb(generator(x))


def test_a_request_says_how_sure_its_geometry_is_and_the_reply_says_what_was_used(
    registry: Registry, checkpoint: Path
) -> None:
    maps = depth_maps(3, seed=7)
    with serving(registry, checkpoint, runtime="eager", threads=2), planner(registry) as client:
        exact, _ = client.estimate(maps, pose_sigma_mm=0.0)
        assert client.last_reply is not None and client.last_reply.pose_sigma_mm == 0.0
        default, _ = client.estimate(maps)
        assert client.last_reply.pose_sigma_mm == DEFAULT_SIGMA_MM
        unsure, _ = client.estimate(maps, pose_sigma_mm=2.5)
        assert client.last_reply.pose_sigma_mm == 2.5
        at_poses, _ = client.estimate_at(np.zeros((1, 3)), np.eye(4)[None], pose_sigma_mm=0.0)
        assert client.last_reply.pose_sigma_mm == 0.0 and at_poses.shape == (1, 100, 100, 3)
    np.testing.assert_array_equal(exact, reference(checkpoint, maps, 0.0))
    np.testing.assert_array_equal(default, reference(checkpoint, maps, DEFAULT_SIGMA_MM))
    np.testing.assert_array_equal(unsure, reference(checkpoint, maps, 2.5))
    # The uncertainty reaches the image: a sharp prior is another input than a blurred one.
    assert np.abs(exact.astype(int) - default).max() > 10


@pytest.mark.parametrize(("max_batch", "expected_passes"), [(8, {1}), (3, {2, 3})])
def test_requests_of_different_uncertainty_share_a_forward_pass_and_keep_their_own(
    registry: Registry, checkpoint: Path, max_batch: int, expected_passes: set[int]
) -> None:
    """Three clients' two regions each, of three uncertainties, in one pass; and in passes of
    three, where a request is split between passes and each pass's input is drawn while the
    network runs the one before: every region keeps its own request's prior. (With passes of
    three the batch starts once two requests wait: the third may join it, 2 passes, or follow
    it, 2 + 1.)"""
    maps = depth_maps(2, seed=8)
    sigmas = {"sharp": 0.0, "default": None, "blurred": 2.0}
    replies: dict[str, np.ndarray] = {}
    with serving(registry, checkpoint, runtime="eager", batch_window_ms=1500.0, max_batch=max_batch) as node:
        ready = threading.Barrier(len(sigmas))

        def ask(name: str) -> None:
            with planner(registry, name) as client:
                assert client.client.wait_for_service(30.0)
                ready.wait()
                replies[name] = client.estimate(maps, pose_sigma_mm=sigmas[name])[0]

        threads = [threading.Thread(target=ask, args=(name,)) for name in sigmas]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        passes = node.forward_passes
    assert passes in expected_passes
    for name, sigma in sigmas.items():
        np.testing.assert_array_equal(replies[name], reference(checkpoint, maps, sigma))


def test_a_checkpoint_serving_its_prior_draws_it_at_the_requests_uncertainty(
    registry: Registry, tmp_path: Path
) -> None:
    """serves "prior": the prior's image at the pose_sigma_mm asked (or the checkpoint's default),
    as models.serving draws it, with its uncertainty and no network pass."""
    path = write_checkpoint(tmp_path / "prior.pt", width=8, prior=True, pose_sigma_mm=DEFAULT_SIGMA_MM)
    checkpoint = fit_for_serving(path, serves="prior")
    maps = depth_maps(2, seed=10)
    generator, depth_range_m = load_generator(checkpoint)

    def prior_at(sigma: float) -> np.ndarray:
        x = network_input(maps, depth_range_m, generator.config, generator.prior, sigma)
        return to_uint8_rgb(prior_images(generator, x))

    with serving(registry, checkpoint, runtime="eager") as node, planner(registry) as client:
        exact, u_exact = client.estimate(maps, pose_sigma_mm=0.0)
        assert client.last_reply is not None and client.last_reply.pose_sigma_mm == 0.0
        default, u_default = client.estimate(maps)
        assert client.last_reply.pose_sigma_mm == DEFAULT_SIGMA_MM and client.last_reply.serves == "prior"
        passes = node.forward_passes
    assert passes == 0
    np.testing.assert_array_equal(exact, prior_at(0.0))
    np.testing.assert_array_equal(default, prior_at(DEFAULT_SIGMA_MM))
    assert np.abs(exact.astype(int) - default).max() > 10
    assert u_exact is not None and u_default is not None and not np.array_equal(u_exact, u_default)


@pytest.mark.parametrize("sigma", [MAX_POSE_SIGMA_MM + 0.5, 1e9])
def test_an_uncertainty_beyond_the_bound_is_a_bad_request_naming_the_field(
    registry: Registry, checkpoint: Path, sigma: float
) -> None:
    with serving(registry, checkpoint), contextlib.closing(Bus("planner", registry)) as bus:
        raw = bus.client(SERVICE, TactileEstimateRequest, TactileEstimateReply)
        with pytest.raises(ServiceCallError, match="pose_sigma_mm must be a finite number of mm <= 5") as refused:
            raw.call(TactileEstimateRequest(depth_maps=depth_maps(1, seed=1), pose_sigma_mm=sigma), timeout_s=30.0)
        assert refused.value.code == "bad_request"
        reply = raw.call(TactileEstimateRequest(depth_maps=depth_maps(1, seed=1), pose_sigma_mm=-3.0), timeout_s=30.0)
        assert reply.pose_sigma_mm == DEFAULT_SIGMA_MM  # negative: the checkpoint's default


def test_a_model_without_a_prior_takes_every_depth_map_as_it_is(registry: Registry, tmp_path: Path) -> None:
    plain = write_checkpoint(tmp_path / "plain.pt", width=8)
    maps = depth_maps(2, seed=9)
    with serving(registry, plain, runtime="eager"), planner(registry) as client:
        exact, _ = client.estimate(maps, pose_sigma_mm=0.0)
        assert client.last_reply is not None and client.last_reply.pose_sigma_mm == -1.0
        default, _ = client.estimate(maps)
        with pytest.raises(InferenceError, match="pose_sigma_mm") as refused:
            client.estimate(maps, pose_sigma_mm=MAX_POSE_SIGMA_MM * 2)
    np.testing.assert_array_equal(exact, default)
    assert refused.value.code == "bad_request"


@pytest.mark.parametrize(("runtime", "tolerance"), [("eager", 0), ("onnxrt", 1)])
def test_the_served_path_gives_the_real_presses_the_image_dtx_evaluate_scores(
    registry: Registry, checkpoint: Path, runtime: str, tolerance: int
) -> None:
    """``dtx evaluate --real-presses`` feeds each press's depth-map to the model with exact
    geometry; a planner asking the node about the same depth-maps with pose_sigma_mm 0 gets the
    same images (byte for byte in eager PyTorch; ONNX Runtime may round a pixel the other way).
    At the checkpoint's default it does not: that blur is what the served path scored before."""
    generator, depth_range_m = load_generator(checkpoint)
    _, images = evaluate_real_presses(generator, depth_range_m, PRESSES)
    maps = images["depth_maps_m"].astype(np.float32)
    assert np.array_equal(maps, images["depth_maps_m"])  # the node's wire type loses nothing
    with serving(registry, checkpoint, runtime=runtime, threads=2), planner(registry) as client:
        served, _ = client.estimate(maps, pose_sigma_mm=0.0)
        blurred, _ = client.estimate(maps)
    assert served.shape == images["model"].shape == (len(images["truth"]), 100, 100, 3)
    assert np.abs(served.astype(int) - images["model"]).max() <= tolerance
    assert np.abs(blurred.astype(int) - images["model"]).max() > 10
