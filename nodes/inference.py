"""Inference server node: serves ``/inference/estimate`` (msgs.TactileEstimateRequest ->
msgs.TactileEstimateReply) with the trained pix2pix generator, for the grasp planner.

- A request holds N regions: ``depth_maps`` (N x 100 x 100 float32, metres in the gel
  frame), or a cloud with ``gel_poses`` (N x 4 x 4, gel to world), from which the depth-maps
  are cut as the patch extractor cuts them (perception.depthmap, y range = the checkpoint's
  depth_range_m), all N in one pass over a spatial index of the cloud.
- Cloud handles: a planner asks about one registered cloud with request after request of
  candidate poses, and a 0.1 mm model cloud is 10^7 points (~130 MB). The reply to a request
  with ``points`` names the cloud (``cloud_id``, SHA-256 of its dtype, shape and bytes: the same
  on every worker); later requests send only that id. The worker keeps the spatial index of its
  last ``index_cache`` clouds (building one takes ~1-5 s); an id it does not hold (evicted, or
  a respawned worker) is refused with code ``unknown_cloud``, and the client sends the points
  again.
- Batching: requests from every client that arrive within ``batch_window_ms`` of the oldest
  waiting one (and all that queued while the previous batch ran) go through the network
  together, in forward passes of at most ``max_batch`` regions; each client gets its own
  reply when the batch is done.
- ``images``: the deterministic estimate (dropout off). ``uncertainty``: with
  ``dropout_samples`` = S > 1, the per-pixel standard deviation (0..255 image units, mean of
  the three channels) of S extra passes with dropout on — pix2pix's noise z; zeros for S = 1.
- ``pose_sigma_mm``: the in-plane pose uncertainty (mm) of the request's geometry, which a
  model with a physics prior blurs its prior's image by (models.prior): 0 for exact geometry,
  up to ``MAX_POSE_SIGMA_MM``; negative for the checkpoint's default. The reply says which it used.
- A bad request (shape, dtype, NaN/inf, empty, too many regions, points, points x regions
  or regions x samples, both or neither input, gel poses that are not rigid transforms, a
  pose_sigma_mm that is not finite or above the bound) gets an
  error reply with code ``bad_request``; a wrong schema is refused by the bus. The node keeps
  serving. A gel that does not reach the cloud is answered per region (``region_status``
  ``out_of_reach``, the empty map's estimate), not by failing the request.
- Scaling out: start several of these nodes; clients' DEALER sockets round-robin over every
  server of the name (launch/serve.yaml).

Params: ``checkpoint`` (models/train.py format), ``runtime`` (onnxrt | eager), ``precision``
(fp32 | bf16 | int8: bf16 with eager only; int8, the encoder's convolutions quantised
(models.runtime.int8_convolutions), with onnxrt only), ``threads``, ``max_regions``, ``max_points``,
``max_batch``, ``batch_window_ms``, ``max_dropout_samples``, ``max_sampled_regions``,
``max_point_visits`` (cloud points near the gels, summed over regions: the work of cutting the
depth-maps), ``index_cache``,
``scene`` (gripper geometry for the points path), ``margin_m`` (crop margin, as the patch
extractor's).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.networks import UNetGenerator
from models.prior import MAX_POSE_SIGMA_MM
from models.runtime import Runner, UncheckedGenerator, eager_runner, onnx_graph, onnx_runner, sampling_copy
from msgs.inference import TactileEstimateReply, TactileEstimateRequest
from msgs.system import ErrorCode
from nodes.node import Node, run_node
from perception.depthmap import DepthMapParams, contact_depth_maps
from perception.errors import PerceptionError
from perception.pointcloud import VoxelIndex, check_transforms

# The precisions each runtime runs (dtx bench inference measures each pair).
PRECISIONS = {"onnxrt": ("fp32", "int8"), "eager": ("fp32", "bf16")}


class BadRequest(ValueError):
    """A request the server cannot answer; the bus sends it back as ServiceError(code, text)."""

    code = ErrorCode.BAD_REQUEST


class UnknownCloud(ValueError):
    """A ``cloud_id`` this worker does not hold: the client sends the points again."""

    code = ErrorCode.UNKNOWN_CLOUD


def cloud_id(points: np.ndarray) -> str:
    """The id of a cloud as sent: SHA-256 (hex) of its dtype, shape and C-order bytes; any
    numeric array, an empty one too (its bytes are none)."""
    digest = hashlib.sha256(f"{points.dtype.str} {points.shape}".encode())
    digest.update(np.ascontiguousarray(points).reshape(-1).view(np.uint8).data)  # no copy; no bytes is fine
    return digest.hexdigest()


def _forward(
    generator: UNetGenerator, depth_range_m: tuple[float, float], runtime: str, precision: str, threads: int
) -> Runner:
    """N x C x H x W float32 -> N x 3 x H x W float32 in [-1, 1], on the chosen runtime."""
    if runtime == "eager":
        return eager_runner(UncheckedGenerator(generator).eval(), bf16=precision == "bf16")
    return onnx_runner(onnx_graph(generator, depth_range_m, precision), threads)


@dataclasses.dataclass
class _Job:
    request: TactileEstimateRequest
    regions: int
    arrived: float  # time.monotonic()
    future: Future[TactileEstimateReply]
    held: VoxelIndex | None  # the kept cloud a request named by its id alone


class InferenceNode(Node):
    @dataclasses.dataclass
    class Params:
        checkpoint: str = ""
        runtime: str = "onnxrt"  # measured faster than eager on 2 busy cores (dtx bench inference)
        precision: str = "fp32"
        threads: int = 2
        max_regions: int = 256
        max_points: int = 12_000_000  # every YCB model cloud at the 0.1 mm training spacing
        max_batch: int = 32
        batch_window_ms: float = 2.0
        max_dropout_samples: int = 16
        max_sampled_regions: int = 1024  # regions x dropout_samples: bounds the time of one request
        # Points read while cutting, over all regions: ~4 ns each in the compiled pass (~1 s).
        max_point_visits: int = 250_000_000
        index_cache: int = 2  # clouds whose spatial index is kept (a 0.1 mm cloud's: ~100-300 MB)
        scene: str = "scenes/ycb_three.yaml"
        margin_m: float = 0.002

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        p = self.params
        if p.precision not in PRECISIONS.get(p.runtime, ()):
            raise ValueError(
                f"runtime {p.runtime!r} with precision {p.precision!r} is not offered: "
                f"the runtimes and their precisions are {PRECISIONS}"
            )
        limits = (
            p.threads,
            p.max_regions,
            p.max_points,
            p.max_batch,
            p.max_dropout_samples,
            p.max_sampled_regions,
            p.max_point_visits,
            p.index_cache,
        )
        if min(limits) < 1 or p.batch_window_ms < 0:
            raise ValueError(
                "threads, max_regions, max_points, max_batch, max_dropout_samples, "
                "max_sampled_regions, max_point_visits and index_cache must be >= 1, "
                "batch_window_ms >= 0"
            )
        if not p.checkpoint:
            raise ValueError("parameter 'checkpoint' is required (a models/train.py checkpoint.pt)")
        started = time.perf_counter()
        torch.set_num_threads(p.threads)
        torch.set_flush_denormal(True)  # denormal activations make CPU convolutions much slower
        # The prior's images render in chunks on the node's own threads; OpenCV's pool inside
        # each chunk only added threads (2.3 -> 2.0 ms CPU per region, same wall time).
        cv2.setNumThreads(1)
        generator, self.depth_range_m = load_generator(p.checkpoint)
        self.config, self.prior = generator.config, generator.prior
        self.deterministic = _forward(generator, self.depth_range_m, p.runtime, p.precision, p.threads)
        self.sampled = _forward(sampling_copy(generator), self.depth_range_m, p.runtime, p.precision, p.threads)
        from workcell.scene import load_scene  # noqa: PLC0415 - the gripper geometry, as the patch extractor's

        self.geometry = load_scene(p.scene).gripper_geometry()
        size = self.config.image_size
        self.depth_map_params = DepthMapParams(shape=(size, size), margin_m=p.margin_m, y_range_m=self.depth_range_m)
        self.model = f"{Path(p.checkpoint).name} (ngf {self.config.ngf}, {p.runtime} {p.precision}) on {self.name}"
        self.forward_passes = 0
        self._clouds: dict[str, VoxelIndex] = {}  # cloud id -> its index, least recently used first
        self._clouds_lock = threading.Lock()  # looked up on the bus thread, filled in the background
        # Renders the physics prior's images of a batch in chunks, one per network thread (below).
        self._prior_pool = ThreadPoolExecutor(p.threads, thread_name_prefix=f"{name}-prior")
        self._warm_up_cutting()
        self._lock = threading.Condition()
        self._waiting: list[_Job] = []
        self._flush_queued = False
        self.create_service("/inference/estimate", TactileEstimateRequest, TactileEstimateReply, self.on_estimate)
        self.log.info(
            "loaded %s in %.2f s: depth range %s m, max batch %d, window %.1f ms",
            self.model,
            time.perf_counter() - started,
            self.depth_range_m,
            p.max_batch,
            p.batch_window_ms,
        )

    # -- requests ---------------------------------------------------------------------------
    def close(self) -> None:
        super().close()
        self._prior_pool.shutdown(wait=True)
        # Flush-to-zero is process state; leave the process as torch starts it (a node run
        # inside another program, e.g. a test, must not change that program's arithmetic).
        torch.set_flush_denormal(False)

    def on_estimate(self, request: TactileEstimateRequest) -> Future[TactileEstimateReply]:
        regions = self._check(request)
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

    def _check(self, request: TactileEstimateRequest) -> int:
        """Number of regions of a well-formed request; BadRequest otherwise."""
        regions = self._check_inputs(request)
        if request.dropout_samples > 1 and regions * request.dropout_samples > self.params.max_sampled_regions:
            raise BadRequest(
                f"too many sampled regions: {regions} regions x {request.dropout_samples} "
                f"dropout_samples > {self.params.max_sampled_regions} per request"
            )
        return regions

    def _check_inputs(self, request: TactileEstimateRequest) -> int:
        p, size = self.params, self.config.image_size
        maps, points, poses = request.depth_maps, request.points, request.gel_poses
        if not 1 <= request.dropout_samples <= p.max_dropout_samples:
            raise BadRequest(f"dropout_samples must be 1..{p.max_dropout_samples}, got {request.dropout_samples}")
        if not (math.isfinite(request.pose_sigma_mm) and request.pose_sigma_mm <= MAX_POSE_SIGMA_MM):
            raise BadRequest(
                f"pose_sigma_mm must be a finite number of mm <= {MAX_POSE_SIGMA_MM:g} (0: exact geometry; "
                f"negative: the checkpoint's default), got {request.pose_sigma_mm}"
            )
        if maps.size and (points.size or poses.size or request.cloud_id):
            raise BadRequest("give either depth_maps or a cloud (points or cloud_id) with gel_poses, not both")
        if maps.size:
            if maps.ndim != 3 or maps.shape[1:] != (size, size):
                raise BadRequest(f"depth_maps must be N x {size} x {size}, got shape {maps.shape}")
            _check_count(maps.shape[0], p.max_regions, "regions")
            if maps.dtype != np.float32:
                raise BadRequest(f"depth_maps must be float32 metres, got {maps.dtype}")
            _check_finite(maps, "depth_maps")
            return int(maps.shape[0])
        if not (points.size or request.cloud_id) or not poses.size:
            raise BadRequest(
                "empty request: give depth_maps (N x 100 x 100), or points (P x 3) or a cloud_id "
                "with gel_poses (N x 4 x 4)"
            )
        if request.cloud_id and not _is_cloud_id(request.cloud_id):
            raise BadRequest(f"cloud_id must be the 64 hex digits a reply gave, got {request.cloud_id[:80]!r}")
        if points.size and (points.ndim != 2 or points.shape[1] != 3):
            raise BadRequest(f"points must be P x 3, got shape {points.shape}")
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise BadRequest(f"gel_poses must be N x 4 x 4, got shape {poses.shape}")
        _check_count(points.shape[0], p.max_points, "points")
        _check_count(poses.shape[0], p.max_regions, "regions")
        for array, what in ((points, "points"), (poses, "gel_poses")):
            if array.dtype not in (np.float32, np.float64):
                raise BadRequest(f"{what} must be float32 or float64, got {array.dtype}")
            _check_finite(array, what)
        try:
            check_transforms(poses, "gel_poses")  # each rigid; the error names gel_poses[i]
        except PerceptionError as exc:
            raise BadRequest(str(exc)) from exc
        return int(poses.shape[0])

    # -- batches (in the background thread) -------------------------------------------------
    def _flush(self) -> None:
        """Wait out the batch window of the oldest request (or a full batch), then run all."""
        window_s = self.params.batch_window_ms / 1e3
        with self._lock:
            self._lock.wait_for(
                lambda: sum(j.regions for j in self._waiting) >= self.params.max_batch,
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
        # A request refused while its depth-maps are cut (too much work) fails alone: the other
        # clients' requests in the batch go on.
        ready, maps, errors, clouds = [], [], [], []
        for job in jobs:
            try:
                job_maps, job_errors, job_cloud = self._depth_maps(job.request, job.held)
            except BadRequest as exc:
                job.future.set_exception(exc)
                continue
            ready.append(job)
            maps.append(job_maps)
            errors.append(job_errors)
            clouds.append(job_cloud)
        if not ready:
            return
        sigmas = [self._pose_sigma_mm(job.request) for job in ready]
        x = self._network_input(maps, sigmas)
        images = to_uint8_rgb(torch.from_numpy(self._batched(self.deterministic, x)))
        samples = [job.request.dropout_samples for job in ready]
        offsets = np.cumsum([0] + [m.shape[0] for m in maps])
        # Every region of a job asking for S samples is repeated S times; all go through together.
        repeated = [np.repeat(x[offsets[i] : offsets[i + 1]], s, axis=0) for i, s in enumerate(samples) if s > 1]
        sampled = self._batched(self.sampled, np.concatenate(repeated)) if repeated else np.zeros((0,))
        cursor = 0
        for i, job in enumerate(ready):
            n, s = offsets[i + 1] - offsets[i], samples[i]
            uncertainty = np.zeros((n, *x.shape[2:]), np.float32)
            if s > 1:
                draws = (sampled[cursor : cursor + n * s] + 1.0) * 127.5  # image units, as images
                cursor += n * s
                uncertainty = draws.reshape(n, s, *draws.shape[1:]).std(axis=1).mean(axis=1).astype(np.float32)
            job.future.set_result(
                TactileEstimateReply(
                    images=images[offsets[i] : offsets[i + 1]],
                    uncertainty=uncertainty,
                    model=self.model,
                    latency_ms=(time.monotonic() - job.arrived) * 1e3,  # queue, window and passes
                    region_status=["out_of_reach" if e else "ok" for e in errors[i]],
                    region_errors=errors[i],
                    depth_range_m=[float(y) for y in self.depth_range_m],
                    cloud_id=clouds[i],
                    worker=self.name,
                    pose_sigma_mm=sigmas[i],
                )
            )

    def _pose_sigma_mm(self, request: TactileEstimateRequest) -> float:
        """The in-plane pose uncertainty (mm) a request's estimate assumes: its own, or the
        checkpoint's default for a negative one; -1 for a model without a physics prior."""
        if self.prior is None:
            return -1.0
        return self.prior.spec.pose_sigma_mm if request.pose_sigma_mm < 0 else request.pose_sigma_mm

    def _network_input(self, maps: list[np.ndarray], sigmas: list[float]) -> np.ndarray:
        """The network's input for each request's depth-maps, whose geometry is known to
        ``sigmas`` (mm). A model with a physics prior needs its image of every map: per-image
        NumPy and OpenCV, 1.9-2.0 ms CPU a region for the demo's model (a quarter of the
        server's, ``dtx bench serve``), mostly outside the GIL, so chunks render side by side on
        the cores the network uses next."""

        def inputs(part: tuple[np.ndarray, float | None]) -> np.ndarray:
            chunk, sigma = part
            return network_input(chunk, self.depth_range_m, self.config, self.prior, sigma).numpy()

        if self.prior is None:
            return inputs((np.concatenate(maps), None))
        threads = self.params.threads
        parts = [(chunk, s) for m, s in zip(maps, sigmas) for chunk in np.array_split(m, min(threads, len(m)))]
        if len(parts) == 1:
            return inputs(parts[0])
        return np.concatenate(list(self._prior_pool.map(inputs, parts)))

    def _depth_maps(
        self, request: TactileEstimateRequest, held: VoxelIndex | None
    ) -> tuple[np.ndarray, list[str], str]:
        """The request's depth-maps; per region, why its gel reaches no surface ("" when it
        does: such a region gets the empty map, every bin y_far, what the gel feels there); the
        id of the cloud they were cut from ("" for depth-maps). ``held``: the kept cloud the
        request named by its id alone."""
        if request.depth_maps.size:
            return request.depth_maps, [""] * len(request.depth_maps), ""
        cloud, index = (request.cloud_id, held) if held is not None else self._keep(request.points, request.cloud_id)
        try:
            patches = contact_depth_maps(
                index,
                np.eye(4),
                request.gel_poses,
                self.geometry,
                self.depth_map_params,
                self.params.max_point_visits,
                allow_empty=True,
                threads=self.params.threads,  # the network's cores, idle while the maps are cut
            )
        except PerceptionError as exc:
            raise BadRequest(
                f"{exc}; send fewer regions per request" if "too much work" in str(exc) else str(exc)
            ) from exc
        errors = [
            "" if count else f"region {i}: no model point in the contact volume: the gel does not reach the object"
            for i, count in enumerate(patches.point_counts)
        ]
        return patches.depth_maps_m, errors, cloud

    def _warm_up_cutting(self) -> None:
        """Load the compiled depth-map kernels for the clouds requests carry (read-only float32
        or float64 views of a message's frames), so that the first planner request does not
        wait ~1 s for them."""
        for dtype in (np.float32, np.float64):
            cloud = np.zeros((1, 3), dtype)
            cloud.flags.writeable = False
            with contextlib.suppress(PerceptionError):  # one point at the gel's centre may miss its crop
                contact_depth_maps(VoxelIndex(cloud), np.eye(4), np.eye(4)[None], self.geometry, self.depth_map_params)

    def _held(self, cloud: str) -> VoxelIndex | None:
        """The kept index of the cloud of that id, now the most recently used; None when not kept."""
        with self._clouds_lock:
            index = self._clouds.pop(cloud, None)
            if index is not None:
                self._clouds[cloud] = index
            return index

    def _keep(self, points: np.ndarray, claimed: str) -> tuple[str, VoxelIndex]:
        """The id and spatial index of a request's points: indexed once, kept among the last
        ``index_cache`` clouds. ``claimed``: the id the request gave with them ("" none)."""
        cloud = cloud_id(points)
        if claimed and claimed != cloud:
            raise BadRequest(f"cloud_id {claimed} is not the id of the points sent ({cloud})")
        index = self._held(cloud)
        if index is None:
            index = VoxelIndex(points)
            with self._clouds_lock:
                self._clouds[cloud] = index
                while len(self._clouds) > self.params.index_cache:
                    del self._clouds[next(iter(self._clouds))]
        return cloud, index

    def _batched(self, forward: Runner, x: np.ndarray) -> np.ndarray:
        step = self.params.max_batch
        outputs = []
        for start in range(0, len(x), step):
            outputs.append(forward(np.ascontiguousarray(x[start : start + step])))
            self.forward_passes += 1
        return np.concatenate(outputs)


def _is_cloud_id(text: str) -> bool:
    return len(text) == 64 and all(c in "0123456789abcdef" for c in text)


def _check_count(count: int, limit: int, what: str) -> None:
    if count > limit:
        raise BadRequest(f"too many {what}: {count} > {limit} per request")


def _check_finite(array: np.ndarray, what: str) -> None:
    if not np.isfinite(array).all():  # one pass over a cloud of millions; where, only when it fails
        first = np.argwhere(~np.isfinite(array))[0]
        raise BadRequest(f"{what} contain NaN or inf (first at index {tuple(int(i) for i in first)})")


if __name__ == "__main__":
    run_node(InferenceNode)
