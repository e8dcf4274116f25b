"""How well could any depth-map-to-tactile model do on a simulated session? (``dtx sim ceiling``)

A model sees only the depth-map: the registered model cloud in the gel frame. The simulated
world also knows what that hides: the true contact (the registration is off by what the
cameras' calibration leaves, ~1-2 mm), the surface micro-relief (no depth camera resolves
0.1-0.3 mm) and the sensor noise. Rendering each pair of a session again with part of that
knowledge gives reference estimates, scored exactly as ``dtx evaluate`` scores a model
(``models.evaluate.ssim_statistics``), from the most to the least informed:

- ``true contact``: the grasp rendered again at its true pose, with everything but the
  sensor noise. It reproduces the session's own images up to that noise, which checks that
  the session is this scene's (a lab session, or another scene, scores far lower).
- ``true contact, no relief``: the same without the micro-relief: a model that knew the pose
  exactly but, like any depth-map, nothing finer than the object's mesh.
- ``depth-map through the renderer``: the pair's own depth-map fed to the GelSight renderer:
  deterministic physics from exactly what the model is given.

A model's dissimilarity ratio is bounded by the rung that knows what its input knows; a target
below that rung asks the depth-map for information it does not hold.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from dataset.images import resize_rgb
from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from models.data import select_records
from models.evaluate import SUMMARY_KEYS, per_object_statistics, ssim_statistics
from sim.gelsight import GelSightRenderError, render_depth_maps, scene_renderer
from sim.world import SimWorld
from workcell.kinematics import grasp_to_tcp_pose
from workcell.scene import Scene, SceneError, load_scene

# Below this SSIM the "true contact" rung does not reproduce the session's images: the session
# was not collected on the scene it names (or with another force).
REPRODUCES_SSIM = 0.95
RUNGS = ("true contact", "true contact, no relief", "depth-map through the renderer")


class CeilingError(ValueError):
    """A dataset the ceiling cannot be computed for; the message says why."""


def _without(scene: Scene, names: set[str]) -> Scene:
    return dataclasses.replace(scene, effects=[e for e in scene.effects if e.name not in names])


def true_contact_images(
    scene: Scene, records: Sequence[SampleRecord], force_n: float, size: tuple[int, int]
) -> np.ndarray:
    """N x H x W x 3 uint8: each record's grasp rendered again in ``scene`` at its true pose
    (the commanded top-down grasp, closed with ``force_n``), resized to ``size`` as the
    collector resizes its frames."""
    world, renderer = SimWorld(scene), scene_renderer(scene, rng=np.random.default_rng(scene.seed))
    images = []
    for record in records:
        x, y, z, theta = record.grasp_pose
        tcp = grasp_to_tcp_pose(x, y, z + scene.gripper.tcp_to_gel_centre_m, theta)
        contact = world.grasp_contact(tcp, force_n, gap_fingers=(record.finger,))
        images.append(resize_rgb(renderer.render(contact.gap_mm[record.finger]), *size))
    return np.stack(images)


def depth_map_images(
    scene: Scene, depth_maps_m: np.ndarray, depth_crop_m: Sequence[float], size: tuple[int, int]
) -> np.ndarray:
    """N x H x W x 3 uint8: each depth-map (gel frame, m; over the crop ``depth_crop_m`` = (x, y,
    z) extents) rendered as the gel gap map of the GelSight's field of view, without GelSight
    effects (sim.gelsight.render_depth_maps), resized to ``size`` as the collector resizes."""
    try:
        images = render_depth_maps(
            scene_renderer(scene, effects=False), depth_maps_m, (depth_crop_m[0], depth_crop_m[2])
        )
    except GelSightRenderError as err:
        raise CeilingError(str(err)) from err
    return np.stack([resize_rgb(image, *size) for image in images])


def _scored(truth: np.ndarray, estimate: np.ndarray, objects: list[str], seed: int) -> dict[str, Any]:
    row = {k: v for k, v in ssim_statistics(truth, estimate, seed=seed).items() if k in SUMMARY_KEYS}
    row["objects"] = per_object_statistics(truth, estimate, objects, seed=seed)
    return row


def information_ceiling(
    root: str | os.PathLike[str],
    split: str = "test",
    force_n: float | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The three reference estimates of the module docstring for one split of a simulated
    session, each scored against the session's images like a model (``seed``: the
    baseline's random draws), overall and per object; the grasps closed with ``force_n`` (N;
    None: the scene's ``gripper.grasp_force_n``, which the collector commands)."""
    if force_n is not None and not (np.isfinite(force_n) and force_n > 0):
        raise CeilingError(f"force_n must be a positive number of newtons, got {force_n}")
    reader = DatasetReader(root)
    records = reader.records if split == "all" else select_records(reader, split)
    if len(records) < 2:
        raise CeilingError(f"the {split} set of {root} has {len(records)} sample(s); need at least 2")
    try:
        scene = load_scene(reader.info.scene)
    except SceneError as exc:
        raise CeilingError(f"{root} names the scene {reader.info.scene!r}, which cannot be loaded: {exc}") from exc
    force_n = scene.gripper.grasp_force_n if force_n is None else force_n
    if reader.info.depth_crop_m is None:
        raise CeilingError(f"{root} does not record its depth-maps' crop (dataset.json depth_crop_m)")
    samples = [reader.load(r) for r in records]
    truth = np.stack([s.tactile_rgb for s in samples])
    objects = [r.object_name for r in records]
    size = truth.shape[1:3]
    report = progress or (lambda _: None)
    estimates = {}
    report(f"{RUNGS[0]}: rendering {len(records)} grasps again")
    estimates[RUNGS[0]] = true_contact_images(_without(scene, {"sensor_noise"}), records, force_n, size)
    report(f"{RUNGS[1]}: rendering {len(records)} grasps again")
    estimates[RUNGS[1]] = true_contact_images(_without(scene, {"sensor_noise", "micro_relief"}), records, force_n, size)
    report(f"{RUNGS[2]}: rendering {len(records)} depth-maps")
    estimates[RUNGS[2]] = depth_map_images(
        scene, np.stack([s.depth_map_m for s in samples]), reader.info.depth_crop_m, size
    )
    rungs = {name: _scored(truth, estimate, objects, seed) for name, estimate in estimates.items()}
    return {
        "dataset": str(root),
        "scene": reader.info.scene,
        "split": split,
        "force_n": force_n,
        "reproduces_session": rungs[RUNGS[0]]["ssim_model_mean"] >= REPRODUCES_SSIM,
        "rungs": rungs,
    }


