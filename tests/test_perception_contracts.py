"""Numerical contracts of the perception core (issue 20): every public function gives a right,
finite answer or its module's own error naming the argument, on every input - dtype families,
extremes and degenerate geometry - and stays inside its documented time and memory bounds."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from perception.depthmap import MAX_DEPTH_MAP_BINS, DepthMapParams, contact_depth_map, crop_bounds
from perception.errors import DepthMapError, PointCloudError, RegistrationError, SegmentationError
from perception.normalisation import NormalisationError, normalise_depth_map
from perception.pointcloud import VoxelIndex, check_transform, transform_points
from perception.registration import MAX_MODEL_POINTS, sample_model_cloud
from perception.segmentation import SegmentationParams, fit_table_plane, segment_object
from workcell.kinematics import ROTATION_TOLERANCE, GripperGeometry, KinematicsError, gel_poses_world, grasp_to_tcp_pose

REPO = Path(__file__).resolve().parent.parent
FAST = settings(max_examples=40, deadline=None)
EXTREMES = [0.0, -0.0, 1e-300, -1e-300, 1e300, -1e300, np.inf, -np.inf, np.nan]


def dtype_variants(points: np.ndarray) -> list[np.ndarray]:
    """The same values in every dtype family and layout a caller may hand over."""
    variants = [
        points.astype(np.float32),
        points.astype(np.float16),
        points.astype(">f8"),
        np.asfortranarray(points),
        np.repeat(points, 2, axis=0)[::2],
        points[::-1][::-1],
    ]
    if np.all(points == np.round(points)) and np.all(np.abs(points) < 100):
        variants += [points.astype(np.int8), points.astype(np.int64), np.abs(points).astype(np.uint16)]
    return variants


def random_rigid(seed: int, offset_m: float = 0.0) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    transform[:3, 3] = np.random.default_rng(seed).uniform(-1, 1, 3) + offset_m
    return transform


# --- family 2: transform_points ---------------------------------------------------------------


@FAST
@given(n=st.integers(0, 20), seed=st.integers(0, 2**16), offset=st.sampled_from([0.0, 1e3, 1e6]))
def test_property_transform_points_is_the_rigid_map_in_every_dtype(n: int, seed: int, offset: float) -> None:
    points = np.random.default_rng(seed).integers(-50, 50, (n, 3)).astype(np.float64)
    transform = random_rigid(seed, offset)
    expected = points @ transform[:3, :3].T + transform[:3, 3]
    for variant in dtype_variants(points):
        moved = transform_points(variant, transform)
        assert moved.dtype == np.float64 and moved.shape == (n, 3)
        np.testing.assert_allclose(moved, np.asarray(variant, np.float64) @ transform[:3, :3].T + transform[:3, 3])
    np.testing.assert_allclose(transform_points(points, transform), expected)


@pytest.mark.parametrize("shape", [(5, 4), (6, 2), (3,), (2, 3, 3), (4, 1)])
def test_transform_points_refuses_arrays_that_are_not_n_by_3(shape: tuple[int, ...]) -> None:
    with pytest.raises(PointCloudError, match=r"points_a_m must be \(N, 3\)"):
        transform_points(np.ones(shape), np.eye(4))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_transform_points_refuses_non_finite_points(bad: float) -> None:
    with pytest.raises(PointCloudError, match="NaN or inf"):
        transform_points(np.array([[0.0, bad, 0.0]]), np.eye(4))


def test_check_transform_tolerance_is_1e6_not_1e5() -> None:
    """np.allclose's default rtol made the real tolerance 1.1e-5."""
    for error, ok in ((0.5 * ROTATION_TOLERANCE, True), (5e-6, False), (1.05e-5, False)):
        skew = np.eye(4)
        skew[0, 0] = np.sqrt(1 + error)  # R^T R differs from I by ``error`` at (0, 0)
        if ok:
            check_transform(skew)
        else:
            with pytest.raises(PointCloudError, match="proper rotation"):
                check_transform(skew)


# --- family 5: VoxelIndex ----------------------------------------------------------------------


