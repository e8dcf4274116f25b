"""The workcell's parts as a scene file describes them: the table, the objects on it (with
their surface micro-relief), the depth cameras, the gripper and its GelSight sensors.

Plain data: ``workcell.scene`` reads and checks them from a scene file.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from workcell.kinematics import GRASP_FORCE_N

RELIEF_KINDS = ("ridges", "knurling", "bumps")


@dataclasses.dataclass
class ReliefSpec:
    """Surface micro-relief of an object: a periodic outward displacement of the surface.

    ``ridges``: raised-cosine profile varying along ``axis`` (object frame);
    ``knurling``: two ridge sets crossed at +-``angle_deg`` about ``axis``;
    ``bumps``: spherical caps on a cubic lattice of spacing ``pitch_mm``.
    """

    kind: str
    pitch_mm: float
    depth_mm: float
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    angle_deg: float = 30.0


@dataclasses.dataclass
class ObjectSpec:
    name: str
    mesh: str | None  # path relative to the repository (or absolute)
    primitive: dict[str, Any] | None  # {"box": [sx, sy, sz]} | {"cylinder": [r, h]} | {"sphere": r}
    x_m: float
    y_m: float
    yaw_rad: float
    z_m: float | None  # None: rest on the table (lowest point at z = 0)
    relief: list[ReliefSpec]


@dataclasses.dataclass
class TableSpec:
    size_m: tuple[float, float] = (1.2, 0.8)
    center_m: tuple[float, float] = (0.0, 0.0)
    thickness_m: float = 0.03


@dataclasses.dataclass
class CameraSpec:
    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_to_world: np.ndarray  # nominal 4x4, OpenCV optical frame


@dataclasses.dataclass
class GripperSpec:
    tcp_to_gel_centre_m: float = 0.16
    max_width_m: float = 0.11
    gel_size_m: tuple[float, float] = (0.0186, 0.0249)  # along gel x, gel z
    elastomer_thickness_m: float = 0.002
    gel_youngs_modulus_mpa: float = 0.25
    # The constant force the gripper closes every grasp with (N): the collector commands it, and
    # the pipeline places the object between the gels by it (perception.gripper_centring).
    grasp_force_n: float = GRASP_FORCE_N

    @property
    def foundation_stiffness_n_per_mm3(self) -> float:
        """Winkler foundation stiffness of the gel layer: pressure (N/mm^2) per mm of local
        indentation = E / thickness, i.e. N/mm of indentation per mm^2 of contact area."""
        return self.gel_youngs_modulus_mpa / (self.elastomer_thickness_m * 1e3)


@dataclasses.dataclass
class GelSightSpec:
    image_height: int = 120
    image_width: int = 160
    mm_per_px: float = 0.1245
    # The renderer's photometric calibration (assets/gelsight, or `dtx calibrate gelsight --out`).
    calibration_dir: str = "assets/gelsight"
