"""Clients in another language, written from docs/ alone (clients/node), against a real graph:
the wire protocol (docs/wire-protocol.md) is a contract only if a stranger can keep it.

Needs `node` and the pinned packages `make setup` installs (clients/node/node_modules)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_inference_node import fit_for_serving, serving

import msgs
from benchmarks.serve import depth_maps, write_checkpoint
from bus.bag import BagWriter, bag_info
from bus.inference_client import SERVICE, Cloud, TactileClient
from bus.pubsub import Bus
from bus.registry import Registry
from dataset.reader import DatasetReader
from msgs.codec import decode, encode
from nodes.foxglove_bridge import FoxgloveBridge

ROOT = Path(__file__).resolve().parent.parent
CLIENTS = ROOT / "clients" / "node"
NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(
    NODE is None, reason="node (Node.js) is not installed: the third-party client tests need it"
)


@pytest.fixture(scope="module")
def node_modules() -> Path:
    modules = CLIENTS / "node_modules"
    assert (modules / "zeromq").is_dir(), f"{modules} is missing: run `make setup` (npm ci in {CLIENTS})"
    return modules


def node(*args: str, bus_dir: Path, timeout_s: float = 300) -> dict:
    done = subprocess.run(
        [str(NODE), str(CLIENTS / "planner.mjs"), *args],
        cwd=CLIENTS,
        text=True,
        capture_output=True,
        timeout=timeout_s,
        env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def served(node_modules: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Registry]]:
    """launch/serve.yaml's two workers on a bus of their own, serving a model that corrects the
    physics prior (as the default model does) of depth-maps by default 1 mm off, with an
    uncertainty (as ``dtx train`` fits one)."""
    bus_dir = Path(tempfile.mkdtemp(prefix="dtxn"))  # ipc paths must stay short
    registry = Registry(bus_dir)
    tiny = write_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", width=8, prior=True, pose_sigma_mm=1.0)
    checkpoint = fit_for_serving(tiny)
    launcher = subprocess.Popen(
        [sys.executable, "-m", "dtx.cli", "launch", "launch/serve.yaml", f"checkpoint:={checkpoint}"],
        cwd=ROOT,
        env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 180
        while len(registry.lookup("service", SERVICE)) < 2:
            assert launcher.poll() is None, launcher.communicate()[0]
            assert time.monotonic() < deadline, "the two workers did not advertise the service"
            time.sleep(0.2)
        yield bus_dir, registry
    finally:
        launcher.send_signal(signal.SIGINT)
        launcher.communicate(timeout=60)
        shutil.rmtree(bus_dir, ignore_errors=True)


def contact_signal(images: np.ndarray) -> np.ndarray:
    """planner.mjs's contact signal: each image's mean |pixel - its channel's median|, levels."""
    pixels = images.astype(np.float64).reshape(len(images), -1, 3)
    return np.abs(pixels - np.median(pixels, axis=1, keepdims=True)).mean(axis=(1, 2))


def assert_ranked(ranking: dict, scores: np.ndarray) -> None:
    """The planner's order: every region once, best score first (all reachable here)."""
    np.testing.assert_allclose(ranking["score"], scores, rtol=1e-9, atol=1e-9)
    assert sorted(ranking["order"]) == list(range(len(scores)))
    assert list(np.diff(np.asarray(ranking["score"])[ranking["order"]]) <= 0) == [True] * (len(scores) - 1)


