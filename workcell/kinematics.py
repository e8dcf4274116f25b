"""Grasp kinematics: UR tool poses for top-down grasps and the gel poses they imply.

Frames: ``world`` has the table top at z = 0, z up. The tool (``tcp``) frame of
a top-down grasp has its z axis pointing down at the table; the fingers close along tool y.
The gel frame ``gel_<finger>`` has its origin at the centre of the gel surface, its x-z plane
in that surface and +y along the outward normal, i.e. from the gel toward the other finger
(into the object): y > 0 is free space in front of the gel, y < 0 indents it.

Conventions chosen here (and relied on by the simulated world and the patch extractor):
- ``gripper_width_m`` is the distance between the two gel surfaces.
- the left gel sits at +width/2 along tool y, the right gel at -width/2;
- each gel's z axis is the tool z axis (along the finger, toward the fingertip) and its
  x axis completes a right-handed frame (x = y cross z).

UR poses are [x, y, z, rx, ry, rz]: position in metres and a rotation vector in radians.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation


class KinematicsError(ValueError):
    """A grasp, pose or transform that does not describe a rigid placement of the gripper."""


# How far R^T R of a transform's rotation block may be from the identity, per element: float64
# rounding of composed transforms stays ~1e-15; a matrix off by more was not built as a rotation.
ROTATION_TOLERANCE = 1e-6

# The constant contact force every grasp of a collection closes with (Algorithm 1), in N: a
# scene's gripper.grasp_force_n unless it says otherwise (workcell.parts.GripperSpec).
GRASP_FORCE_N = 10.0

# Tool z pointing down at the table: a half turn about world x (tool x = world x).
_TOOL_DOWN = Rotation.from_euler("x", np.pi)


@dataclasses.dataclass(frozen=True)
class GripperGeometry:
    """Where the gels sit relative to the TCP, and how big they are (metres)."""

    tcp_to_gel_centre_m: float = 0.16
    gel_size_m: tuple[float, float] = (0.0186, 0.0249)  # extent along gel x, gel z
    elastomer_thickness_m: float = 0.002
    max_width_m: float = 0.11
    # The part of the gel the tactile camera images (extent along gel x, gel z), centred on the
    # gel: what a depth-map must cover to line up with the tactile image. None: the whole gel.
    sensed_area_m: tuple[float, float] | None = None

    @property
    def sensed_extent_m(self) -> tuple[float, float]:
        return self.sensed_area_m if self.sensed_area_m is not None else self.gel_size_m


_IDENTITY_3 = np.eye(3)


def rigid_transform(a_to_b: np.ndarray, name: str = "transform") -> np.ndarray:
    """Return ``a_to_b`` as a float64 4x4 rigid transform, or raise KinematicsError.

    Rigid means: every entry finite, last row exactly [0, 0, 0, 1], and a proper rotation block
    (|R^T R - I| <= ROTATION_TOLERANCE per element, det R > 0). Any real dtype (bool, integer,
    float), any strides; complex, text and object arrays are refused, never cast."""
    try:
        raw = np.asarray(a_to_b)
    except (TypeError, ValueError) as err:
        raise KinematicsError(f"{name} must be a 4x4 array of numbers: {err}") from None
    if raw.dtype.kind not in "biuf":
        raise KinematicsError(f"{name} must be a 4x4 array of real numbers, got {raw.dtype}")
    matrix = raw.astype(np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise KinematicsError(f"{name} must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    # The entries are finite, so the tolerance is a plain bound (np.allclose says the same with
    # rtol=0, at twice the cost: every contact depth-map checks two transforms). Columns of norm
    # over 1 + tolerance fail it anyway; entries that large are refused before R^T R can overflow.
    if (
        np.abs(rotation).max() > 1.0 + ROTATION_TOLERANCE
        or np.abs(rotation.T @ rotation - _IDENTITY_3).max() > ROTATION_TOLERANCE
        or np.linalg.det(rotation) <= 0
    ):
        raise KinematicsError(f"{name} rotation block is not a proper rotation")
    if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
        raise KinematicsError(f"{name} last row must be [0, 0, 0, 1], got {matrix[3]}")
    return matrix


def grasp_to_tcp_pose(x_m: float, y_m: float, z_m: float, theta_z_rad: float) -> np.ndarray:
    """TCP pose (UR [x, y, z, rx, ry, rz], world) of a top-down grasp with yaw ``theta_z_rad``.

    The palm is parallel to the table (tool z = -world z); only the yaw about world z is free.
    All four arguments must be finite real numbers (metres, radians); otherwise KinematicsError
    names the argument, as a NaN or inf pose would reach the arm as a command.
    """
    for name, value in (("x_m", x_m), ("y_m", y_m), ("z_m", z_m), ("theta_z_rad", theta_z_rad)):
        try:
            finite = np.isfinite(float(value))
        except (TypeError, ValueError):
            finite = False
        if not finite:
            raise KinematicsError(f"grasp {name} must be a finite number, got {value!r}")
    rotation = Rotation.from_euler("z", float(theta_z_rad)) * _TOOL_DOWN
    return np.concatenate([[float(x_m), float(y_m), float(z_m)], rotation.as_rotvec()])


def pose_to_matrix(pose6: np.ndarray) -> np.ndarray:
    """UR pose [x, y, z, rx, ry, rz] -> 4x4 homogeneous transform (float64)."""
    pose = np.asarray(pose6, dtype=np.float64)
    if pose.shape != (6,) or not np.all(np.isfinite(pose)):
        raise KinematicsError(f"pose must be 6 finite numbers, got {pose6!r}")
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(pose[3:]).as_matrix()
    transform[:3, 3] = pose[:3]
    return transform


def matrix_to_pose(transform: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform -> UR pose [x, y, z, rx, ry, rz].

    The rotation block is projected onto the nearest rotation (scipy does this), so a matrix
    that drifted slightly from orthonormal still gives a valid rotation vector.
    """
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise KinematicsError(f"transform must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotvec = Rotation.from_matrix(matrix[:3, :3]).as_rotvec()
    return np.concatenate([matrix[:3, 3], rotvec])


def gel_poses_world(
    tcp_pose_world: np.ndarray, gripper_width_m: float, geometry: GripperGeometry = GripperGeometry()
) -> dict[str, np.ndarray]:
    """Gel-to-world transforms (4x4) of both fingers, keys ``"left"`` and ``"right"``.

    ``tcp_pose_world`` is a finite UR pose (6,) or a rigid 4x4 tcp-to-world transform
    (:func:`rigid_transform`: finite, last row [0, 0, 0, 1], proper rotation);
    ``gripper_width_m`` finite in [0, max_width_m]. Otherwise KinematicsError: the gel poses are
    always finite rigid transforms.
    """
    try:
        width = float(gripper_width_m)
    except (TypeError, ValueError):
        width = float("nan")
    if not (np.isfinite(width) and 0.0 <= width <= geometry.max_width_m):
        raise KinematicsError(f"gripper width {gripper_width_m!r} m outside [0, {geometry.max_width_m}] m")
    tcp_pose = np.asarray(tcp_pose_world, dtype=np.float64)
    if tcp_pose.shape == (4, 4):
        tcp_to_world = rigid_transform(tcp_pose, "tcp_pose_world").copy()
    else:
        tcp_to_world = pose_to_matrix(tcp_pose)
    # Re-orthonormalise so float rounding of an accumulated transform cannot skew the gel frames.
    tcp_to_world[:3, :3] = Rotation.from_matrix(tcp_to_world[:3, :3]).as_matrix()

    tool_x, tool_y, tool_z = np.eye(3)
    poses = {}
    for finger, side in (("left", 1.0), ("right", -1.0)):
        gel_y = -side * tool_y  # toward the other finger
        gel_z = tool_z
        gel_x = np.cross(gel_y, gel_z)
        gel_to_tcp = np.eye(4)
        gel_to_tcp[:3, :3] = np.column_stack([gel_x, gel_y, gel_z])
        gel_to_tcp[:3, 3] = side * 0.5 * width * tool_y + geometry.tcp_to_gel_centre_m * tool_z
        poses[finger] = tcp_to_world @ gel_to_tcp
    return poses


def across_the_gels_m(points_m: np.ndarray, theta_z_rad: float, geometry: GripperGeometry) -> np.ndarray:
    """Where the object's points that lie in the gels' band sit across the gripper (m along the
    closing axis, tool y, from the gels' midpoint) for a top-down grasp turned ``theta_z_rad``
    about world z. ``points_m``: N x 3, world axes, relative to the gels' centre; the band is
    the gel's length along the gel axis by its height about its centre: what the gels' faces
    sweep as the open fingers come down. The extent of the result is what the fingers close on;
    a point at or beyond half the open width lies under an open gel."""
    points = np.asarray(points_m, dtype=np.float64)
    gel_axis = np.array([np.cos(theta_z_rad), np.sin(theta_z_rad)])
    closing_axis = np.array([-np.sin(theta_z_rad), np.cos(theta_z_rad)])
    gel_length_m, gel_height_m = geometry.gel_size_m
    band = (np.abs(points[:, :2] @ gel_axis) <= gel_length_m / 2) & (np.abs(points[:, 2]) <= gel_height_m / 2)
    return points[band, :2] @ closing_axis
