"""Forward kinematics of Universal Robots arms from their published DH parameters.

Used to check, before a joint move is sent, that the TCP it ends at lies in the workspace.
The controller applies the TCP offset configured on the pendant; pass the same offset here.
"""

from __future__ import annotations

import numpy as np

from workcell.kinematics import matrix_to_pose, pose_to_matrix

# Standard (Denavit-Hartenberg) parameters from Universal Robots' published tables:
# link offsets d and lengths a in metres, twists alpha in radians.
DH_PARAMETERS: dict[str, dict[str, tuple[float, ...]]] = {
    "ur5e": {
        "d": (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
        "a": (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
        "alpha": (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0),
    },
    "ur5": {
        "d": (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823),
        "a": (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0),
        "alpha": (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0),
    },
}


def joint_frames(q_rad: np.ndarray, model: str = "ur5e") -> list[np.ndarray]:
    """Base-frame transforms of the base and of each of the six joint frames (flange last)."""
    dh = DH_PARAMETERS[model]
    frames = [np.eye(4)]
    for theta, d, a, alpha in zip(q_rad, dh["d"], dh["a"], dh["alpha"]):
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        link = np.array(
            [
                [ct, -st * ca, st * sa, a * ct],
                [st, ct * ca, -ct * sa, a * st],
                [0.0, sa, ca, d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        frames.append(frames[-1] @ link)
    return frames


def tcp_pose(q_rad: np.ndarray, model: str = "ur5e", tcp_offset: np.ndarray | None = None) -> np.ndarray:
    """TCP pose [x, y, z, rx, ry, rz] (m, rad) in the base frame for joint angles ``q_rad``.

    ``tcp_offset`` is the TCP pose in the flange frame (as set on the pendant); none means
    the flange centre.
    """
    flange = joint_frames(np.asarray(q_rad, dtype=np.float64), model)[-1]
    if tcp_offset is not None:
        flange = flange @ pose_to_matrix(np.asarray(tcp_offset, dtype=np.float64))
    return matrix_to_pose(flange)
