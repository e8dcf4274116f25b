"""The objects of a session registered again from calibrated cameras (``dtx dataset redepth
--calibration``), as its patch extractor registered them, then placed by the session's own
touches, which the extractor, registering before the first grasp, could not use:

1. a turn of a near-symmetric object that the cameras cannot tell from the registered one (a
   box or a bottle turned half round, a can turned any way about its axis) is offered to the
   touches, whose frames can tell (:class:`TurnJudge`);
2. each object's place and turn on the table is fitted to its training touches and the cameras'
   points together (``dataset.touch_calibration.fit_cell``, the calibration's own fit), with the
   cameras as calibrated;
3. its turn is then set to the fraction of a degree its frames prefer (``TurnJudge.refined``):
   the touches' places hold a can's turn about its axis to a degree only.

On the demo session, with cameras calibrated from 400 touches an object, the registration took
the gelatin box and the can half a turn wrong (the box's mesh turned half round lies 0.6 mm from
itself); the box's touches lie 0.9 mm from their prediction at the true turn and 1.8 mm at the
registered one. The touches then place the bottle's and the box's surfaces within 0.03 mm of the
truth (registered: 0.13 and 0.69 mm from it). Only the training split's touches are used, so the
test split stays honest.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d

import msgs
from dataset.check import records_checksum
from dataset.reader import DatasetReader
from dataset.records import DatasetError
from dataset.splits import split_records
from dataset.touch_calibration import (
    PLACING_TOUCHES_PER_OBJECT,
    camera_views,
    fit_cell,
    offsets_cameras,
    registration_frames,
)
from dataset.touches import touch_fitter
from dataset.turns import TurnJudge, segmented_objects, turns_alike
from drivers.depth_camera.base import DepthCameraError, load_calibration_of
from msgs import strict_json
from perception.errors import PointCloudError
from perception.pointcloud import check_transform, depth_images_to_world
from perception.pose_scores import add_s_error_m
from perception.registration import register_model, sample_model_cloud
from perception.touch_calibration import TouchCalibrationError, pose_error
from sim.world import SimWorld
from workcell.scene import load_scene


def calibrated_frames(
    session: str | os.PathLike[str], calibration_dir: str | os.PathLike[str]
) -> list[msgs.DepthImage]:
    """The newest registration frame of each camera of ``session`` with the extrinsic of its
    file in ``calibration_dir`` (``<frame id>.yaml``); DatasetError when a file is missing or
    describes another camera (image size or intrinsics differ)."""
    calibrated = []
    for frame_id, frames in sorted(registration_frames(session).items()):
        path = Path(calibration_dir) / f"{frame_id}.yaml"
        try:
            calibration = load_calibration_of(str(path), frames[-1].intrinsics, f"{frame_id} of {session}")
        except DepthCameraError as err:
            raise DatasetError(str(err)) from err
        calibrated.append(dataclasses.replace(frames[-1], camera_to_world=calibration.camera_to_world))
    return calibrated


def register_again(
    session: str | os.PathLike[str], frames: list[msgs.DepthImage], by_touches: bool = True, jobs: int = 1
) -> dict[str, np.ndarray]:
    """Each object of ``session`` registered again, as its patch extractor did (segmentation,
    then registration, same seed), from its cameras' ``frames`` (e.g. :func:`calibrated_frames`,
    or a fresh calibration's ``TouchCalibration.calibrated``); with ``by_touches``, its turn
    chosen and its place fitted by the session's training touches (module docstring), measured
    in ``jobs`` processes."""
    reader = DatasetReader(session)
    scene = load_scene(reader.info.scene)
    train = split_records(reader.records, reader.info.split_seed)["train"]
    objects = list(segmented_objects(reader, scene, depth_images_to_world(frames)))
    registered = {
        name: register_model(prepared, points, seed=reader.info.split_seed).model_to_world
        for name, prepared, points in objects
    }
    if not by_touches:
        return registered
    with contextlib.ExitStack() as processes:
        fitter = touch_fitter(processes, reader, jobs)
        judge = TurnJudge(reader, train, fitter.residuals)
        for name, prepared, points in objects:
            pose = registered[name]
            registered[name] = judge.choose(name, [pose, *turns_alike(prepared, points, pose)])
        views = {f.header.frame_id: camera_views([f], scene, registered)[1] for f in frames}
        try:
            cell, _, _ = fit_cell(reader, fitter.touches, train, registered, views, PLACING_TOUCHES_PER_OBJECT)
        except TouchCalibrationError as err:
            warnings.warn(f"the objects keep their registered places: {err}", stacklevel=2)
            return registered
        return {name: judge.refined(name, pose) for name, pose in cell.objects.items()}


# What ``dtx calibrate touches`` writes beside the cameras: the objects of the session it was
# calibrated from, as its joint fit placed them.
PLACEMENTS_FILE = "placements.json"


def placements_file(session: str | os.PathLike[str], objects: dict[str, np.ndarray]) -> str:
    """The text of :data:`PLACEMENTS_FILE`: ``objects`` (name -> model_to_world) as a calibration
    of ``session`` placed them, with the checksum of the session's records, so that only that
    session takes them."""
    return (
        strict_json.dumps(
            {
                "session_records_sha256": records_checksum(DatasetReader(session)),
                "objects": {name: np.asarray(pose).tolist() for name, pose in sorted(objects.items())},
            },
            indent=1,
        )
        + "\n"
    )


def objects_placed(
    session: str | os.PathLike[str], calibration_dir: str | os.PathLike[str], jobs: int = 1
) -> tuple[dict[str, np.ndarray], str]:
    """Each object of ``session`` where its depth-maps are to be cut with the cameras of
    ``calibration_dir``, and how it was found: the calibration's own fit when it was calibrated
    from this very session (:data:`PLACEMENTS_FILE`; the fit placed the objects with the cameras
    and 400 touches an object: on the demo session ADD-S 0.003-0.20 mm), else registered again
    from the calibrated cameras and placed by the session's touches (:func:`register_again`)."""
    path = Path(calibration_dir) / PLACEMENTS_FILE
    if path.exists():
        session_sha256, objects = _read_placements(path)
        if session_sha256 == records_checksum(DatasetReader(session)):
            return objects, f"placed by the calibration's own fit of this session ({path})"
    frames = calibrated_frames(session, calibration_dir)
    return register_again(session, frames, jobs=jobs), "registered again from the calibrated cameras, placed by touches"


