"""``dtx bench serve``: the inference server node end to end through the bus.

The real node (nodes.inference; ``--workers`` of them, as launch/serve.yaml starts them) runs
in its own process on a private bus directory; this process is the grasp planner (bus.inference_client.TactileClient). Figures:
- ``p50_ms``/``p99_ms``: one region per request, requests one after another, measured from
  the call to the decoded reply (encode, ipc, batching window, network, reply);
- ``regions_per_s``: ``--clients`` planners sending ``--regions`` regions per request back to
  back for ``--seconds``; the node batches across them.
- ``--points``: the grasp planner's cloud form (``estimate_at``): the registered model cloud of
  each YCB object at the depth-maps' training spacing (0.1 mm, float32) with ``--poses`` candidate
  gel poses on its surface per request, back to back; per object and pose count: the
  depth-map cutting step in this process (``cut_regions_per_s``: the node's batched, indexed
  pass, and ``cut_device_regions_per_s`` the same on ``--device`` where not the CPU; ``cut_per_gel_regions_per_s``: one contact_depth_map over the whole cloud per gel, the
  way before the index), then through the node, request to reply: ``handle_regions_per_s`` and
  ``handle_p50_ms`` (a ``Cloud``: its points travel in the first request, ``first_request_ms``,
  which also builds the index; then only its id), ``points_regions_per_s`` and
  ``points_p50_ms`` (the whole cloud in every request, the index kept), and
  ``maps_regions_per_s`` and ``maps_p50_ms``: the same regions sent as depth-maps, same run;
  ``handle_server_cpu_ms_per_region``: the node's CPU while it answered the handle requests;
  ``stage_cpu_ms_per_region``: each stage of such a request alone in this process on the same
  regions (cut, prior, network, encode; benchmarks._serve_stages), with ``network_regions_per_s``,
  the network's own rate on them (the graph the node serves, its batches and threads); and the
  issue-33 targets as ratios of this run: ``handle_over_network`` (>= 0.95), ``handle_over_maps``
  (>= 0.95), ``server_cpu_over_network`` (<= 1.3).
``--device``: where the node computes (cpu | cuda | auto, launch/serve.yaml's ``device``).
Weights: a trained ``--checkpoint``, or a fresh seeded generator of ``--width`` (untrained,
PyTorch's default initialisation; same cost as a trained one of that width); ``--prior``: a
fresh generator that corrects the default scene's physics prior.
Targets (issue 7): p50 <= 25 ms, >= 150 regions/s on 2 cores; issue 18: the cutting step >= 300
regions/s for 64 poses on a 0.1 mm cloud, and the cloud form end to end (handle) near the depth-map form.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from benchmarks._serve_forms import FORMS, run_forms
from benchmarks._serve_stages import served_network, stage_costs
from bus.inference_client import SERVICE, Cloud, InferenceError, TactileClient
from bus.pubsub import Bus
from bus.registry import Registry
from dataset.synth import analytic_contact_maps
from models.checkpoint import TrainConfig, load_generator
from models.networks import GeneratorConfig, UNetGenerator
from models.prior import PriorSpec
from models.runtime import DEVICES, CudaUnavailable, resolve_device
from nodes.inference import InferenceNode
from nodes.inference_passes import max_batch_on, thread_split
from perception.depthmap import (
    MODEL_CLOUD_SEED,
    MODEL_POINT_SPACING_M,
    DepthMapParams,
    contact_depth_map,
    contact_depth_maps,
)
from perception.depthmap_tensor import points_on_device
from perception.pointcloud import VoxelIndex
from perception.registration import ModelCloud, sample_model_cloud
from workcell.kinematics import GripperGeometry
from workcell.scene import load_scene

DEPTH_RANGE_M = (-0.0015, 0.0025)  # the synthetic dataset's (dataset.synth)
YCB = sorted(str(p) for p in (Path(__file__).resolve().parent.parent / "assets" / "ycb").glob("*.obj"))


# The prior a collection session on the default scene gives (models.prior): its GelSight, and
# its depth-maps' crop (the sensed 19.9 x 14.9 mm plus 2 mm margins; y range -5..10 mm), drawn
# over the sensor's field on 84 rows of square pixels, as the demo's config draws it.
SESSION_PRIOR = PriorSpec(
    scene="scenes/ycb_three.yaml", depth_crop_m=(0.02392, 0.015, 0.01894), drawn_at="sensor", drawn_rows=84
)


def write_checkpoint(
    path: Path,
    width: int,
    seed: int = 0,
    depth_range_m: tuple[float, float] = DEPTH_RANGE_M,
    prior: bool = False,
    pose_sigma_mm: float = 0.0,
) -> Path:
    """A checkpoint in models/train.py's format (what load_generator reads) holding a fresh,
    seeded generator of width ``width``, correcting the default scene's physics prior if asked,
    whose depth-maps are by default ``pose_sigma_mm`` off in the gel plane."""
    torch.manual_seed(seed)
    config = TrainConfig(
        generator=GeneratorConfig(
            ngf=width, prior=prior, prior_drawn_at=SESSION_PRIOR.drawn_at, prior_drawn_rows=SESSION_PRIOR.drawn_rows
        )
    )
    torch.save(
        {
            "generator": UNetGenerator(config.generator).state_dict(),
            "train_config": config.to_dict(),
            "depth_range_m": list(depth_range_m),
            "depth_map_method": "surface",  # as a model trained today
            **({"prior": dataclasses.replace(SESSION_PRIOR, pose_sigma_mm=pose_sigma_mm).to_dict()} if prior else {}),
        },
        path,
    )
    return path


def depth_maps(count: int, seed: int, y_far_m: float = DEPTH_RANGE_M[1]) -> np.ndarray:
    """count x 100 x 100 float32 contact depth-maps (metres) of random analytic contacts."""
    return analytic_contact_maps(count, seed, y_far_m)


def start_server(
    name: str, checkpoint: Path, params: dict[str, Any], env: dict[str, str], log: TextIO
) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "nodes.inference",
            "--name",
            name,
            "--params",
            json.dumps({"checkpoint": str(checkpoint), **params}),
        ],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _throughput(registry: Registry, maps: np.ndarray, clients: int, seconds: float) -> tuple[float, int]:
    """(regions per second while every client sends, regions served in all with the warm-ups)."""
    counts = [0] * clients
    errors: list[Exception] = []
    start = threading.Barrier(clients + 1)

    def planner(index: int) -> None:
        try:
            with contextlib.closing(Bus(f"planner{index}", registry)) as bus, TactileClient(bus, 60.0) as client:
                client.estimate(maps)  # connected and warm before the clock starts
                start.wait()
                deadline = time.monotonic() + seconds
                while time.monotonic() < deadline:
                    client.estimate(maps)
                    counts[index] += len(maps)
        except (InferenceError, threading.BrokenBarrierError) as exc:
            errors.append(exc)
            start.abort()  # nobody waits for a client that failed

    threads = [threading.Thread(target=planner, args=(i,)) for i in range(clients)]
    for thread in threads:
        thread.start()
    with contextlib.suppress(threading.BrokenBarrierError):
        start.wait()
    began = time.monotonic()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    return sum(counts) / (time.monotonic() - began), sum(counts) + clients * len(maps)


def surface_gel_poses(cloud: ModelCloud, count: int, seed: int, press_m: float = 0.0005) -> np.ndarray:
    """``count`` gel-to-world poses touching the model (model frame = world) at random surface
    points: the gel's +y against the outward normal, ``press_m`` into the surface, a random
    turn about the normal."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for pose, i in zip(poses, rng.integers(len(cloud.points_m), size=count)):
        y_axis = -cloud.normals[i]
        helper = np.eye(3)[int(np.argmin(np.abs(y_axis)))]
        x_axis = np.cross(y_axis, helper)
        x_axis /= np.linalg.norm(x_axis)
        angle = rng.uniform(0, 2 * np.pi)
        x_axis = np.cos(angle) * x_axis + np.sin(angle) * np.cross(y_axis, x_axis)
        pose[:3, :3] = np.column_stack([x_axis, y_axis, np.cross(x_axis, y_axis)])
        pose[:3, 3] = cloud.points_m[i] + press_m * y_axis
    return poses


