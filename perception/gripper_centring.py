"""Where a parallel gripper leaves a free-standing object: centred between its gels.

A registration gives the object's pose before the grasp; the fingers close symmetrically about
the TCP and push the object until both gels hold it. The patch extractor and ``dtx dataset
redepth`` move the registered pose there before cutting the gels' depth-maps
(perception.depthmap)."""

from __future__ import annotations

import numpy as np

from perception.depthmap import points_for_kernel
from perception.pointcloud import check_transform
from workcell.kinematics import GripperGeometry


def centre_between_gels(
    points_model_m: np.ndarray,
    model_to_world: np.ndarray,
    gel_left_to_world: np.ndarray,
    gel_right_to_world: np.ndarray,
    geometry: GripperGeometry = GripperGeometry(),
) -> np.ndarray:
    """``model_to_world`` moved along the closing axis so the model sits centred between the gels.

    A parallel gripper that closes on a free-standing object pushes it until both gels hold it,
    so after a grasp the object is no longer where it was registered: it is centred between the
    fingers, which close symmetrically about the TCP. The registration cannot know that; the
    gripper width can. The shift equalises the two gels' nearest model surface (the minimum gel
    y of the model points over each gel's whole face) and moves nothing across the gels. When
    either gel has no model point in front of its face, the pose is returned unchanged.
    """
    points = points_for_kernel(points_model_m).astype(np.float64, copy=False)
    nearest = []
    for gel_to_world in (gel_left_to_world, gel_right_to_world):
        model_to_gel = np.linalg.inv(check_transform(gel_to_world, "gel_to_world")) @ check_transform(
            model_to_world, "model_to_world"
        )
        # The face is a small part of the model: y only for the points in front of it.
        x = points @ model_to_gel[0, :3] + model_to_gel[0, 3]
        z = points @ model_to_gel[2, :3] + model_to_gel[2, 3]
        on_face = np.flatnonzero(
            (np.abs(x) <= 0.5 * geometry.gel_size_m[0]) & (np.abs(z) <= 0.5 * geometry.gel_size_m[1])
        )
        if on_face.size == 0:
            return np.asarray(model_to_world, dtype=np.float64).copy()
        y = np.take(points, on_face, axis=0) @ model_to_gel[1, :3] + model_to_gel[1, 3]
        nearest.append(float(y.min()))
    # Moving the model by s along the left gel's +y (toward the right gel) adds s to the left
    # gel's gap and takes s from the right one's.
    shift_m = 0.5 * (nearest[1] - nearest[0])
    moved = np.asarray(model_to_world, dtype=np.float64).copy()
    moved[:3, 3] += shift_m * np.asarray(gel_left_to_world, dtype=np.float64)[:3, 1]
    return moved
