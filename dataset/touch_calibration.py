"""``dtx calibrate touches``: the depth cameras' extrinsics corrected from a session's touches.

A collected sample holds a touch: the gel's pose from the arm (``gel_to_world``), the tactile
image, and the depth-map cut from the object's registered pose (``model_to_world``). The
GelSight renderer draws what that depth-map predicts, moved over a grid of places and depths
(``_TouchRenderer``); where the frame shows the contact elsewhere in the gel plane, the
registration is off. Each camera's frames of the session (``/perception/registration_frames``
in the session's bag) level it on the table, and one fit of every camera's and object's place
and turn on the table to the touches and the cameras' points (``perception.touch_calibration``)
gives each camera's true extrinsic; a second round reads the touches again against the fitted
objects.

Only the training split's touches are used, so an evaluation on the session's test split stays
honest. The result is a calibration directory of ``camera_<name>.yaml`` files in the layout of
``launch/calibration/`` (``drivers.depth_camera.base``), which the depth camera nodes, the
transform tree and ``dtx dataset redepth --calibration`` read.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

import msgs
from dataset.reader import DatasetReader
from dataset.records import DatasetError, SampleRecord
from dataset.redepth import depth_map_again, depth_map_params, model_index
from dataset.splits import split_records
from drivers.depth_camera.base import DepthCameraError, load_calibration_of
from nodes.bag import BagError, iter_envelopes
from perception.pointcloud import depth_images_to_world, depth_to_points_camera, transform_points
from perception.registration import prepare_model, register_model, sample_model_cloud
from perception.segmentation import crop_to_workspace, segment_object, segmentation_params_for
from perception.touch_calibration import (
    CellCorrection,
    TouchCalibrationError,
    TouchOffset,
    moved_depth_map,
    pose_error,
    profiled_fit,
    solve_cell,
    table_levelling,
)
from sim.gelsight import render_depth_maps, scene_renderer
from sim.world import SimWorld
from workcell.scene import Scene, load_scene

REGISTRATION_FRAMES_TOPIC = "/perception/registration_frames"
# A calibration should rest on many touches: fewer than this in all is refused.
MIN_TOUCHES = 30
# The grids (x, z, y in mm, about the fit so far) a touch's place and depth are searched over,
# coarse to fine: place across the gel, then along it, then both finely with their curvature.
SEARCH = (
    (np.arange(-6, 7) * 0.4, np.zeros(1), np.arange(-2, 2) * 0.3 + 0.15),
    (np.zeros(1), np.arange(-4, 5) * 0.4, np.arange(-1, 2) * 0.1),
    (np.arange(-1, 2) * 0.1, np.arange(-1, 2) * 0.1, np.arange(-1, 2) * 0.1),
)
# A frame whose change from the background stays below this (levels) shows no contact.
MIN_CONTACT_LEVELS = 8.0
# Rounds of measuring against depth-maps cut at the corrected pose.
CORRECTION_ROUNDS = 2
# Touches an object's correction is measured on (each costs ~100 renderings per round). More
# sharpen the cameras (on the demo session 400 left the right camera at 0.20 mm 0.013 deg
# against 0.38 mm 0.031 deg), but the session registered again with those cameras took the
# gelatin box's other, near-symmetric turn and the model's test ratio fell from 0.575 to 0.69
# (docs/measurements.md): until the registration's turn is chosen by the touches, 150.
MAX_TOUCHES_PER_OBJECT = 150
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


class _TouchRenderer:
    """Fits every touch of an object: the depth-map cut again at a corrected pose, moved over a
    grid of places in the gel plane and depths, drawn by the GelSight renderer and compared with
    the frame (:data:`SEARCH`, coarse to fine, all touches of a stage in one batch)."""

    def __init__(self, reader: DatasetReader, scene: Scene) -> None:
        self.reader = reader
        self.params, _ = depth_map_params(reader)
        self.geometry = scene.gripper_geometry()
        self.scene = scene
        self.renderer = scene_renderer(scene, size=self.params.shape, effects=False)
        self.background = self.renderer.background().astype(np.float32)
        crop = reader.info.depth_crop_m
        assert crop is not None  # depth_map_params refuses a dataset without one
        self.crop_xz_m = (crop[0], crop[2])
        rows, cols = self.params.shape
        self.bin_pitch_mm = (crop[2] * 1e3 / rows, crop[0] * 1e3 / cols)
        pitch_rows, pitch_cols = self.renderer.pixel_pitch_mm
        h, w = self.renderer.config.shape
        self.z_mm = (np.arange(h) - (h - 1) / 2) * pitch_rows
        self.x_mm = (np.arange(w) - (w - 1) / 2) * pitch_cols

    def _ssd(self, cuts: list[np.ndarray], frames: np.ndarray, centres: np.ndarray, grid: tuple) -> np.ndarray:
        """N x |x| x |z| x |y|: each touch's frame against its cut moved to centre + grid."""
        far = self.params.y_range_m[1]
        offsets = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 3)
        out = np.empty((len(cuts), len(offsets)))
        for i, (cut, frame, centre) in enumerate(zip(cuts, frames, centres)):
            maps = np.stack([moved_depth_map(cut, self.bin_pitch_mm, centre + o, far) for o in offsets])
            changes = render_depth_maps(self.renderer, maps, self.crop_xz_m).astype(np.float32) - self.background
            out[i] = ((changes - frame) ** 2).sum(axis=(1, 2, 3))
        return out.reshape(len(cuts), *(len(g) for g in grid))

    def touches(self, records: list[SampleRecord], correction_world: np.ndarray) -> list[TouchOffset | None]:
        """Each record's touch against the prediction at ``correction_world`` @ the registered
        pose; None where the frame shows no contact, or the cut none the renderer can place."""
        out: list[TouchOffset | None] = [None] * len(records)
        cuts, frames, weights, placed = [], [], [], []
        for i, record in enumerate(records):
            gel_to_world = np.array(record.gel_to_world)
            moved = np.linalg.inv(gel_to_world) @ correction_world @ gel_to_world
            # The cut is centred between the gels (where the grasp pushed the object): a
            # correction moves it in the gel plane only, never across the gels.
            moved[1, 3] = 0.0
            model_to_gel = moved @ np.array(record.model_to_gel)
            cut = depth_map_again(model_index(self.scene, record.object_name), model_to_gel, self.geometry, self.params)
            frame = self.reader.load(record).tactile_diff_rgb.astype(np.float32) - 128.0
            weight = np.abs(self._cut_change(cut)).sum(axis=2)
            if float(np.abs(frame).max()) >= MIN_CONTACT_LEVELS and weight.sum() > 0:
                placed.append(i)
                cuts.append(cut)
                frames.append(frame)
                weights.append(weight)
        if not placed:
            return out
        measured = np.stack(frames)
        centres = np.zeros((len(placed), 3))
        information = np.zeros((len(placed), 2, 2))
        for grid in SEARCH:
            ssd = self._ssd(cuts, measured, centres, grid)
            for j in range(len(placed)):
                fit, information[j] = profiled_fit(ssd[j], grid, measured[j].size)
                centres[j] += fit
        for i, weight, centre, info in zip(placed, weights, centres, information):
            if not info.any():
                continue
            gel_to_world = np.array(records[i].gel_to_world)
            centre_gel_m = np.array([weight.sum(0) @ self.x_mm, 0.0, weight.sum(1) @ self.z_mm]) / weight.sum() * 1e-3
            out[i] = TouchOffset(centre[:2], info, transform_points(centre_gel_m[None], gel_to_world)[0], gel_to_world)
        return out

    def _cut_change(self, cut: np.ndarray) -> np.ndarray:
        """The change image of a cut as it is (where the predicted contact is, for its place)."""
        return render_depth_maps(self.renderer, cut[None], self.crop_xz_m)[0].astype(np.float32) - self.background