def _cut_rates(
    index: VoxelIndex,
    on_device: torch.Tensor | None,
    poses: np.ndarray,
    geometry: GripperGeometry,
    params: DepthMapParams,
    per_gel: int,
    threads: int,
) -> dict[str, float]:
    """Depth-map cutting in this process, regions/s: the batched indexed pass on the node's
    ``threads`` (index built beforehand, as the node caches it), with the index's points
    ``on_device`` too where the node serves on a GPU (``cut_device_regions_per_s``), and the way
    before it (a pass over the whole cloud per gel, ``per_gel`` gels)."""

    def batched(device_points: torch.Tensor | None) -> float:
        cut = (index, np.eye(4), poses, geometry, params)
        contact_depth_maps(*cut, threads=threads, device_points=device_points)  # compiled and warm
        started = time.perf_counter()
        contact_depth_maps(*cut, threads=threads, device_points=device_points)
        return round(len(poses) / (time.perf_counter() - started), 1)

    rates = {"cut_regions_per_s": batched(None)}
    if on_device is not None:
        rates["cut_device_regions_per_s"] = batched(on_device)
    started = time.perf_counter()
    for pose in poses[:per_gel]:
        contact_depth_map(index.points_m, np.eye(4), pose, geometry, params)
    return {**rates, "cut_per_gel_regions_per_s": round(per_gel / (time.perf_counter() - started), 1)}


