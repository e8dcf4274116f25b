"""What the inference node (nodes.inference) accepts: its parameters' and a request's checks,
the errors it sends back with their codes, and the id a cloud is known by."""

from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np

from models.checkpoint import SERVES as CHECKPOINT_SERVES
from models.prior import MAX_POSE_SIGMA_MM
from msgs.inference import TactileEstimateRequest
from msgs.system import ErrorCode
from perception.errors import PerceptionError
from perception.pointcloud import check_transforms

# The precisions each runtime runs (dtx bench inference measures each pair).
PRECISIONS = {"onnxrt": ("fp32", "int8"), "eager": ("fp32", "bf16")}
# The node's ``serves``: "" what the checkpoint serves (models.serving), or either, overriding it.
SERVES = ("", *CHECKPOINT_SERVES)  # "": what the checkpoint serves


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


def checked_regions(request: TactileEstimateRequest, p: Any, size: int) -> int:
    """Number of regions of a well-formed request to a node of parameters ``p``
    (InferenceNode.Params) serving ``size`` x ``size`` maps; BadRequest otherwise."""
    _check_fields(request)
    maps, points, poses = request.depth_maps, request.points, request.gel_poses
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
            "empty request: give depth_maps (N x 100 x 100), or points (P x 3) or a cloud_id with gel_poses (N x 4 x 4)"
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


def _check_fields(request: TactileEstimateRequest) -> None:
    """BadRequest naming the first field whose type is not the message's, or whose
    ``dropout_samples`` or ``pose_sigma_mm`` the node does not serve. The codec checks the types
    of a request off the wire; one handed over in process may hold anything."""
    for name in ("depth_maps", "points", "gel_poses"):
        if not isinstance(getattr(request, name), np.ndarray):
            raise BadRequest(f"{name} must be a numpy array, got {_shown(getattr(request, name))}")
    if not isinstance(request.cloud_id, str):
        raise BadRequest(f"cloud_id must be text (the 64 hex digits a reply gave), got {_shown(request.cloud_id)}")
    samples = request.dropout_samples
    if not (_is_integer(samples) and samples == 1):
        raise BadRequest(
            f"dropout_samples is not served since protocol v4: every reply carries the calibrated "
            f"uncertainty (uncertainty, region_uncertainty); send 1, got {_shown(samples)} (an integer: no bool, float or text)"
        )
    sigma = request.pose_sigma_mm
    # Ints and floats of at most 64 bits: the reply carries the sigma back, and the codec sends
    # no long double (its item() is no Python float).
    real = _is_integer(sigma) or isinstance(sigma, (float, np.float16, np.float32))
    try:
        finite = real and math.isfinite(float(sigma))  # an int beyond float64 overflows here
    except OverflowError:
        finite = False
    if not (finite and sigma <= MAX_POSE_SIGMA_MM):
        raise BadRequest(
            f"pose_sigma_mm must be a finite number of mm <= {MAX_POSE_SIGMA_MM:g} (0: exact geometry; "
            f"negative: the checkpoint's default), got {_shown(sigma)}"
        )


def _is_integer(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _shown(value: object) -> str:
    """``value`` for an error message, in bounded length whatever a client sent."""
    if isinstance(value, int) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    if isinstance(value, str):
        return repr(value[:40]) + (f" ... ({len(value)} characters)" if len(value) > 40 else "")
    if value is None or isinstance(value, (int, float, np.number, np.bool_)):
        return repr(value)
    return f"a {type(value).__name__}"


def _is_cloud_id(text: str) -> bool:
    return len(text) == 64 and all(c in "0123456789abcdef" for c in text)


def _check_count(count: int, limit: int, what: str) -> None:
    if count > limit:
        raise BadRequest(f"too many {what}: {count} > {limit} per request")


def _check_finite(array: np.ndarray, what: str) -> None:
    if not np.isfinite(array).all():  # one pass over a cloud of millions; where, only when it fails
        first = np.argwhere(~np.isfinite(array))[0]
        raise BadRequest(f"{what} contain NaN or inf (first at index {tuple(int(i) for i in first)})")


def checked_serves(p: Any, generator: Any) -> str:
    """What a node of parameters ``p`` serves of ``generator`` (models.checkpoint.load_generator):
    its ``serves`` or, for "", the checkpoint's; ValueError for a prior the checkpoint lacks."""
    serves = str(p.serves or generator.serves)
    if serves == "prior" and generator.prior is None:
        raise ValueError(
            f"serves 'prior': {p.checkpoint} has no physics prior to serve (its generator takes the "
            "depth-map alone); serve its network"
        )
    return serves


def check_params(p: Any) -> None:
    """ValueError naming what is wrong with the node's parameters (InferenceNode.Params)."""
    if p.precision not in PRECISIONS.get(p.runtime, ()):
        raise ValueError(
            f"runtime {p.runtime!r} with precision {p.precision!r} is not offered: "
            f"the runtimes and their precisions are {PRECISIONS}"
        )
    limits = (p.threads, p.max_regions, p.max_points, p.max_point_visits, p.index_cache)
    if min(limits) < 1 or p.max_batch < 0 or p.batch_window_ms < 0 or not 0 <= p.int8_max_ssim_loss <= 1:
        raise ValueError(
            "threads, max_regions, max_points, max_point_visits and index_cache must be >= 1, "
            "max_batch >= 0 (0: the device's own), batch_window_ms >= 0, int8_max_ssim_loss in [0, 1]"
        )
    if p.serves not in SERVES:
        raise ValueError(
            f"serves must be one of {', '.join(repr(s) for s in SERVES)} ('': what the checkpoint serves), "
            f"got {p.serves!r}"
        )
    if not p.checkpoint:
        raise ValueError("parameter 'checkpoint' is required (a models/train.py checkpoint.pt)")
