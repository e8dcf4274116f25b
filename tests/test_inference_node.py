"""The inference server node in this process: replies, what a checkpoint serves (its network
or its prior) and the uncertainty served with it, the points path, bad requests, and batching
across clients. Weights: a tiny untrained generator (ngf 8) saved in models/train.py's
checkpoint format, given an untrained uncertainty network where a test needs one."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import msgs
from benchmarks.serve import depth_maps, write_checkpoint
from bus.inference_client import SERVICE, Cloud, InferenceError, TactileClient
from bus.pubsub import Bus
from bus.registry import Registry
from bus.services import ServiceCallError
from models.checkpoint import TrainConfig, load_checkpoint, load_generator, save_atomic
from models.data import network_input, to_uint8_rgb
from models.networks import UNetGenerator
from models.runtime import cuda_missing, onnx_graph, onnx_runner
from models.serving import prior_images
from models.uncertainty import Calibration, ServedUncertainty, UncertaintyConfig, UncertaintyNet
from msgs.inference import TactileEstimateReply, TactileEstimateRequest
from nodes.inference import InferenceNode, cloud_id
from nodes.inference_passes import ThreadSplit
from perception.depthmap import DepthMapParams, contact_depth_map
from workcell.scene import load_scene


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", width=8)


def fit_for_serving(path: Path, serves: str = "", seed: int = 0) -> Path:
    """The checkpoint at ``path`` with what ``dtx fit-serving`` adds: an uncertainty (an untrained
    network of width 4, its calibration a scale of 1) and, when given, what it serves."""
    state = load_checkpoint(path)
    torch.manual_seed(seed)
    channels = TrainConfig.from_dict(state["train_config"]).generator.input_channels
    uncertainty = ServedUncertainty(
        UncertaintyNet(channels, width=4), Calibration((1.0,), (1.0,)), UncertaintyConfig(width=4)
    )
    state["uncertainty"] = uncertainty.to_state()
    if serves:
        state["serves"] = serves
    save_atomic(state, path)
    return path


@contextlib.contextmanager
def serving(registry: Registry, checkpoint: Path, **params: Any) -> Iterator[InferenceNode]:
    """The node on the CPU unless a test names its device: the node's default (auto) would serve
    on a GPU host's CUDA, in another arithmetic than the CPU references here and in one pass at
    a time, where the CPU's lanes split a request."""
    node = InferenceNode(
        "inference", {"checkpoint": str(checkpoint), "threads": 1, "device": "cpu", **params}, registry=registry
    )
    thread = threading.Thread(target=node.spin)
    thread.start()
    try:
        yield node
    finally:
        node.request_shutdown()
        thread.join()
        node.close()


@contextlib.contextmanager
def planner(registry: Registry, name: str = "planner") -> Iterator[TactileClient]:
    with contextlib.closing(Bus(name, registry)) as bus, TactileClient(bus, timeout_s=30.0) as client:
        yield client


def reference(checkpoint: Path, maps: np.ndarray) -> np.ndarray:
    """The generator's own estimate (eager PyTorch, dropout off)."""
    generator, depth_range_m = load_generator(checkpoint)
    with torch.inference_mode():
        return to_uint8_rgb(generator(network_input(maps, depth_range_m, generator.config, generator.prior)))


