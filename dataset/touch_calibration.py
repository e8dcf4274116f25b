"""``dtx calibrate touches``: the depth cameras' extrinsics corrected from a session's touches.

A collected sample holds a touch: the gel's pose from the arm (``gel_to_world``), the tactile
image, and the depth-map cut from the object's registered pose (``model_to_world``). The
GelSight renderer draws what that depth-map predicts, moved over a grid of places and depths
(``dataset.touches``); where the frame shows the contact elsewhere in the gel plane, the
registration is off. A near-symmetric object registered half a turn wrong (a can, any turn
about its axis) is first turned the way its touches' frames prefer (``dataset.turns``). Each
camera's frames of the session (``/perception/registration_frames`` in the session's bag) level
it on the table, and one fit of every camera's and object's place and turn on the table to the
touches and the cameras' points (``perception.touch_calibration``) gives each camera's true
extrinsic; a second round reads the touches again against the fitted objects, and each object's
turn is last set to the fraction of a degree its frames prefer (``TurnJudge.refined``).

Only the training split's touches are used, so an evaluation on the session's test split stays
honest. The result is a calibration directory of ``camera_<name>.yaml`` files in the layout of
``launch/calibration/`` (``drivers.depth_camera.base``), which the depth camera nodes, the
transform tree and ``dtx dataset redepth --calibration`` read.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

import msgs
from bus.bag import BagError, iter_envelopes
from dataset.reader import DatasetReader
from dataset.records import DatasetError, SampleRecord
from dataset.redepth import depth_map_params
from dataset.splits import split_records
from dataset.touches import measure_session_touches, touch_fitter
from dataset.turns import TurnJudge, segmented_objects, turns_alike
from perception.pointcloud import depth_images_to_world, depth_to_points_camera, transform_points
from perception.registration import sample_model_cloud
from perception.segmentation import crop_to_workspace, segmentation_params_for
from perception.touch_calibration import (
    CellCorrection,
    TouchCalibrationError,
    TouchOffset,
    pose_error,
    solve_cell,
    table_levelling,
)
from sim.world import SimWorld
from workcell.scene import Scene, load_scene

REGISTRATION_FRAMES_TOPIC = "/perception/registration_frames"
# The in-plane pose uncertainty of depth-maps cut with touch-calibrated cameras and the objects
# placed by the touches (mm): ADD-S 0.01-0.16 mm on the demo's objects. On the same maps and
# budget, 0.1 against 0.2: test split ratio 0.542 vs 0.551, contact windows 0.510 vs 0.512 (with
# the cameras alone and no placing, 0.2 had beaten 0.5: 0.574 vs 0.601). What make demo and the
# accuracy-time report train such a session's models with (dtx train --session-pose-sigma-mm).
CALIBRATED_POSE_SIGMA_MM = 0.1
# A calibration should rest on many touches: fewer than this in all is refused.
MIN_TOUCHES = 30
# Touches an object's correction is measured on in each round (each costs ~100 renderings), the
# next round measuring against depth-maps cut at the last round's fit. The cameras' fit needs
# many in its last round (on the demo session 150 left the right camera at 0.38 mm 0.031 deg,
# 400 at 0.22 mm 0.007 deg); its first round only brings the objects near, and 150 there gave
# the same cameras as 400 (0.12 / 0.23 mm against 0.13 / 0.22) in 40 % less time. Placing the
# objects, the cameras calibrated, needs fewer (150 placed the demo's bottle and box to
# 0.02-0.03 mm).
CALIBRATION_TOUCHES_PER_OBJECT = (150, 400)
PLACING_TOUCHES_PER_OBJECT = (150, 150)
# A camera's points below this height (m) are the table it is levelled on; points within
# _OBJECT_REACH_M of a registered object (and above the table band) are its view of it.
_TABLE_BAND_M = 0.006
_OBJECT_REACH_M = 0.01
# The model cloud that reach is measured to (the joint fit measures to the mesh itself).
_MESH_SPACING_M = 0.002


@dataclasses.dataclass
class TouchCalibration:
    """What ``calibrate_touches`` found: the joint fit, each camera's whole correction
    (``calibrated camera_to_world = corrections[c] @ given``) and its frame with it, and the
    touches the fit used per object."""

    cell: CellCorrection
    corrections: dict[str, np.ndarray]  # by frame id
    calibrated: dict[str, msgs.DepthImage]  # by frame id
    object_touches: dict[str, int]  # with contact, per object
    no_contact: int

    def report(self, truth: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
        """The report as plain data (``--json``); with the scene's true extrinsics, each camera's
        error against them before and after."""
        cameras: dict[str, Any] = {}
        for frame_id, correction in self.corrections.items():
            calibrated = self.calibrated[frame_id].camera_to_world
            row: dict[str, Any] = {
                "correction_mm": float(np.linalg.norm(correction[:3, 3]) * 1e3),
                "point_residual_mm": self.cell.point_residual_mm[frame_id],
                "unobservable": self.cell.unobservable[frame_id],
            }
            if truth is not None and frame_id in truth:
                row["error_before_mm"], row["error_before_deg"] = pose_error(
                    np.linalg.inv(correction) @ calibrated, truth[frame_id]
                )
                row["error_mm"], row["error_deg"] = pose_error(calibrated, truth[frame_id])
            cameras[frame_id.removeprefix("camera_")] = row
        objects = {
            name: {
                "touches": self.object_touches[name],
                "outliers": self.cell.touch_outliers.get(name, 0),
                "offset_before_mm": self.cell.touch_residual_before_mm.get(name),
                "offset_after_mm": self.cell.touch_residual_after_mm.get(name),
            }
            for name in self.object_touches
        }
        return {"cameras": cameras, "objects": objects, "no_contact_touches": self.no_contact}


def registration_frames(session: str | os.PathLike[str]) -> dict[str, list[msgs.DepthImage]]:
    """The depth frames the session's registrations used, per camera frame id, from its bags
    (``session.mcap`` and the ``session.N.mcap`` of a respawned recorder)."""
    frames: dict[str, list[msgs.DepthImage]] = {}
    bags = sorted(Path(session).glob("session*.mcap"))
    if not bags:
        raise DatasetError(f"{session} has no session bag (session.mcap): its camera frames are needed")
    for bag in bags:
        try:
            for _, envelope in iter_envelopes(bag, {REGISTRATION_FRAMES_TOPIC}):
                if envelope.topic == REGISTRATION_FRAMES_TOPIC and isinstance(envelope.message, msgs.DepthImage):
                    frames.setdefault(envelope.message.header.frame_id, []).append(envelope.message)
        except BagError as err:
            raise DatasetError(str(err)) from err
    if not frames:
        raise DatasetError(
            f"{session}: its bag holds no {REGISTRATION_FRAMES_TOPIC}; record that topic (dtx demo does) "
            "to calibrate the cameras"
        )
    return frames


def camera_views(
    frames: list[msgs.DepthImage], scene: Scene, registered: dict[str, np.ndarray]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One camera's table levelling (world frame) and, levelled, its points of each registered
    object (within :data:`_OBJECT_REACH_M` of it, above the table)."""
    points = np.concatenate(
        [transform_points(depth_to_points_camera(f.depth_m(), f.intrinsics), f.camera_to_world) for f in frames]
    )
    points = crop_to_workspace(points, segmentation_params_for(scene))
    levelling = table_levelling(points[points[:, 2] < _TABLE_BAND_M])
    points = transform_points(points, levelling)
    views = {}
    for name, model_to_world in registered.items():
        model = sample_model_cloud(scene.mesh(name), _MESH_SPACING_M, seed=0)
        distance, _ = cKDTree(transform_points(model.points_m, model_to_world)).query(
            points, distance_upper_bound=_OBJECT_REACH_M
        )
        views[name] = points[np.isfinite(distance) & (points[:, 2] > _TABLE_BAND_M)]
    return levelling, views


