"""Samples as the collector announces them on the bus (msgs.DatasetSample), into a dataset:
the collector writes through here, and so does the replay that rebuilds a dataset from a bag,
which is what makes the two datasets identical."""

from __future__ import annotations

from collections.abc import Sequence

import msgs
from dataset.records import DatasetError, DatasetInfo, code_version
from dataset.writer import DatasetWriter
from perception.surface import DEPTH_MAP_METHODS


def write_samples(writer: DatasetWriter, samples: Sequence[msgs.DatasetSample]) -> None:
    """Announced samples into the dataset, landing together (a grasp's two fingers: both or
    neither); the collector and the replay share this. A sample whose map another rule made
    than the dataset's (a session resumed with another ``depth_map_method``) is refused."""
    others = sorted({s.depth_map_method for s in samples} - {writer.info.depth_map_method})
    if others:
        raise DatasetError(
            f"{writer.root} holds {writer.info.depth_map_method} depth-maps, not {', '.join(others)} ones: "
            f"continue it with depth_map_method {writer.info.depth_map_method}, or write another dataset"
        )
    writer.write_together(
        [
            writer.encode(
                sample_id=s.sample_id,
                object_name=s.object_name,
                grasp_id=s.grasp_id,
                finger=s.finger,
                grasp_pose=s.grasp_pose,
                tactile_rgb=s.tactile_image,
                tactile_diff_rgb=s.tactile_diff_image,
                depth_map_m=s.depth_map_m,
                registration_fitness=s.registration_fitness,
                stamps_ns=s.stamps_ns,
                model_to_gel=s.model_to_gel,
                gel_to_world=s.gel_to_world,
                model_to_world=s.model_to_world,
            )
            for s in samples
        ]
    )


def dataset_info(sample: msgs.DatasetSample) -> DatasetInfo:
    """The dataset-wide facts an announced sample carries, its depth-map rule among them."""
    if sample.depth_map_method not in DEPTH_MAP_METHODS:
        raise DatasetError(
            f"sample {sample.sample_id!r}: depth_map_method must be one of {', '.join(DEPTH_MAP_METHODS)}, "
            f"got {sample.depth_map_method!r}"
        )
    height, width = sample.tactile_image.shape[:2]
    return DatasetInfo(
        image_height=height,
        image_width=width,
        depth_range_m=(sample.depth_range_m[0], sample.depth_range_m[1]),
        scene=sample.scene,
        effects=tuple(sample.effects),
        code_version=code_version(),
        split_seed=sample.split_seed,
        depth_crop_m=(sample.depth_crop_m[0], sample.depth_crop_m[1], sample.depth_crop_m[2]),
        depth_map_method=sample.depth_map_method,
    )
