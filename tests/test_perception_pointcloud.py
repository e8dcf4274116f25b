"""Back-projection with distortion, invalid pixels, merging cameras; density control."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msgs.sensors import CameraIntrinsics, DepthImage
from perception.density import PAPER_DENSITIES_PER_CM3, downsample_to_density, voxel_size_for_density
from perception.errors import PerceptionError, PointCloudError
from perception.pointcloud import (
    VoxelIndex,
    depth_images_to_world,
    depth_to_points_camera,
    merge_depth_images,
    pixel_rays,
    transform_points,
)

DISTORTED = CameraIntrinsics(
    width=64, height=48, fx=60.0, fy=58.0, cx=31.7, cy=24.2, distortion=[0.09, -0.27, 0.001, -0.002, 0.09]
)


def test_back_projected_points_reproject_onto_their_pixels_with_distortion():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.6, 3.0, (DISTORTED.height, DISTORTED.width)).astype(np.float32)
    points = depth_to_points_camera(depth, DISTORTED)
    assert points.shape == (DISTORTED.height * DISTORTED.width, 3) and points.dtype == np.float64
    np.testing.assert_allclose(points[:, 2], depth.ravel().astype(np.float64))
    camera_matrix = np.array([[DISTORTED.fx, 0, DISTORTED.cx], [0, DISTORTED.fy, DISTORTED.cy], [0, 0, 1]])
    pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera_matrix, np.array(DISTORTED.distortion))
    u, v = np.meshgrid(np.arange(DISTORTED.width), np.arange(DISTORTED.height))
    np.testing.assert_allclose(pixels.reshape(-1, 2), np.column_stack([u.ravel(), v.ravel()]), atol=1e-3)


def test_without_distortion_rays_are_the_pinhole_model():
    pinhole = CameraIntrinsics(width=8, height=6, fx=5.0, fy=4.0, cx=3.5, cy=2.5)
    rays = pixel_rays(pinhole)
    np.testing.assert_allclose(rays[2, 7], [(7 - 3.5) / 5.0, (2 - 2.5) / 4.0], atol=1e-12)


def test_nan_inf_zero_and_out_of_range_pixels_are_dropped():
    depth = np.full((DISTORTED.height, DISTORTED.width), 1.0, dtype=np.float32)
    depth[0, :4] = [np.nan, np.inf, -np.inf, 0.0]
    depth[1, :3] = [0.3, 5.0, -1.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        points = depth_to_points_camera(depth, DISTORTED, range_m=(0.5, 4.5))
    assert len(points) == depth.size - 7
    assert np.all(np.isfinite(points)) and np.all(points[:, 2] == 1.0)


def test_uint16_millimetres_with_zero_as_no_return():
    depth_mm = np.full((DISTORTED.height, DISTORTED.width), 1500, dtype=np.uint16)
    depth_mm[0, 0] = 0
    image = DepthImage(depth=depth_mm, intrinsics=DISTORTED, camera_to_world=np.eye(4))
    points = merge_depth_images([image])
    assert len(points) == depth_mm.size - 1
    np.testing.assert_allclose(points[:, 2], 1.5, rtol=1e-6)


def test_two_cameras_facing_each_other_merge_in_world():
    """Two cameras 2 m apart looking at each other see a wall at x = 0 from both sides."""

    def camera_at(x, forward):
        transform = np.eye(4)
        transform[:3, :3] = np.column_stack([np.cross([0, 0, -1.0], forward), [0, 0, -1.0], forward])
        transform[:3, 3] = [x, 0, 0]
        return transform

    intrinsics = CameraIntrinsics(width=16, height=12, fx=20.0, fy=20.0, cx=7.5, cy=5.5)
    depth = np.full((12, 16), 1.0, dtype=np.float32)
    images = [
        DepthImage(depth=depth, intrinsics=intrinsics, camera_to_world=camera_at(-1.0, np.array([1.0, 0, 0]))),
        DepthImage(depth=depth, intrinsics=intrinsics, camera_to_world=camera_at(1.0, np.array([-1.0, 0, 0]))),
    ]
    clouds = depth_images_to_world(images)
    assert [len(c) for c in clouds] == [192, 192]
    merged = merge_depth_images(images)
    np.testing.assert_allclose(merged[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sort(clouds[0][:, 1]), np.sort(-clouds[1][:, 1]), atol=1e-12)


def test_bad_inputs_say_what_is_wrong():
    with pytest.raises(PointCloudError, match="depth image is"):
        depth_to_points_camera(np.ones((3, 3)), DISTORTED)
    with pytest.raises(PointCloudError, match="depth range"):
        depth_to_points_camera(np.ones((48, 64)), DISTORTED, range_m=(0.0, 4.0))
    with pytest.raises(PointCloudError, match="focal"):
        pixel_rays(CameraIntrinsics(fx=0.0))
    with pytest.raises(PointCloudError, match="no depth images"):
        merge_depth_images([])
    skew = np.eye(4)
    skew[0, 1] = 0.1
    with pytest.raises(PointCloudError, match="rotation"):
        transform_points(np.zeros((1, 3)), skew)
    assert issubclass(PointCloudError, PerceptionError)


def test_voxel_size_follows_from_density():
    assert voxel_size_for_density(1.0) == pytest.approx(0.01)
    assert voxel_size_for_density(80.0) == pytest.approx(0.01 / 80 ** (1 / 3))
    for density in PAPER_DENSITIES_PER_CM3:
        assert voxel_size_for_density(density) ** 3 * 1e6 == pytest.approx(1.0 / density)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(PerceptionError, match="density"):
            voxel_size_for_density(bad)


@pytest.mark.parametrize("density", PAPER_DENSITIES_PER_CM3)
def test_downsampled_solid_cloud_has_at_most_the_requested_density(density):
    """A 10 cm cube filled at 2 mm spacing (125 points/cm³) thins to about the asked density:
    one point per occupied voxel, the partly filled boundary voxels adding at most 35 %."""
    grid = np.arange(0.0, 0.1, 0.002) + 0.001
    solid = np.stack(np.meshgrid(grid, grid, grid), axis=-1).reshape(-1, 3)
    thinned = downsample_to_density(solid, density)
    measured = len(thinned) / 1000.0  # cube volume in cm³
    assert density * 0.9 <= measured <= density * 1.35


depth_value = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32), st.sampled_from([0.5, 4.5, 0.0, -0.0, np.nan, np.inf])
)


@settings(max_examples=100, deadline=None)
@given(values=st.lists(depth_value, min_size=12, max_size=12), offset=st.sampled_from([0.0, 1000.0, -1000.0]))
def test_property_only_finite_in_range_points_come_out(values, offset):
    """Any float32 depth, including NaN, inf, zero, negatives and the range limits, with the
    camera placed up to a kilometre from the origin: no NaN or inf escapes, no warning."""
    intrinsics = CameraIntrinsics(width=4, height=3, fx=3.0, fy=3.0, cx=1.5, cy=1.0, distortion=[0.1, -0.05, 0, 0, 0])
    depth = np.array(values, dtype=np.float32).reshape(3, 4)
    camera_to_world = np.eye(4)
    camera_to_world[:3, 3] = offset
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        points = merge_depth_images([DepthImage(depth=depth, intrinsics=intrinsics, camera_to_world=camera_to_world)])
    with np.errstate(invalid="ignore"):
        valid = (depth >= 0.5) & (depth <= 4.5)
    assert len(points) == int(np.count_nonzero(valid))
    assert np.all(np.isfinite(points))
    np.testing.assert_allclose(points[:, 2] - offset, depth[valid].astype(np.float64), atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    radius_m=st.floats(0.0, 0.05),
    cell_m=st.floats(0.001, 0.02),
    offset_m=st.floats(-1e3, 1e3),
)
def test_voxel_index_hands_out_every_point_of_the_ball(seed, radius_m, cell_m, offset_m):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.05, 0.05, size=(2000, 3)) + offset_m
    index = VoxelIndex(points, cell_m)
    centre = points[rng.integers(len(points))] + rng.uniform(-0.02, 0.02, 3)
    near = index.within(centre, radius_m)
    inside = points[np.linalg.norm(points - centre, axis=1) <= radius_m]
    assert {tuple(p) for p in inside} <= {tuple(p) for p in near}
    assert len(near) == len({tuple(p) for p in near})  # no point twice
    assert np.array_equal(index.within(centre, radius_m), near)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    balls=st.integers(0, 12),
    points=st.sampled_from([0, 5, 2000]),
    radius_m=st.sampled_from([0.0, 0.004, 0.02, 0.3, np.inf]),
    cell_m=st.sampled_from([0.001, 0.005, 0.05]),
    offset_m=st.sampled_from([0.0, 1e3]),
)
def test_voxel_index_answers_many_balls_as_it_answers_each(seed, balls, points, radius_m, cell_m, offset_m):
    """The batched look-up gives each ball exactly the runs, in the order, one query gives, and
    both are every occupied cell of the ball's box of cells, keys ascending (here found by
    testing every occupied cell): boxes searched column by column, or scanned when they outgrow
    the occupied cells (few points, a huge radius); centres inside, outside and far from the cloud."""
    rng = np.random.default_rng(seed)
    index = VoxelIndex(rng.uniform(-0.05, 0.05, size=(points, 3)) + offset_m, cell_m)
    centres = offset_m + rng.uniform(-0.08, 0.08, size=(balls, 3))
    owner, starts, ends, corners = index.cells_within_many(centres, radius_m)
    assert np.all(np.diff(owner) >= 0)
    occupied = np.stack(np.unravel_index(index.keys, tuple(index.shape)), axis=1)
    for ball, centre in enumerate(centres):
        mine = owner == ball
        expected = index.slices_within(centre, radius_m)
        np.testing.assert_array_equal(starts[mine], expected[0])
        np.testing.assert_array_equal(ends[mine], expected[1])
        with np.errstate(invalid="ignore"):  # inf - inf where the radius is inf: NaN, not in any box
            low = np.floor((centre - radius_m - index.origin_m) / cell_m)
            high = np.floor((centre + radius_m - index.origin_m) / cell_m)
        inside = np.all((occupied >= low) & (occupied <= high), axis=1) | (radius_m == np.inf)
        np.testing.assert_array_equal(expected[0], index.starts[inside])
        cells = np.floor((corners[mine] - index.origin_m) / cell_m + 0.5).astype(np.int64)
        np.testing.assert_array_equal(
            np.ravel_multi_index(cells.T, index.shape), index.keys[np.searchsorted(index.starts, expected[0])]
        )


def test_voxel_index_refuses_balls_that_are_not_balls():
    index = VoxelIndex(np.zeros((3, 3)))
    with pytest.raises(PointCloudError, match=r"centres_m must be finite \(x, y, z\)"):
        index.cells_within_many(np.array([[0.0, np.nan, 0.0]]), 0.01)
    with pytest.raises(PointCloudError, match=r"centres_m must be finite \(x, y, z\)"):
        index.cells_within_many(np.zeros((2, 2)), 0.01)
    with pytest.raises(PointCloudError, match="radius_m must be >= 0"):
        index.cells_within_many(np.zeros((2, 3)), float("nan"))
    with pytest.raises(PointCloudError, match="centre_m must be finite"):
        index.within([0.0, 0.0], 0.01)


def test_voxel_index_edge_cases():
    index = VoxelIndex(np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.1]]))
    assert len(index.within([5.0, 5.0, 5.0], 0.01)) == 0
    assert len(index.within([0.0, 0.0, 0.0], 0.0)) == 1
    assert len(VoxelIndex(np.zeros((0, 3))).within([0.0, 0.0, 0.0], 1.0)) == 0
    with pytest.raises(PointCloudError, match="finite"):
        VoxelIndex(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(PointCloudError, match="cell size"):
        VoxelIndex(np.zeros((1, 3)), cell_m=0.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(0, 3000),
    cell_m=st.sampled_from([1e-7, 0.0005, 0.005, 0.05]),
    dtype=st.sampled_from([np.float32, np.float64]),
    offset_m=st.sampled_from([0.0, -250.0, 1e4]),
)
def test_voxel_index_buckets_as_a_stable_sort_of_the_cell_keys(seed, n, cell_m, dtype, offset_m):
    """Counting sort (few cells per point) and argsort (a sparse grid) both give what a stable
    argsort of the row-major cell keys gives: the same points, order, runs and keys."""
    points = (np.random.default_rng(seed).uniform(-0.02, 0.02, (n, 3)) + offset_m).astype(dtype)
    index = VoxelIndex(points, cell_m)
    assert index.points_m.dtype == dtype
    if n == 0:
        assert len(index.points_m) == 0 and len(index.keys) == 0
        return
    cells = np.floor((points.astype(np.float64) - points.min(axis=0).astype(np.float64)) / cell_m).astype(np.int64)
    keys = np.ravel_multi_index(cells.T, index.shape)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(index.points_m, points[order])
    unique, first, counts = np.unique(keys[order], return_index=True, return_counts=True)
    np.testing.assert_array_equal(index.keys, unique)
    np.testing.assert_array_equal(index.starts, first)
    np.testing.assert_array_equal(index.ends, first + counts)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    count=st.integers(1, 8),
    flaw=st.sampled_from(["none", "skew", "near_tolerance", "reflection", "last_row", "nan", "inf"]),
)
def test_property_check_transforms_judges_each_pose_as_check_transform(seed, count, flaw):
    """The vectorised screen accepts exactly the stacks whose every pose check_transform
    accepts, and refuses with check_transform's message for the first bad pose, named name[i]."""
    from scipy.spatial.transform import Rotation

    from perception.pointcloud import check_transform, check_transforms

    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(count, 3))
    bad = int(rng.integers(count))
    changes = {
        "skew": (0, 1, 1e-3),
        "near_tolerance": (0, 0, 9e-7),
        "reflection": None,
        "last_row": (3, 0, 1e-12),
        "nan": (1, 2, np.nan),
        "inf": (2, 3, np.inf),
    }
    if flaw == "reflection":
        poses[bad, :3, 0] *= -1.0
    elif flaw != "none":
        row, col, value = changes[flaw]
        poses[bad, row, col] = value if flaw in ("nan", "inf") else poses[bad, row, col] + value
    expected = None
    for i, pose in enumerate(poses):
        try:
            check_transform(pose, f"poses[{i}]")
        except PointCloudError as err:
            expected = str(err)
            break
    if expected is None:
        np.testing.assert_array_equal(check_transforms(poses, "poses"), poses)
    else:
        with pytest.raises(PointCloudError) as caught:
            check_transforms(poses, "poses")
        assert str(caught.value) == expected
