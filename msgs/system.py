"""Bus housekeeping: logs, heartbeats, clock, transforms, service errors."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class Log(Message):
    SCHEMA = "dtx.system.Log"
    VERSION = 1

    level: str = "info"
    node: str = ""
    text: str = ""


@dataclasses.dataclass
class Heartbeat(Message):
    """Published by every node once a second: who it is, what it offers, and how it fares."""

    SCHEMA = "dtx.system.Heartbeat"
    VERSION = 1

    node: str = ""
    pid: int = 0
    status: str = "ok"
    publishers: list[str] = dataclasses.field(default_factory=list)
    subscribers: list[str] = dataclasses.field(default_factory=list)
    services: list[str] = dataclasses.field(default_factory=list)
    counters: dict[str, int] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class Clock(Message):
    """Simulated time, published by ``dtx bag play --clock`` (like ROS's /clock)."""

    SCHEMA = "dtx.system.Clock"
    VERSION = 1

    sim_time_ns: int = 0


@dataclasses.dataclass
class FrameTransform(Message):
    """Pose of ``child_frame_id`` in ``header.frame_id``: translation (m), quaternion (x, y, z, w)."""

    SCHEMA = "dtx.system.FrameTransform"
    VERSION = 1

    child_frame_id: str = ""
    translation: np.ndarray = empty((3,), np.float64)
    rotation: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))


@dataclasses.dataclass
class Empty(Message):
    """Request or reply that carries nothing but its header."""

    SCHEMA = "dtx.system.Empty"
    VERSION = 1


class ErrorCode:
    """What went wrong with a service call, for the caller's program to branch on; a
    ServiceError's ``text`` is for people and may be reworded (docs/wire-protocol.md §3)."""

    BAD_REQUEST = "bad_request"  # the request breaks the protocol or the service's rules
    WRONG_TYPE = "wrong_type"  # a valid message of another schema
    HANDLER_ERROR = "handler_error"  # the server failed on a valid request (a bug)
    UNKNOWN_CLOUD = "unknown_cloud"  # inference: a cloud id this worker does not hold
    NOT_REGISTERED = "not_registered"  # patch extractor: the object has no registered pose
    OUT_OF_REACH = "out_of_reach"  # patch extractor: a gel reaches no point of the object
    # Set by the calling side (bus.services.ServiceClient), never sent:
    TIMEOUT = "timeout"
    UNAVAILABLE = "unavailable"
    CANCELLED = "cancelled"
    REQUEST_TOO_LARGE = "request_too_large"


@dataclasses.dataclass
class ServiceError(Message):
    """The reply a service sends instead of its answer when a request cannot be served:
    ``code`` one of :class:`ErrorCode`'s, ``text`` what happened, for people."""

    SCHEMA = "dtx.system.ServiceError"
    VERSION = 1

    code: str = ""
    text: str = ""
