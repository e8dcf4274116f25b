"""Segmentation + registration checked against the simulated world's ground truth.

Used by ``dtx perception register-check`` and by ``benchmarks/perception.py``. For each mesh
and trial the scene's own objects are replaced by that one mesh at a random pose resting on the
table (uniform x, y in the workspace, uniform yaw), both depth cameras are rendered with the
scene's depth effects (calibration offset included), and the pipeline runs on what the
drivers would report: the depth images with the *nominal* extrinsics.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import open3d as o3d

from msgs.sensors import CameraIntrinsics, DepthImage
from perception.errors import PerceptionError
from perception.pointcloud import depth_images_to_world
from perception.pose_scores import add_error_m, add_s_error_m
from perception.registration import (
    ModelCloud,
    PreparedModel,
    RegistrationParams,
    prepare_model,
    register_model,
    sample_model_cloud,
)
from perception.segmentation import segment_object, segmentation_params_for
from sim.world import SimWorld
from workcell.parts import ObjectSpec
from workcell.scene import Scene, load_scene

DEFAULT_SCENE = "scenes/ycb_three.yaml"


@dataclasses.dataclass
class Trial:
    accepted: bool  # the pipeline returned a pose (no PerceptionError)
    add_s_mm: float  # NaN when not accepted
    add_mm: float
    total_ms: float  # segmentation + registration wall time, also when it failed
    cpu_ms: float  # the same in process CPU time (steadier on a shared machine)
    segmentation_ms: float
    registration_ms: float
    coarse_ms: float
    fine_ms: float
    error: str = ""


def render_depth_images(
    world: SimWorld, scene: Scene, calibration: dict[str, np.ndarray] | None = None
) -> list[DepthImage]:
    """Both cameras' depth frames as the drivers publish them: with the nominal extrinsic, or
    with ``calibration[camera]`` (camera_to_world) where given, as a calibrated driver would."""
    images = []
    for camera in scene.cameras:
        intrinsics = CameraIntrinsics(
            width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy
        )
        images.append(
            DepthImage(
                depth=world.render_depth(camera.name),
                intrinsics=intrinsics,
                camera_to_world=(calibration or {}).get(camera.name, world.nominal_camera_to_world(camera.name)),
            )
        )
    return images


def scene_with_object(
    scene: Scene, mesh_path: str | Path, rng: np.random.Generator, footprint_radius_m: float
) -> Scene:
    """The scene with its objects replaced by ``mesh_path`` at a random pose resting on the table."""
    low = np.asarray(scene.workspace_min_m[:2]) + footprint_radius_m
    high = np.asarray(scene.workspace_max_m[:2]) - footprint_radius_m
    if np.any(high <= low):
        raise PerceptionError(f"object of radius {footprint_radius_m:.3f} m does not fit the workspace")
    x_m, y_m = rng.uniform(low, high)
    obj = ObjectSpec(
        name=Path(mesh_path).stem,
        mesh=str(mesh_path),
        primitive=None,
        x_m=float(x_m),
        y_m=float(y_m),
        yaw_rad=float(rng.uniform(0.0, 2.0 * np.pi)),
        z_m=None,
        relief=[],
    )
    return dataclasses.replace(scene, objects=[obj])


def run_trial(
    scene: Scene,
    model: ModelCloud,
    surface: o3d.geometry.TriangleMesh,
    prepared: PreparedModel,
    params: RegistrationParams,
    seed: int,
    calibration: dict[str, np.ndarray] | None = None,
) -> Trial:
    world = SimWorld(scene, seed=seed)
    clouds = depth_images_to_world(render_depth_images(world, scene, calibration))
    truth = world.object_to_world[0]
    started, started_cpu = time.perf_counter(), time.process_time()
    try:
        segmented = segment_object(clouds, segmentation_params_for(scene), seed=seed)
        segmentation_ms = (time.perf_counter() - started) * 1e3
        result = register_model(prepared, segmented.points_world_m, params, seed=seed)
    except PerceptionError as exc:
        nan = float("nan")
        return Trial(
            False,
            nan,
            nan,
            (time.perf_counter() - started) * 1e3,
            (time.process_time() - started_cpu) * 1e3,
            nan,
            nan,
            nan,
            nan,
            str(exc),
        )
    total_ms, cpu_ms = (time.perf_counter() - started) * 1e3, (time.process_time() - started_cpu) * 1e3
    return Trial(
        True,
        add_s_error_m(surface, model.points_m, result.model_to_world, truth) * 1e3,
        add_error_m(model.points_m, result.model_to_world, truth) * 1e3,
        total_ms,
        cpu_ms,
        segmentation_ms,
        result.time_ms["total"],
        result.time_ms["coarse"],
        result.time_ms["fine"],
    )


def summarise(trials: Sequence[Trial], success_add_s_mm: float) -> dict:
    """Success = a pose was returned and its ADD-S is within ``success_add_s_mm``."""
    add_s = np.array([t.add_s_mm for t in trials])
    accepted = np.array([t.accepted for t in trials])
    success = accepted & (np.nan_to_num(add_s, nan=np.inf) <= success_add_s_mm)

    def stat(values, q):
        values = np.asarray(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        return round(float(np.percentile(values, q)), 3) if len(values) else None

    return {
        "trials": len(trials),
        "success_rate": round(float(success.mean()), 4),
        "accepted_rate": round(float(accepted.mean()), 4),
        "add_s_mm_median": stat(add_s, 50),
        "add_s_mm_p90": stat(add_s, 90),
        "add_mm_median": stat([t.add_mm for t in trials], 50),
        "time_ms_median": stat([t.total_ms for t in trials], 50),
        "cpu_ms_median": stat([t.cpu_ms for t in trials], 50),
        "segmentation_ms_median": stat([t.segmentation_ms for t in trials], 50),
        "registration_ms_median": stat([t.registration_ms for t in trials], 50),
        "coarse_ms_median": stat([t.coarse_ms for t in trials], 50),
        "fine_ms_median": stat([t.fine_ms for t in trials], 50),
        "errors": sorted({t.error for t in trials if t.error}),
    }


def register_check(
    mesh_paths: Sequence[str | Path],
    trials: int,
    seed: int,
    scene_path: str = DEFAULT_SCENE,
    params: RegistrationParams = RegistrationParams(),
    success_add_s_mm: float = 10.0,
    drop_effects: Sequence[str] = (),
    calibration: dict[str, np.ndarray] | None = None,
) -> dict[str, dict]:
    """Per mesh stem: success rate, ADD-S/ADD statistics (mm) and median stage times (ms).

    ``drop_effects`` names scene effects to switch off (e.g. ``extrinsic_offset`` to see the
    error left without the camera calibration offset); ``calibration`` (camera name ->
    camera_to_world) is what the cameras report instead of the nominal extrinsics, e.g. a touch
    calibration carried over from another session.
    """
    if trials < 1:
        raise PerceptionError(f"trials must be >= 1, got {trials}")
    scene = load_scene(scene_path)
    scene = dataclasses.replace(scene, effects=[e for e in scene.effects if e.name not in set(drop_effects)])
    rng = np.random.default_rng(seed)
    report = {}
    for mesh_path in mesh_paths:
        model = sample_model_cloud(mesh_path, seed=seed)
        surface = o3d.io.read_triangle_mesh(Path(mesh_path))
        prepared = prepare_model(model, params)
        # The simulator turns the mesh about its own origin, so that is where the radius counts from.
        footprint = float(np.max(np.linalg.norm(model.points_m[:, :2], axis=1)))
        results = [
            run_trial(
                scene_with_object(scene, mesh_path, rng, footprint),
                model,
                surface,
                prepared,
                params,
                seed=int(rng.integers(2**31)),
                calibration=calibration,
            )
            for _ in range(trials)
        ]
        report[Path(mesh_path).stem] = summarise(results, success_add_s_mm)
    return report
