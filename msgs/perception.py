"""Patch extractor messages: registration and contact depth-maps."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class DepthMap(Message):
    """Contact depth-map of one finger in frame ``gel_<finger>``.

    ``depth_map_m`` is m x k float32: for each x-z bin a gel y (metres; y > 0 not touching,
    y < 0 indenting) of the model points in the crop volume, by ``method``, the rule the map
    was cut with (``perception.depthmap.DepthMapParams.method``, one of
    ``perception.surface.DEPTH_MAP_METHODS``): ``"surface"``, where the object's surface is
    at the bin centre; ``"nearest_point"`` (the paper's rule), the minimum y of the bin's
    points. Empty bins hold the far end of ``y_range_m`` (y_near, y_far), which is also the
    range normalised for learning.
    ``crop_m`` is the crop volume's extent (x, y, z) in metres. ``model_to_gel`` (4x4) places
    the object's model cloud in this gel's frame as the map was made from it: with the model,
    a map can be made again (other densities, other bins). ``gel_to_world`` (4x4) is the gel's
    pose the map was cut for, as the arm measured it, and ``model_to_world`` (4x4) the object's
    registered pose before it was centred between the gels: with the tactile image, a touch
    that tells where the object really is (``perception.touch_calibration``).
    """

    SCHEMA = "dtx.perception.DepthMap"
    VERSION = 4

    depth_map_m: np.ndarray = empty((0, 0), np.float32)
    finger: str = ""
    crop_m: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    y_range_m: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0])
    point_count: int = 0
    model_to_gel: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    gel_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    model_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    method: str = ""


@dataclasses.dataclass
class RegisterRequest(Message):
    """Ask the patch extractor to segment and register ``object_name``'s model."""

    SCHEMA = "dtx.perception.RegisterRequest"
    VERSION = 1

    object_name: str = ""
    seed: int = 0


@dataclasses.dataclass
class RegisterReply(Message):
    """Registered model pose (4x4, model to ``world``) with its quality figures."""

    SCHEMA = "dtx.perception.RegisterReply"
    VERSION = 1

    object_name: str = ""
    model_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    fitness: float = 0.0
    inlier_rmse_m: float = 0.0
    centroid_world: np.ndarray = empty((3,), np.float64)
    point_counts: dict[str, int] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class PatchRequest(Message):
    """Ask for both fingers' depth-maps given the gel poses (4x4, gel to ``world``)."""

    SCHEMA = "dtx.perception.PatchRequest"
    VERSION = 1

    object_name: str = ""
    gel_left_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    gel_right_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))


@dataclasses.dataclass
class PatchReply(Message):
    SCHEMA = "dtx.perception.PatchReply"
    VERSION = 1

    left: DepthMap = dataclasses.field(default_factory=DepthMap)
    right: DepthMap = dataclasses.field(default_factory=DepthMap)
