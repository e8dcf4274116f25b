"""The accuracy-time report's camera-calibration sweep: how many grasps a lab must spend on
touch calibration (``dtx calibrate touches --grasps N``) for the cameras' extrinsics, and what
the geometry they give lets an estimate reach. Runs on the report's collected session, whose
scene holds the true extrinsics."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.redepth import depth_map_again, depth_map_params, model_index, poses_at
from dataset.registered_again import register_again
from dataset.splits import split_records
from dataset.touch_calibration import TouchCalibration, calibrate_touches, registration_frames, scene_camera_truth
from perception.depthmap import DepthMapParams
from perception.touch_calibration import TouchCalibrationError, pose_error
from report.specs import Point, point
from report.sweeps.common import renderer_ratio
from report.workspace import Workspace
from workcell.scene import Scene


def _seconds_per_grasp(records: list[SampleRecord]) -> float:
    """The session's own pace: from its first grasp's tactile frame to its last, per grasp."""
    stamps = sorted({(r.grasp_id, r.stamps_ns["tactile"]) for r in records}, key=lambda row: row[1])
    return (stamps[-1][1] - stamps[0][1]) * 1e-9 / max(len(stamps) - 1, 1)


def calibration_grasps(ws: Workspace) -> list[Point]:
    """The cameras calibrated from the touches of the session's first N training grasps (``dtx
    calibrate touches --grasps N``) -> the worse camera's error against the scene's truth (mm);
    time = those grasps at the session's own pace (a simulated arm's is faster than a real one's)
    plus the fit's CPU time.
    Beside it, what that geometry allows: the test split's depth-maps cut again with the
    calibration (each object registered again) through the GelSight renderer, scored as ``dtx
    evaluate`` scores a model (the ceiling rung ``dtx sim ceiling`` calls the model's input)."""
    reader = DatasetReader(ws.collected)
    truth = scene_camera_truth(reader.info.scene)
    if truth is None:
        raise RuntimeError(f"{reader.info.scene} offsets no camera: there is nothing to calibrate")
    pace_s = _seconds_per_grasp(reader.records)
    available = len({r.grasp_key for r in split_records(reader.records, reader.info.split_seed)["train"]})
    test = ws.first_test
    params, scene = depth_map_params(reader)
    clouds = {name: model_index(scene, name) for name in sorted({r.object_name for r in test.records})}
    recorded = test.depth_maps([ws.collected])  # the maps its own cameras gave
    before = [pose_error(np.asarray(world), truth[frame]) for frame, world in _given_extrinsics(ws.collected).items()]
    points = [
        point(
            "calibration_grasps",
            "none (the given extrinsics)",
            0.0,
            max(mm for mm, _ in before),
            error_deg=round(max(deg for _, deg in before), 4),
            **renderer_ratio(test, scene, reader.info.depth_crop_m, recorded),
        )
    ]
    for grasps in sorted({min(n, available) for n in ws.plan.calibration_grasps}):
        started = time.process_time()
        try:
            calibration = calibrate_touches(ws.collected, grasps=grasps)
        except TouchCalibrationError as err:
            points.append(point("calibration_grasps", f"{grasps} grasps", grasps * pace_s, None, refused=str(err)))
            continue
        fit_s = time.process_time() - started
        cameras = calibration.report(truth)["cameras"].values()
        maps = _test_maps_with(ws, calibration, clouds, params, scene)
        points.append(
            point(
                "calibration_grasps",
                f"{grasps} grasps",
                grasps * pace_s + fit_s,
                max(row["error_mm"] for row in cameras),
                error_deg=round(max(row["error_deg"] for row in cameras), 4),
                fit_cpu_s=round(fit_s, 1),
                touches=sum(calibration.object_touches.values()),
                touches_per_object=", ".join(f"{name} {n}" for name, n in sorted(calibration.object_touches.items())),
                **renderer_ratio(test, scene, reader.info.depth_crop_m, maps),
            )
        )
    return points


def _test_maps_with(
    ws: Workspace, calibration: TouchCalibration, clouds: dict, params: DepthMapParams, scene: Scene
) -> np.ndarray:
    """The session's test depth-maps cut again (``params``, ``scene``: its patch extractor's) with
    the objects registered by ``calibration``'s cameras alone (placed by all the session's
    touches, the objects would hide the cameras' share)."""
    registered = register_again(ws.collected, list(calibration.calibrated.values()), by_touches=False)
    poses = poses_at(ws.first_test.records, registered, scene, params)
    geometry = scene.gripper_geometry()
    return np.stack(
        [depth_map_again(clouds[r.object_name], poses[r.sample_id][0], geometry, params) for r in ws.first_test.records]
    )


def _given_extrinsics(session: Path) -> dict[str, np.ndarray]:
    """Each camera's camera_to_world as the session's registrations used it, by frame id."""
    return {frame: images[-1].camera_to_world for frame, images in registration_frames(session).items()}
