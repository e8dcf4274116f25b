"""The stages of a cloud request in the inference node, each measured alone in the benchmark's
process on the very regions the node is asked about (``dtx bench serve --points``): the cut
(perception.depthmap.contact_depth_maps on the kept index, the node's threads or its GPU), the prior (the
network's input with the physics prior's images, models.data.network_input), the network (the
graph the node serves, in its batches, same runtime, precision, threads and device; the prior's
image alone where the checkpoint serves the prior), the uncertainty (models.uncertainty, where the
checkpoint has one) and the encoding of the reply (msgs.codec). The network's own rate here is what the planner's path is
measured against: the work around it is what separates the two."""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import torch

from models.data import network_input, to_uint8_rgb
from models.networks import UNetGenerator
from models.runtime import Runner, network_runner
from models.serving import prior_images
from msgs.codec import encode
from msgs.inference import TactileEstimateReply
from nodes.inference_passes import ThreadSplit, thread_split
from perception.depthmap import DepthMapParams, contact_depth_maps
from perception.pointcloud import VoxelIndex
from perception.surface import DEPTH_MAP_METHODS
from workcell.kinematics import GripperGeometry


def _cpu_ms_per_region(work: Callable[[], object], regions: int, repeats: int) -> float:
    """This process's CPU ms per region of ``work``, best of ``repeats`` (the least disturbed)."""
    best = float("inf")
    for _ in range(repeats):
        started = time.process_time()
        work()
        best = min(best, time.process_time() - started)
    return best / regions * 1e3


@dataclasses.dataclass(frozen=True)
class ServedNetwork:
    """The graph the node serves, as it runs it: ``run`` in ``lanes`` forward passes side by side
    (each on its lane's threads; nodes.inference_passes.thread_split) of ``max_batch`` regions;
    and ``one_pass`` the same graph on all the node's ``threads``, one pass at a time (None where
    the node runs one pass at a time: ``run`` is that graph)."""

    run: Runner
    lanes: int
    max_batch: int
    one_pass: Runner | None
    threads: int


def served_network(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    model: str,
    serves: str,
    threads: int,
    max_batch: int,
) -> tuple[ServedNetwork, ThreadSplit, str]:
    """The graph the node serves as it runs it (its replies' ``serves``, and its ``model`` line:
    int8 refused falls back to fp32), how it shares its threads, and its device; this process set
    as the node's, so that the network and the prior compute here as they do there."""
    served_as = re.search(r"\(ngf \d+, (?:(\w+) (\w+), )?(\w+)\)", model)
    if served_as is None:
        raise ValueError(f"the node's model line {model!r} does not say '(ngf N, [runtime precision, ]device)'")
    runtime, precision, device = served_as.groups()
    split = thread_split(threads, device)
    if serves == "prior":  # no network pass: the prior's image is what the input carries

        def prior(x: np.ndarray | torch.Tensor) -> np.ndarray:
            return prior_images(generator, torch.as_tensor(x)).cpu().numpy()

        network = ServedNetwork(run=prior, lanes=split.lanes, max_batch=max_batch, one_pass=None, threads=1)
    else:
        served = (generator, depth_range_m, runtime, precision)
        network = ServedNetwork(
            run=network_runner(*served, split.lane_threads, device),
            lanes=split.lanes,
            max_batch=max_batch,
            one_pass=None if split.lanes == 1 else network_runner(*served, threads, device),
            threads=threads,
        )
    if generator.prior is not None and device != "cpu":  # the prior draws where the node's does
        generator.prior = generator.prior.on(device)
    torch.set_num_threads(split.lane_threads)
    cv2.setNumThreads(1)
    return network, split, device


def network_rate(
    run: Runner, x: np.ndarray | torch.Tensor, max_batch: int, repeats: int, lanes: int = 1
) -> tuple[float, float, np.ndarray]:
    """(regions/s, CPU ms per region, the outputs) of ``run`` over ``x`` in passes of
    ``max_batch``, ``lanes`` of them side by side as the node runs them, ``repeats`` times back
    to back. The outputs are a first, untimed round over every pass: it warms every pass, not
    one, since a GPU left idle by the stage before clocks down, and a few timed passes of a
    small request would measure its ramp rather than the network."""

    def one_pass(start: int) -> np.ndarray:
        return run(x[start : start + max_batch])

    starts = list(range(0, len(x), max_batch))
    with ThreadPoolExecutor(lanes) as pool:
        outputs = np.concatenate(list(pool.map(one_pass, starts)))
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in pool.map(one_pass, starts * repeats):
            pass
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return len(x) * repeats / wall, cpu / (len(x) * repeats) * 1e3, outputs


