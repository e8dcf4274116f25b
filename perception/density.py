"""Point-density control for the density study (paper Table II: 1, 10, 20, 40, 80 points/cm³).

Like PCL's voxel-grid filter used in the paper, Open3D's voxel_down_sample replaces the points
of each occupied voxel by their centroid, so at most one point is left per voxel. A density of
D points per cm³ therefore means one point per voxel of volume 1/D cm³:

    voxel edge = (1 / D)^(1/3) cm,   e.g. 1 -> 10 mm, 10 -> 4.64 mm, 80 -> 2.32 mm.

This is an upper bound on the density in occupied space; a surface cloud finer than the voxel
edge reaches it, a coarser one keeps its own spacing.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from perception.errors import PerceptionError

PAPER_DENSITIES_PER_CM3 = (1.0, 10.0, 20.0, 40.0, 80.0)
# The paper's densities leave a 0.24 x 0.19 mm-bin depth-map almost empty (voxels of 2.3-10 mm):
# these show where its bins begin to fill (1 mm and 0.46 mm voxels), between them and the
# 0.1 mm model cloud the pipeline uses.
DENSER_PER_CM3 = (1000.0, 10000.0)


def voxel_size_for_density(points_per_cm3: float) -> float:
    """Voxel edge in metres that leaves at most ``points_per_cm3`` points per cm³."""
    density = float(points_per_cm3)
    if not (np.isfinite(density) and density > 0):
        raise PerceptionError(f"density must be a positive number of points/cm³, got {points_per_cm3!r}")
    return 0.01 * density ** (-1.0 / 3.0)


def downsample_to_density(points_m: np.ndarray, points_per_cm3: float) -> np.ndarray:
    """Voxel-grid the (N, 3) cloud (metres) to the requested density; returns (M, 3) float64."""
    points = np.asarray(points_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PerceptionError(f"points must be (N, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise PerceptionError("points contain NaN or inf")
    voxel = voxel_size_for_density(points_per_cm3)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.voxel_down_sample(voxel).points, dtype=np.float64)
