"""Which way round a near-symmetric object stands, chosen by its touches. A box, a bottle or
a can turned half round about the vertical fits the depth cameras' points almost as well as the
right way round (the gelatin box's mesh turned half round lies 0.6 mm from itself), so the
registration may take either; the touches, which feel the object's edges, can tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np
from scipy.spatial import cKDTree

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.redepth import depth_map_params
from dataset.touches import records_cut_at, touches_of_grasps
from perception.planar_icp import is_upright, turned_about_centre
from perception.registration import PreparedModel, prepare_model, sample_model_cloud
from perception.segmentation import segment_object, segmentation_params_for
from perception.touch_calibration import TouchOffset, pose_error
from workcell.scene import Scene

# Turns (rad) about the vertical a resting object's registration is checked against: a box, a
# bottle or a can looks much alike to the cameras turned half round (a can at every turn).
CHECKED_TURNS_RAD = (0.5 * np.pi, np.pi, 1.5 * np.pi)
# A turned pose the cameras cannot tell from the registered one: its ICP fitness at most this
# much lower and its RMSE at most this much higher (m). On the demo session the bottle's,
# can's and box's half turns fit within 0.001 and 0.03 mm, their quarter turns (box, bottle) not.
TURN_FITNESS_MARGIN = 0.01
TURN_RMSE_MARGIN_M = 0.0002
# Grasps whose touches (both fingers) choose between such turns, and how much nearer their
# median offset must be at another turn to take it over the registered one. On the demo session
# the true turn's touches lie 0.15-0.64 mm from their prediction, the other turn's 0.93-1.79 mm.
TURN_GRASPS = 8
TURN_MARGIN = 0.8


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
    depth-maps as ``dtx dataset redepth`` would cut them against the frames (``measure``: a
    ``TouchRenderer.touches`` or a ``TouchPool.touches``). The pose whose touches lie nearest
    their prediction (median offset, a touch the renderer cannot place counting as farthest)
    wins; the registered one (first) unless another is nearer by :data:`TURN_MARGIN`."""

    def __init__(
        self,
        reader: DatasetReader,
        train: list[SampleRecord],
        measure: Callable[[list[SampleRecord]], list[TouchOffset | None]],
    ) -> None:
        self.train, self.measure = train, measure
        self.params, self.scene = depth_map_params(reader)

    def choose(self, name: str, poses: list[np.ndarray]) -> np.ndarray:
        records = touches_of_grasps(self.train, name, TURN_GRASPS)
        if len(poses) == 1 or not records:
            return poses[0]
        found = self.measure(
            [r for pose in poses for r in records_cut_at(records, {name: pose}, self.scene, self.params)]
        )
        distances = np.array([np.inf if t is None else np.linalg.norm(t.offset_gel_mm) for t in found])
        offsets = np.median(distances.reshape(len(poses), len(records)), axis=1)
        best = int(np.argmin(offsets))
        return poses[best] if offsets[best] < offsets[0] * TURN_MARGIN else poses[0]