def _reply_and_uncertainty(
    generator: UNetGenerator, x: torch.Tensor, outputs: np.ndarray, repeats: int
) -> tuple[TactileEstimateReply, dict[str, float]]:
    """The reply the node sends for the served ``outputs`` of network input ``x``, and the
    uncertainty's CPU ms per region where the checkpoint has one ({} where it has none)."""
    images = to_uint8_rgb(torch.from_numpy(outputs))
    uncertainty = generator.uncertainty
    if uncertainty is None:
        return TactileEstimateReply(images=images), {}
    estimate = torch.from_numpy(outputs)
    u = uncertainty.levels(x, estimate)
    region_u = [float(m) for m in u.reshape(len(u), -1).mean(axis=1)]
    reply = TactileEstimateReply(images=images, uncertainty=u, uncertainty_status="ok", region_uncertainty=region_u)
    cost = _cpu_ms_per_region(lambda: uncertainty.levels(x, estimate), len(u), repeats)
    return reply, {"uncertainty_cpu_ms": round(cost, 3)}


def _cut_cpu_ms_by_method(
    cut: Callable[[], object],
    index: VoxelIndex,
    poses: np.ndarray,
    geometry: GripperGeometry,
    params: DepthMapParams,
    threads: int,
    device_points: torch.Tensor | None,
    repeats: int,
) -> dict[str, float]:
    """The served cut's CPU ms a region (``cut``, by ``params.method``: ``cut_cpu_ms``) and each
    bin rule's (perception.surface) beside it in the same run, the served one timed once: what the
    surface costs over the nearest point."""

    def cut_by(method: str) -> Callable[[], object]:
        other = dataclasses.replace(params, method=method)
        return lambda: contact_depth_maps(
            index, np.eye(4), poses, geometry, other, allow_empty=True, threads=threads, device_points=device_points
        )

    served = round(_cpu_ms_per_region(cut, len(poses), repeats), 3)
    by_method = {
        f"cut_{m}_cpu_ms": served
        if m == params.method
        else round(_cpu_ms_per_region(cut_by(m), len(poses), repeats), 3)
        for m in DEPTH_MAP_METHODS
    }
    return {"cut_cpu_ms": served, **by_method}


def stage_costs(
    index: VoxelIndex,
    device_points: torch.Tensor | None,
    poses: np.ndarray,
    geometry: GripperGeometry,
    params: DepthMapParams,
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    network: ServedNetwork,
    input_threads: int,
    repeats: int,
) -> dict[str, float]:
    """CPU ms per region of each stage of a request of ``poses`` on the cloud ``index`` (cut on
    ``input_threads`` or the device of ``device_points``, its points there, as the node cuts
    them; None: the CPU), and the network's own rate on these regions as the node runs it
    (``network_regions_per_s``) and one pass at a time on all its threads."""

    def cut() -> np.ndarray:
        maps = contact_depth_maps(
            index,
            np.eye(4),
            poses,
            geometry,
            params,
            allow_empty=True,
            threads=input_threads,
            device_points=device_points,
        )
        return maps.depth_maps_m

    maps = cut()
    x = network_input(maps, depth_range_m, generator.config, generator.prior)  # where the prior draws, as the node's
    n = len(poses)
    rate, network_cpu, outputs = network_rate(network.run, x, network.max_batch, repeats, network.lanes)
    reply, stages = _reply_and_uncertainty(generator, x, outputs, repeats)
    one_pass_rate, one_pass_cpu = rate, network_cpu
    if network.one_pass is not None:
        lane_threads = torch.get_num_threads()
        torch.set_num_threads(network.threads)  # eager PyTorch's threads are the process's
        try:
            one_pass_rate, one_pass_cpu, _ = network_rate(network.one_pass, x, network.max_batch, repeats)
        finally:
            torch.set_num_threads(lane_threads)

    return {
        **stages,
        **_cut_cpu_ms_by_method(cut, index, poses, geometry, params, input_threads, device_points, repeats),
        "prior_cpu_ms": round(
            _cpu_ms_per_region(
                lambda: network_input(maps, depth_range_m, generator.config, generator.prior), n, repeats
            ),
            3,
        ),
        "network_cpu_ms": round(network_cpu, 3),
        "encode_cpu_ms": round(_cpu_ms_per_region(lambda: encode("/inference/estimate", reply), n, repeats), 3),
        "network_regions_per_s": round(rate, 1),
        "network_one_pass_cpu_ms": round(one_pass_cpu, 3),
        "network_one_pass_regions_per_s": round(one_pass_rate, 1),
    }