def test_the_node_planner_gets_the_python_clients_images_byte_for_byte(
    served: tuple[Path, Registry], tmp_path: Path
) -> None:
    """§3 from the page alone: the images byte for byte, the uncertainty and its region means as
    the Python client gets them, and the candidates ranked by their image less their uncertainty."""
    bus_dir, registry = served
    maps = depth_maps(3, seed=5).astype("<f4")
    (tmp_path / "maps.f32").write_bytes(maps.tobytes())
    images_path, uncertainty_path = tmp_path / "images.u8", tmp_path / "u.f32"
    result = node(
        "images", str(tmp_path / "maps.f32"), "3", str(images_path), "-1", str(uncertainty_path), bus_dir=bus_dir
    )
    with contextlib.closing(Bus("planner", registry)) as bus, TactileClient(bus, timeout_s=60.0) as client:
        images, uncertainty = client.estimate(maps)
        reply = client.last_reply
    assert reply is not None and uncertainty is not None
    assert result["a"][0] == ["|u1", [3, 100, 100, 3]] and result["region_status"] == ["ok"] * 3
    assert images_path.read_bytes() == np.ascontiguousarray(images).tobytes()
    assert result["pose_sigma_mm"] == 1.0  # the checkpoint's default
    assert (result["region_points"], result["region_surface_bins"]) == ([-1] * 3, reply.region_surface_bins)
    assert (result["uncertainty_status"], result["serves"]) == ("ok", "network")
    node_u = np.frombuffer(uncertainty_path.read_bytes(), "<f4").reshape(3, 100, 100)
    np.testing.assert_allclose(node_u, uncertainty, rtol=1e-5)
    np.testing.assert_allclose(result["region_uncertainty"], reply.region_uncertainty, rtol=1e-5)
    assert result["ranking"]["by"] == "contact signal - region_uncertainty"
    assert_ranked(result["ranking"], contact_signal(images) - np.asarray(result["region_uncertainty"]))


def test_the_node_planner_ranks_by_the_image_alone_when_the_uncertainty_is_absent(
    node_modules: Path, registry: Registry, tmp_path: Path
) -> None:
    """§3's absent case from the page alone: a checkpoint trained before the uncertainty sends an
    empty array and no region means, and the planner ranks by the images alone, saying so."""
    checkpoint = write_checkpoint(tmp_path / "old.pt", width=8)
    maps = depth_maps(3, seed=7).astype("<f4")
    (tmp_path / "maps.f32").write_bytes(maps.tobytes())
    images_path, uncertainty_path = tmp_path / "images.u8", tmp_path / "u.f32"
    with serving(registry, checkpoint, runtime="eager"):
        result = node(
            "images",
            str(tmp_path / "maps.f32"),
            "3",
            str(images_path),
            "-1",
            str(uncertainty_path),
            bus_dir=registry.root,
        )
    images = np.frombuffer(images_path.read_bytes(), np.uint8).reshape(3, 100, 100, 3)
    assert (result["uncertainty_status"], result["region_uncertainty"]) == ("absent", [])
    assert not uncertainty_path.exists()
    assert result["ranking"]["by"] == "contact signal (uncertainty absent)"
    assert_ranked(result["ranking"], contact_signal(images))


def test_the_node_planner_says_its_geometry_is_exact_and_gets_the_python_clients_images(
    served: tuple[Path, Registry], tmp_path: Path
) -> None:
    """§3's pose_sigma_mm from the page alone: 0 gives the Python client's exact-geometry images,
    byte for byte, and the reply says 0 was used; they are not the default's."""
    bus_dir, registry = served
    maps = depth_maps(3, seed=6).astype("<f4")
    (tmp_path / "maps.f32").write_bytes(maps.tobytes())
    exact = node("images", str(tmp_path / "maps.f32"), "3", str(tmp_path / "exact.u8"), "0", bus_dir=bus_dir)
    node("images", str(tmp_path / "maps.f32"), "3", str(tmp_path / "default.u8"), bus_dir=bus_dir)
    with contextlib.closing(Bus("planner", registry)) as bus, TactileClient(bus, timeout_s=60.0) as client:
        images, _ = client.estimate(maps, pose_sigma_mm=0.0)
    assert exact["pose_sigma_mm"] == 0.0
    assert (tmp_path / "exact.u8").read_bytes() == np.ascontiguousarray(images).tobytes()
    assert (tmp_path / "default.u8").read_bytes() != (tmp_path / "exact.u8").read_bytes()


def test_every_malformed_request_of_the_node_planner_gets_an_error_reply(served: tuple[Path, Registry]) -> None:
    result = node("malformed", bus_dir=served[0])
    unanswered = {name: r for name, r in result["results"].items() if r is None or r["code"] != "bad_request"}
    assert result["variants"] == 28 and result["answered"] == 28, unanswered
    assert result["served_after"]
    refused = result["dropout_samples_2"]  # §3: a v4 request still asking for dropout samples
    assert refused["code"] == "bad_request" and "dropout_samples is not served since protocol v4" in refused["text"]