@FAST
@given(
    seed=st.integers(0, 2**16),
    radius=st.sampled_from([0.0, 5e-324, 0.003, 1.0, 1e30, 2e20, 1e300, np.inf]),
    offset=st.sampled_from([0.0, -1e5, 1e6]),
    cell=st.sampled_from([1e-6, 0.005, 1.0]),
)
def test_property_voxel_index_ball_is_a_superset_of_the_true_ball(
    seed: int, radius: float, offset: float, cell: float
) -> None:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.05, 0.05, (200, 3)) + offset
    index = VoxelIndex(points, cell_m=cell)
    centre = points[rng.integers(len(points))] + rng.uniform(-0.01, 0.01, 3)
    near = index.within(centre, radius)
    inside = points[np.linalg.norm(points - centre, axis=1) <= radius]
    got = {tuple(p) for p in near}
    assert {tuple(p) for p in inside} <= got and len(got) == len(near)
    if radius >= 1.0:
        assert len(near) == len(points)
    np.testing.assert_array_equal(index.within(centre, radius), near)


@pytest.mark.parametrize("radius", [np.inf, 1e30, 2e20])
def test_voxel_index_huge_radius_returns_every_point(radius: float) -> None:
    points = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    assert len(VoxelIndex(points).within([0.0, 0.0, 0.0], radius)) == 50


@pytest.mark.parametrize(
    "centre, radius",
    [
        ([np.nan, 0, 0], 1.0),
        ([0, 0, 0], np.nan),
        ([0, 0, 0], -1.0),
        ([np.inf, 0, 0], 1.0),
        ([0, 0], 1.0),
        ([0, 0, 0], "big"),
    ],
)
def test_voxel_index_refuses_undefined_queries(centre: list, radius: float) -> None:
    with pytest.raises(PointCloudError, match="centre_m|radius_m"):
        VoxelIndex(np.zeros((3, 3))).within(centre, radius)


def test_voxel_index_stray_point_far_away() -> None:
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (100, 3))
    # 100 km along one axis: 2e7 cells along it, a grid that fits int64 keys; the answer is right.
    far_x = np.vstack([points, [1e5, 0.0, 0.0]])
    assert len(VoxelIndex(far_x).within([1e5, 0.0, 0.0], 0.001)) == 1
    # 100 km along every axis: 8e21 cells cannot be keyed; a clear refusal, not "invalid dims".
    with pytest.raises(PointCloudError, match="more than 2\\^62"):
        VoxelIndex(np.vstack([points, [1e5, 1e5, 1e5]]))
    with pytest.raises(PointCloudError, match="more than 2\\^62"):
        VoxelIndex(points, cell_m=1e-300)


def test_voxel_index_micrometre_cells_answer_a_millimetre_query_from_the_occupied_cells() -> None:
    points = np.random.default_rng(1).uniform(-0.005, 0.005, (2000, 3))
    index = VoxelIndex(points, cell_m=1e-6)  # a 1 mm ball's box spans 2001^3 = 8e9 cells
    centre = points[0]
    near = index.within(centre, 0.001)
    inside = points[np.linalg.norm(points - centre, axis=1) <= 0.001]
    assert {tuple(p) for p in inside} <= {tuple(p) for p in near}
    assert np.all(np.abs(near - centre) <= 0.001 + 1e-6)  # only the cells of the ball's box
    small = index.within(centre, 3e-6)  # a box of 7^3 cells: enumerated, the same rule
    assert any(np.array_equal(p, centre) for p in small)


# --- family 6: normalise_depth_map, crop_bounds -----------------------------------------------


@FAST
@given(
    y_near=st.floats(-1e3, 1e3),
    width=st.floats(1e-3, 1e3),
    values=st.lists(
        st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(EXTREMES)), min_size=1, max_size=30
    ),
)
@example(y_near=0.0, width=0.001, values=[8.98846567431158e304])  # scaled before clipping, it overflowed
def test_property_normalised_depth_is_finite_in_range_and_monotone(
    y_near: float, width: float, values: list[float]
) -> None:
    depth = np.array(values)
    with np.errstate(over="ignore"):  # values beyond float32 become +-inf there
        as_float32 = depth.astype(np.float32)
    for variant in (depth, depth.astype(">f8"), depth[::-1], as_float32):
        out = normalise_depth_map(variant, (y_near, y_near + width))
        assert out.dtype == np.float32 and out.shape == variant.shape
        assert np.all(np.isfinite(out)) and np.all(np.abs(out) <= 1.0)
    finite = np.sort(depth[np.isfinite(depth)])
    assert np.all(np.diff(normalise_depth_map(finite, (y_near, y_near + width))) >= 0)


