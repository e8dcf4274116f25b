"""Which way round a near-symmetric object stands, chosen by its touches. A box, a bottle or
a can turned half round about the vertical fits the depth cameras' points almost as well as the
right way round (the gelatin box's mesh turned half round lies 0.6 mm from itself), and a can
at every turn, so the registration may take any of them; the touches, which feel the object's
edges and, on a can, a side a few tenths of a millimetre out of round, can tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np
from scipy.spatial import cKDTree

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.redepth import depth_map_params, model_cloud
from dataset.touches import records_cut_at, touches_of_grasps
from perception.planar_icp import is_upright, turned_about_centre
from perception.pointcloud import transform_points
from perception.registration import PreparedModel, prepare_model, sample_model_cloud
from perception.segmentation import segment_object, segmentation_params_for
from perception.touch_calibration import planar_transform, pose_error
from workcell.scene import Scene

# Turns (rad) about the vertical a resting object's registration is checked against: a box, a
# bottle or a can looks much alike to the cameras turned half round, a can at every turn. The
# master chef can's radius varies from 49.5 to 50.1 mm round its side (median over its height);
# turned 5 deg, half a step, its side moves 0.02 mm at the median and 0.11 mm at most, which
# :data:`FINE_TURNS_DEG` takes up once the object is placed.
CHECKED_TURNS_RAD = tuple(np.radians(np.arange(10, 360, 10)))
# A turned pose the cameras cannot tell from the registered one: its ICP fitness at most this
# much lower and its RMSE at most this much higher (m). On the demo session the bottle's,
# can's and box's half turns fit within 0.001 and 0.03 mm, their quarter turns (box, bottle) not.
TURN_FITNESS_MARGIN = 0.01
TURN_RMSE_MARGIN_M = 0.0002
# Grasps whose touches (both fingers) choose between such turns, by the sum of their residuals
# (``TouchRenderer.residuals``). On the demo session's recorded poses the true turn's sum is 0.78
# of the half turn's (box) and the half turn's 1.30 of the true one's (bottle); of a can's 27
# turns alike to the cameras, the one 2 deg from the truth is least (0.94 of the registered
# one's, 105 deg off), the next other turn 0.97: from 32 grasps, not from 8.
TURN_GRASPS = 32
# The turns (deg) about its centre an object, once placed, is drawn at against the frames: the
# cameras and the touches' places hold a can's turn about its axis to a degree (on the demo
# session 0.74 deg off, a place 0.09 mm off), the frames' residual is least within 0.25 deg of
# the true turn.
FINE_TURNS_DEG = np.arange(-2.0, 2.01, 0.25)


def segmented_objects(
    reader: DatasetReader, scene: Scene, clouds: Sequence[np.ndarray]
) -> Iterator[tuple[str, PreparedModel, np.ndarray]]:
    """Each object of ``reader``'s session as its patch extractor segments it from ``clouds``
    (world, m) and prepares its model (same seed): (name, prepared model, its points, world m)."""
    names = {r.object_name for r in reader.records}
    for spec in scene.objects:
        if not spec.mesh or spec.name not in names:
            continue
        segmented = segment_object(
            clouds,
            segmentation_params_for(scene),
            hint_world_m=np.array([spec.x_m, spec.y_m, 0.0]),
            seed=reader.info.split_seed,
        )
        yield (
            spec.name,
            prepare_model(sample_model_cloud(spec.mesh, seed=reader.info.split_seed)),
            segmented.points_world_m,
        )


def turns_alike(prepared: PreparedModel, observed_world_m: np.ndarray, model_to_world: np.ndarray) -> list[np.ndarray]:
    """The registered upright pose turned by each of :data:`CHECKED_TURNS_RAD` and refined, where
    the cameras' points fit it as well (:data:`TURN_FITNESS_MARGIN`, :data:`TURN_RMSE_MARGIN_M`);
    none for a pose that is not upright, and each pose once (within 1 mm and 1 deg)."""
    if not is_upright(model_to_world):
        return []
    fine = np.asarray(prepared.fine.points)
    normals = np.asarray(prepared.fine.normals)
    tree = cKDTree(fine)
    distance_m = prepared.params.icp_distances_m[-1]
    iterations = prepared.params.icp_max_iterations
    args = (observed_world_m, tree, fine, normals, model_to_world)
    _, fitness, rmse_m = turned_about_centre(*args, 0.0, distance_m, iterations)
    alike = [model_to_world]
    for turn in CHECKED_TURNS_RAD:
        turned, turned_fitness, turned_rmse_m = turned_about_centre(*args, turn, distance_m, iterations)
        if turned_fitness < fitness - TURN_FITNESS_MARGIN or turned_rmse_m > rmse_m + TURN_RMSE_MARGIN_M:
            continue
        # ICP from a quarter turn may slide back to a pose already kept
        if all(max(pose_error(turned, kept)) > 1.0 for kept in alike):
            alike.append(turned)
    return alike[1:]


class TurnJudge:
    """Chooses between poses of an object the cameras cannot tell apart by its touches among
    ``train`` (the training split's, so that the test split stays honest): at each pose, the
    depth-maps as ``dtx dataset redepth`` would cut them, drawn by the renderer against the
    frames (``residuals``: a ``TouchRenderer.residuals`` or a ``TouchPool.residuals``). The pose
    whose drawings match the frames best (the least sum of residuals) wins; the first (the
    registered one) where no touch was recorded."""

    def __init__(
        self, reader: DatasetReader, train: list[SampleRecord], residuals: Callable[[list[SampleRecord]], np.ndarray]
    ) -> None:
        self.train, self.residuals = train, residuals
        self.params, self.scene = depth_map_params(reader)

    def choose(self, name: str, poses: list[np.ndarray]) -> np.ndarray:
        records = touches_of_grasps(self.train, name, TURN_GRASPS)
        if len(poses) == 1 or not records:
            return poses[0]
        return poses[int(np.argmin(self._totals(name, poses, records)))]

    def refined(self, name: str, model_to_world: np.ndarray) -> np.ndarray:
        """``model_to_world`` (placed) turned about the vertical through its model's centre by
        the turn of :data:`FINE_TURNS_DEG` whose drawings match the frames best, and between two
        steps where a parabola through the least sum of residuals and its neighbours puts it;
        as it is where every turn matches them alike."""
        records = touches_of_grasps(self.train, name, TURN_GRASPS)
        if not records:
            return model_to_world
        centre_world_m = transform_points(model_cloud(self.scene, name).mean(axis=0)[None], model_to_world)[0]
        turns_rad = np.radians(FINE_TURNS_DEG)
        poses = [turned_about_vertical(model_to_world, centre_world_m, turn) for turn in turns_rad]
        totals = self._totals(name, poses, records)
        if not np.ptp(totals) > 0:
            return model_to_world  # every turn alike: the frames tell nothing (argmin would take -2 deg)
        best = int(np.argmin(totals))
        if 0 < best < len(totals) - 1:
            before, least, after = totals[best - 1 : best + 2]
            curvature = before - 2 * least + after
            step = (before - after) / (2 * curvature) if curvature > 0 else 0.0
            return turned_about_vertical(
                model_to_world, centre_world_m, turns_rad[best] + step * (turns_rad[1] - turns_rad[0])
            )
        return poses[best]

    def _totals(self, name: str, poses: list[np.ndarray], records: list[SampleRecord]) -> np.ndarray:
        """Per pose of object ``name``, the sum of ``records``' residuals with their maps cut there."""
        found = self.residuals(
            [r for pose in poses for r in records_cut_at(records, {name: pose}, self.scene, self.params)]
        )
        return found.reshape(len(poses), len(records)).sum(axis=1)


def turned_about_vertical(model_to_world: np.ndarray, centre_world_m: np.ndarray, turn_rad: float) -> np.ndarray:
    """``model_to_world`` turned by ``turn_rad`` about the vertical through ``centre_world_m``."""
    turn = planar_transform(turn_rad, 0.0, 0.0)
    turn[:3, 3] = centre_world_m - turn[:3, :3] @ centre_world_m
    turn[2, 3] = 0.0
    return turn @ model_to_world
