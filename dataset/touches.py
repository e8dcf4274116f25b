"""A session's touches measured against depth-maps cut with the object at a pose: the
GelSight renderer draws what each cut predicts, moved over a grid of places in the gel plane and
depths, and the place where the drawing best matches the frame is where the touch says the
object was (``TouchOffset``, the offset from the prediction and how sharply the frame pins it).

The measurements behind ``dtx calibrate touches`` (the cameras) and ``dtx dataset redepth
--calibration`` (each object's turn and place); ``TouchPool`` shares them out among processes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

import numpy as np

from dataset.reader import DatasetReader
from dataset.records import FINGERS, DatasetError, SampleRecord
from dataset.redepth import depth_map_again, depth_map_params, model_index, poses_at
from perception.depthmap import DepthMapParams, crop_bounds
from perception.pointcloud import transform_points
from perception.touch_calibration import TouchOffset, moved_depth_map, profiled_fit
from sim.gelsight import render_depth_maps, scene_renderer
from workcell.scene import Scene, load_scene

# The grids (x, z, y in mm, about the fit so far) a touch's place and depth are searched over,
# coarse to fine: place across the gel, then along it, then both finely with their curvature.
SEARCH = (
    (np.arange(-6, 7) * 0.4, np.zeros(1), np.arange(-2, 2) * 0.3 + 0.15),
    (np.zeros(1), np.arange(-4, 5) * 0.4, np.arange(-1, 2) * 0.1),
    (np.arange(-1, 2) * 0.1, np.arange(-1, 2) * 0.1, np.arange(-1, 2) * 0.1),
)
# A frame whose change from the background stays below this (levels) shows no contact.
MIN_CONTACT_LEVELS = 8.0
# The depths (mm, along the gel normal) a pose's prediction of a frame is drawn at before the
# two are compared: how deep the grasp force pressed each gel is known to about 0.1 mm.
RESIDUAL_DEPTHS_MM = np.arange(-3, 4) * 0.05


class TouchRenderer:
    """Fits every touch of an object: the depth-map cut again at a corrected pose, moved over a
    grid of places in the gel plane and depths, drawn by the GelSight renderer and compared with
    the frame (:data:`SEARCH`, coarse to fine, all touches of a stage in one batch)."""

    def __init__(self, reader: DatasetReader, scene: Scene) -> None:
        self.reader = reader
        self.cut_params = depth_map_params(reader)[0]  # the dataset's own: what residuals judge
        # A touch is placed by where its contact is: the nearest point of each bin keeps an edge
        # narrower than a bin in contact, where the surface at the bin centres can miss it (on the
        # demo session 347 of the training touches went unplaced that way against 328).
        self.params = dataclasses.replace(self.cut_params, method="nearest_point")
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
        far = crop_bounds(self.geometry, self.params)[3]
        offsets = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 3)
        out = np.empty((len(cuts), len(offsets)))
        for i, (cut, frame, centre) in enumerate(zip(cuts, frames, centres)):
            maps = np.stack([moved_depth_map(cut, self.bin_pitch_mm, centre + o, far) for o in offsets])
            changes = render_depth_maps(self.renderer, maps, self.crop_xz_m).astype(np.float32) - self.background
            out[i] = ((changes - frame) ** 2).sum(axis=(1, 2, 3))
        return out.reshape(len(cuts), *(len(g) for g in grid))

    def residuals(self, records: list[SampleRecord]) -> np.ndarray:
        """Each record's frame against the renderer's image of the depth-map the dataset would
        hold with the object at the record's ``model_to_gel``, at the best of
        :data:`RESIDUAL_DEPTHS_MM`: the sum of squared differences (levels²), how far the pose
        predicts what the gel felt, its place in the gel plane included."""
        if not records:
            return np.zeros(0)
        cuts = [
            depth_map_again(
                model_index(self.scene, r.object_name), np.array(r.model_to_gel), self.geometry, self.cut_params
            )
            for r in records
        ]
        frames = np.stack([self._frame(r) for r in records])
        grid = (np.zeros(1), np.zeros(1), RESIDUAL_DEPTHS_MM)
        return self._ssd(cuts, frames, np.zeros((len(records), 3)), grid).reshape(len(records), -1).min(axis=1)

    def _frame(self, record: SampleRecord) -> np.ndarray:
        """A record's tactile change image, levels about no change (H x W x 3, float32)."""
        return self.reader.load(record).tactile_diff_rgb.astype(np.float32) - 128.0

    def touches(self, records: list[SampleRecord]) -> list[TouchOffset | None]:
        """Each record's touch against the prediction cut with the object at the record's
        ``model_to_gel`` (:func:`records_cut_at`); None where the frame shows no contact, or the
        cut none the renderer can place."""
        out: list[TouchOffset | None] = [None] * len(records)
        cuts, frames, weights, placed = [], [], [], []
        for i, record in enumerate(records):
            model_to_gel = np.array(record.model_to_gel)
            cut = depth_map_again(model_index(self.scene, record.object_name), model_to_gel, self.geometry, self.params)
            frame = self._frame(record)
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


