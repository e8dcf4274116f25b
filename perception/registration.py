"""Registration of an object's complete model cloud to its segmented partial view (paper §III-B.2).

An object resting on the table (``table_z_m`` set) is first searched for upright, as its mesh
frame stands, at a turn about the vertical (:func:`_register_resting`: 3 degrees of freedom,
a sweep of yaws refined by planar ICP). That is the only way to register a thin flat object,
whose view is a plane (FPFH histograms all alike, point-to-plane ICP free to slide); on the YCB
objects it is as accurate as the general search. An object lying otherwise normally fails the
fitness check there and goes on to the general search.

General: coarse RANSAC on FPFH feature correspondences; fine point-to-plane ICP. The observed
cluster is the *source* and the model the *target*: then ICP fitness is the fraction of
observed points that lie on the model, which is near 1 for a right pose whatever part of the
object the cameras see (with the model as source it would be the visible fraction instead).
A result is accepted only if fitness and inlier RMSE pass their thresholds and the posed model
rests on the table; otherwise RANSAC is retried with another seed, and after ``attempts`` a
RegistrationError says why each attempt was refused — never a silently wrong pose.

The model's FPFH features are computed once per object (:func:`prepare_model`). A pose is scored
against the truth by ``perception.pose_scores``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception.errors import RegistrationError
from perception.planar_icp import refine_best, sweep_subset, sweep_yaws, upright_refined
from perception.pointcloud import principal_spread_m, seeded_open3d

_reg = o3d.pipelines.registration
# Open3D's binding takes ``indices`` as optional (None, the default: a feature for every point)
# where its stub declares it required; the cast states the binding's real signature.
_FpfhFeature = Callable[[o3d.geometry.PointCloud, o3d.geometry.KDTreeSearchParam], o3d.pipelines.registration.Feature]
_compute_fpfh_feature = cast(_FpfhFeature, _reg.compute_fpfh_feature)
# Most points sample_model_cloud makes: a 0.1 mm cloud (MODEL_POINT_SPACING_M) of a 0.2 m² box.
MAX_MODEL_POINTS = 32_000_000


@dataclasses.dataclass(frozen=True)
class RegistrationParams:
    """The coarse voxel size drives the feature scales; distances are metres."""

    voxel_size_m: float = 0.008  # coarse stage: features and RANSAC
    icp_voxel_size_m: float = 0.004  # fine stage: ICP
    normal_radius_factor: float = 2.0  # x voxel size
    feature_radius_factor: float = 5.0  # x voxel size (FPFH support)
    feature_max_nn: int = 50  # FPFH cost grows linearly with it
    ransac_distance_factor: float = 1.5  # x voxel size
    ransac_max_iterations: int = 20_000
    ransac_confidence: float = 0.999
    icp_distances_m: tuple[float, ...] = (0.016, 0.008)  # ICP stages; fitness is judged at the last
    icp_max_iterations: int = 50
    min_fitness: float = 0.8
    max_rmse_m: float = 0.004
    attempts: int = 5
    # Objects rest on the table (world z = 0 after segmentation levels each camera to it);
    # None for an object that is held or stacked.
    table_z_m: float | None = 0.0
    table_tolerance_m: float = 0.01
    resting_yaw_steps: int = 24  # upright search: yaws tried, 15 deg apart
    resting_sweep_iterations: int = 10  # planar ICP steps per yaw on the coarse clouds
    resting_sweep_points: int = 256  # observed points the sweep pairs (a seeded random subset)
    resting_candidates: int = 3  # the best yaws of the sweep refined on the fine clouds


@dataclasses.dataclass
class ModelCloud:
    """Model points and outward normals in the model (mesh) frame, metres, and the height the
    model stands on: its mesh's lowest vertex (a resting object touches the table there; the
    lowest sampled point lies above it by up to a sample spacing, and a thinned cloud's lowest
    voxel mean by more: 0.3-0.6 mm on the YCB can and gelatin box at 4 mm voxels)."""

    points_m: np.ndarray  # (N, 3) float64
    normals: np.ndarray  # (N, 3) float64, unit
    lowest_z_m: float


@dataclasses.dataclass
class RegistrationResult:
    model_to_world: np.ndarray  # (4, 4) float64
    fitness: float  # fraction of observed points within the last ICP distance of the model
    inlier_rmse_m: float
    attempts: int  # RANSAC attempts used; 0 when the upright search gave the pose
    time_ms: dict[str, float]  # "coarse", "fine", "total"


def sample_model_cloud(mesh_path: str | Path, point_spacing_m: float = 0.002, seed: int = 0) -> ModelCloud:
    """Sample a model cloud over a mesh surface, one point per ``point_spacing_m``² of area on
    average, with the triangles' outward normals.

    Uniform random sampling, not Poisson disk: it is ~100x faster (1.5 M points in ~1 s, where
    Poisson disk takes ~30 s for 250 k), and every user thins or bins the cloud anyway. For
    registration the default 2 mm is plenty; a contact depth-map needs points finer than its
    bins (0.23 x 0.29 mm at 100 x 100), e.g. 0.2 mm.

    At most MAX_MODEL_POINTS points (~1.5 GB with normals): a spacing that would ask for more
    on this mesh raises RegistrationError before anything is allocated, as does a spacing that
    is not a finite positive number.
    """
    try:
        spacing = float(point_spacing_m)
    except (TypeError, ValueError):
        spacing = float("nan")
    if not (np.isfinite(spacing) and spacing > 0):
        raise RegistrationError(f"point spacing must be a positive number of metres, got {point_spacing_m!r}")
    mesh = o3d.io.read_triangle_mesh(Path(mesh_path))
    if len(mesh.triangles) == 0:
        raise RegistrationError(f"mesh {mesh_path} has no triangles (missing or unreadable file?)")
    area_m2 = float(mesh.get_surface_area())
    if not (np.isfinite(area_m2) and area_m2 > 0):
        raise RegistrationError(f"mesh {mesh_path} has surface area {area_m2} m², not a positive number")
    # Divided twice, not by spacing², which underflows to 0 below ~1e-162 m.
    wanted = area_m2 / spacing / spacing
    if not wanted <= MAX_MODEL_POINTS:
        raise RegistrationError(
            f"point spacing {point_spacing_m!r} m asks for {wanted:.3g} points on the "
            f"{area_m2:.3g} m² of {mesh_path}, more than {MAX_MODEL_POINTS}"
        )
    count = max(int(wanted), 100)
    with seeded_open3d(seed):
        cloud = mesh.sample_points_uniformly(count, use_triangle_normal=True)
    return ModelCloud(
        points_m=np.asarray(cloud.points, dtype=np.float64),
        normals=np.asarray(cloud.normals, dtype=np.float64),
        lowest_z_m=float(np.asarray(mesh.vertices)[:, 2].min()),
    )


def _to_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return cloud


def _features(cloud: o3d.geometry.PointCloud, params: RegistrationParams) -> o3d.pipelines.registration.Feature:
    radius = params.voxel_size_m * params.feature_radius_factor
    return _compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=params.feature_max_nn)
    )


def _check_cloud(points: np.ndarray, name: str, minimum: int) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise RegistrationError(f"{name} must be (N, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise RegistrationError(f"{name} contains NaN or inf")
    if len(points) < minimum:
        raise RegistrationError(f"{name} has {len(points)} points, at least {minimum} needed")
    return points


def _check_not_degenerate(points: np.ndarray, voxel_size_m: float, name: str, rejections: list[str]) -> None:
    """Refuse a line or a plane for the general search, after the ``rejections`` already met.

    A line or a plane leaves rotations about it unobservable: FPFH histograms are all alike and
    ICP's normal equations are singular, so any pose it returned would be arbitrary. (A plane
    lying on the table is still observable upright, by :func:`_register_resting`.)
    """
    spread = principal_spread_m(points)
    shape = "linear" if spread[1] < voxel_size_m else "planar" if spread[0] < 0.25 * voxel_size_m else ""
    if shape:
        raise RegistrationError(
            "; ".join([*rejections, f"{name} is nearly {shape} (spread {spread[::-1]} m); pose not observable"])
        )


@dataclasses.dataclass
class PreparedModel:
    """A model thinned for both stages: a coarse cloud with FPFH features for RANSAC and a
    finer cloud with the mesh normals for point-to-plane ICP.

    Built once per object (Algorithm 1 registers every object against the same model), so a
    registration pays only for the observed side.
    """

    coarse: o3d.geometry.PointCloud
    features: o3d.pipelines.registration.Feature
    fine: o3d.geometry.PointCloud
    lowest_z_m: float  # ModelCloud.lowest_z_m
    params: RegistrationParams


def _thin(points: np.ndarray, normals: np.ndarray | None, voxel_m: float, name: str) -> o3d.geometry.PointCloud:
    cloud = _to_cloud(points, normals).voxel_down_sample(voxel_m)
    if len(cloud.points) < 10:
        raise RegistrationError(f"{name} thins to {len(cloud.points)} points at {voxel_m} m voxels, 10 needed")
    return cloud


def prepare_model(model: ModelCloud, params: RegistrationParams = RegistrationParams()) -> PreparedModel:
    points = _check_cloud(model.points_m, "model cloud", 10)
    normals = np.asarray(model.normals, dtype=np.float64)
    if normals.shape != points.shape or not np.all(np.isfinite(normals)):
        raise RegistrationError(f"model normals must be finite and shaped like the points {points.shape}")
    lowest_z_m = float(model.lowest_z_m)
    if not (np.isfinite(lowest_z_m) and lowest_z_m <= points[:, 2].min() + 1e-9):
        raise RegistrationError(
            f"model's lowest z {model.lowest_z_m!r} m must be a finite height at or below its lowest point "
            f"({points[:, 2].min():.6f} m)"
        )
    coarse = _thin(points, normals, params.voxel_size_m, "model cloud")
    return PreparedModel(
        coarse=coarse,
        features=_features(coarse, params),
        fine=_thin(points, normals, params.icp_voxel_size_m, "model cloud"),
        lowest_z_m=lowest_z_m,
        params=params,
    )


def _check_registration_params(model: PreparedModel, params: RegistrationParams) -> None:
    """Refuse ``params`` that disagree with those ``model`` was prepared with, or that leave ICP
    or the upright search nothing to do."""
    shared = ("voxel_size_m", "icp_voxel_size_m", "normal_radius_factor", "feature_radius_factor", "feature_max_nn")
    if any(getattr(model.params, name) != getattr(params, name) for name in shared):
        raise RegistrationError(
            f"model was prepared with other {', '.join(shared)} than asked for; prepare it again with these parameters"
        )
    if len(params.icp_distances_m) == 0 or min(params.icp_distances_m) <= 0:
        raise RegistrationError(f"ICP needs at least one positive distance, got {params.icp_distances_m}")
    if (
        min(params.resting_yaw_steps, params.resting_candidates, params.resting_sweep_iterations) < 1
        or params.resting_sweep_points < 3
    ):
        raise RegistrationError(
            "the upright search needs at least 1 yaw step, candidate and sweep iteration and "
            f"3 sweep points, got {params.resting_yaw_steps}, {params.resting_candidates}, "
            f"{params.resting_sweep_iterations} and {params.resting_sweep_points}"
        )


@dataclasses.dataclass
class _StageClock:
    """Seconds one registration has spent in its coarse and fine stages, over every search it tried."""

    started: float
    coarse_s: float = 0.0
    fine_s: float = 0.0

    def result(self, model_to_world: np.ndarray, fitness: float, rmse_m: float, attempt: int) -> RegistrationResult:
        """The accepted pose of RANSAC attempt ``attempt`` (0: the upright search's), with the
        stage times so far and the total until now."""
        return RegistrationResult(
            model_to_world=model_to_world,
            fitness=fitness,
            inlier_rmse_m=rmse_m,
            attempts=attempt,
            time_ms={
                "coarse": self.coarse_s * 1e3,
                "fine": self.fine_s * 1e3,
                "total": (time.perf_counter() - self.started) * 1e3,
            },
        )


def register_model(
    model: PreparedModel, observed_world_m: np.ndarray, params: RegistrationParams | None = None, seed: int = 0
) -> RegistrationResult:
    """Pose of the model in world (4x4 model_to_world) that lays it onto the observed cluster.

    ``params`` default to those ``model`` was prepared with; the voxel sizes and feature
    settings must match them.
    """
    params = model.params if params is None else params
    _check_registration_params(model, params)
    observed = _check_cloud(observed_world_m, "observed cluster", 10)
    clock = _StageClock(started=time.perf_counter())
    # Registration runs about the observed centroid: a scene far from the origin would otherwise
    # lose precision in Open3D's float products and in the RANSAC pose estimate.
    offset = observed.mean(axis=0)
    source = _thin(observed - offset, None, params.voxel_size_m, "observed cluster")
    source_fine = _thin(observed - offset, None, params.icp_voxel_size_m, "observed cluster")
    rejections: list[str] = []
    if params.table_z_m is not None:
        model_fine_points = np.asarray(model.fine.points)
        model_to_world, fitness, rmse_m, clock.coarse_s, clock.fine_s = _register_resting(
            model_fine_points,
            np.asarray(model.fine.normals),
            np.asarray(model.coarse.points),
            np.asarray(source.points),
            np.asarray(source_fine.points),
            params.table_z_m - offset[2] - model.lowest_z_m,
            params,
            seed,
        )
        model_to_world[:3, 3] += offset
        problem = _quality_problem(fitness, rmse_m, model_to_world, model_fine_points, params)
        if not problem:
            return clock.result(model_to_world, fitness, rmse_m, 0)
        rejections.append(f"upright: {problem}")
    return _register_general(model, source, source_fine, offset, params, seed, clock, rejections)


def _register_general(
    model: PreparedModel,
    source: o3d.geometry.PointCloud,
    source_fine: o3d.geometry.PointCloud,
    offset: np.ndarray,
    params: RegistrationParams,
    seed: int,
    clock: _StageClock,
    rejections: list[str],
) -> RegistrationResult:
    """The general search on the observed clouds (centred on ``offset``): RANSAC, then ICP,
    retried with another seed until a pose passes :func:`_quality_problem`; after ``attempts``
    a RegistrationError lists ``rejections`` and why each attempt was refused."""
    _check_not_degenerate(np.asarray(source.points), params.voxel_size_m, "observed cluster", rejections)
    source_features = _observed_features(source, source_fine, params)
    model_fine_points = np.asarray(model.fine.points)
    for attempt in range(1, params.attempts + 1):
        t0 = time.perf_counter()
        coarse = _coarse_alignment(source, source_features, model, params, seed, attempt)
        t1 = time.perf_counter()
        fine = _refine(source_fine, model.fine, coarse.transformation, params)
        t2 = time.perf_counter()
        clock.coarse_s += t1 - t0
        clock.fine_s += t2 - t1
        model_to_world = _model_to_world(fine.transformation, offset)
        problem = _quality_problem(fine.fitness, fine.inlier_rmse, model_to_world, model_fine_points, params)
        if problem:
            rejections.append(problem)
            continue
        return clock.result(model_to_world, float(fine.fitness), float(fine.inlier_rmse), attempt)
    raise RegistrationError(f"no pose passed after {params.attempts} attempts: " + "; ".join(rejections))


def _observed_features(
    source: o3d.geometry.PointCloud, source_fine: o3d.geometry.PointCloud, params: RegistrationParams
) -> o3d.pipelines.registration.Feature:
    """Normals of both observed clouds (point-to-plane ICP and FPFH need them) and the coarse
    cloud's FPFH features."""
    normal_search = o3d.geometry.KDTreeSearchParamHybrid(
        radius=params.voxel_size_m * params.normal_radius_factor, max_nn=30
    )
    source.estimate_normals(normal_search)
    source_features = _features(source, params)
    source_fine.estimate_normals(normal_search)
    return source_features


def _coarse_alignment(
    source: o3d.geometry.PointCloud,
    source_features: o3d.pipelines.registration.Feature,
    model: PreparedModel,
    params: RegistrationParams,
    seed: int,
    attempt: int,
) -> o3d.pipelines.registration.RegistrationResult:
    """RANSAC on FPFH correspondences, observed to model, seeded by (``seed``, ``attempt``)."""
    ransac_distance = params.voxel_size_m * params.ransac_distance_factor
    checkers = [
        _reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        _reg.CorrespondenceCheckerBasedOnDistance(ransac_distance),
    ]
    criteria = _reg.RANSACConvergenceCriteria(params.ransac_max_iterations, params.ransac_confidence)
    # No mutual filter: on small partial views it leaves too few correspondences.
    with seeded_open3d(seed, attempt):
        return _reg.registration_ransac_based_on_feature_matching(
            source,
            model.coarse,
            source_features,
            model.features,
            False,
            ransac_distance,
            _reg.TransformationEstimationPointToPoint(False),
            3,
            checkers,
            criteria,
        )


def _refine(
    source_fine: o3d.geometry.PointCloud,
    model_fine: o3d.geometry.PointCloud,
    transformation: np.ndarray,
    params: RegistrationParams,
) -> o3d.pipelines.registration.RegistrationResult:
    """Point-to-plane ICP from ``transformation`` (observed to model) through every ICP
    distance; the last stage's result (its fitness is judged at the last distance)."""
    icp_criteria = _reg.ICPConvergenceCriteria(
        relative_fitness=1e-5, relative_rmse=1e-5, max_iteration=params.icp_max_iterations
    )
    # ICP from a wide capture distance down to the final one: a coarse pose several mm off
    # would otherwise lock onto the few correspondences inside the final distance.
    for distance in params.icp_distances_m:
        fine = _reg.registration_icp(
            source_fine,
            model_fine,
            distance,
            transformation,
            _reg.TransformationEstimationPointToPlane(),
            icp_criteria,
        )
        transformation = fine.transformation
    return fine


def _model_to_world(observed_to_model: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The model's pose in world from ICP's transform of the observed points (centred on
    ``offset``) onto the model, its rotation made exactly orthonormal."""
    model_to_world = np.linalg.inv(np.asarray(observed_to_model, dtype=np.float64))
    model_to_world[:3, :3] = Rotation.from_matrix(model_to_world[:3, :3]).as_matrix()
    model_to_world[:3, 3] += offset
    model_to_world[3] = [0.0, 0.0, 0.0, 1.0]
    return model_to_world


def _register_resting(
    model_points_m: np.ndarray,
    model_normals: np.ndarray,
    model_coarse_m: np.ndarray,
    observed_coarse_m: np.ndarray,
    observed_fine_m: np.ndarray,
    model_z_m: float,
    params: RegistrationParams,
    seed: int,
) -> tuple[np.ndarray, float, float, float, float]:
    """Best upright pose (model to the observed points' frame, fitness, RMSE m, sweep s,
    refinement s) of a model resting on the table, its frame's origin at height ``model_z_m``
    (that frame), as its mesh frame stands, turned about the vertical.

    Each of ``resting_yaw_steps`` yaws starts with the model's centroid under the observed one
    and runs a few planar ICP steps with the coarse clouds at the widest ICP distance; the
    ``resting_candidates`` best by fitness are refined through every ICP distance with the
    coarse clouds, and the best of those with the fine clouds at the last distance. Every yaw is
    tried (not the first that passes) so that a near-symmetric object's better turn wins.
    """
    t0 = time.perf_counter()
    tree, coarse_tree = cKDTree(model_points_m), cKDTree(model_coarse_m)
    sweep = sweep_yaws(
        sweep_subset(observed_coarse_m, params.resting_sweep_points, seed),
        coarse_tree,
        model_coarse_m,
        model_points_m[:, :2].mean(axis=0),
        model_z_m,
        params.resting_yaw_steps,
        params.icp_distances_m[:1],
        params.resting_sweep_iterations,
    )
    t1 = time.perf_counter()
    pose = refine_best(
        sweep,
        params.resting_candidates,
        observed_coarse_m,
        coarse_tree,
        model_coarse_m,
        model_z_m,
        params.icp_distances_m,
        params.icp_max_iterations,
    )
    model_to_world, fitness, rmse_m = upright_refined(
        observed_fine_m,
        tree,
        model_points_m,
        model_normals,
        pose,
        model_z_m,
        params.icp_distances_m[-1],
        params.icp_max_iterations,
    )
    return model_to_world, fitness, rmse_m, t1 - t0, time.perf_counter() - t1


def _quality_problem(
    fitness: float,
    inlier_rmse_m: float,
    model_to_world: np.ndarray,
    model_points_m: np.ndarray,
    params: RegistrationParams,
) -> str:
    """Why an ICP result cannot be trusted, or "" if it passes every check."""
    if fitness < params.min_fitness:
        return f"fitness {fitness:.3f} < {params.min_fitness}"
    if inlier_rmse_m > params.max_rmse_m:
        return f"inlier RMSE {inlier_rmse_m * 1e3:.2f} mm > {params.max_rmse_m * 1e3:.2f} mm"
    if params.table_z_m is not None:
        # Fitness only asks that what was seen lies on the model. A wrong pose can pass that by
        # hiding the rest of the model where the cameras did not look — below the table or
        # floating above it. A resting object touches the table with its lowest point.
        lowest = float((model_points_m @ model_to_world[2, :3]).min() + model_to_world[2, 3])
        if abs(lowest - params.table_z_m) > params.table_tolerance_m:
            return (
                f"model's lowest point at z = {lowest * 1e3:.1f} mm, not resting on the table "
                f"(z = {params.table_z_m * 1e3:.1f} ± {params.table_tolerance_m * 1e3:.1f} mm)"
            )
    return ""