def _prior_cpu_ms_per_region(checkpoint: Path, maps: np.ndarray) -> float | None:
    """CPU ms per region of the physics prior's images (what the node renders beside each
    depth-map, models.prior), in this process, best of three; None for a model without one."""
    generator, _ = load_generator(checkpoint)
    if generator.prior is None:
        return None
    best = float("inf")
    for _ in range(3):
        started = time.process_time()
        generator.prior.channels(maps)
        best = min(best, time.process_time() - started)
    return best / len(maps) * 1e3


def _request_rate(call: Any, regions: int, requests: int) -> tuple[float, float]:
    """(p50 ms of ``requests`` calls, regions/s over them)."""
    latencies = []
    for _ in range(requests):
        started = time.perf_counter()
        call()
        latencies.append(time.perf_counter() - started)
    return round(statistics.median(latencies) * 1e3, 1), round(regions * requests / sum(latencies), 1)


def bench_points(
    registry: Registry,
    args: argparse.Namespace,
    checkpoint: Path,
    model: str,
    serves: str,
    servers: list[subprocess.Popen[bytes]],
) -> list[dict]:
    """The planner's cloud form beside the depth-map form and the network alone, per YCB
    object and pose count, with the stages' costs (benchmarks._serve_stages)."""
    generator, depth_range_m = load_generator(checkpoint)
    network, split, device = served_network(generator, depth_range_m, model, serves, args.threads, args.max_batch)
    geometry = load_scene(InferenceNode.Params.scene).gripper_geometry()  # as the server's
    params = DepthMapParams(y_range_m=depth_range_m, method=generator.depth_map_method)  # as the server cuts
    rows = []
    with contextlib.closing(Bus("planner_points", registry)) as bus, TactileClient(bus, 300.0) as client:
        for mesh in YCB[: args.objects]:
            cloud = sample_model_cloud(mesh, MODEL_POINT_SPACING_M, seed=MODEL_CLOUD_SEED)
            points = cloud.points_m.astype(np.float32)  # what a planner sends: half the bytes
            index = VoxelIndex(points)
            on_device = points_on_device(index.points_m, device) if device != "cpu" else None  # as the node's
            for count in args.poses:
                poses = surface_gel_poses(cloud, count, args.seed)
                maps = contact_depth_maps(index, np.eye(4), poses, geometry, params).depth_maps_m
                row: dict[str, Any] = {
                    "object": Path(mesh).stem,
                    "cloud_points": len(points),
                    "poses": count,
                    **_cut_rates(index, on_device, poses, geometry, params, min(count, 4), args.threads),
                }
                handle = Cloud(points)
                started = time.perf_counter()
                client.estimate_at(handle, poses)
                row["first_request_ms"] = round((time.perf_counter() - started) * 1e3, 1)
                cpu_before = sum(_cpu_seconds(server.pid) for server in servers)
                row["handle_p50_ms"], row["handle_regions_per_s"] = _request_rate(
                    lambda: client.estimate_at(handle, poses), count, args.point_requests
                )
                server_cpu = sum(_cpu_seconds(server.pid) for server in servers) - cpu_before
                row["handle_server_cpu_ms_per_region"] = round(server_cpu / (count * args.point_requests) * 1e3, 2)
                row["points_p50_ms"], row["points_regions_per_s"] = _request_rate(
                    lambda: client.estimate_at(points, poses), count, args.point_requests
                )
                row["maps_p50_ms"], row["maps_regions_per_s"] = _request_rate(
                    lambda: client.estimate(maps), count, args.point_requests
                )
                stages = stage_costs(
                    index, on_device, poses, geometry, params, generator, depth_range_m, network,
                    split.input_threads, args.point_requests,
                )  # fmt: skip
                rows.append({**row, "stage_cpu_ms_per_region": stages, **_ratios(row, stages)})
    return rows