def test_the_node_planner_sends_a_cloud_once_per_worker_and_then_its_id(
    served: tuple[Path, Registry], tmp_path: Path
) -> None:
    """§3's cloud handle from the page alone: six requests about one cloud over two workers carry
    its points twice (once to each), then the id; the images and each region's points and surface
    bins are the Python client's, byte for byte; an id no worker holds is refused with
    unknown_cloud."""
    bus_dir, registry = served
    x, z = np.meshgrid(np.linspace(-0.012, 0.012, 120), np.linspace(-0.015, 0.015, 120))
    points = np.stack([x.ravel(), np.full(x.size, -0.0005), z.ravel()], axis=1).astype("<f4")
    shifted, away = np.eye(4), np.eye(4)
    shifted[0, 3], away[1, 3] = 0.002, -1.0
    poses = np.stack([np.eye(4), shifted, away]).astype("<f8")
    (tmp_path / "points.f32").write_bytes(points.tobytes())
    (tmp_path / "poses.f64").write_bytes(poses.tobytes())
    result = node(
        "cloud",
        str(tmp_path / "points.f32"),
        str(len(points)),
        str(tmp_path / "poses.f64"),
        "3",
        "6",
        str(tmp_path / "images.u8"),
        bus_dir=bus_dir,
    )
    assert (result["with_points"], result["id_only"], result["refused"]) == (2, 4, 0), result
    assert result["unknown_id"] == "unknown_cloud"
    with contextlib.closing(Bus("planner", registry)) as bus, TactileClient(bus, timeout_s=60.0) as client:
        cloud = Cloud(points)
        for _ in range(3):
            images, _ = client.estimate_at(cloud, poses)
    assert cloud.id == result["cloud_id"] and len(cloud.held_by) == 2
    assert (tmp_path / "images.u8").read_bytes() == np.ascontiguousarray(images).tobytes()
    reply = client.last_reply
    assert reply is not None and result["region_points"] == reply.region_points
    assert result["region_surface_bins"] == reply.region_surface_bins and reply.region_points[2] == 0