def registration_frames(session: str | os.PathLike[str]) -> dict[str, list[msgs.DepthImage]]:
    """The depth frames the session's registrations used, per camera frame id, from its bags
    (``session.mcap`` and the ``session.N.mcap`` of a respawned recorder)."""
    frames: dict[str, list[msgs.DepthImage]] = {}
    bags = sorted(Path(session).glob("session*.mcap"))
    if not bags:
        raise DatasetError(f"{session} has no session bag (session.mcap): its camera frames are needed")
    for bag in bags:
        try:
            for _, envelope in iter_envelopes(bag):
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


def measure_session_touches(
    measure: Callable[[list[SampleRecord], np.ndarray], list[TouchOffset | None]],
    records: list[SampleRecord],
    predicted: dict[str, np.ndarray],
) -> tuple[dict[str, list[TouchOffset]], int]:
    """Each object's touches (at most :data:`MAX_TOUCHES_PER_OBJECT`, a seeded draw) against
    depth-maps cut with the object at ``predicted[object]`` (``measure``: a
    ``_TouchRenderer.touches`` or a ``_TouchPool.touches``), and how many showed no contact."""
    by_object: dict[str, list[SampleRecord]] = {}
    for record in records:
        by_object.setdefault(record.object_name, []).append(record)
    touches: dict[str, list[TouchOffset]] = {}
    no_contact = 0
    for name, chosen in sorted(by_object.items()):
        if len(chosen) > MAX_TOUCHES_PER_OBJECT:
            picks = np.random.default_rng(0).choice(len(chosen), MAX_TOUCHES_PER_OBJECT, replace=False)
            chosen = [chosen[i] for i in sorted(picks)]
        registered = np.array(chosen[0].model_to_world)
        found = measure(chosen, predicted[name] @ np.linalg.inv(registered))
        touches[name] = [t for t in found if t is not None]
        no_contact += len(found) - len(touches[name])
    return touches, no_contact