@pytest.mark.parametrize(
    "depth_range",
    [
        (-1e308, 1e308),
        (-1e39, 0.0),
        (0.0, np.inf),
        (np.nan, 1.0),
        (1.0, 1.0),
        (1.0, np.nextafter(1.0, 2.0)),
        (0.0,),
        (0.0, 1.0, 2.0),
        "ab",
        3.0,
    ],
)
def test_undefined_depth_ranges_are_refused(depth_range: object) -> None:
    with pytest.raises(NormalisationError, match="depth range|depth_range_m"):
        normalise_depth_map(np.zeros((2, 2)), depth_range)


def test_normalisation_of_the_widest_finite_range_is_right() -> None:
    out = normalise_depth_map(np.array([-3e38, 0.0, 3e38]), (-3e38, 3e38))
    np.testing.assert_allclose(out, [-1.0, 0.0, 1.0])


@pytest.mark.parametrize("y_range", [(-1e39, 1e39), (0.0, 1e39), (-np.inf, 0.001), (0.001,), (0.0, 0.001, 0.002)])
def test_crop_bounds_refuses_ranges_float32_cannot_hold(y_range: tuple) -> None:
    with pytest.raises(DepthMapError, match="float32|y_range_m"):
        crop_bounds(GripperGeometry(), DepthMapParams(y_range_m=y_range))


# --- family 10: DepthMapParams.shape ----------------------------------------------------------


@pytest.mark.parametrize(
    "shape", [(100.0, 100.0), (100,), (10, 10, 10), (True, 5), "ab", 7, (np.float32(4), 4), (0, 4), (-1, 4)]
)
def test_bin_shapes_that_are_not_two_positive_integers_are_refused(shape: object) -> None:
    with pytest.raises(DepthMapError, match="bin shape"):
        contact_depth_map(np.zeros((1, 3)), np.eye(4), np.eye(4), params=DepthMapParams(shape=shape))


def test_bin_count_is_bounded() -> None:
    with pytest.raises(DepthMapError, match="bins, more than"):
        crop_bounds(GripperGeometry(), DepthMapParams(shape=(10**5, 10**5)))
    side = int(np.sqrt(MAX_DEPTH_MAP_BINS))
    crop_bounds(GripperGeometry(), DepthMapParams(shape=(np.int64(side), side)))  # numpy ints are integers
    with pytest.raises(DepthMapError, match="bins, more than"):
        crop_bounds(GripperGeometry(), DepthMapParams(shape=(side, side + 1)))


@FAST
@given(
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from([np.float16, np.float32, np.float64, ">f8"]),
    offset=st.sampled_from([0.0, 1e4, -1e6]),
    layout=st.sampled_from(["c", "f", "reversed"]),
)
def test_property_depth_map_is_finite_for_any_dtype_far_from_the_origin(
    seed: int, dtype: str, offset: float, layout: str
) -> None:
    points = (np.random.default_rng(seed).integers(-8, 9, (300, 3)) * 1e-3).astype(dtype)
    points = {"c": points, "f": np.asfortranarray(points), "reversed": points[::-1]}[layout]
    shift = np.eye(4)
    shift[:3, 3] = offset
    patch = contact_depth_map(points, shift, shift, params=DepthMapParams(shape=(8, 8)))
    assert np.all(np.isfinite(patch.depth_map_m)) and np.all(np.abs(patch.normalised) <= 1)


@pytest.mark.parametrize("dtype", [np.int8, np.uint8, np.int64, np.bool_])
def test_depth_map_of_integer_points_is_the_float_map(dtype: type) -> None:
    points = np.zeros((1, 3), dtype)
    expected = contact_depth_map(np.zeros((1, 3)), np.eye(4), np.eye(4), params=DepthMapParams(shape=(4, 4)))
    got = contact_depth_map(points, np.eye(4), np.eye(4), params=DepthMapParams(shape=(4, 4)))
    np.testing.assert_array_equal(got.depth_map_m, expected.depth_map_m)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e300])
