"""Where a parallel gripper leaves a free-standing object: between its gels, each pressed as its
own contact needs to carry the grasp force.

A registration gives the object's pose before the grasp; the fingers close symmetrically about
the TCP and push the object until both gels hold it, and then squeeze it with the grasp force.
Both gels carry that force (the object is at rest), but a gel on a narrow edge sinks deeper for
it than one on a broad face (workcell.compliance): the object sits where each gel's press is its
own. The patch extractor and ``dtx dataset redepth`` move the registered pose there before
cutting the gels' depth-maps (perception.depthmap).

Placing the object so that both gels reach equally far into it (the rule before, the same as a
grasp force of 0 here) put each gel 0.06-0.12 mm off at the median on the demo session, 0.3-0.4
at p90, where the bottle's and the box's edges press 2 mm against a face's 0.2
(docs/measurements.md, issue 50)."""

from __future__ import annotations

import numpy as np

from perception.binning import min_y_per_bin
from perception.depthmap import points_for_kernel
from perception.errors import DepthMapError
from perception.pointcloud import check_transform
from workcell.compliance import contact_grid_shape, indentation_for_force_mm
from workcell.kinematics import GripperGeometry


def centre_between_gels(
    points_model_m: np.ndarray,
    model_to_world: np.ndarray,
    gel_left_to_world: np.ndarray,
    gel_right_to_world: np.ndarray,
    geometry: GripperGeometry,
    grasp_force_n: float,
    stiffness_n_per_mm3: float,
) -> np.ndarray:
    """``model_to_world`` moved along the closing axis to where the grasp holds the model.

    The gripper width fixes the sum of the two gels' presses; the grasp force splits it. Each
    gel's gaps (the least gel y of the model points over each cell of its face's contact grid,
    workcell.compliance.contact_grid_shape: a few of the model cloud's 0.1 mm samples a cell)
    give its first touch and the press that carries ``grasp_force_n`` on a gel of
    ``stiffness_n_per_mm3`` (workcell.compliance; at most the elastomer's thickness), and the
    model moves so that the two presses differ by as much. Nothing moves across the gels. When
    either gel has no model point in front of its face, the pose is returned unchanged.
    DepthMapError for a force or stiffness that is not a finite number >= 0 (> 0)."""
    if not (np.isfinite(grasp_force_n) and grasp_force_n >= 0):
        raise DepthMapError(f"grasp_force_n must be a finite number of newtons >= 0, got {grasp_force_n!r}")
    if not (np.isfinite(stiffness_n_per_mm3) and stiffness_n_per_mm3 > 0):
        raise DepthMapError(f"stiffness_n_per_mm3 must be a finite positive number, got {stiffness_n_per_mm3!r}")
    points = points_for_kernel(points_model_m).astype(np.float64, copy=False)
    model_pose = check_transform(model_to_world, "model_to_world")
    shape, cell_area_mm2 = contact_grid_shape(geometry.gel_size_m)
    # Each gel's first-touch gap plus its press (mm): the shift makes the two equal, as it made
    # the two first touches equal before (the presses' difference is split between the gels).
    touch_and_press_mm = []
    for gel_to_world in (gel_left_to_world, gel_right_to_world):
        model_to_gel = np.linalg.inv(check_transform(gel_to_world, "gel_to_world")) @ model_pose
        gaps_mm = _face_gaps_mm(points, model_to_gel, geometry, shape)
        if gaps_mm is None:
            return model_pose.copy()
        touch_mm = float(gaps_mm.min())
        press_mm, _, _ = indentation_for_force_mm(
            gaps_mm - touch_mm, cell_area_mm2, grasp_force_n, stiffness_n_per_mm3, geometry.elastomer_thickness_m * 1e3
        )
        touch_and_press_mm.append(touch_mm + press_mm)
    # Moving the model by s along the left gel's +y (toward the right gel) adds s to the left
    # gel's gaps and takes s from the right one's.
    shift_m = 0.5 * (touch_and_press_mm[1] - touch_and_press_mm[0]) * 1e-3
    moved = model_pose.copy()
    moved[:3, 3] += shift_m * np.asarray(gel_left_to_world, dtype=np.float64)[:3, 1]
    return moved


def _face_gaps_mm(
    points: np.ndarray, model_to_gel: np.ndarray, geometry: GripperGeometry, shape: tuple[int, int]
) -> np.ndarray | None:
    """The least gel y (mm) of the model ``points`` in front of each cell of a (rows along gel
    z, cols along gel x) grid of the gel's face, +inf where a cell has none; None for none at all."""
    half_x, half_z = 0.5 * geometry.gel_size_m[0], 0.5 * geometry.gel_size_m[1]
    # The face is a small part of the model: y only for the points in front of it.
    x = points @ model_to_gel[0, :3] + model_to_gel[0, 3]
    z = points @ model_to_gel[2, :3] + model_to_gel[2, 3]
    on_face = np.flatnonzero((np.abs(x) <= half_x) & (np.abs(z) <= half_z))
    if on_face.size == 0:
        return None
    y = np.take(points, on_face, axis=0) @ model_to_gel[1, :3] + model_to_gel[1, 3]
    gaps_m, _ = min_y_per_bin(x[on_face], z[on_face], y, half_x, half_z, shape)
    return gaps_m * 1e3
