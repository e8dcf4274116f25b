"""The grasp planner's questions to the inference server, and its answers."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class TactileEstimateRequest(Message):
    """Estimate tactile images for N candidate regions.

    Either ``depth_maps`` (N x 100 x 100 float32, metres in the gel frame, as the patch
    extractor makes them) or an object's cloud with ``gel_poses`` (N x 4 x 4, gel to
    ``world``), from which the server extracts depth-maps. The cloud is ``points`` (P x 3
    float32/float64, metres in ``world``), or ``cloud_id`` alone: the id a reply gave for a
    cloud sent earlier, which the worker keeps (a worker that no longer holds it answers
    ``unknown_cloud``: send the points again). ``pose_sigma_mm``: how far off in the gel
    plane (mm, one standard deviation per axis) the geometry may be — the registration's
    uncertainty, 0 for exact geometry; negative asks for the checkpoint's default (the
    uncertainty of the session it was trained on). One value for the request: a planner whose
    regions differ in it sends them as separate requests, which the server batches together.

    ``dropout_samples`` is kept only so that a client still asking for dropout samples (the
    per-pixel spread of stochastic passes, served up to protocol v3; it was ~0 and uncorrelated
    with the error) is told why it is refused: any value but 1 is ``bad_request``. Every reply
    carries the calibrated uncertainty with no option (TactileEstimateReply).
    """

    SCHEMA = "dtx.inference.TactileEstimateRequest"
    VERSION = 4

    depth_maps: np.ndarray = empty((0, 100, 100), np.float32)
    points: np.ndarray = empty((0, 3), np.float32)
    cloud_id: str = ""
    gel_poses: np.ndarray = empty((0, 4, 4), np.float64)
    dropout_samples: int = 1
    pose_sigma_mm: float = -1.0


@dataclasses.dataclass
class TactileEstimateReply(Message):
    """N x H x W x 3 uint8 estimated tactile images, and their uncertainty.

    ``serves``: what the images are, the checkpoint's choice (or the server's override):
    ``"network"`` (the generator's image) or ``"prior"`` (the physics prior's image, as the
    generator draws it with no correction; no network pass runs).

    ``uncertainty`` (N x H x W float32, image levels 0..255): per pixel, a calibrated estimate
    u of the RMS of e = |estimate - truth| averaged over the three channels (models.uncertainty:
    in every decile of u, RMS(e) / mean u ~ 1 on the training session's validation split).
    ``region_uncertainty[i]``: the mean u of region i. ``uncertainty_status``: ``"ok"``, or
    ``"absent"`` for a checkpoint trained before the uncertainty existed; then ``uncertainty``
    is empty (0 x H x W) and ``region_uncertainty`` is [] (never zeros passed off as certain).

    ``region_points[i]``: the cloud's points in gel i's contact volume (points requests; -1 for a
    depth-map sent as one). ``region_surface_bins[i]``: how many bins of region i's depth-map hold
    a surface within ``depth_range_m`` (below y_far); the others hold y_far: nothing there within
    the range, or, from a cloud, too few points to say where the surface is (perception.surface
    leaves such a bin empty rather than make a surface up). Few of either say the estimate rests on
    little geometry: the default model's clouds put about five points in a bin.

    ``region_status[i]`` is ``"ok"``, or ``"out_of_reach"`` when gel i does not reach the
    cloud (points requests only): a planner asks about many candidate poses at once, and one
    that misses the object is an answer about that pose, not a fault of the batch. Its image
    is the estimate for an empty depth-map (the gel touching nothing) and ``region_errors[i]``
    says why in a sentence ("" for ok regions). ``depth_range_m`` is the server's
    (y_near, y_far) in the gel frame: depth-maps are clipped to it and y_far means no surface.
    ``cloud_id`` names the cloud a points request used ("" for depth-maps): the same cloud
    (dtype, shape, values) gets the same id from every worker. ``worker`` is the node that answered.
    ``pose_sigma_mm`` is the in-plane pose uncertainty (mm) the estimate assumed: the request's,
    or the checkpoint's default for a negative one; -1 for a model without a physics prior, which
    takes every depth-map as it is.
    """

    SCHEMA = "dtx.inference.TactileEstimateReply"
    VERSION = 6

    images: np.ndarray = empty((0, 100, 100, 3), np.uint8)
    uncertainty: np.ndarray = empty((0, 100, 100), np.float32)
    uncertainty_status: str = "absent"
    region_uncertainty: list[float] = dataclasses.field(default_factory=list)
    serves: str = "network"
    model: str = ""
    latency_ms: float = 0.0
    region_status: list[str] = dataclasses.field(default_factory=list)
    region_errors: list[str] = dataclasses.field(default_factory=list)
    region_points: list[int] = dataclasses.field(default_factory=list)
    region_surface_bins: list[int] = dataclasses.field(default_factory=list)
    depth_range_m: list[float] = dataclasses.field(default_factory=list)
    cloud_id: str = ""
    worker: str = ""
    pose_sigma_mm: float = -1.0