def test_the_node_planner_loses_no_request_when_a_worker_is_killed(served: tuple[Path, Registry]) -> None:
    """kill -9 of one worker mid-session: the spec's liveness and retry rules carry every request."""
    bus_dir, registry = served
    count = 40
    planner = subprocess.Popen(
        [str(NODE), str(CLIENTS / "planner.mjs"), "steady", str(count)],
        cwd=CLIENTS,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
    )
    assert planner.stderr is not None
    try:
        for line in planner.stderr:
            if line.startswith("answered 10"):
                break
        victim = registry.lookup("service", SERVICE)[0].pid
        os.kill(victim, signal.SIGKILL)
        output, errors = planner.communicate(timeout=300)
    finally:
        if planner.poll() is None:
            planner.kill()
    assert planner.returncode == 0, errors
    result = json.loads(output.strip().splitlines()[-1])
    assert result["count"] == count and result["lost"] == 0, result
    # The launcher respawned the victim: both names serve again.
    deadline = time.monotonic() + 120
    while len(registry.lookup("service", SERVICE)) < 2:
        assert time.monotonic() < deadline, "the killed worker was not respawned"
        time.sleep(0.2)


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
def test_the_official_mcap_reader_reads_a_recorded_bag_and_a_cut_one(
    node_modules: Path, tmp_path: Path, compression: str
) -> None:
    """@mcap/core with @mcap/support's decompressors (as Foxglove Studio reads), knowing only
    docs/bag-format.md, decodes every dtx channel of a bag in each chunk compression, and of the
    same bag cut short by a crash as much as the Python reader does."""
    path = tmp_path / "session.mcap"
    writer = BagWriter(path, compression=compression, chunk_size=64 * 1024)
    for i in range(20):
        for topic, message in (
            ("/gripper/state", msgs.GripperState(width_m=0.01 * i)),
            ("/camera/left/depth", msgs.DepthImage(depth=np.full((48, 64), i, np.uint16))),
            ("/cloud", msgs.PointCloud(points=np.full((30, 3), i, np.float32))),
        ):
            message.header.stamp_ns = 1_000_000 * (i + 1)
            frames = encode(topic, message, "test")
            writer.write(decode(frames), frames, log_time_ns=message.header.stamp_ns)
    writer.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    for bag, complete in ((path, True), (cut, False)):
        done = subprocess.run(
            [str(NODE), str(CLIENTS / "read_bag.mjs"), str(bag)],
            cwd=CLIENTS,
            text=True,
            capture_output=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr
        result = json.loads(done.stdout)
        python = bag_info(bag)
        assert python.truncated is not complete and result["stream"]["done"] is complete
        readers = [result["stream"], result["indexed"]] if complete else [result["stream"]]
        for read in readers:
            assert {topic: entry["count"] for topic, entry in read["topics"].items()} == {
                topic: entry["count"] for topic, entry in python.topics.items()
            }
            assert read["decoded"] == sum(
                entry["count"] for topic, entry in python.topics.items() if entry["encoding"] == "dtx/msgpack+buffers"
            )
        assert read["topics"]["/gripper/state"]["encoding"] == "dtx/jsonschema"
    assert 0 < sum(e["count"] for e in result["stream"]["topics"].values()) < 120


@contextlib.contextmanager
def running_bridge(registry: Registry) -> Iterator[FoxgloveBridge]:
    bridge = FoxgloveBridge("foxglove", {"port": 0, "max_rate_hz": 100.0}, registry=registry)
    thread = threading.Thread(target=bridge.spin)
    thread.start()
    try:
        yield bridge
    finally:
        bridge.request_shutdown()
        thread.join()
        bridge.close()


def start_viewer(bridge: FoxgloveBridge, subprotocol: str, seconds: int) -> subprocess.Popen[str]:
    """clients/node/foxglove_view.mjs: subscribes to each channel on advertise, reports at the end."""
    return subprocess.Popen(
        [str(NODE), str(CLIENTS / "foxglove_view.mjs"), f"ws://127.0.0.1:{bridge.port}", subprotocol, str(seconds)],
        cwd=CLIENTS,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def viewer_report(viewer: subprocess.Popen[str]) -> dict:
    output, errors = viewer.communicate()
    assert viewer.returncode == 0, errors
    seen = json.loads(output)
    assert seen["opened"] and not seen["errors"] and not seen["statuses"], seen["statuses"][:5]
    return seen


@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_foxglove_clients_of_either_subprotocol_see_every_channel_and_a_latched_cloud(
    node_modules: Path, registry: Registry, subprotocol: str
) -> None:
    """@foxglove/ws-protocol, as Studio 1.x and Lichtblick connect: a cloud published once
    before the viewer came is still shown, and so are the images that stream."""
    with contextlib.closing(Bus("sensors", registry)) as bus, running_bridge(registry) as bridge:
        cloud = bus.publisher("/object/cloud", msgs.PointCloud, latched=True)
        camera = bus.publisher("/gelsight_left/image", msgs.TactileImage)
        cloud.publish(msgs.PointCloud(points=np.zeros((10, 3), np.float32)))
        # The viewer comes once the bridge holds the cloud, so it can only see it resent.
        deadline = time.monotonic() + 60
        while "/object/cloud/foxglove" not in bridge.resender.last:
            assert time.monotonic() < deadline, "the bridge never received the latched cloud"
            cloud.service_subscriptions()  # a node's executor does this: the latched resend to the bridge
            time.sleep(0.05)
        viewer = start_viewer(bridge, subprotocol, 6)
        while viewer.poll() is None:
            camera.publish(msgs.TactileImage(image=np.zeros((12, 16, 3), np.uint8), sensor="left"))
            cloud.service_subscriptions()
            time.sleep(0.05)
        seen = viewer_report(viewer)
    assert {"/object/cloud/foxglove", "/gelsight_left/image/foxglove"} <= set(seen["advertised"])
    assert seen["messages"].get("/object/cloud/foxglove", 0) >= 1, seen
    assert seen["messages"].get("/gelsight_left/image/foxglove", 0) >= 1, seen


def test_a_hundred_subscriptions_right_after_advertise_are_never_refused(
    node_modules: Path, registry: Registry
) -> None:
    """100 topics appear while the official client is connected and subscribes to each channel
    the moment it is advertised: no "Unknown channel ID" (or any other status), and every
    channel's messages reach it."""
    topics = [f"/trial_{i:03d}/image" for i in range(100)]
    with contextlib.closing(Bus("sensors", registry)) as bus, running_bridge(registry) as bridge:
        viewer = start_viewer(bridge, "foxglove.sdk.v1", 14)
        publishers = []
        image = msgs.TactileImage(image=np.zeros((4, 4, 3), np.uint8), sensor="left")
        while viewer.poll() is None:
            if len(publishers) < len(topics):  # 20 new topics per discovery round (1 s)
                publishers += [
                    bus.publisher(topic, msgs.TactileImage) for topic in topics[len(publishers) : len(publishers) + 20]
                ]
            for publisher in publishers:
                publisher.publish(image)
            time.sleep(1.0)
        seen = viewer_report(viewer)
    assert {topic + "/foxglove" for topic in topics} <= set(seen["advertised"])
    assert not [topic for topic in topics if seen["messages"].get(topic + "/foxglove", 0) == 0]


TRANSFORM_TREE = {"world->camera_left", "world->camera_right", "world->tcp", "tcp->gel_left", "tcp->gel_right"}


def free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as sock:
        return int(sock.getsockname()[1])


@pytest.mark.slow
def test_a_live_session_shows_every_sample_of_both_fingers_and_every_transform(
    node_modules: Path, tmp_path: Path
) -> None:
    """A 25-grasp session with foxglove:=true, watched by the official client from its start:
    the two fingers' samples share a topic and the tree's transforms share /tf, yet 50 of 50
    samples and every transform arrive; the bridge's last heartbeat says what it thinned, per topic."""
    bus_dir, port, out = Path(tempfile.mkdtemp(prefix="dtxf")), free_port(), tmp_path / "session"
    # Started first, the viewer connects the moment the bridge listens: it misses nothing.
    viewer = subprocess.Popen(
        [str(NODE), str(CLIENTS / "foxglove_view.mjs"), f"ws://127.0.0.1:{port}", "foxglove.websocket.v1", "600"],
        cwd=CLIENTS,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        session = subprocess.run(
            [sys.executable, "-m", "dtx.cli", "launch", "launch/collect_sim.yaml", f"out:={out}", "grasps:=25"]
            + ["seed:=0", "record:=false", "foxglove:=true", f"foxglove_port:={port}"],
            cwd=ROOT,
            env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
            text=True,
            capture_output=True,
            timeout=600,
        )
        assert session.returncode == 0, session.stdout[-3000:]
        seen = viewer_report(viewer)  # it reports when the bridge closes its connection
        bridge = next(status for status in Registry(bus_dir).node_statuses() if status["node"] == "foxglove")
    finally:
        if viewer.poll() is None:
            viewer.kill()
        shutil.rmtree(bus_dir, ignore_errors=True)
    assert len(DatasetReader(out).records) == 50
    assert seen["frames"]["/collector/sample/foxglove"] == {"gel_left": 25, "gel_right": 25}, seen["frames"]
    assert set(seen["frames"]["/tf/foxglove"]) == TRANSFORM_TREE, seen["frames"]
    assert set(seen["frames"]["/perception/object_pose/foxglove"]) == {"world->object"}
    thinned = {key.removeprefix("thinned:"): n for key, n in bridge["counters"].items() if key.startswith("thinned:")}
    assert {topic.removesuffix("/foxglove") for topic in seen["messages"]} <= set(thinned), bridge["counters"]
    assert thinned["/collector/sample"] == 0 and thinned["/perception/object_pose"] == 0, thinned
    shown = ("/collector/sample/foxglove", "/tf/foxglove", "/perception/object_pose/foxglove")
    print("frames:", json.dumps({topic: seen["frames"][topic] for topic in shown}, sort_keys=True))
    print("longest gap s:", json.dumps({topic: seen["longest_gap_s"].get(topic) for topic in shown}, sort_keys=True))
    print("thinned per topic:", json.dumps(thinned, sort_keys=True))
