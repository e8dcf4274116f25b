"""Object segmentation in the cameras' world clouds (paper §III-B.1).

Steps: crop to the workspace box; per camera, fit the table plane with RANSAC and level the
cloud onto the table; keep what stands clearly above it, and the raised patches of a thin object
lying on it (see :func:`above_table`); merge; thin with a voxel grid (so
clustering costs the same whatever the camera resolution); cluster (DBSCAN: Euclidean
clustering with a density floor); keep the cluster nearest to a hint point (default: the
largest) and return its points at full resolution. ``point_counts`` holds the count after each
step ("voxel" and "clustered" count grid points, "object" full-resolution points).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception.errors import SegmentationError
from perception.pointcloud import principal_spread_m, seeded_open3d
from workcell.scene import Scene


@dataclasses.dataclass(frozen=True)
class SegmentationParams:
    """Workspace box in world (metres) and the thresholds of each step."""

    workspace_min_m: tuple[float, float, float] = (-0.4, -0.4, -0.05)
    workspace_max_m: tuple[float, float, float] = (0.4, 0.4, 0.5)
    # Clustering runs on a voxel grid of this size (DBSCAN's cost grows with the neighbours
    # within eps); the object is then returned at the cameras' full resolution.
    voxel_size_m: float = 0.005
    plane_distance_m: float = 0.006
    plane_iterations: int = 200
    plane_sample_points: int = 5000
    # A thin object (a flat tool a few mm thick) rises less above the table than the depth noise
    # spreads the table's own points. Averaged over a grid cell the noise shrinks by sqrt(n):
    # a cell of the table band is raised when its mean height exceeds this many standard errors.
    raised_cell_sigmas: float = 4.0
    # The table's normal is world z; a plane tilted more than this is an object face, not the table.
    max_table_tilt_rad: float = np.deg2rad(10.0)
    cluster_eps_m: float = 0.015
    cluster_min_points: int = 10
    min_object_points: int = 30
    level_to_table: bool = True


@dataclasses.dataclass
class SegmentationResult:
    points_world_m: np.ndarray  # (N, 3) float64, the object cluster (levelled onto z = 0 table)
    centroid_world_m: np.ndarray  # (3,)
    table_planes: list[np.ndarray]  # per camera (4,): a x + b y + c z + d = 0, unit normal, c > 0
    point_counts: dict[str, int]  # after each step, in order


def crop_to_workspace(points_world_m: np.ndarray, params: SegmentationParams) -> np.ndarray:
    """Points inside the workspace box; NaN and inf fail the comparisons and go too."""
    points_world_m = np.asarray(points_world_m, dtype=np.float64)
    if points_world_m.ndim != 2 or points_world_m.shape[1] != 3:
        raise SegmentationError(f"points must be (N, 3), got {points_world_m.shape}")
    low, high = params.workspace_min_m, params.workspace_max_m
    inside = np.ones(len(points_world_m), dtype=bool)
    for axis in range(3):  # per column: 3x faster than np.all over an (N, 3) mask
        column = points_world_m[:, axis]
        inside &= (column >= low[axis]) & (column <= high[axis])
    return points_world_m[inside]


def fit_table_plane(
    points_world_m: np.ndarray, params: SegmentationParams, seed: int = 0, camera_index: int = 0
) -> np.ndarray:
    """RANSAC table plane (a, b, c, d), unit normal pointing up (c > 0), of a cropped cloud.

    ``points_world_m``: finite (N, 3) metres, N >= 3, not all on one line (identical or
    collinear points fix no plane); otherwise SegmentationError says which. The plane returned
    is always finite with a unit normal."""
    points_world_m = np.asarray(points_world_m, dtype=np.float64)
    if points_world_m.ndim != 2 or points_world_m.shape[1] != 3 or not np.all(np.isfinite(points_world_m)):
        raise SegmentationError(f"points must be finite (N, 3), got shape {points_world_m.shape}")
    if len(points_world_m) < 3:
        raise SegmentationError(
            f"only {len(points_world_m)} points inside the workspace "
            f"{params.workspace_min_m}..{params.workspace_max_m} m"
        )
    # Three plane parameters are well fixed by a few thousand points; running RANSAC on all
    # ~10^5 table points would only cost time. The caller applies the plane to every point.
    rng = np.random.default_rng([abs(int(seed)), camera_index])
    sample = (
        points_world_m
        if len(points_world_m) <= params.plane_sample_points
        else points_world_m[rng.choice(len(points_world_m), params.plane_sample_points, replace=False)]
    )
    # Spread of the sample across its second principal direction: zero for identical or
    # collinear points, where RANSAC's three-point planes have no normal.
    spread_m = principal_spread_m(sample)
    if not spread_m[1] > 1e-9 * max(1.0, float(np.abs(sample).max())):
        raise SegmentationError(
            f"the {len(points_world_m)} workspace points are identical or collinear "
            f"(spread {spread_m[::-1]} m): no table plane"
        )
    with seeded_open3d(seed):
        plane, _ = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample)).segment_plane(
            params.plane_distance_m, 3, params.plane_iterations
        )
    plane = np.asarray(plane, dtype=np.float64)
    if not (np.all(np.isfinite(plane)) and np.linalg.norm(plane[:3]) > 0):
        raise SegmentationError(f"RANSAC found no plane in the {len(points_world_m)} workspace points")
    plane /= np.linalg.norm(plane[:3])
    if plane[2] < 0:
        plane = -plane
    tilt = np.arccos(np.clip(plane[2], -1.0, 1.0))
    if tilt > params.max_table_tilt_rad:
        raise SegmentationError(
            f"largest plane is tilted {np.rad2deg(tilt):.1f} deg from horizontal; no table in the workspace"
        )
    return plane


def plane_to_table(plane: np.ndarray) -> np.ndarray:
    """4x4 rigid transform taking the fitted plane onto the table top z = 0 (smallest rotation)."""
    normal, offset = plane[:3], plane[3]
    transform = np.eye(4)
    axis = np.cross(normal, [0.0, 0.0, 1.0])
    if np.linalg.norm(axis) > 0:
        angle = np.arctan2(np.linalg.norm(axis), normal[2])
        transform[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    transform[2, 3] = offset
    return transform


def above_table(points_xy_m: np.ndarray, height_m: np.ndarray, params: SegmentationParams) -> np.ndarray:
    """Mask of the points on an object: those higher than ``plane_distance_m`` above the table,
    and those of a thin object that does not rise that far.

    ``plane_distance_m`` must clear the table's noise (a Kinect's 1.4 mm σ reaches 6 mm), so a
    4 mm plate would vanish entirely under it. In the band below it the points are binned on a
    grid of ``voxel_size_m`` cells: a cell whose mean height exceeds ``raised_cell_sigmas``
    standard errors of the table noise (σ / sqrt(points in the cell), σ measured on this
    camera's band) is raised, and its points higher than σ are kept. Only band points enter the
    mean, so the table points next to a tall object do not ride on its height.
    """
    certain = height_m > params.plane_distance_m
    band = np.abs(height_m) <= params.plane_distance_m
    band_height = height_m[band]
    # Robust σ (median absolute deviation) of the band; a few thousand points fix it well.
    sample = band_height[:: max(1, len(band_height) // params.plane_sample_points)]
    sigma_m = 1.4826 * float(np.median(np.abs(sample - np.median(sample)))) if len(sample) else 0.0
    cell = np.floor(points_xy_m[band] / params.voxel_size_m).astype(np.int64)
    cell -= cell.min(axis=0)
    cell_index = cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1]
    counts = np.bincount(cell_index)
    mean_m = np.bincount(cell_index, weights=band_height) / np.maximum(counts, 1)
    raised = mean_m > params.raised_cell_sigmas * sigma_m / np.sqrt(np.maximum(counts, 1))
    kept = certain.copy()
    kept[band] = raised[cell_index] & (band_height > sigma_m)
    return kept


def segment_object(
    clouds_world_m: Sequence[np.ndarray],
    params: SegmentationParams = SegmentationParams(),
    hint_world_m: np.ndarray | None = None,
    seed: int = 0,
) -> SegmentationResult:
    """Cluster of object points from the cameras' world clouds, with point counts per step.

    Pass one (N, 3) cloud per camera (a single array is taken as one camera): the table plane is fitted per camera because each camera's
    extrinsic error tilts and lifts its table differently (a few mm over the workspace), so
    one plane for the merged cloud would leave a band of table points behind as false objects.
    With ``level_to_table`` each camera's cloud is then moved so its table lies on z = 0, the
    world's definition, which removes the height and tilt part of the calibration error.
    ``hint_world_m`` picks the cluster whose centroid is nearest to it in x, y; without it the
    largest cluster wins. ``seed`` makes the plane RANSAC repeatable.
    """
    if isinstance(clouds_world_m, np.ndarray) and clouds_world_m.ndim == 2:
        clouds_world_m = [clouds_world_m]  # one merged cloud: a single table plane for all of it
    if len(clouds_world_m) == 0:
        raise SegmentationError("no point clouds given")
    counts = dict.fromkeys(("input", "workspace", "above_table"), 0)
    above_parts, planes = [], []
    for index, cloud_world in enumerate(clouds_world_m):
        above, plane = _above_own_table(cloud_world, params, seed, index, counts)
        above_parts.append(above)
        planes.append(plane)

    above_full = np.concatenate(above_parts)
    above_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(above_full))
    above_cloud = above_cloud.voxel_down_sample(params.voxel_size_m)
    grid_points = np.asarray(above_cloud.points)
    counts["voxel"] = len(grid_points)
    if len(grid_points) < params.min_object_points:
        raise SegmentationError(f"only {len(grid_points)} points above the table plane")

    labels = np.asarray(above_cloud.cluster_dbscan(params.cluster_eps_m, params.cluster_min_points))
    counts["clustered"] = int(np.count_nonzero(labels >= 0))
    chosen = _chosen_cluster(grid_points, labels, hint_world_m)
    # Back to full resolution: every above-table point within one voxel of a cluster point.
    distance, _ = cKDTree(grid_points[labels == chosen]).query(above_full, distance_upper_bound=params.voxel_size_m)
    obj = above_full[np.isfinite(distance)]
    counts["object"] = len(obj)
    if len(obj) < params.min_object_points:
        raise SegmentationError(f"object cluster has {len(obj)} points, fewer than {params.min_object_points}")
    return SegmentationResult(
        points_world_m=obj, centroid_world_m=obj.mean(axis=0), table_planes=planes, point_counts=counts
    )


def _above_own_table(
    cloud_world_m: np.ndarray, params: SegmentationParams, seed: int, camera_index: int, counts: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """One camera's points on objects above its own table plane (levelled onto z = 0 with
    ``level_to_table``) and that plane; adds the camera's points to the "input", "workspace"
    and "above_table" ``counts``."""
    counts["input"] += int(np.asarray(cloud_world_m).shape[0])
    points = crop_to_workspace(cloud_world_m, params)
    counts["workspace"] += len(points)
    plane = fit_table_plane(points, params, seed=seed, camera_index=camera_index)
    height_m = points @ plane[:3] + plane[3]
    above = points[above_table(points[:, :2], height_m, params)]
    if params.level_to_table:
        levelling = plane_to_table(plane)
        above = above @ levelling[:3, :3].T + levelling[:3, 3]
    counts["above_table"] += len(above)
    return above, plane


def _chosen_cluster(grid_points: np.ndarray, labels: np.ndarray, hint_world_m: np.ndarray | None) -> int:
    """Label of the cluster whose x, y centroid is nearest to ``hint_world_m``, or of the
    largest cluster without a hint; DBSCAN's noise (label -1) is no cluster."""
    cluster_ids = np.unique(labels[labels >= 0])
    if len(cluster_ids) == 0:
        raise SegmentationError("no cluster above the table")
    if hint_world_m is None:
        sizes = np.array([np.count_nonzero(labels == c) for c in cluster_ids])
        return cluster_ids[np.argmax(sizes)]
    hint = np.asarray(hint_world_m, dtype=np.float64)[:2]
    centroids = np.array([grid_points[labels == c, :2].mean(axis=0) for c in cluster_ids])
    return cluster_ids[np.argmin(np.linalg.norm(centroids - hint, axis=1))]


# The table plane must be inside the crop even when a camera's calibration error lowers it.
_TABLE_MARGIN_M = 0.05


def segmentation_params_for(scene: Scene) -> SegmentationParams:
    """Segmentation bounds for a workcell: its workspace, reaching 5 cm below the table top."""
    low = np.asarray(scene.workspace_min_m, dtype=np.float64) - [0.0, 0.0, _TABLE_MARGIN_M]
    return SegmentationParams(workspace_min_m=tuple(low), workspace_max_m=tuple(scene.workspace_max_m))