def _ratios(row: dict[str, Any], stages: dict[str, float]) -> dict[str, float]:
    """The issue's targets as ratios of this row's side-by-side figures: the cloud handle
    against the network alone (>= 0.95), as the node runs it and one pass at a time on all its
    threads, and against the depth-map form (>= 0.95); the server's CPU per region against the
    network's own (<= 1.3), both ways."""
    handle, cpu = row["handle_regions_per_s"], row["handle_server_cpu_ms_per_region"]
    return {
        "network_regions_per_s": stages["network_regions_per_s"],
        "handle_over_network": round(handle / stages["network_regions_per_s"], 3),
        "handle_over_one_pass_network": round(handle / stages["network_one_pass_regions_per_s"], 3),
        "handle_over_maps": round(handle / row["maps_regions_per_s"], 3),
        "server_cpu_over_network": round(cpu / stages["network_cpu_ms"], 3),
        "server_cpu_over_one_pass_network": round(cpu / stages["network_one_pass_cpu_ms"], 3),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The benchmark; with ``--forms``, once per form of the checkpoint, side by side
    (benchmarks._serve_forms)."""
    return run_forms(args, _run_form) if args.forms else _run_form(args, {})


def _run_form(args: argparse.Namespace, node_params: dict[str, Any]) -> dict[str, Any]:
    try:
        device = resolve_device(args.device, args.runtime, args.precision)  # the node's own check, before it starts
    except CudaUnavailable as exc:
        raise SystemExit(f"dtx bench serve: {exc.code}: {exc}") from exc
    max_batch_on(device, args.max_batch)  # a bad width refused before a node starts; 0: the node's own
    with tempfile.TemporaryDirectory(prefix="dtxb") as tmp:
        checkpoint, weights, depth_range_m = _weights(args, Path(tmp))
        bus_dir = Path(tmp) / "bus"
        registry = Registry(bus_dir)
        log_path = Path(tmp) / "server.log"
        servers = _start_servers(args, checkpoint, bus_dir, log_path, node_params)
        try:
            maps = depth_maps(max(args.regions, 16), args.seed, depth_range_m[1])
            _wait_until_serving(registry, servers, args.workers, log_path)
            model, serves, latencies = _latencies_ms(registry, len(servers), maps, args.requests)
            # The pass width the nodes took (what they serve decides it on the CPU), for the stages.
            args = argparse.Namespace(
                **{**vars(args), "max_batch": max_batch_on(device, args.max_batch, network=serves == "network")}
            )
            cpu_before = sum(_cpu_seconds(server.pid) for server in servers)
            throughput, served = _throughput(registry, maps[: args.regions], args.clients, args.seconds)
            # On a shared machine the wall-clock rate depends on the neighbours; the servers'
            # own CPU time per region much less (2 free cores serve at most 2 / that).
            cpu_per_region = (sum(_cpu_seconds(server.pid) for server in servers) - cpu_before) / served
            points = bench_points(registry, args, checkpoint, model, serves, servers) if args.points else None
            prior_ms = _prior_cpu_ms_per_region(checkpoint, maps)
        finally:
            _stop_servers(servers)
        failed = [server.returncode for server in servers if server.returncode not in (0, -signal.SIGINT)]
        if failed:
            raise RuntimeError(f"an inference node failed ({failed}): {log_path.read_text()[-2000:]}")
    return {
        "weights": weights,
        "model": model,
        "workers": args.workers,
        "threads_per_worker": args.threads,
        # How each worker shares them (nodes.inference_passes.thread_split); the network alone
        # in the points rows runs as the node runs it, and one pass at a time on all of them.
        "serves": serves,
        "thread_split": dataclasses.asdict(thread_split(args.threads, device)),
        "p50_ms": round(statistics.median(latencies), 2),
        "p99_ms": round(float(np.percentile(latencies, 99)), 2),
        "regions_per_s": round(throughput, 1),
        "server_cpu_ms_per_region": round(cpu_per_region * 1e3, 2),
        "server_bound_regions_per_s_2_cores": round(2.0 / cpu_per_region, 1),
        **(
            {
                "prior_cpu_ms_per_region": round(prior_ms, 2),
                "prior_share_of_server_cpu": round(prior_ms / (cpu_per_region * 1e3), 2),
            }
            if prior_ms
            else {}
        ),
        "throughput_setup": f"{args.clients} clients x {args.regions} regions/request, max_batch {args.max_batch}",
        "targets": "p50 <= 25 ms, >= 150 regions/s on 2 cores",
        **({"points": points} if points is not None else {}),
    }


def _weights(args: argparse.Namespace, tmp: Path) -> tuple[Path, str, tuple[float, float]]:
    """(checkpoint to serve, its description, its depth range in metres): ``--checkpoint``, or a
    fresh seeded generator written to ``tmp``."""
    if args.checkpoint:
        checkpoint, weights = Path(args.checkpoint), f"checkpoint {args.checkpoint}"
        depth_range = torch.load(checkpoint, map_location="cpu", weights_only=True)["depth_range_m"]
    else:
        checkpoint = write_checkpoint(tmp / "fresh.pt", args.width, args.seed, prior=args.prior)
        weights = f"fresh generator, width {args.width}{', physics prior' if args.prior else ''} (seeded, untrained)"
        depth_range = DEPTH_RANGE_M
    return checkpoint, weights, (float(depth_range[0]), float(depth_range[1]))


def _start_servers(
    args: argparse.Namespace, checkpoint: Path, bus_dir: Path, log_path: Path, node_params: dict[str, Any]
) -> list[subprocess.Popen[bytes]]:
    """``--workers`` inference nodes on the bus in ``bus_dir``, all logging to ``log_path``, with
    ``node_params`` beside the benchmark's own."""
    params = {
        **node_params,
        "runtime": args.runtime,
        "precision": args.precision,
        "device": args.device,
        "threads": args.threads,
        "max_batch": args.max_batch,
        "batch_window_ms": args.window_ms,
    }
    with open(log_path, "w") as log:
        return [
            start_server(
                f"inference_bench_{i + 1}", checkpoint, params, {**os.environ, "DTX_BUS_DIR": str(bus_dir)}, log
            )
            for i in range(args.workers)
        ]


def _wait_until_serving(
    registry: Registry, servers: list[subprocess.Popen[bytes]], workers: int, log_path: Path
) -> None:
    """Until ``workers`` nodes offer the service; RuntimeError if one exits first."""
    while len(registry.lookup("service", SERVICE)) < workers:  # loading the model
        if any(server.poll() is not None for server in servers):
            raise RuntimeError(f"an inference node failed to start: {log_path.read_text()[-2000:]}")
        time.sleep(0.1)


def _latencies_ms(registry: Registry, workers: int, maps: np.ndarray, requests: int) -> tuple[str, str, list[float]]:
    """(the model the nodes serve, what they serve of it (network | prior), ms from call to
    decoded reply of ``requests`` one-region requests one after another), after one warm-up
    request per worker."""
    with contextlib.closing(Bus("planner", registry)) as bus, TactileClient(bus, 120.0) as client:
        for _ in range(workers):
            client.estimate(maps[:1])  # warm-up: lazy allocations in every worker
        model = client.last_reply.model.rsplit(" on ", 1)[0] if client.last_reply else ""
        serves = client.last_reply.serves if client.last_reply else ""
        latencies = []
        for i in range(requests):
            started = time.perf_counter()
            client.estimate(maps[i % len(maps)])
            latencies.append((time.perf_counter() - started) * 1e3)
    return model, serves, latencies


def _stop_servers(servers: list[subprocess.Popen[bytes]]) -> None:
    """SIGINT to every node, then a kill for any still running after 30 s."""
    for server in servers:
        server.send_signal(signal.SIGINT)
    for server in servers:
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dtx bench serve``."""
    parser.add_argument("--checkpoint", help="serve this trained generator instead of a fresh one")
    parser.add_argument("--width", type=int, default=32, help="ngf of the fresh generator")
    parser.add_argument("--runtime", choices=["onnxrt", "eager"], default="onnxrt")
    parser.add_argument("--precision", choices=["fp32", "bf16", "int8"], default="fp32")
    parser.add_argument("--device", choices=list(DEVICES), default="cpu", help="where the node computes")
    parser.add_argument("--workers", type=int, default=1, help="inference node processes (round robin)")
    parser.add_argument("--threads", type=int, default=2, help="compute threads per worker")
    parser.add_argument(
        "--max-batch", type=int, default=0, help="regions in one forward pass (0: the node's default for the device)"
    )
    parser.add_argument("--window-ms", type=float, default=2.0)
    parser.add_argument("--requests", type=int, default=200, help="single-region requests for the latency")
    parser.add_argument("--regions", type=int, default=32, help="regions per request for the throughput")
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--prior", action="store_true", help="the fresh generator corrects the physics prior")
    parser.add_argument("--points", action="store_true", help="also the cloud form (estimate_at) on YCB clouds")
    parser.add_argument("--poses", type=int, nargs="+", default=[64, 256], help="gel poses per cloud request")
    parser.add_argument("--objects", type=int, default=len(YCB), help="the first N YCB objects (--points)")
    parser.add_argument("--point-requests", type=int, default=3, help="requests per object and pose count")
    parser.add_argument(
        "--forms",
        nargs="+",
        choices=FORMS,
        default=[],
        help="serve --checkpoint as each of these, side by side in one run: before (as a checkpoint trained "
        "before the uncertainty: its network alone), network (with the uncertainty), served (its own choice)",
    )
    parser.add_argument("--dataset", help="with --forms: each form's accuracy on this dataset's test split")