def calibrate_touches(session: str | os.PathLike[str], grasps: int | None = None, jobs: int = 1) -> TouchCalibration:
    """Correct each camera of ``session`` from its training split's touches (module docstring);
    with ``grasps``, from those of that many grasps only, the first of each object in turn
    (what a shorter session of the same objects would have given). ``jobs`` > 1 fits the
    touches in that many processes (the same result)."""
    if not (isinstance(jobs, int) and jobs >= 1):
        raise DatasetError(f"jobs must be a whole number >= 1, got {jobs!r}")
    reader = DatasetReader(session)
    scene = load_scene(reader.info.scene)
    train = split_records(reader.records, reader.info.split_seed)["train"]
    if grasps is not None:
        train = _first_grasps(train, grasps)
    missing = [r.sample_id for r in train if r.gel_to_world is None or r.model_to_world is None]
    if missing:
        raise DatasetError(
            f"{session}: {len(missing)} training samples (e.g. {missing[0]}) record no gel_to_world or "
            "model_to_world; collect the session with this version"
        )
    frames = registration_frames(session)
    with contextlib.ExitStack() as processes:
        fitter = touch_fitter(processes, reader, jobs)
        newest = [f[-1] for f in frames.values()]
        judge = TurnJudge(reader, train, fitter.residuals)
        predicted = _turns_chosen(reader, scene, train, newest, judge)
        levelling, views = {}, {}
        for frame_id, camera_frames in sorted(frames.items()):
            levelling[frame_id], views[frame_id] = camera_views(camera_frames[-3:], scene, predicted)
        cell, touches, no_contact = fit_cell(
            reader, fitter.touches, train, predicted, views, CALIBRATION_TOUCHES_PER_OBJECT
        )
        cell = dataclasses.replace(cell, objects={n: judge.refined(n, pose) for n, pose in cell.objects.items()})
    corrections = {c: cell.cameras[c] @ levelling[c] for c in frames}
    calibrated = {
        c: dataclasses.replace(frames[c][-1], camera_to_world=corrections[c] @ frames[c][-1].camera_to_world)
        for c in frames
    }
    return TouchCalibration(cell, corrections, calibrated, {n: len(t) for n, t in touches.items()}, no_contact)