def test_depth_map_refuses_non_finite_points_or_transforms(bad: float) -> None:
    if np.isfinite(bad):  # finite but far: no point in the crop, said so
        with pytest.raises(DepthMapError, match="no model point"):
            contact_depth_map(np.array([[bad, 0.0, 0.0]]), np.eye(4), np.eye(4))
        return
    with pytest.raises(DepthMapError, match="NaN or inf"):
        contact_depth_map(np.array([[bad, 0.0, 0.0]]), np.eye(4), np.eye(4))
    gel = np.eye(4)
    gel[0, 3] = bad
    with pytest.raises(PointCloudError, match="gel_to_world"):
        contact_depth_map(np.zeros((1, 3)), np.eye(4), gel)


# --- family 7: kinematics ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["x_m", "y_m", "z_m", "theta_z_rad"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, "one", None])
def test_grasp_pose_refuses_non_finite_arguments(name: str, bad: object) -> None:
    args = {"x_m": 0.1, "y_m": 0.2, "z_m": 0.3, "theta_z_rad": 0.4, name: bad}
    with pytest.raises(KinematicsError, match=name):
        grasp_to_tcp_pose(**args)


def _bad_tcp_transforms() -> list[np.ndarray]:
    base = random_rigid(3)
    bad = []
    for row, col, value in ((0, 3, np.nan), (1, 3, np.inf), (3, 0, 0.5), (3, 3, 2.0), (0, 0, 1.1)):
        matrix = base.copy()
        matrix[row, col] = value
        bad.append(matrix)
    mirrored = base.copy()
    mirrored[:3, 0] *= -1
    return bad + [mirrored]


@pytest.mark.parametrize("tcp", _bad_tcp_transforms())
def test_gel_poses_refuse_a_tcp_transform_that_is_not_rigid(tcp: np.ndarray) -> None:
    with pytest.raises(KinematicsError, match="tcp_pose_world"):
        gel_poses_world(tcp, 0.05)


@FAST
@given(
    x=st.floats(-1e6, 1e6),
    y=st.floats(-1e6, 1e6),
    z=st.floats(-1e3, 1e3),
    theta=st.floats(-1e3, 1e3),
    width=st.floats(0.0, 0.11),
    as_matrix=st.booleans(),
)
def test_property_gel_poses_are_finite_and_rigid(
    x: float, y: float, z: float, theta: float, width: float, as_matrix: bool
) -> None:
    from workcell.kinematics import pose_to_matrix

    pose = grasp_to_tcp_pose(x, y, z, theta)
    poses = gel_poses_world(pose_to_matrix(pose) if as_matrix else pose, width)
    for gel in poses.values():
        check_transform(gel)
    gap = poses["left"][:3, 3] - poses["right"][:3, 3]
    assert np.linalg.norm(gap) == pytest.approx(width, abs=1e-9 * max(1.0, abs(x), abs(y)))


@pytest.mark.parametrize("width", [np.nan, -1e-9, 0.11 + 1e-9, np.inf, "w"])
def test_gel_poses_refuse_widths_outside_the_gripper(width: object) -> None:
    with pytest.raises(KinematicsError, match="gripper width"):
        gel_poses_world(np.zeros(6), width)


# --- family 8: table plane --------------------------------------------------------------------


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((100, 3)),
        np.full((100, 3), 0.1),
        np.outer(np.linspace(-0.3, 0.3, 100), [1.0, 0.5, 0.0]),
        np.outer(np.linspace(-0.3, 0.3, 100), [0.0, 0.0, 1.0]) + 1e3,
    ],
)
def test_identical_or_collinear_points_have_no_table_plane(points: np.ndarray) -> None:
    with pytest.raises(SegmentationError, match="identical or collinear"):
        fit_table_plane(points, SegmentationParams())


def test_segment_object_says_why_a_line_has_no_table() -> None:
    line = np.outer(np.linspace(-0.3, 0.3, 500), [1.0, 0.0, 0.0])
    with pytest.raises(SegmentationError, match="identical or collinear"):
        segment_object([line])


