"""One written (tactile image, depth-map) pair, as the collector announces it."""

from __future__ import annotations

import dataclasses

import numpy as np

from msgs.base import Message, empty


@dataclasses.dataclass
class DatasetSample(Message):
    """Everything one dataset sample holds, as the collector wrote it: a session bag can
    rebuild the dataset from these alone (``launch/replay.yaml``). ``depth_map_method`` is the
    rule that made ``depth_map_m`` (``msgs.DepthMap.method``: ``"surface"`` or
    ``"nearest_point"``)."""

    SCHEMA = "dtx.dataset.DatasetSample"
    VERSION = 4

    sample_id: str = ""
    object_name: str = ""
    grasp_id: int = 0
    finger: str = ""
    grasp_pose: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    tactile_image: np.ndarray = empty((0, 0, 3), np.uint8)
    tactile_diff_image: np.ndarray = empty((0, 0, 3), np.uint8)
    depth_map_m: np.ndarray = empty((0, 0), np.float32)
    depth_range_m: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0])
    registration_fitness: float = 0.0
    model_to_gel: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    gel_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    model_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    depth_crop_m: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    stamps_ns: dict[str, int] = dataclasses.field(default_factory=dict)
    scene: str = ""
    effects: list[str] = dataclasses.field(default_factory=list)
    split_seed: int = 0
    depth_map_method: str = ""  # the rule that made depth_map_m (msgs.DepthMap.method)
