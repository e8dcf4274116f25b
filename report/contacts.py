"""Analytic contacts for the report: one deterministic list of surfaces, written as datasets
at any depth-map resolution, so that every sweep that needs ground truth it can render again
sees the same contacts (the surfaces and renderer are dataset.synth's)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dataset.images import subtract_background
from dataset.records import DatasetInfo, code_version
from dataset.synth import (
    CAMERA_FIELD_WIDTH_MM,
    SHAPES,
    SurfaceMm,
    depth_map_from_surface,
    gel_gap_from_surface,
    gelsight_renderer,
    random_surface,
)
from dataset.writer import DatasetWriter

DEPTH_RANGE_M = (-0.0015, 0.0025)
CROP_SCALE = 1.2  # dataset.synth's default: the depth-map crop is wider than the camera field
CROP_MM = CAMERA_FIELD_WIDTH_MM * CROP_SCALE
RENDERING_SCENE = "scenes/ycb_three.yaml"


@dataclasses.dataclass(frozen=True)
class Contact:
    sample_id: str
    shape: str
    grasp_id: int
    finger: str
    surface: SurfaceMm


def contacts(samples: int, seed: int) -> list[Contact]:
    """``samples`` contacts, two fingers per grasp, drawn per grasp like dataset.synth."""
    out = []
    for grasp_id in range((samples + 1) // 2):
        rng = np.random.default_rng([seed, grasp_id])
        shape = SHAPES[int(rng.integers(len(SHAPES)))]
        for finger in ("left", "right")[: min(2, samples - 2 * grasp_id)]:
            out.append(
                Contact(f"{shape}-g{grasp_id:05d}-{finger}", shape, grasp_id, finger, random_surface(shape, rng))
            )
    return out


def write_dataset(out: Path, items: list[Contact], size: int, seed: int) -> Path:
    """The contacts as a size x size dataset (depth-map bins = image pixels, as the network
    maps one to the other); the same contacts at every size, so splits and ids agree."""
    if (out / "manifest.jsonl").exists():
        return out
    renderer, pitch = gelsight_renderer(size)
    background = renderer.render(np.full((size, size), np.inf, np.float32))
    # The scene whose GelSight (calibration, field of view) renders these images, and the square
    # crop the depth-maps cover: what a generator's physics prior (models.prior) needs.
    info = DatasetInfo(
        image_height=size,
        image_width=size,
        depth_range_m=DEPTH_RANGE_M,
        scene=RENDERING_SCENE,
        effects=(),
        code_version=code_version(),
        split_seed=seed,
        depth_crop_m=(CROP_MM * 1e-3, DEPTH_RANGE_M[1] - DEPTH_RANGE_M[0], CROP_MM * 1e-3),
    )
    writer = DatasetWriter(out, info)
    for c in items:
        tactile = renderer.render(gel_gap_from_surface(c.surface, size, size, pitch))
        writer.write(
            sample_id=c.sample_id,
            object_name=c.shape,
            grasp_id=c.grasp_id,
            finger=c.finger,
            grasp_pose=(0.0, 0.0, 0.1, 0.0),
            tactile_rgb=tactile,
            tactile_diff_rgb=subtract_background(tactile, background),
            depth_map_m=depth_map_from_surface(c.surface, size, CROP_MM, DEPTH_RANGE_M[1]),
            registration_fitness=1.0,
        )
    return out
