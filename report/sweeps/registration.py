"""The registration sweeps: FPFH voxel, RANSAC iterations, ICP stages, and the simulated depth
effects registration runs on."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from benchmarks.perception import _sweep_cases, _sweep_row
from benchmarks.sim import DEPTH_EFFECTS
from dataset.reader import DatasetReader
from perception.registration import RegistrationParams
from perception.touch_calibration import TouchCalibrationError
from report.specs import Point, point
from report.sweeps.common import median_cpu_ms
from report.workspace import Workspace
from sim.world import SimWorld
from workcell.scene import load_scene

SCENE = "scenes/ycb_three.yaml"


def depth_effects(ws: Workspace) -> list[Point]:
    """ycb_three's depth effects off, alone (full plan) and all on -> time per 512 x 424 depth
    frame, and ADD-S of registration (default parameters) on clouds made with them."""
    scene = load_scene(SCENE)
    present = [e for e in DEPTH_EFFECTS if any(s.name == e for s in scene.effects)]
    every = sorted({s.name for s in scene.effects})
    settings: list[tuple[str, ...]] = [()]
    if ws.plan.depth_effects_alone:
        settings += [(e,) for e in present]
    settings.append(tuple(present))
    points = []
    for kept in settings:
        variant = dataclasses.replace(scene, effects=[s for s in scene.effects if s.name in kept])
        world = SimWorld(variant, seed=ws.plan.seed)
        camera = world.camera_names()[0]
        world.render_depth(camera)  # the first frame casts every ray and caches it
        frame_ms = median_cpu_ms(lambda: world.render_depth(camera), ws.plan.depth_frames)
        cases = _sweep_cases(SCENE, ws.plan.registration_poses, ws.plan.seed, [e for e in every if e not in kept])
        row = _sweep_row(cases, RegistrationParams(), {})
        setting = "none" if not kept else ("all" if len(kept) > 1 else kept[0])
        points.append(
            point(
                "depth_effects",
                setting,
                frame_ms,
                row["add_s_mm_median"],
                accepted_rate=row["accepted_rate"],
                registration_ms=row["cpu_ms_median"],
            )
        )
    return points


def _registration_points(sweep: str, cases, settings, calibrated_cases) -> list[Point]:
    points = []
    for label, params in settings:
        row = _sweep_row(cases, params, {})
        extra = {}
        if calibrated_cases:
            calibrated = _sweep_row(calibrated_cases, params, {})
            extra = {
                "add_s_mm_calibrated": calibrated["add_s_mm_median"],
                "add_s_mm_p90_calibrated": calibrated["add_s_mm_p90"],
            }
        points.append(
            point(
                sweep,
                label,
                row["cpu_ms_median"],
                row["add_s_mm_median"],
                add_s_mm_p90=row["add_s_mm_p90"],
                accepted_rate=row["accepted_rate"],
                **extra,
            )
        )
    return points


def _touch_calibrated_extrinsics(ws: Workspace) -> dict[str, np.ndarray] | None:
    """Each camera of SCENE as the report's session's touch calibration corrected it (camera
    name -> camera_to_world); None where the session saw another scene or its touches cannot
    calibrate (the tables then give the given cameras alone)."""
    if Path(DatasetReader(ws.collected).info.scene).name != Path(SCENE).name:
        return None
    try:
        calibration, _ = ws.touch_calibration
    except TouchCalibrationError:
        return None
    return {frame.removeprefix("camera_"): image.camera_to_world for frame, image in calibration.calibrated.items()}


def registration(ws: Workspace) -> list[Point]:
    """FPFH + RANSAC + ICP on segmented clusters of the five YCB meshes in ycb_three (with its
    effects): voxel size, RANSAC iterations, ICP distance stages -> ADD-S median and time, with
    the scene's given cameras (1-2 mm off) and, beside it, the same clusters seen by the cameras
    the session's touch calibration corrected."""
    cases = _sweep_cases(SCENE, ws.plan.registration_poses, ws.plan.seed, [])
    extrinsics = _touch_calibrated_extrinsics(ws)
    calibrated = _sweep_cases(SCENE, ws.plan.registration_poses, ws.plan.seed, [], extrinsics) if extrinsics else None
    base = RegistrationParams()
    voxel = [
        (
            f"{v} mm",
            dataclasses.replace(base, voxel_size_m=v * 1e-3, icp_voxel_size_m=min(v * 1e-3, base.icp_voxel_size_m)),
        )
        for v in ws.plan.voxel_mm
    ]
    ransac = [(f"{n:,}", dataclasses.replace(base, ransac_max_iterations=n)) for n in ws.plan.ransac_iterations]
    icp = [
        ("/".join(map(str, stages)) + " mm", dataclasses.replace(base, icp_distances_m=tuple(d * 1e-3 for d in stages)))
        for stages in ws.plan.icp_distances_mm
    ]
    return (
        _registration_points("registration_voxel", cases, voxel, calibrated)
        + _registration_points("registration_ransac", cases, ransac, calibrated)
        + _registration_points("registration_icp", cases, icp, calibrated)
    )
