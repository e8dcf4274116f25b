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
# Densest grid asked for: 10 um voxels, a tenth of the 0.1 mm model cloud's spacing (a finer grid
# thins nothing). Open3D indexes voxels with 32-bit integers, so a cloud may span at most
# 2**31 - 1 voxels along an axis (21 km at this density).
MAX_POINTS_PER_CM3 = 1e9
MAX_VOXELS_PER_AXIS = 2**31 - 1


def voxel_size_for_density(points_per_cm3: float) -> float:
    """Voxel edge in metres that leaves at most ``points_per_cm3`` points per cm³: a real number
    in (0, MAX_POINTS_PER_CM3]; otherwise PerceptionError naming the density."""
    real = isinstance(points_per_cm3, (int, float, np.integer, np.floating)) and not isinstance(
        points_per_cm3, (bool, np.bool_)
    )
    if not (real and 0 < points_per_cm3 <= MAX_POINTS_PER_CM3):
        raise PerceptionError(
            f"density must be a number of points/cm³ in (0, {MAX_POINTS_PER_CM3:g}], got {points_per_cm3!r}"
        )
    density = float(points_per_cm3)
    return 0.01 * density ** (-1.0 / 3.0)


def downsample_to_density(points_m: np.ndarray, points_per_cm3: float) -> np.ndarray:
    """Voxel-grid the (N, 3) cloud (metres) to the requested density; returns (M, 3) float64,
    M <= N (no point: none). ``points_m`` finite, of a real dtype, spanning at most
    MAX_VOXELS_PER_AXIS voxels along each axis; the density as :func:`voxel_size_for_density`.
    Otherwise PerceptionError naming the argument, before Open3D is called."""
    raw = np.asarray(points_m)
    if raw.ndim != 2 or raw.shape[1] != 3 or raw.dtype.kind not in "biuf":
        raise PerceptionError(f"points must be (N, 3) real numbers, got {raw.shape} {raw.dtype}")
    points = raw.astype(np.float64)
    if not np.all(np.isfinite(points)):
        raise PerceptionError("points contain NaN or inf")
    voxel = voxel_size_for_density(points_per_cm3)
    # Half-extents, so that a cloud spanning float64's whole range does not overflow.
    half_extent = float(np.max(0.5 * points.max(axis=0) - 0.5 * points.min(axis=0))) if len(points) else 0.0
    if half_extent >= 0.5 * voxel * MAX_VOXELS_PER_AXIS:
        raise PerceptionError(
            f"points span {2 * half_extent:.3g} m, more than {MAX_VOXELS_PER_AXIS} voxels of {voxel:.3g} m "
            f"({points_per_cm3!r} points/cm³)"
        )
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.voxel_down_sample(voxel).points, dtype=np.float64)