def served_reference(
    checkpoint: Path, maps: np.ndarray, serves: str, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """What a checkpoint serving ``serves`` answers, computed here on ``device``: its images (the
    generator's in eager PyTorch, or the prior's as models.serving draws them) and their
    uncertainty u."""
    generator, depth_range_m = load_generator(checkpoint)
    assert generator.uncertainty is not None
    prior = None if generator.prior is None else generator.prior.on(device)
    with torch.inference_mode():
        x = network_input(maps, depth_range_m, generator.config, prior).to(device)
        estimate = prior_images(generator, x) if serves == "prior" else generator.to(device)(x)
        return to_uint8_rgb(estimate.cpu()), generator.uncertainty.to(device).levels(x, estimate)


@pytest.mark.parametrize("runtime", ["onnxrt", "eager"])
def test_estimates_are_the_generators_and_deterministic_and_an_old_checkpoints_uncertainty_is_absent(
    registry: Registry, checkpoint: Path, runtime: str
) -> None:
    """A checkpoint trained before the uncertainty serves its network and says its uncertainty is
    absent: an empty array and no region means, never zeros passed off as certain."""
    maps = depth_maps(3, seed=1)
    with serving(registry, checkpoint, runtime=runtime), planner(registry) as client:
        images, uncertainty = client.estimate(maps)
        again, _ = client.estimate(maps)
        reply = client.last_reply
    assert reply is not None
    assert images.shape == (3, 100, 100, 3) and images.dtype == np.uint8
    assert uncertainty is None and reply.uncertainty_status == "absent" and reply.region_uncertainty == []
    assert reply.uncertainty.shape == (0, 100, 100) and reply.uncertainty.dtype == np.float32
    assert reply.serves == "network"
    np.testing.assert_array_equal(images, again)
    # ONNX Runtime may round a few pixels the other way.
    assert np.abs(images.astype(int) - reference(checkpoint, maps)).max() <= 1
    assert "tiny.pt" in reply.model and runtime in reply.model
    assert "serves the network (its uncertainty absent) on inference" in reply.model


def test_int8_serves_the_graph_with_the_encoder_quantised(registry: Registry, checkpoint: Path) -> None:
    """The node answers with models.runtime's int8 graph, calibrated as anyone calibrates it,
    when told to take whatever int8 loses (this untrained one loses much: the node's default
    serves it in fp32, tests/test_inference_device.py)."""
    maps = depth_maps(3, seed=4)
    generator, depth_range_m = load_generator(checkpoint)
    graph = onnx_runner(onnx_graph(generator, depth_range_m, "int8"), threads=1)
    expected = to_uint8_rgb(
        torch.from_numpy(graph(network_input(maps, depth_range_m, generator.config, generator.prior).numpy()))
    )
    with serving(registry, checkpoint, precision="int8", int8_max_ssim_loss=1.0), planner(registry) as client:
        images, _ = client.estimate(maps)
        model = client.last_reply.model if client.last_reply else ""
    np.testing.assert_array_equal(images, expected)
    assert "onnxrt int8" in model


@pytest.mark.parametrize(
    ("runtime", "precision"), [("eager", "int8"), ("onnxrt", "bf16"), ("onnxrt", "fp16"), ("tensorrt", "fp32")]
)
def test_a_runtime_and_precision_that_do_not_go_together_are_refused(
    checkpoint: Path, tmp_path: Path, runtime: str, precision: str
) -> None:
    params = {"checkpoint": str(checkpoint), "runtime": runtime, "precision": precision}
    with pytest.raises(ValueError, match=f"runtime '{runtime}' with precision '{precision}' is not offered"):
        InferenceNode("refused", params, registry=Registry(tmp_path / "bus"))


@pytest.mark.parametrize(
    ("param", "value", "named"),
    [("max_batch", -1, "max_batch >= 0"), ("threads", 0, "threads, max_regions"), ("batch_window_ms", -1.0, "batch")],
)
def test_bad_limits_are_refused_naming_them(
    checkpoint: Path, tmp_path: Path, param: str, value: float, named: str
) -> None:
    with pytest.raises(ValueError, match=named):
        InferenceNode("refused", {"checkpoint": str(checkpoint), param: value}, registry=Registry(tmp_path / "bus"))


def test_passes_default_to_the_devices_width_and_each_thread_runs_a_pass_on_the_cpu(
    registry: Registry, tmp_path: Path
) -> None:
    prior = write_checkpoint(tmp_path / "prior.pt", width=8, prior=True)
    with serving(registry, prior, device="cpu", threads=4) as node:
        assert (node.max_batch, node.split) == (
            8,
            ThreadSplit(lanes=4, lane_threads=1, input_threads=1, input_in_lanes=True),
        )
    plain = write_checkpoint(tmp_path / "plain.pt", width=8)
    with serving(registry, plain, device="cpu", threads=4, max_batch=5) as node:
        assert (node.max_batch, node.split) == (
            5,
            ThreadSplit(lanes=4, lane_threads=1, input_threads=1, input_in_lanes=True),
        )


def test_a_generator_that_corrects_the_physics_prior_is_served_with_it(registry: Registry, tmp_path: Path) -> None:
    checkpoint = write_checkpoint(tmp_path / "prior.pt", width=8, prior=True)
    maps = depth_maps(3, seed=2)
    # Two threads: the prior's images of the three maps are rendered in two chunks.
    with serving(registry, checkpoint, threads=2), planner(registry) as client:
        images, _ = client.estimate(maps)
    assert np.abs(images.astype(int) - reference(checkpoint, maps)).max() <= 1


@pytest.mark.parametrize("prior", [False, True], ids=["plain", "prior"])
def test_a_checkpoint_with_an_uncertainty_serves_it_in_every_reply(
    registry: Registry, tmp_path: Path, prior: bool
) -> None:
    """No option asked: u per pixel, finite and positive, the checkpoint's own uncertainty of the
    pass's input and the served estimate (passes of 2: u follows its region across passes), and
    each region's mean u."""
    checkpoint = fit_for_serving(write_checkpoint(tmp_path / "fitted.pt", width=8, prior=prior))
    maps = depth_maps(5, seed=2)
    with serving(registry, checkpoint, runtime="eager", max_batch=2) as node, planner(registry) as client:
        images, uncertainty = client.estimate(maps)
        reply = client.last_reply
        passes = node.forward_passes
    assert reply is not None and uncertainty is not None and passes == 3
    assert reply.uncertainty_status == "ok" and reply.serves == "network" and "uncertainty" not in reply.model
    assert uncertainty.shape == (5, 100, 100) and uncertainty.dtype == np.float32
    assert np.isfinite(uncertainty).all() and (uncertainty > 0).all()
    expected_images, expected_u = served_reference(checkpoint, maps, "network")
    assert np.abs(images.astype(int) - expected_images).max() <= 1
    np.testing.assert_allclose(uncertainty, expected_u, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(reply.region_uncertainty, uncertainty.mean(axis=(1, 2)), rtol=1e-5)
    assert len(reply.region_uncertainty) == 5


def test_a_checkpoint_with_a_sensor_floor_serves_it_and_names_its_presses(registry: Registry, tmp_path: Path) -> None:
    """A checkpoint dtx calibrate uncertainty wrote: every reply's u is the checkpoint's own u with
    the lab sensor's floor added in quadrature, and the reply's model names the presses."""
    checkpoint = fit_for_serving(write_checkpoint(tmp_path / "lab.pt", width=8))
    state = load_checkpoint(checkpoint)
    floor = np.linspace(0.0, 20.0, 100 * 100, dtype=np.float32).reshape(100, 100)
    source = {"file": "lab_presses.npz", "presses": 30, "sha256": "0" * 64}
    state["uncertainty"]["sensor_floor"] = {"levels": torch.from_numpy(floor), "source": source}
    save_atomic(state, checkpoint)
    maps = depth_maps(3, seed=4)
    with serving(registry, checkpoint, runtime="eager") as _, planner(registry) as client:
        _, uncertainty = client.estimate(maps)
        reply = client.last_reply
    assert reply is not None and uncertainty is not None
    assert "its uncertainty with the floor of the sensor of lab_presses.npz" in reply.model
    _, expected = served_reference(checkpoint, maps, "network")
    np.testing.assert_allclose(uncertainty, expected, rtol=1e-4, atol=1e-4)
    assert np.all(uncertainty >= floor * (1 - 1e-6)) and uncertainty[:, -1, -1].min() > 19.99


def test_a_checkpoint_serving_its_prior_never_runs_the_network(
    registry: Registry, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """serves "prior" (the checkpoint's choice): the prior's image exactly as the generator with no
    correction draws it, and its uncertainty, with no network built or run."""
    checkpoint = fit_for_serving(write_checkpoint(tmp_path / "prior.pt", width=8, prior=True), serves="prior")
    maps = depth_maps(3, seed=3)
    expected_images, expected_u = served_reference(checkpoint, maps, "prior")

    def no_network(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a checkpoint serving its prior ran the network")

    monkeypatch.setattr("nodes.inference.network_runner", no_network)
    monkeypatch.setattr(UNetGenerator, "forward", no_network)
    monkeypatch.setattr(UNetGenerator, "forward_unchecked", no_network)
    with serving(registry, checkpoint, threads=2, max_batch=2) as node, planner(registry) as client:
        images, uncertainty = client.estimate(maps)
        reply = client.last_reply
        passes = node.forward_passes
    assert reply is not None and uncertainty is not None
    assert passes == 0 and reply.serves == "prior" and "serves the prior: no network pass" in reply.model
    np.testing.assert_array_equal(images, expected_images)
    np.testing.assert_allclose(uncertainty, expected_u, rtol=1e-4, atol=1e-4)
    assert reply.uncertainty_status == "ok" and len(reply.region_uncertainty) == 3


@pytest.mark.skipif(bool(cuda_missing("eager")), reason="no CUDA device")
@pytest.mark.parametrize("serves", ["network", "prior"])
def test_on_cuda_the_served_images_and_u_are_what_the_checkpoint_computes_there(
    registry: Registry, tmp_path: Path, serves: str
) -> None:
    """On a GPU the node draws the prior, runs the network and u there, in passes of 2: the
    checkpoint's own answer on that device (the CPU's differs by CUDA's arithmetic, within
    tests/test_prior_tensor.py's bounds), a level apart where a pass's width changes the sums."""
    checkpoint = fit_for_serving(write_checkpoint(tmp_path / "fitted.pt", width=8, prior=True), serves=serves)
    maps = depth_maps(5, seed=2)
    with (
        serving(registry, checkpoint, runtime="eager", device="cuda", max_batch=2) as node,
        planner(registry) as client,
    ):
        images, uncertainty = client.estimate(maps)
        reply = client.last_reply
    assert reply is not None and uncertainty is not None and reply.serves == serves and "cuda" in reply.model
    assert node.forward_passes == (3 if serves == "network" else 0)
    expected_images, expected_u = served_reference(checkpoint, maps, serves, "cuda")
    assert np.abs(images.astype(int) - expected_images).max() <= 1
    np.testing.assert_allclose(uncertainty, expected_u, rtol=1e-3, atol=1e-3)


def test_the_node_param_serves_overrides_the_checkpoints_choice(registry: Registry, tmp_path: Path) -> None:
    """A benchmark runs the network and the prior side by side on one checkpoint."""
    checkpoint = fit_for_serving(write_checkpoint(tmp_path / "prior.pt", width=8, prior=True), serves="prior")
    maps = depth_maps(2, seed=4)
    replies = {}
    for serves in ("network", "prior", ""):
        with serving(registry, checkpoint, runtime="eager", serves=serves) as node, planner(registry) as client:
            client.estimate(maps)
            replies[serves] = (client.last_reply, node.forward_passes)
    for serves, (reply, passes) in replies.items():
        assert reply is not None
        assert reply.serves == (serves or "prior") and (passes > 0) == (serves == "network")
        expected_images, expected_u = served_reference(checkpoint, maps, reply.serves)
        assert np.abs(reply.images.astype(int) - expected_images).max() <= (1 if reply.serves == "network" else 0)
        np.testing.assert_allclose(reply.uncertainty, expected_u, rtol=1e-4, atol=1e-4)
    assert np.abs(replies["network"][0].images.astype(int) - replies["prior"][0].images).max() > 0


@pytest.mark.parametrize(
    ("serves", "refused"), [("prior", "has no physics prior to serve"), ("both", "serves must be")]
)
def test_serving_a_prior_the_checkpoint_lacks_or_anything_else_is_refused_at_start(
    checkpoint: Path, tmp_path: Path, serves: str, refused: str
) -> None:
    with pytest.raises(ValueError, match=refused):
        InferenceNode("refused", {"checkpoint": str(checkpoint), "serves": serves}, registry=Registry(tmp_path / "bus"))


# On a GPU the node cuts a cloud's depth-maps there (perception.depthmap_tensor): the same maps.
SERVING_DEVICES = [{}] + ([{"device": "cuda", "runtime": "eager"}] if not cuda_missing("eager") else [])


@pytest.mark.parametrize("on", SERVING_DEVICES, ids=lambda on: on.get("device", "cpu"))
def test_points_and_gel_poses_give_the_patch_extractors_depth_maps(
    registry: Registry, checkpoint: Path, on: dict[str, str]
) -> None:
    _, depth_range_m = load_generator(checkpoint)
    # A bumpy surface 0.5 mm into the gel, seen by two gels placed somewhere in the world.
    x, z = np.meshgrid(np.linspace(-0.012, 0.012, 150), np.linspace(-0.015, 0.015, 150))
    y = -0.0005 + 0.0008 * np.sin(x * 600) * np.cos(z * 400)
    points_gel = np.stack([x.ravel(), y.ravel(), z.ravel(), np.ones(x.size)], axis=1)
    poses = []
    for angle, offset in ((0.3, [0.4, -0.2, 0.1]), (-1.1, [0.1, 0.3, 0.05])):
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
        pose[:3, 3] = offset
        poses.append(pose)
    cloud = (poses[0] @ points_gel.T).T[:, :3]  # the same surface in front of gel 0 ...
    cloud = np.concatenate([cloud, (poses[1] @ points_gel.T).T[:, :3]])  # ... and of gel 1
    params = DepthMapParams(y_range_m=depth_range_m)
    geometry = load_scene(InferenceNode.Params.scene).gripper_geometry()  # as the server's
    expected = np.stack([contact_depth_map(cloud, np.eye(4), pose, geometry, params).depth_map_m for pose in poses])
    with serving(registry, checkpoint, **on), planner(registry) as client:
        images, _ = client.estimate_at(cloud, np.stack(poses))
        from_maps, _ = client.estimate(expected)
    np.testing.assert_array_equal(images, from_maps)


def _maps(n: int = 1, value: float = 0.001, dtype: Any = np.float32) -> np.ndarray:
    return np.full((n, 100, 100), value, dtype)


BAD_REQUESTS = [
    (TactileEstimateRequest(), "empty request"),
    (TactileEstimateRequest(depth_maps=_maps()[:, :50, :50]), "must be N x 100 x 100"),
    (TactileEstimateRequest(depth_maps=_maps()[0]), "must be N x 100 x 100"),
    (TactileEstimateRequest(depth_maps=_maps(dtype=np.float64)), "must be float32"),
    (TactileEstimateRequest(depth_maps=_maps(value=np.nan)), "NaN or inf"),
    (TactileEstimateRequest(depth_maps=_maps(value=np.inf)), "NaN or inf"),
    (TactileEstimateRequest(depth_maps=_maps(5)), "too many regions: 5 > 4"),
    (TactileEstimateRequest(depth_maps=_maps(), dropout_samples=2), "dropout_samples is not served since protocol v4"),
    (
        TactileEstimateRequest(depth_maps=_maps(), dropout_samples=0),
        "carries the calibrated uncertainty.*send 1, got 0",
    ),
    (TactileEstimateRequest(depth_maps=_maps(), points=np.zeros((10, 3)), gel_poses=np.eye(4)[None]), "not both"),
    (TactileEstimateRequest(points=np.zeros((10, 3))), "empty request"),
    (TactileEstimateRequest(cloud_id="ab" * 32), "empty request"),
    (TactileEstimateRequest(cloud_id="not an id", gel_poses=np.eye(4)[None]), "cloud_id must be the 64 hex digits"),
    (TactileEstimateRequest(depth_maps=_maps(), cloud_id="ab" * 32), "not both"),
    (TactileEstimateRequest(gel_poses=np.eye(4)[None]), "empty request"),
    (TactileEstimateRequest(points=np.zeros((10, 2)), gel_poses=np.eye(4)[None]), "points must be P x 3"),
    (TactileEstimateRequest(points=np.zeros((1001, 3)), gel_poses=np.eye(4)[None]), "too many points"),
    (
        TactileEstimateRequest(points=np.zeros((600, 3)), gel_poses=np.stack([np.eye(4)] * 4)),
        "too much work: 2400 model points near 4 gels > 2000",
    ),
    (TactileEstimateRequest(points=np.zeros((10, 3), np.int32), gel_poses=np.eye(4)[None]), "float32 or float64"),
    (TactileEstimateRequest(points=np.full((10, 3), np.nan), gel_poses=np.eye(4)[None]), "NaN or inf"),
    (TactileEstimateRequest(points=np.zeros((10, 3)), gel_poses=np.eye(3)[None]), "gel_poses must be N x 4 x 4"),
    (TactileEstimateRequest(points=np.zeros((10, 3)), gel_poses=2 * np.eye(4)[None]), "not a proper rotation"),
    (
        TactileEstimateRequest(points=np.zeros((10, 3)), gel_poses=np.stack([np.eye(4), np.ones((4, 4))])),
        r"gel_poses\[1\]",
    ),
]


def test_a_gel_out_of_reach_is_answered_for_its_region_and_the_others_are_served(
    registry: Registry, checkpoint: Path
) -> None:
    """A planner asks about many candidate poses at once; one that misses the object must not
    cost it the answers for the others."""
    _, depth_range_m = load_generator(checkpoint)
    x, z = np.meshgrid(np.linspace(-0.012, 0.012, 120), np.linspace(-0.015, 0.015, 120))
    cloud = np.stack([x.ravel(), np.full(x.size, -0.0005), z.ravel()], axis=1)  # a plane 0.5 mm into gel 0
    away = np.eye(4)
    away[1, 3] = -1.0  # a metre behind the cloud
    with serving(registry, checkpoint), planner(registry) as client:
        images, _ = client.estimate_at(cloud, np.stack([np.eye(4), away]))
        reply = client.last_reply
        empty, _ = client.estimate(np.full((1, 100, 100), depth_range_m[1], np.float32))
    assert reply is not None and reply.region_status == ["ok", "out_of_reach"]
    assert reply.region_errors[0] == "" and "region 1: no model point in the contact volume" in reply.region_errors[1]
    assert reply.depth_range_m == list(depth_range_m)
    np.testing.assert_array_equal(images[1], empty[0])  # what the gel feels touching nothing


def test_each_region_says_how_many_points_and_surface_bins_its_estimate_rests_on(
    registry: Registry, checkpoint: Path
) -> None:
    """A plane 0.5 mm into the gel at 0.1 mm points holds every bin; the same plane with a 6 mm
    hole holds the hole's bins empty (the surface rule makes no lid over it) and says how many are
    left; a gel out of reach holds none; a depth-map sent as one counts its bins below y_far and no
    points (-1). The counts are those of the patch extractor's maps of the same cloud."""
    _, depth_range_m = load_generator(checkpoint)
    x, z = np.meshgrid(np.arange(-0.015, 0.015, 1e-4), np.arange(-0.012, 0.012, 1e-4))
    plane = np.stack([x.ravel(), np.full(x.size, -0.0005), z.ravel()], axis=1)
    holed = plane[np.hypot(plane[:, 0], plane[:, 2]) > 0.003]
    away = np.eye(4)
    away[1, 3] = -1.0
    geometry = load_scene(InferenceNode.Params.scene).gripper_geometry()
    params = DepthMapParams(y_range_m=depth_range_m)
    sent = np.full((1, 100, 100), depth_range_m[1], np.float32)
    sent[0, :, :30] = -0.0005
    with serving(registry, checkpoint), planner(registry) as client:
        client.estimate_at(plane, np.stack([np.eye(4), away]))
        whole = client.last_reply
        client.estimate_at(holed, np.eye(4)[None])
        with_hole = client.last_reply
        client.estimate(sent)
        from_map = client.last_reply
    assert whole is not None and with_hole is not None and from_map is not None
    expected = [contact_depth_map(cloud, np.eye(4), np.eye(4), geometry, params) for cloud in (plane, holed)]
    assert whole.region_points == [expected[0].point_count, 0] and whole.region_surface_bins == [10_000, 0]
    surface = int(np.count_nonzero(expected[1].depth_map_m < np.float32(depth_range_m[1])))
    assert with_hole.region_points == [expected[1].point_count] and with_hole.region_surface_bins == [surface]
    assert 10_000 - 626 <= surface < 10_000 - 500  # the 6 mm hole covers 626 bins; its edge bins are known
    assert from_map.region_points == [-1] and from_map.region_surface_bins == [3_000]


def test_every_bad_request_gets_an_error_reply_and_the_server_serves_on(registry: Registry, checkpoint: Path) -> None:
    limits = {"max_regions": 4, "max_points": 1000, "max_point_visits": 2000}
    with serving(registry, checkpoint, **limits), contextlib.closing(Bus("planner", registry)) as bus:
        raw = bus.client(SERVICE, TactileEstimateRequest, TactileEstimateReply)
        for request, message in BAD_REQUESTS:
            with pytest.raises(ServiceCallError, match=message) as failure:
                raw.call(request, timeout_s=30.0, retries=0)
            assert failure.value.code == "bad_request"
            assert raw.call(TactileEstimateRequest(depth_maps=_maps()), timeout_s=30.0).images.shape == (1, 100, 100, 3)
        wrong_schema = bus.client(SERVICE, msgs.GripperCommand, msgs.GripperState)
        with pytest.raises(ServiceCallError) as failure:
            wrong_schema.call(msgs.GripperCommand(), timeout_s=30.0)
        assert failure.value.code == "wrong_type"
        with TactileClient(bus, timeout_s=30.0) as client:
            with pytest.raises(InferenceError, match="too many regions") as refused:
                client.estimate(_maps(5))
            assert refused.value.code == "bad_request"
            assert client.estimate(_maps(4))[0].shape == (4, 100, 100, 3)


def test_requests_of_two_clients_share_one_forward_pass(registry: Registry, checkpoint: Path) -> None:
    maps = {"a": depth_maps(2, seed=3), "b": depth_maps(3, seed=4)}
    replies: dict[str, np.ndarray] = {}
    # A long window: the second request surely comes while the first waits for company.
    with serving(registry, checkpoint, runtime="eager", batch_window_ms=1500.0, max_batch=8) as node:
        ready = threading.Barrier(2)

        def ask(name: str) -> None:
            with planner(registry, name) as client:
                assert client.client.wait_for_service(30.0)
                ready.wait()
                replies[name] = client.estimate(maps[name])[0]

        threads = [threading.Thread(target=ask, args=(name,)) for name in maps]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        passes = node.forward_passes
    assert passes == 1
    for name, images in replies.items():
        assert np.abs(images.astype(int) - reference(checkpoint, maps[name])).max() <= 1


def test_a_request_larger_than_max_batch_runs_in_several_passes(registry: Registry, checkpoint: Path) -> None:
    maps = depth_maps(5, seed=5)
    with serving(registry, checkpoint, runtime="eager", max_batch=2) as node, planner(registry) as client:
        images, _ = client.estimate(maps)
        passes = node.forward_passes
    assert passes == 3  # 5 regions in batches of 2
    assert images.shape == (5, 100, 100, 3)
    assert np.abs(images.astype(int) - reference(checkpoint, maps)).max() <= 1


def test_a_request_smaller_than_a_pass_is_spread_over_the_lanes(registry: Registry, checkpoint: Path) -> None:
    """Two threads: six regions in passes of up to 8 run as two passes of three, one a lane."""
    maps = depth_maps(6, seed=6)
    with serving(registry, checkpoint, runtime="eager", threads=2, max_batch=8) as node, planner(registry) as client:
        images, _ = client.estimate(maps)
        passes = node.forward_passes
    assert passes == 2
    assert np.abs(images.astype(int) - reference(checkpoint, maps)).max() <= 1


def test_a_cloud_handle_answers_like_its_points_and_an_evicted_one_is_sent_again(
    registry: Registry, checkpoint: Path
) -> None:
    """A cloud's points travel once; later requests name it by the id its reply gave and get
    the same images. A worker that no longer holds it (index_cache 1, another cloud came) says
    unknown_cloud, and the client sends the points again on its own."""
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.01, 0.01, (5000, 3)).astype(np.float32)
    moved = points.copy()
    moved[:, 1] += np.float32(0.0002)
    poses = np.stack([np.eye(4)] * 2)
    with (
        serving(registry, checkpoint, runtime="eager", index_cache=1),
        planner(registry) as client,
        contextlib.closing(Bus("raw", registry)) as bus,
    ):
        raw = bus.client(SERVICE, TactileEstimateRequest, TactileEstimateReply)
        sent = raw.call(TactileEstimateRequest(points=points, gel_poses=poses), timeout_s=30.0)
        assert sent.cloud_id == cloud_id(points) and sent.worker == "inference"
        named = raw.call(TactileEstimateRequest(cloud_id=sent.cloud_id, gel_poses=poses), timeout_s=30.0)
        np.testing.assert_array_equal(named.images, sent.images)
        assert named.cloud_id == sent.cloud_id
        other = raw.call(TactileEstimateRequest(points=moved, gel_poses=poses), timeout_s=30.0)
        assert other.cloud_id not in ("", sent.cloud_id)
        with pytest.raises(ServiceCallError, match="does not hold cloud") as evicted:
            raw.call(TactileEstimateRequest(cloud_id=sent.cloud_id, gel_poses=poses), timeout_s=30.0)
        assert evicted.value.code == "unknown_cloud"
        with pytest.raises(ServiceCallError, match="is not the id of the points sent") as wrong:
            raw.call(TactileEstimateRequest(points=moved, cloud_id=sent.cloud_id, gel_poses=poses), timeout_s=30.0)
        assert wrong.value.code == "bad_request"

        cloud = Cloud(points)
        images, _ = client.estimate_at(cloud, poses)  # the points travel
        assert cloud.id == sent.cloud_id and cloud.held_by == {"inference"}
        np.testing.assert_array_equal(images, sent.images)
        np.testing.assert_array_equal(client.estimate_at(cloud, poses)[0], sent.images)  # the id alone
        raw.call(TactileEstimateRequest(points=moved, gel_poses=poses), timeout_s=30.0)  # evicts it
        np.testing.assert_array_equal(client.estimate_at(cloud, poses)[0], sent.images)  # refused, sent again
        assert cloud.held_by == {"inference"}


def test_a_request_refused_while_its_maps_are_cut_fails_alone_in_its_batch(checkpoint: Path, tmp_path: Path) -> None:
    """Too much work is found in the batch thread; the other clients' requests batched with it
    are answered."""
    import time
    from concurrent.futures import Future

    from nodes.inference import BadRequest, _Job
    from nodes.inference_requests import checked_regions

    node = InferenceNode(
        "batch_probe",
        {"checkpoint": str(checkpoint), "runtime": "eager", "max_point_visits": 2000},
        registry=Registry(tmp_path / "bus"),
    )
    try:
        heavy = TactileEstimateRequest(points=np.zeros((600, 3)), gel_poses=np.stack([np.eye(4)] * 4))
        light = TactileEstimateRequest(depth_maps=depth_maps(1, seed=3))
        jobs = [
            _Job(request, checked_regions(request, node.params, 100), time.monotonic(), Future(), None)
            for request in (heavy, light)
        ]
        node._run(jobs)
        with pytest.raises(BadRequest, match="too much work"):
            jobs[0].future.result(timeout=0)
        assert jobs[1].future.result(timeout=0).images.shape == (1, 100, 100, 3)
    finally:
        node.close()
