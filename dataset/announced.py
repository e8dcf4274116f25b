"""Samples as the collector announces them on the bus (msgs.DatasetSample), into a dataset:
the collector writes through here, and so does the replay that rebuilds a dataset from a bag,
which is what makes the two datasets identical."""
from __future__ import annotations

import msgs
from dataset.format import DatasetInfo, DatasetWriter, code_version


def write_sample(writer: DatasetWriter, sample: msgs.DatasetSample) -> None:
    """One announced sample into the dataset (the collector and the replay share this)."""
    writer.write(sample_id=sample.sample_id, object_name=sample.object_name, grasp_id=sample.grasp_id,
                 finger=sample.finger, grasp_pose=sample.grasp_pose, tactile_rgb=sample.tactile_image,
                 tactile_diff_rgb=sample.tactile_diff_image, depth_map_m=sample.depth_map_m,
                 registration_fitness=sample.registration_fitness, stamps_ns=sample.stamps_ns,
                 model_to_gel=sample.model_to_gel)


def dataset_info(sample: msgs.DatasetSample) -> DatasetInfo:
    """The dataset-wide facts an announced sample carries."""
    height, width = sample.tactile_image.shape[:2]
    return DatasetInfo(image_height=height, image_width=width,
                       depth_range_m=(sample.depth_range_m[0], sample.depth_range_m[1]), scene=sample.scene,
                       effects=tuple(sample.effects), code_version=code_version(), split_seed=sample.split_seed,
                       depth_crop_m=(sample.depth_crop_m[0], sample.depth_crop_m[1], sample.depth_crop_m[2]))