def records_cut_at(
    records: list[SampleRecord], model_to_world: dict[str, np.ndarray], scene: Scene, params: DepthMapParams
) -> list[SampleRecord]:
    """``records`` as ``dtx dataset redepth`` would write them with each object at
    ``model_to_world[object]``: centred between its grasp's gels (``dataset.redepth.poses_at``;
    both fingers of every grasp must be among ``records``)."""
    poses = poses_at(records, model_to_world, scene, params)
    return [
        dataclasses.replace(
            r, model_to_gel=poses[r.sample_id][0].tolist(), model_to_world=poses[r.sample_id][1].tolist()
        )
        for r in records
    ]


def touches_of_grasps(records: list[SampleRecord], name: str, grasps: int) -> list[SampleRecord]:
    """Both fingers' ``records`` of at most ``grasps`` of object ``name``'s grasps (a seeded draw
    of those that record both fingers' gels: a grasp's cut is centred on both). ``grasps`` an
    integer >= 0; otherwise DatasetError naming it."""
    if not (isinstance(grasps, (int, np.integer)) and not isinstance(grasps, bool) and grasps >= 0):
        huge = isinstance(grasps, int) and grasps.bit_length() > 64  # past 4,300 digits an int has no repr
        shown = f"an integer of {grasps.bit_length()} bits" if huge else repr(grasps)[:80]
        raise DatasetError(f"grasps must be an integer >= 0 (how many of {name!r}'s grasps), got {shown}")
    fingers: dict[str, int] = {}
    for record in records:
        if record.object_name == name and record.gel_to_world is not None:
            fingers[record.grasp_key] = fingers.get(record.grasp_key, 0) + 1
    keys = sorted(key for key, count in fingers.items() if count == len(FINGERS))
    if len(keys) > grasps:
        keys = [keys[i] for i in sorted(np.random.default_rng(0).choice(len(keys), grasps, replace=False))]
    chosen = set(keys)
    return [r for r in records if r.grasp_key in chosen]


def measure_session_touches(
    measure: Callable[[list[SampleRecord]], list[TouchOffset | None]],
    records: list[SampleRecord],
    predicted: dict[str, np.ndarray],
    scene: Scene,
    params: DepthMapParams,
    per_object: int,
) -> tuple[dict[str, list[TouchOffset]], int]:
    """Each object's touches (both fingers of at most ``per_object`` / 2 of its grasps,
    :func:`touches_of_grasps`) against depth-maps cut with the object at
    ``predicted[object]`` (``measure``: a ``TouchRenderer.touches`` or a ``TouchPool.touches``),
    and how many showed no contact."""
    touches: dict[str, list[TouchOffset]] = {}
    no_contact = 0
    for name in sorted({r.object_name for r in records}):
        chosen = touches_of_grasps(records, name, per_object // len(FINGERS))
        found = measure(records_cut_at(chosen, predicted, scene, params))
        touches[name] = [t for t in found if t is not None]
        no_contact += len(found) - len(touches[name])
    return touches, no_contact


class TouchPool:
    """``TouchRenderer.touches`` and ``.residuals`` shared out among ``jobs`` processes, each
    with a renderer of its own: every touch is fitted alone, so the result is the same as in one
    process."""

    def __init__(self, session: str | os.PathLike[str], jobs: int) -> None:
        self.jobs = jobs
        self.pool = ProcessPoolExecutor(
            jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_start_renderer, initargs=(session,)
        )

    def __enter__(self) -> TouchPool:
        return self

    def __exit__(self, *_: object) -> None:
        self.pool.shutdown()

    def touches(self, records: list[SampleRecord]) -> list[TouchOffset | None]:
        found: list[TouchOffset | None] = [None] * len(records)
        for i, share in enumerate(self._shares(_touches_here, records)):
            found[i :: self.jobs] = share.result()
        return found

    def residuals(self, records: list[SampleRecord]) -> np.ndarray:
        found = np.zeros(len(records))
        for i, share in enumerate(self._shares(_residuals_here, records)):
            found[i :: self.jobs] = share.result()
        return found

    def _shares(self, work: Callable[[list[SampleRecord]], Any], records: list[SampleRecord]) -> list[Future[Any]]:
        return [self.pool.submit(work, records[i :: self.jobs]) for i in range(self.jobs)]


_RENDERER: TouchRenderer | None = None  # a TouchPool process's own


def _start_renderer(session: str | os.PathLike[str]) -> None:
    global _RENDERER
    reader = DatasetReader(session)
    _RENDERER = TouchRenderer(reader, load_scene(reader.info.scene))


def touch_fitter(processes: contextlib.ExitStack, reader: DatasetReader, jobs: int) -> TouchRenderer | TouchPool:
    """A ``TouchRenderer`` of ``reader``'s session, or with ``jobs`` > 1 a ``TouchPool`` whose
    processes ``processes`` shuts down."""
    if jobs > 1:
        return processes.enter_context(TouchPool(reader.root, jobs))
    return TouchRenderer(reader, load_scene(reader.info.scene))


def _touches_here(records: list[SampleRecord]) -> list[TouchOffset | None]:
    assert _RENDERER is not None  # set by the pool's initializer
    return _RENDERER.touches(records)


def _residuals_here(records: list[SampleRecord]) -> np.ndarray:
    assert _RENDERER is not None  # set by the pool's initializer
    return _RENDERER.residuals(records)