def format_table(result: dict[str, Any]) -> str:
    """The ceiling as a plain-text table: one row per rung, then per object."""
    rungs = result["rungs"]
    n = rungs[RUNGS[0]]["n"]
    lines = [
        f"information ceiling of {result['dataset']} ({result['split']} split, {n} pairs; scene "
        f"{result['scene']}, grasp force {result['force_n']:g} N), scored like dtx evaluate:",
        f"{'estimate':<34}{'object':<18}{'SSIM':>8}{'baseline':>10}{'ratio':>7}",
    ]
    for name, row in rungs.items():
        for label, stats in [("all", row), *row["objects"].items()]:
            lines.append(
                f"{name if label == 'all' else '':<34}{label:<18}{stats['ssim_model_mean']:>8.3f}"
                f"{stats['ssim_baseline_mean']:>10.3f}{stats['dissimilarity_ratio']:>7.2f}"
            )
    if not result["reproduces_session"]:
        lines.append(
            f"warning: the true-contact rendering scores {rungs[RUNGS[0]]['ssim_model_mean']:.3f} "
            f"(< {REPRODUCES_SSIM}) against the session's images: they were not made by this scene at "
            f"{result['force_n']:g} N, so the rungs are no ceiling for them"
        )
    return "\n".join(lines)