@FAST
@given(
    seed=st.integers(0, 2**16),
    tilt_deg=st.floats(0.0, 5.0),
    height=st.floats(-0.04, 0.04),
    dtype=st.sampled_from([np.float32, np.float64, ">f8"]),
)
def test_property_plane_of_a_coplanar_table_is_its_plane(seed: int, tilt_deg: float, height: float, dtype: str) -> None:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.3, 0.3, (400, 2))
    slope = np.tan(np.deg2rad(tilt_deg))
    points = np.column_stack([xy, height + slope * xy[:, 0]]).astype(dtype)
    plane = fit_table_plane(points, SegmentationParams(), seed=seed)
    assert np.all(np.isfinite(plane)) and plane[2] > 0
    assert np.linalg.norm(plane[:3]) == pytest.approx(1.0)
    assert np.max(np.abs(np.asarray(points, np.float64) @ plane[:3] + plane[3])) < 1e-4


# --- family 11: sample_model_cloud ------------------------------------------------------------


@pytest.fixture(scope="module")
def box_mesh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mesh") / "box.ply"
    o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh.create_box(0.05, 0.05, 0.05))
    return path


@pytest.mark.parametrize("spacing", [1e-5, 1e-150, 1e-160, 1e-170, 5e-324, 0.0, -1.0, np.nan, np.inf, "x", None])
def test_model_cloud_spacing_that_asks_too_much_or_is_no_number_is_refused(box_mesh: Path, spacing: object) -> None:
    with pytest.raises(RegistrationError, match="point spacing"):
        sample_model_cloud(box_mesh, spacing)


def test_model_cloud_at_the_bound_and_just_inside(box_mesh: Path) -> None:
    area = 6 * 0.05**2
    at_bound = np.sqrt(area / MAX_MODEL_POINTS)
    with pytest.raises(RegistrationError, match="more than"):
        sample_model_cloud(box_mesh, np.nextafter(at_bound, 0.0) * (1 - 1e-9))
    cloud = sample_model_cloud(box_mesh, 0.005)
    assert np.all(np.isfinite(cloud.points_m)) and len(cloud.points_m) >= 100


# --- memory bound -----------------------------------------------------------------------------


def test_documented_bounds_hold_under_a_memory_cap() -> None:
    """Under an address-space cap of what the imports take plus 400 MiB, a 1 mm query of a
    1 um-cell index (2001^3 cells in its box), a 1e5 x 1e5 depth-map and a 10 um model cloud
    (each of which asked for tens of GB) answer or refuse without touching the cap."""
    script = textwrap.dedent("""
        import resource, sys
        import numpy as np
        from perception.depthmap import DepthMapParams, contact_depth_map
        from perception.errors import DepthMapError, RegistrationError
        from perception.pointcloud import VoxelIndex
        from perception.registration import sample_model_cloud
        import open3d as o3d
        mesh = sys.argv[1]
        o3d.io.write_triangle_mesh(mesh, o3d.geometry.TriangleMesh.create_box(0.05, 0.05, 0.05))
        with open("/proc/self/status") as status:
            vm_kb = next(int(line.split()[1]) for line in status if line.startswith("VmSize"))
        cap = vm_kb * 1024 + 400 * 2 ** 20
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
        points = np.random.default_rng(0).uniform(-0.005, 0.005, (20000, 3))
        near = VoxelIndex(points, cell_m=1e-6).within(points[0], 0.001)
        assert 0 < len(near) < len(points)
        try:
            contact_depth_map(points, np.eye(4), np.eye(4), params=DepthMapParams(shape=(10 ** 5, 10 ** 5)))
        except DepthMapError as err:
            assert "bins" in str(err)
        try:
            sample_model_cloud(mesh, 1e-5)
        except RegistrationError as err:
            assert "more than" in str(err)
        print("bounded")
    """)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "-c", script, str(Path(os.environ.get("TMPDIR", "/tmp")) / f"box{os.getpid()}.ply")],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=120,
    )
    assert done.returncode == 0 and "bounded" in done.stdout, done.stderr[-2000:]