def _turns_chosen(
    reader: DatasetReader,
    scene: Scene,
    train: list[SampleRecord],
    newest: list[msgs.DepthImage],
    judge: TurnJudge,
) -> dict[str, np.ndarray]:
    """Each touched object's pose as the session registered it (recorded with its samples), or
    the turn of it that the cameras cannot tell apart (from their ``newest`` frames, as
    recorded) and the touches prefer: a fit started half a turn off would read every touch
    against the wrong face."""
    recorded = {r.object_name: np.array(r.model_to_world) for r in train}
    chosen = {}
    for name, prepared, points in segmented_objects(reader, scene, depth_images_to_world(newest)):
        if name in recorded:
            chosen[name] = judge.choose(name, [recorded[name], *turns_alike(prepared, points, recorded[name])])
    return chosen


def fit_cell(
    reader: DatasetReader,
    measure: Callable[[list[SampleRecord]], list[TouchOffset | None]],
    train: list[SampleRecord],
    predicted: dict[str, np.ndarray],
    views: dict[str, dict[str, np.ndarray]],
    per_object: Sequence[int],
) -> tuple[CellCorrection, dict[str, list[TouchOffset]], int]:
    """The joint fit of cameras and objects (``perception.touch_calibration.solve_cell``) after
    a round of measuring ``train``'s touches against the objects as fitted (at ``predicted``
    first) for each of ``per_object`` (touches an object that round), with the last round's
    touches and no-contacts; TouchCalibrationError when fewer than :data:`MIN_TOUCHES` show a
    contact the renderer can place."""
    params, scene = depth_map_params(reader)
    models = {name: o3d.io.read_triangle_mesh(Path(scene.mesh(name))) for name in predicted}
    for touches_per_object in per_object:
        touches, no_contact = measure_session_touches(measure, train, predicted, scene, params, touches_per_object)
        counted = sum(len(t) for t in touches.values())
        if counted < MIN_TOUCHES:
            raise TouchCalibrationError(
                f"{reader.root}: {counted} of its {len(train)} training touches show a contact the renderer can "
                f"place ({', '.join(f'{n} {len(t)}' for n, t in touches.items())}); a fit needs >= {MIN_TOUCHES}"
            )
        cell = solve_cell(touches, predicted, views, models)
        predicted = cell.objects
    return cell, touches, no_contact


def offsets_cameras(scene: Scene) -> bool:
    """Whether a simulated scene offsets its cameras from their nominal extrinsics
    (``extrinsic_offset``): the scenes whose truth a calibration is scored against."""
    return any(effect.name == "extrinsic_offset" for effect in scene.effects)


def scene_camera_truth(scene_path: str) -> dict[str, np.ndarray] | None:
    """The true camera_to_world of each camera of a simulated scene whose cameras are offset
    (``extrinsic_offset``), by frame id; None for a scene without offsets."""
    scene = load_scene(scene_path)
    if not offsets_cameras(scene):
        return None
    world = SimWorld(scene)
    return {f"camera_{name}": world.true_camera_to_world(name) for name in world.camera_names()}


def _first_grasps(records: list[SampleRecord], grasps: int) -> list[SampleRecord]:
    """The records of ``grasps`` grasps: each object's first ones, taken in turn."""
    if grasps < 1:
        raise DatasetError(f"grasps must be a whole number >= 1, got {grasps}")
    by_object: dict[str, list[int]] = {}
    for record in records:
        ids = by_object.setdefault(record.object_name, [])
        if record.grasp_id not in ids:
            ids.append(record.grasp_id)
    chosen: set[tuple[str, int]] = set()
    for rank in range(max((len(ids) for ids in by_object.values()), default=0)):
        for name, ids in sorted(by_object.items()):
            if rank < len(ids) and len(chosen) < grasps:
                chosen.add((name, sorted(ids)[rank]))
    return [r for r in records if (r.object_name, r.grasp_id) in chosen]