def _read_placements(path: Path) -> tuple[str, dict[str, np.ndarray]]:
    """A :data:`PLACEMENTS_FILE`'s session checksum and objects; DatasetError naming what is wrong."""
    try:
        record = json.loads(path.read_text())
        session_sha256 = record["session_records_sha256"]
        if not isinstance(session_sha256, str):
            raise TypeError(f"session_records_sha256 is {session_sha256!r}, not a checksum")
        return session_sha256, {name: check_transform(pose, name) for name, pose in record["objects"].items()}
    except (ValueError, KeyError, TypeError, AttributeError, PointCloudError) as err:
        raise DatasetError(f"{path} is not a placements file of dtx calibrate touches: {err!r}") from err


def placement_report(session: str | os.PathLike[str], registered: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Per object: how far ``registered`` moved it from the pose its samples record (mm, deg) and,
    on a simulated scene whose cameras are offset (``offsets_cameras``: its truth is known),
    its ADD-S against the scene's placement (mm, the mean distance to the true mesh surface)."""
    reader = DatasetReader(session)
    scene = load_scene(reader.info.scene)
    recorded = {r.object_name: np.array(r.model_to_world) for r in reader.records if r.model_to_world is not None}
    truth = {}
    if offsets_cameras(scene):
        world = SimWorld(scene)
        truth = {spec.name: pose for spec, pose in zip(world.scene.objects, world.object_to_world)}
    report = {}
    for name, pose in sorted(registered.items()):
        row = dict(zip(("moved_mm", "moved_deg"), pose_error(pose, recorded[name]))) if name in recorded else {}
        if name in truth:
            mesh = o3d.io.read_triangle_mesh(Path(scene.mesh(name)))
            points = sample_model_cloud(scene.mesh(name), seed=0).points_m
            row["add_s_mm"] = add_s_error_m(mesh, points, pose, truth[name]) * 1e3
        report[name] = row
    return report
