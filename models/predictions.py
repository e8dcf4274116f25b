"""A checkpoint's estimates of a set of dataset samples, with their ground truth
(:class:`Predictions`): what models.evaluate analyses, over one session or several."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from dataset.images import deformation_map
from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from models.networks import ModelConfigError, UNetGenerator
from models.serving import predict_served


@dataclasses.dataclass
class Predictions:
    """Ground truth and estimates (N x H x W x 3 uint8) of one evaluated set."""

    sample_ids: list[str]
    objects: list[str]
    depth_maps_m: np.ndarray
    truth: np.ndarray
    truth_deformation: np.ndarray
    estimate: np.ndarray
    # Where each sample's gel was on its object (model in the gel frame), when the dataset
    # records it; with the scene's meshes the qualitative figure draws the object.
    model_to_gel: list[np.ndarray | None] = dataclasses.field(default_factory=list)
    scene: str = ""
    depth_crop_m: tuple[float, float, float] | None = None
    # The uncertainty served with each estimate (N x H x W, image levels); None: the checkpoint has none.
    uncertainty: np.ndarray | None = None
    # The source of the real sensor's floor that u carries (models.sensor_floor), if it carries one.
    sensor_floor: dict[str, Any] | None = None


def predict_records(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    reader: DatasetReader,
    records: Sequence[SampleRecord],
    what: str,
    least: int = 2,
) -> Predictions:
    """Estimates for ``records`` of ``reader``'s dataset (``what`` names them in the error when
    there are fewer than ``least``)."""
    if len(records) < least:
        raise ModelConfigError(f"{what} has {len(records)} sample(s); need at least 2")
    samples = [reader.load(r) for r in records]
    depth = np.stack([s.depth_map_m for s in samples])
    estimate, uncertainty = predict_served(generator, depth, depth_range_m)
    return Predictions(
        sample_ids=[r.sample_id for r in records],
        objects=[r.object_name for r in records],
        depth_maps_m=depth,
        truth=np.stack([s.tactile_rgb for s in samples]),
        truth_deformation=np.stack([deformation_map(s.tactile_diff_rgb) for s in samples]),
        estimate=estimate,
        uncertainty=uncertainty,
        sensor_floor=None if generator.uncertainty is None else generator.uncertainty.floor_source(),
        model_to_gel=[None if r.model_to_gel is None else np.array(r.model_to_gel) for r in records],
        scene=reader.info.scene,
        depth_crop_m=reader.info.depth_crop_m,
    )


def joined(parts: Sequence[Predictions], sample_ids: Sequence[str]) -> Predictions:
    """``parts`` (one a session) as one set, its samples named ``sample_ids``; the scene and
    crop are theirs where all share them, else "" and None (the figures then draw no object)."""
    uncertainty = [p.uncertainty for p in parts]
    one_scene = len({p.scene for p in parts}) == 1 and len({p.depth_crop_m for p in parts}) == 1
    return Predictions(
        sample_ids=list(sample_ids),
        objects=[name for p in parts for name in p.objects],
        depth_maps_m=np.concatenate([p.depth_maps_m for p in parts]),
        truth=np.concatenate([p.truth for p in parts]),
        truth_deformation=np.concatenate([p.truth_deformation for p in parts]),
        estimate=np.concatenate([p.estimate for p in parts]),
        uncertainty=None if any(u is None for u in uncertainty) else np.concatenate(uncertainty),  # type: ignore[arg-type]
        sensor_floor=parts[0].sensor_floor,  # one checkpoint's predictions
        model_to_gel=[m for p in parts for m in p.model_to_gel],
        scene=parts[0].scene if one_scene else "",
        depth_crop_m=parts[0].depth_crop_m if one_scene else None,
    )