class _TouchPool:
    """``_TouchRenderer.touches`` shared out among ``jobs`` processes, each with a renderer of
    its own: every touch is fitted alone, so the result is the same as in one process."""

    def __init__(self, session: str | os.PathLike[str], jobs: int) -> None:
        self.jobs = jobs
        self.pool = ProcessPoolExecutor(
            jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_start_renderer, initargs=(session,)
        )

    def __enter__(self) -> _TouchPool:
        return self

    def __exit__(self, *_: object) -> None:
        self.pool.shutdown()

    def touches(self, records: list[SampleRecord], correction_world: np.ndarray) -> list[TouchOffset | None]:
        shares = [self.pool.submit(_touches_here, records[i :: self.jobs], correction_world) for i in range(self.jobs)]
        found: list[TouchOffset | None] = [None] * len(records)
        for i, share in enumerate(shares):
            found[i :: self.jobs] = share.result()
        return found


_RENDERER: _TouchRenderer | None = None  # a _TouchPool process's own


def _start_renderer(session: str | os.PathLike[str]) -> None:
    global _RENDERER
    reader = DatasetReader(session)
    _RENDERER = _TouchRenderer(reader, load_scene(reader.info.scene))


def _touches_here(records: list[SampleRecord], correction_world: np.ndarray) -> list[TouchOffset | None]:
    assert _RENDERER is not None  # set by the pool's initializer
    return _RENDERER.touches(records, correction_world)


def _camera_views(
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


def calibrate_touches(
    session: str | os.PathLike[str], rounds: int = CORRECTION_ROUNDS, grasps: int | None = None, jobs: int = 1
) -> TouchCalibration:
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
    predicted = {r.object_name: np.array(r.model_to_world) for r in train}
    frames = registration_frames(session)
    levelling, views = {}, {}
    for frame_id, camera_frames in sorted(frames.items()):
        levelling[frame_id], views[frame_id] = _camera_views(camera_frames[-3:], scene, predicted)
    models = {name: o3d.io.read_triangle_mesh(scene.mesh(name)) for name in predicted}
    with contextlib.ExitStack() as processes:
        if jobs > 1:
            measure = processes.enter_context(_TouchPool(session, jobs)).touches
        else:
            measure = _TouchRenderer(reader, scene).touches
        cell, touches, no_contact = _rounds(session, rounds, measure, train, predicted, views, models)
    corrections = {c: cell.cameras[c] @ levelling[c] for c in frames}
    calibrated = {
        c: dataclasses.replace(frames[c][-1], camera_to_world=corrections[c] @ frames[c][-1].camera_to_world)
        for c in frames
    }
    return TouchCalibration(cell, corrections, calibrated, {n: len(t) for n, t in touches.items()}, no_contact)


def _rounds(
    session: str | os.PathLike[str],
    rounds: int,
    measure: Callable[[list[SampleRecord], np.ndarray], list[TouchOffset | None]],
    train: list[SampleRecord],
    predicted: dict[str, np.ndarray],
    views: dict[str, dict[str, np.ndarray]],
    models: dict[str, o3d.geometry.TriangleMesh],
) -> tuple[CellCorrection, dict[str, list[TouchOffset]], int]:
    """The joint fit after ``rounds`` of measuring the touches against the objects as fitted
    (the registered poses ``predicted`` first), with the last round's touches and no-contacts."""
    for _ in range(rounds):
        touches, no_contact = measure_session_touches(measure, train, predicted)
        counted = sum(len(t) for t in touches.values())
        if counted < MIN_TOUCHES:
            raise TouchCalibrationError(
                f"{session}: {counted} of its {len(train)} training touches show a contact the renderer can place "
                f"({', '.join(f'{n} {len(t)}' for n, t in touches.items())}); a calibration needs >= {MIN_TOUCHES}"
            )
        cell = solve_cell(touches, predicted, views, models)
        predicted = cell.objects
    return cell, touches, no_contact


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


def register_again(session: str | os.PathLike[str], frames: list[msgs.DepthImage]) -> dict[str, np.ndarray]:
    """Each object of ``session`` registered again, as its patch extractor did (segmentation,
    then registration, same seed), from its cameras' ``frames`` (e.g. :func:`calibrated_frames`,
    or a fresh calibration's ``TouchCalibration.calibrated``)."""
    reader = DatasetReader(session)
    scene = load_scene(reader.info.scene)
    clouds = depth_images_to_world(frames)
    registered = {}
    for spec in scene.objects:
        if not spec.mesh or spec.name not in {r.object_name for r in reader.records}:
            continue
        segmented = segment_object(
            clouds,
            segmentation_params_for(scene),
            hint_world_m=np.array([spec.x_m, spec.y_m, 0.0]),
            seed=reader.info.split_seed,
        )
        prepared = prepare_model(sample_model_cloud(spec.mesh, seed=reader.info.split_seed))
        registered[spec.name] = register_model(
            prepared, segmented.points_world_m, seed=reader.info.split_seed
        ).model_to_world
    return registered


def scene_camera_truth(scene_path: str) -> dict[str, np.ndarray] | None:
    """The true camera_to_world of each camera of a simulated scene whose cameras are offset
    (``extrinsic_offset``), by frame id; None for a scene without offsets."""
    scene = load_scene(scene_path)
    if not any(effect.name == "extrinsic_offset" for effect in scene.effects):
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
