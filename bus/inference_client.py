"""The grasp planner's side of ``/inference/estimate``: what would the gel feel here?

    with TactileClient() as client:                    # or TactileClient(node.bus) inside a node
        images, uncertainty = client.estimate(depth_maps)
        cloud = Cloud(cloud_world)                     # one object's registered cloud, asked about often
        images, uncertainty = client.estimate_at(cloud, gel_poses, pose_sigma_mm=0.3)
        if uncertainty is not None:                    # None: a checkpoint without one (absent)
            region_u = client.last_reply.region_uncertainty  # mean u of each region, image levels

Every server of the name on the bus is used in turn (round robin), local or, with the
launch file's ``peers:``, remote.

``uncertainty`` (N x H x W float32, image levels 0..255) comes with every reply: per pixel, the
checkpoint's calibrated estimate of the RMS of |estimate - truth| (the channels' mean); None
when the checkpoint has none (the reply's ``uncertainty_status`` ``absent``), never zeros.
``last_reply`` is the whole reply: ``region_uncertainty``, ``serves`` (network | prior),
``region_status``, ``region_points`` and ``region_surface_bins`` (how much geometry each estimate
rests on: a thinned cloud's regions hold fewer), ``model``...

``pose_sigma_mm``: how far off in the gel plane (mm, one sigma) the geometry may be, e.g. the
registration's uncertainty after a touch calibration; 0 for exact geometry; None for the
checkpoint's default (its training session's). ``last_reply.pose_sigma_mm`` is the one used.
"""

from __future__ import annotations

import dataclasses
import functools
from types import TracebackType

import numpy as np

from bus.pubsub import Bus
from bus.services import ServiceCallError
from msgs.inference import TactileEstimateReply, TactileEstimateRequest

SERVICE = "/inference/estimate"


class InferenceError(RuntimeError):
    """The inference server refused the request (``code`` bad_request, ...), was not found
    (``unavailable``) or did not answer in time (``timeout``)."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(f"{SERVICE}: {code}: {text}")
        self.code, self.text = code, text


@dataclasses.dataclass
class Cloud:
    """An object's cloud (P x 3, world, metres) a planner asks about again and again. Its
    points travel until every worker has answered about them; after that only the id the
    workers gave (``docs/wire-protocol.md``, cloud handles)."""

    points: np.ndarray
    id: str = ""
    held_by: set[str] = dataclasses.field(default_factory=set)  # workers that answered with ``id``

    def __post_init__(self) -> None:
        points = np.asarray(self.points)
        if points.dtype.kind not in "biuf":  # complex would be cast, text parsed
            raise InferenceError("bad_request", f"points must be real numbers, got {points.dtype}")
        self.points = points if points.dtype == np.float32 else points.astype(np.float64)  # float32 halves the bytes


class TactileClient:
    """Estimated tactile images (N x H x W x 3 uint8) and their per-pixel uncertainty
    (N x H x W float32, image levels 0..255; None where the checkpoint has none) for N
    candidate regions."""

    def __init__(
        self,
        bus: Bus | None = None,
        timeout_s: float = 10.0,
        retries: int = 0,
        service: str = SERVICE,
    ) -> None:
        self._own_bus = bus is None  # a planner that is a node lends its bus; a script gets its own
        self.bus = bus if bus is not None else Bus("tactile_client")
        # No retry by default: a retried batch may reach another worker and run twice.
        self.timeout_s, self.retries = timeout_s, retries
        self.client = self.bus.client(service, TactileEstimateRequest, TactileEstimateReply)
        self.last_reply: TactileEstimateReply | None = None

    def estimate(
        self, depth_maps: np.ndarray, *, pose_sigma_mm: float | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """From depth-maps: N x 100 x 100 metres in the gel frame (a single 100 x 100 map is one region);
        real numbers within float32's range, as they travel (else InferenceError bad_request, as
        the server would answer a NaN or inf; a larger value would overflow the cast)."""
        maps = np.asarray(depth_maps)
        if maps.dtype.kind not in "biuf" or not np.all(np.abs(maps) <= np.finfo(np.float32).max):  # NaN fails
            raise InferenceError("bad_request", "depth_maps must be real metres within float32's range (no NaN or inf)")
        maps = maps.astype(np.float32)
        return self._call(
            TactileEstimateRequest(
                depth_maps=maps[None] if maps.ndim == 2 else maps,
                pose_sigma_mm=_wire_sigma(pose_sigma_mm),
            )
        )

    def estimate_at(
        self,
        cloud: Cloud | np.ndarray,
        gel_poses: np.ndarray,
        *,
        pose_sigma_mm: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """From the object's cloud (a ``Cloud``, or P x 3 points in world, metres, sent whole
        each time) and candidate gel poses (N x 4 x 4, gel to world). A gel that reaches no
        point of the cloud gets the no-contact estimate; which ones did is in
        ``last_reply.region_status`` ("ok" / "out_of_reach")."""
        cloud = cloud if isinstance(cloud, Cloud) else Cloud(cloud)
        poses = np.asarray(gel_poses, dtype=np.float64)
        poses = poses[None] if poses.ndim == 2 else poses
        request = functools.partial(
            TactileEstimateRequest,
            gel_poses=poses,
            pose_sigma_mm=_wire_sigma(pose_sigma_mm),
        )
        if cloud.id and len(cloud.held_by) >= self.client.server_count():
            try:
                return self._call(request(cloud_id=cloud.id), cloud)
            except InferenceError as exc:
                if exc.code != "unknown_cloud":
                    raise
                cloud.held_by.clear()  # a worker evicted it or was respawned: the points go again
        return self._call(request(points=cloud.points, cloud_id=cloud.id), cloud)

    def _call(
        self, request: TactileEstimateRequest, cloud: Cloud | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        try:
            reply = self.client.call(request, timeout_s=self.timeout_s, retries=self.retries)
        except ServiceCallError as exc:
            raise InferenceError(exc.code, exc.text) from exc
        self.last_reply = reply
        if cloud is not None:
            if reply.cloud_id != cloud.id:
                cloud.id, cloud.held_by = reply.cloud_id, set()
            cloud.held_by.add(reply.worker)
        return reply.images, reply.uncertainty if reply.uncertainty_status == "ok" else None

    def close(self) -> None:
        self.client.close()
        if self._own_bus:
            self.bus.close()

    def __enter__(self) -> "TactileClient":
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def _wire_sigma(pose_sigma_mm: float | None) -> float:
    """The request's field: None (the checkpoint's default) travels as -1."""
    return -1.0 if pose_sigma_mm is None else float(pose_sigma_mm)
