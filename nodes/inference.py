"""Inference server node: serves ``/inference/estimate`` (msgs.TactileEstimateRequest ->
msgs.TactileEstimateReply) with the trained pix2pix generator, for the grasp planner.

- A request holds N regions: ``depth_maps`` (N x 100 x 100 float32, metres in the gel
  frame), or a cloud with ``gel_poses`` (N x 4 x 4, gel to world), from which the depth-maps
  are cut as the patch extractor cuts them (perception.depthmap, y range = the checkpoint's
  depth_range_m), all N in one pass over a spatial index of the cloud.
- Cloud handles: the reply to a request with ``points`` names the cloud (``cloud_id``, SHA-256 of
  its dtype, shape and bytes: the same on every worker); later requests send only that id. A worker
  keeps the spatial index of its last ``index_cache`` clouds (~1-5 s to build each); an id it does
  not hold is refused with ``unknown_cloud``, and the client sends the points again.
- Batching: requests from every client that arrive within ``batch_window_ms`` of the oldest
  waiting one (and all that queued while the previous batch ran) go through the network
  together, in forward passes of at most ``max_batch`` regions; each client gets its own
  reply when the batch is done. On the CPU each of ``threads`` serves whole passes (cut, prior,
  network, uncertainty); on a GPU a pass's input is drawn while the one before runs.
- ``images``: what the checkpoint serves (models.serving), or the node's ``serves``: the
  network's estimate (dropout off), or the physics prior's image, for which no network runs.
- ``uncertainty``, in every reply: per pixel u (levels 0..255), the checkpoint's calibrated RMS
  of |estimate - truth| (models.uncertainty) from each pass's input and served estimate, on the
  node's device; ``region_uncertainty`` each region's mean u. A checkpoint without one: status
  ``absent``, the array empty (never zeros).
- ``region_points`` and ``region_surface_bins``: each region's cloud points in its contact volume
  and its map's bins holding a surface, how much geometry the estimate rests on.
- ``pose_sigma_mm``: the in-plane pose uncertainty (mm) of the request's geometry, which a
  model with a physics prior blurs its prior's image by (models.prior): 0 for exact geometry,
  up to ``MAX_POSE_SIGMA_MM``; negative for the checkpoint's default. The reply says which it used.
- A bad request (shape, dtype, NaN/inf, empty, too many regions, points or points x regions, both
  or neither input, gel poses that are not rigid transforms, a pose_sigma_mm that is not finite or
  above the bound, dropout_samples other than 1) gets an error reply with code ``bad_request``; a
  wrong schema is refused by the bus. The node keeps serving. A gel that does not reach the cloud
  is answered per region (``region_status`` ``out_of_reach``, the empty map's estimate).
- Scaling out: start several of these nodes; clients round-robin over them (launch/serve.yaml).

Params: ``checkpoint`` (models/train.py format), ``serves`` ("": the checkpoint's choice; network or
prior override it, prior only for a checkpoint with one), ``runtime`` (onnxrt | eager), ``precision``
(fp32 | bf16 | int8: bf16 with eager only; int8, the encoder's convolutions quantised
(models.runtime.int8_convolutions), with onnxrt on the CPU only), ``device`` (cpu | cuda | auto:
ONNX Runtime's CUDA provider or eager PyTorch on the GPU, the physics prior drawn there too
(models.prior_tensor), a cloud's depth-maps cut there (perception.depthmap_tensor) and the
network's input left there; auto takes CUDA where the runtime has it; cuda without it: the node does
not start, its status the code ``cuda_unavailable`` and the reason on /log),
``int8_max_ssim_loss`` (int8 is measured against fp32 at start on contacts drawn as its
calibration's; above this SSIM loss the node serves fp32 and logs why), ``threads`` (shared
between the forward passes and the next passes' input: nodes.inference_passes.thread_split),
``max_regions``, ``max_points``, ``max_batch`` (regions in one forward pass; 0: the device's
own, nodes.inference_passes.max_batch_on), ``batch_window_ms``, ``max_point_visits`` (cloud
points near the gels, summed over regions: the work of cutting the depth-maps), ``index_cache``,
``scene`` (gripper geometry for the points path), ``margin_m`` (crop margin, as the patch
extractor's).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
import torch

from bus.node import Node, run_node
from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.errors import ModelConfigError
from models.networks import UNetGenerator
from models.prior import PhysicsPrior
from models.runtime import CudaUnavailable, Runner, int8_ssim_loss, network_runner, resolve_device
from models.serving import prior_images
from models.uncertainty import ServedUncertainty
from msgs.inference import TactileEstimateReply, TactileEstimateRequest
from nodes.inference_passes import ServedRegions, forward_pass_parts, max_batch_on, thread_split
from nodes.inference_requests import BadRequest, UnknownCloud, check_params, checked_regions, checked_serves, cloud_id
from perception.depthmap import DepthMapParams, PlannedCut, contact_depth_maps, plan_contact_cut, surface_bins
from perception.depthmap_tensor import points_on_device
from perception.errors import PerceptionError
from perception.pointcloud import VoxelIndex


@dataclasses.dataclass(frozen=True)
class _KeptCloud:
    index: VoxelIndex
    device_points: torch.Tensor | None  # the index's points on the node's GPU, where it serves on one


@dataclasses.dataclass
class _Job:
    request: TactileEstimateRequest
    regions: int
    arrived: float  # time.monotonic()
    future: Future[TactileEstimateReply]
    held: _KeptCloud | None  # the kept cloud a request named by its id alone


class InferenceNode(Node):
    @dataclasses.dataclass
    class Params:
        checkpoint: str = ""
        serves: str = ""  # "": the checkpoint's choice; network | prior override it
        runtime: str = "onnxrt"  # measured faster than eager on 2 busy cores (dtx bench inference)
        precision: str = "fp32"
        device: str = "auto"
        # The demo's model loses 0.00001 in int8; an untrained width-8 one 0.33 on an AMD Zen 3 and
        # 0.0004 on an Intel Xeon with AVX-512 VNNI (the CPU's int8 kernels decide). 0.01 is a
        # third of what the demo's model adds to the renderer's SSIM on the contact windows.
        int8_max_ssim_loss: float = 0.01
        threads: int = 2
        max_regions: int = 256
        max_points: int = 12_000_000  # every YCB model cloud at the 0.1 mm training spacing
        max_batch: int = 0  # regions in one forward pass; 0: the device's own (max_batch_on)
        batch_window_ms: float = 2.0
        # Points read while cutting, over all regions: ~4 ns each in the compiled pass (~1 s).
        max_point_visits: int = 250_000_000
        index_cache: int = 2  # clouds whose spatial index is kept (a 0.1 mm cloud's: ~100-300 MB)
        scene: str = "scenes/ycb_three.yaml"
        margin_m: float = 0.002

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        p = self.params
        check_params(p)
        try:
            self.device = resolve_device(p.device, p.runtime, p.precision)
        except CudaUnavailable as exc:
            self._refuse_to_start(exc)
        started = time.perf_counter()
        generator, self.depth_range_m = load_generator(p.checkpoint)
        self.serves = checked_serves(p, generator)  # network | prior: the checkpoint's, or the override
        self.config = generator.config
        self.generator = generator
        torch.set_flush_denormal(True)  # denormal activations make CPU convolutions much slower
        # The prior's images render in chunks on the node's own threads; OpenCV's pool inside
        # each chunk only added threads (2.3 -> 2.0 ms CPU per region, same wall time).
        cv2.setNumThreads(1)
        try:
            self.precision, self.network = self._runner(generator)
        except CudaUnavailable as exc:  # a CUDA provider that could not start (no GPU, no cuDNN)
            if p.device != "auto":
                self._refuse_to_start(exc)
            self.log.warning("device auto could not use CUDA (%s); serving on the CPU", exc)
            self.device = "cpu"
            self.precision, self.network = self._runner(generator)
        self.prior = self._prior_on_device(generator.prior)
        self.uncertainty = self._uncertainty_on_device(generator.uncertainty)
        self.max_batch = max_batch_on(self.device, p.max_batch, network=self.serves == "network")
        from workcell.scene import load_scene  # noqa: PLC0415 - the gripper geometry, as the patch extractor's

        self.geometry = load_scene(p.scene).gripper_geometry()
        size = self.config.image_size
        method = generator.depth_map_method  # a cloud is cut by the rule the checkpoint was trained on
        self.depth_map_params = DepthMapParams((size, size), p.margin_m, self.depth_range_m, method=method)
        self.model = self._model_text()
        self.forward_passes = 0  # passes of the network (none while serving the prior)
        self._clouds: dict[str, _KeptCloud] = {}  # cloud id -> its index, least recently used first
        self._clouds_lock = threading.Lock()  # looked up on the bus thread, filled in the background
        # The prior's images in chunks where this thread draws the input (a GPU node's; below).
        self._prior_pool = ThreadPoolExecutor(self.split.input_threads, thread_name_prefix=f"{name}-prior")
        self._lanes = ThreadPoolExecutor(self.split.lanes, thread_name_prefix=f"{name}-pass")  # forward passes
        self._warm_up_cutting()
        self._lock = threading.Condition()
        self._waiting: list[_Job] = []
        self._flush_queued = False
        self.create_service("/inference/estimate", TactileEstimateRequest, TactileEstimateReply, self.on_estimate)
        self.log.info(
            "loaded %s in %.2f s: depth range %s m, max batch %d, window %.1f ms, %s",
            self.model,
            time.perf_counter() - started,
            self.depth_range_m,
            self.max_batch,
            p.batch_window_ms,
            self.split,
        )

    def _model_text(self) -> str:
        """What this worker serves, in the replies' ``model`` and the log: checkpoint, runtime, device."""
        p, ngf = self.params, self.config.ngf
        if self.network is None:
            served = f"(ngf {ngf}, {self.device}) serves the prior: no network pass"
        else:
            served = f"(ngf {ngf}, {p.runtime} {self.precision}, {self.device}) serves the network"
        trust = " (its uncertainty absent)" if self.uncertainty is None else self.uncertainty.reply_note()
        return f"{Path(p.checkpoint).name} {served}{trust} on {self.name}"

    def _runner(self, generator: UNetGenerator) -> tuple[str, Runner | None]:
        """(the precision served, the network's runner); ("", None) serving the prior, for which
        no network runs. int8 is served only where it holds: measured against fp32 first
        (models.runtime.int8_ssim_loss)."""
        p = self.params
        self.split = thread_split(p.threads, self.device)
        torch.set_num_threads(self.split.lane_threads)
        if self.serves == "prior":
            return "", None

        def forward(network: UNetGenerator, precision: str) -> Runner:
            threads = self.split.lane_threads
            return network_runner(network, self.depth_range_m, p.runtime, precision, threads, self.device)

        precision, deterministic = p.precision, forward(generator, p.precision)
        if precision == "int8":
            fp32 = forward(generator, "fp32")
            loss = int8_ssim_loss(generator, self.depth_range_m, fp32, deterministic)
            if loss > p.int8_max_ssim_loss:
                self.log.warning(
                    "int8 refused: it loses %.4f SSIM against fp32 on contacts like its calibration's, more "
                    "than int8_max_ssim_loss %g; serving fp32",
                    loss,
                    p.int8_max_ssim_loss,
                )
                precision, deterministic = "fp32", fp32
            else:
                self.log.info("int8 holds: %.5f SSIM lost against fp32 (at most %g)", loss, p.int8_max_ssim_loss)
        return precision, deterministic

    def _refuse_to_start(self, error: CudaUnavailable) -> NoReturn:
        """Stop before serving: the reason on /log, its code this node's last status (its
        heartbeat, and ``dtx node list --all`` after it exits); run_node then exits without a
        respawn, as for any bad parameter."""
        self.log.error("%s: %s", error.code, error)
        self.status = error.code
        self._beat()
        Node.close(self)
        torch.set_flush_denormal(False)  # as close() leaves the process
        status = {"node": self.name, "pid": os.getpid(), "status": error.code, "text": str(error), "stamp": time.time()}
        self.bus.registry.write_node_status(self.name, status)
        raise error

    # -- requests ---------------------------------------------------------------------------
    def close(self) -> None:
        super().close()
        self._lanes.shutdown(wait=True)
        self._prior_pool.shutdown(wait=True)
        # Flush-to-zero is process state; leave the process as torch starts it (a node run
        # inside another program, e.g. a test, must not change that program's arithmetic).
        torch.set_flush_denormal(False)

    def on_estimate(self, request: TactileEstimateRequest) -> Future[TactileEstimateReply]:
        regions = checked_regions(request, self.params, self.config.image_size)
        held = None
        if request.cloud_id and not request.points.size:
            held = self._held(request.cloud_id)
            if held is None:
                raise UnknownCloud(
                    f"this worker ({self.name}) does not hold cloud {request.cloud_id} (it keeps its "
                    f"last {self.params.index_cache}): send the points again"
                )
        job = _Job(request, regions, time.monotonic(), Future(), held)
        with self._lock:
            self._waiting.append(job)
            self._lock.notify()  # a flush waiting for a full batch counts again
            start = not self._flush_queued
            self._flush_queued = True
        if start:
            self.background.submit(self._flush)
        return job.future

    # -- batches (in the background thread) -------------------------------------------------
    def _flush(self) -> None:
        """Wait out the batch window of the oldest request (or a full batch), then run all."""
        window_s = self.params.batch_window_ms / 1e3
        with self._lock:
            self._lock.wait_for(
                lambda: sum(j.regions for j in self._waiting) >= self.max_batch,
                timeout=max(0.0, self._waiting[0].arrived + window_s - time.monotonic()),
            )
            jobs, self._waiting, self._flush_queued = self._waiting, [], False
        try:
            self._run(jobs)
        except Exception as exc:  # noqa: BLE001 - an unexpected failure answers every waiting client, never hangs one
            for job in jobs:
                if not job.future.done():
                    job.future.set_exception(exc)

    def _run(self, jobs: list[_Job]) -> None:
        # A request refused before its depth-maps are cut (too much work) fails alone: the other
        # clients' requests in the batch go on.
        ready, sources, clouds = [], [], []
        for job in jobs:
            try:
                source, cloud = self._regions_of(job.request, job.held)
            except BadRequest as exc:
                job.future.set_exception(exc)
                continue
            ready.append(job)
            sources.append(source)
            clouds.append(cloud)
        if not ready:
            return
        sigmas = [self._pose_sigma_mm(job.request) for job in ready]
        served, point_counts, surfaces = self._estimates(sources, sigmas)
        offsets = np.cumsum([0] + [len(source) for source in sources])
        for i, job in enumerate(ready):
            rows = slice(offsets[i], offsets[i + 1])
            missed = "no model point in the contact volume: the gel does not reach the object"
            errors = [f"region {k}: {missed}" if c == 0 else "" for k, c in enumerate(point_counts[i])]
            if served.uncertainty is None:  # a checkpoint trained before the uncertainty: absent, never zeros
                u, status, region_u = np.zeros((0, *served.images.shape[1:3]), np.float32), "absent", []
            else:
                u, status, region_u = served.uncertainty[rows], "ok", served.region_uncertainty[rows].tolist()
            job.future.set_result(
                TactileEstimateReply(
                    images=served.images[rows],
                    uncertainty=u,
                    uncertainty_status=status,
                    region_uncertainty=region_u,
                    serves=self.serves,
                    model=self.model,
                    latency_ms=(time.monotonic() - job.arrived) * 1e3,  # queue, window and passes
                    region_status=["out_of_reach" if e else "ok" for e in errors],
                    region_errors=errors,
                    region_points=point_counts[i].tolist(),
                    region_surface_bins=surfaces[i].tolist(),
                    depth_range_m=[float(y) for y in self.depth_range_m],
                    cloud_id=clouds[i],
                    worker=self.name,
                    pose_sigma_mm=sigmas[i],
                )
            )

    def _estimates(
        self, sources: list[np.ndarray | PlannedCut], sigmas: list[float]
    ) -> tuple[ServedRegions, list[np.ndarray], list[np.ndarray]]:
        """(what is served for every region of the requests' ``sources``, in order; the points
        each region's gel met, -1 for a depth-map sent as one; the bins of each region's map with
        a surface below y_far), in passes of at most ``max_batch`` over the lanes, each writing its
        rows of the reply. On the CPU each lane cuts its pass's maps, draws their prior and serves
        them; on a GPU this thread draws each pass's input while the lane serves the one before."""
        point_counts = [np.full(len(source), -1, np.int64) for source in sources]
        surface = [np.zeros(len(source), np.int64) for source in sources]
        served = ServedRegions.empty(sum(len(s) for s in sources), self.config.image_size, self.uncertainty is not None)

        def draw(parts: list[tuple[int, int, int]]) -> torch.Tensor:
            maps = []
            for i, first, stop in parts:
                source = sources[i]
                if isinstance(source, PlannedCut):
                    patches = source.cut(first, stop, self.split.input_threads)
                    point_counts[i][first:stop] = patches.point_counts
                    part = patches.depth_maps_m
                else:
                    part = source[first:stop]
                surface[i][first:stop] = surface_bins(part, self.depth_range_m[1])
                maps.append((part, sigmas[i]))
            return self._network_input(maps)

        def drawn_and_served(parts: list[tuple[int, int, int]], rows: slice) -> None:
            self._serve_pass(draw(parts), served, rows)

        outputs, first_row = [], 0
        for parts in forward_pass_parts([len(source) for source in sources], self.max_batch, self.split.lanes):
            rows = slice(first_row, first_row + sum(stop - first for _, first, stop in parts))
            first_row = rows.stop
            if self.split.input_in_lanes:
                outputs.append(self._lanes.submit(drawn_and_served, parts, rows))
            else:
                outputs.append(self._lanes.submit(self._serve_pass, draw(parts), served, rows))
            if self.network is not None:
                self.forward_passes += 1
        for output in outputs:
            output.result()
        return served, point_counts, surface

    def _serve_pass(self, x: torch.Tensor, served: ServedRegions, rows: slice) -> None:
        """One pass, in a lane: the served estimate of network input ``x`` (the network's, or the
        prior's ``x`` carries) as the reply sends it, and its u, into ``served``'s ``rows``."""
        if self.network is None:
            estimate = prior_images(self.generator, x)
        else:
            estimate = torch.from_numpy(self.network(x))
        served.images[rows] = to_uint8_rgb(estimate)
        if served.uncertainty is not None and self.uncertainty is not None:
            u = served.uncertainty[rows]
            u[...] = self.uncertainty.levels(x, estimate)
            served.region_uncertainty[rows] = u.reshape(len(u), -1).mean(axis=1, dtype=np.float64)

    def _prior_on_device(self, prior: PhysicsPrior | None) -> PhysicsPrior | None:
        """The physics prior drawing where the network computes: on CUDA as batched tensor
        operations (models.prior_tensor), on the CPU in chunks on the node's threads; a renderer
        the tensor form does not cover stays on the CPU, with a log line saying why."""
        if prior is None or self.device == "cpu":
            return prior
        try:
            return prior.on(self.device)
        except ModelConfigError as exc:
            self.log.warning("the physics prior draws on the CPU: %s", exc)
            return prior

    def _uncertainty_on_device(self, uncertainty: ServedUncertainty | None) -> ServedUncertainty | None:
        """The checkpoint's uncertainty computing on the node's GPU where PyTorch has one (ONNX
        Runtime's CUDA provider may serve where it has not), else on the CPU."""
        on_gpu = self.device != "cpu" and torch.cuda.is_available()
        return uncertainty.to(self.device) if uncertainty is not None and on_gpu else uncertainty

    def _pose_sigma_mm(self, request: TactileEstimateRequest) -> float:
        """The in-plane pose uncertainty (mm) a request's estimate assumes: its own, or the
        checkpoint's default for a negative one; -1 for a model without a physics prior."""
        if self.prior is None:
            return -1.0
        return self.prior.spec.pose_sigma_mm if request.pose_sigma_mm < 0 else request.pose_sigma_mm

    def _network_input(self, parts: list[tuple[np.ndarray, float]]) -> torch.Tensor:
        """The network's input for depth-maps whose geometry is known to the sigma (mm) beside
        them. A model with a physics prior needs its image of every map: per-image NumPy and
        OpenCV (about 25 short calls a map), in a CPU node's lane on its thread, else in chunks
        on the input threads; on a GPU, drawn there and left there for the network."""

        def inputs(part: tuple[np.ndarray, float | None]) -> torch.Tensor:
            chunk, sigma = part
            return network_input(chunk, self.depth_range_m, self.config, self.prior, sigma)

        if self.prior is None:
            return inputs((np.concatenate([m for m, _ in parts]), None))
        if self.prior.device != "cpu":  # one batched call a request's part on the device
            return torch.cat([inputs(part) for part in parts])
        threads = self.split.input_threads
        chunks = [(chunk, s) for m, s in parts for chunk in np.array_split(m, min(threads, len(m)))]
        # A lane draws its own pass on its thread: the pool's one thread would serialise the lanes.
        drawn = [inputs(c) for c in chunks] if threads == 1 else list(self._prior_pool.map(inputs, chunks))
        return drawn[0] if len(drawn) == 1 else torch.cat(drawn)

    def _regions_of(
        self, request: TactileEstimateRequest, held: _KeptCloud | None
    ) -> tuple[np.ndarray | PlannedCut, str]:
        """The request's regions: its depth-maps, or the planned cut of its gels on its cloud
        (looked up and bounded now, cut pass by pass; a gel that reaches no surface gets the
        empty map, every bin y_far, what the gel feels there); and the id of the cloud ("" for
        depth-maps). ``held``: the kept cloud the request named by its id alone."""
        if request.depth_maps.size:
            return request.depth_maps, ""
        cloud, kept = (request.cloud_id, held) if held is not None else self._keep(request.points, request.cloud_id)
        try:
            plan = plan_contact_cut(
                kept.index,
                np.eye(4),
                request.gel_poses,
                self.geometry,
                self.depth_map_params,
                self.params.max_point_visits,
                allow_empty=True,
                device_points=kept.device_points,
            )
        except PerceptionError as exc:
            raise BadRequest(
                f"{exc}; send fewer regions per request" if "too much work" in str(exc) else str(exc)
            ) from exc
        return plan, cloud

    def _warm_up_cutting(self) -> None:
        """Load the compiled depth-map kernels for the clouds requests carry (read-only float32
        or float64 views of a message's frames), so that the first planner request does not
        wait ~1 s for them."""
        for dtype in (np.float32, np.float64):
            cloud = np.zeros((1, 3), dtype)
            cloud.flags.writeable = False
            index = VoxelIndex(cloud)
            on_device = points_on_device(index.points_m, self.device) if self.device != "cpu" else None
            with contextlib.suppress(PerceptionError):  # one point at the gel's centre may miss its crop
                contact_depth_maps(
                    index,
                    np.eye(4),
                    np.eye(4)[None],
                    self.geometry,
                    self.depth_map_params,
                    device_points=on_device,
                )

    def _held(self, cloud: str) -> _KeptCloud | None:
        """The kept index of the cloud of that id, now the most recently used; None when not kept."""
        with self._clouds_lock:
            kept = self._clouds.pop(cloud, None)
            if kept is not None:
                self._clouds[cloud] = kept
            return kept

    def _keep(self, points: np.ndarray, claimed: str) -> tuple[str, _KeptCloud]:
        """The id and spatial index of a request's points: indexed once (and copied to the GPU
        the node serves on, where the maps are then cut), kept among the last ``index_cache``
        clouds. ``claimed``: the id the request gave with them ("" none)."""
        cloud = cloud_id(points)
        if claimed and claimed != cloud:
            raise BadRequest(f"cloud_id {claimed} is not the id of the points sent ({cloud})")
        kept = self._held(cloud)
        if kept is None:
            index = VoxelIndex(points)
            on_device = points_on_device(index.points_m, self.device) if self.device != "cpu" else None
            kept = _KeptCloud(index, on_device)
            with self._clouds_lock:
                self._clouds[cloud] = kept
                while len(self._clouds) > self.params.index_cache:
                    del self._clouds[next(iter(self._clouds))]
        return cloud, kept


if __name__ == "__main__":
    run_node(InferenceNode)
