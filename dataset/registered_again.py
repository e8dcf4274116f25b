"""The objects of a session registered again from calibrated cameras (``dtx dataset redepth
--calibration``), as its patch extractor registered them, then placed by the session's own
touches, which the extractor, registering before the first grasp, could not use:

1. a turn of a near-symmetric object that the cameras cannot tell from the registered one (a
   box or a bottle turned half round) is offered to the touches, which can tell (:class:`TurnJudge`);
2. each object's place and turn on the table is fitted to its training touches and the cameras'
   points together (``dataset.touch_calibration.fit_cell``, the calibration's own fit), with the
   cameras as calibrated.

On the demo session, with cameras calibrated from 400 touches an object, the registration took
the gelatin box and the can half a turn wrong (the box's mesh turned half round lies 0.6 mm from
itself); the box's touches lie 0.9 mm from their prediction at the true turn and 1.8 mm at the
registered one. The touches then place the bottle to 0.02 mm (registered: 0.13 mm) and the box
to 0.41 mm (0.69 mm). Only the training split's touches are used, so the test split stays honest.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import warnings
from pathlib import Path

import numpy as np

import msgs
from dataset.reader import DatasetReader
from dataset.records import DatasetError
from dataset.splits import split_records
from dataset.touch_calibration import PLACING_TOUCHES_PER_OBJECT, camera_views, fit_cell, registration_frames
from dataset.touches import touch_measure
from dataset.turns import TurnJudge, segmented_objects, turns_alike
from drivers.depth_camera.base import DepthCameraError, load_calibration_of
from perception.pointcloud import depth_images_to_world
from perception.registration import register_model
from perception.touch_calibration import TouchCalibrationError
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
    with contextlib.ExitStack() as processes:
        judge = TurnJudge(reader, train, touch_measure(processes, reader, jobs)) if by_touches else None
        registered = {}
        for name, prepared, points in segmented_objects(reader, scene, depth_images_to_world(frames)):
            pose = register_model(prepared, points, seed=reader.info.split_seed).model_to_world
            registered[name] = (
                pose if judge is None else judge.choose(name, [pose, *turns_alike(prepared, points, pose)])
            )
        if judge is None:
            return registered
        views = {f.header.frame_id: camera_views([f], scene, registered)[1] for f in frames}
        try:
            cell, _, _ = fit_cell(reader, judge.measure, train, registered, views, PLACING_TOUCHES_PER_OBJECT)
        except TouchCalibrationError as err:
            warnings.warn(f"the objects keep their registered places: {err}", stacklevel=2)
            return registered
    return cell.objects
