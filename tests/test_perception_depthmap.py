"""Contact depth-maps: binning rules, empty-bin policy, normalisation, and the hard cases.

Tests of the nearest-point rule (the minimum y of a bin's points, bin edges, gap filling, the
plain NumPy reference) pin ``method="nearest_point"``; claims that hold for both rules run over
both (METHODS); contracts and errors use the default (the surface rule, perception.surface, whose
own tests are tests/test_surface_depthmap.py)."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial.transform import Rotation

from perception.binning import fill_sampling_gaps, min_y_per_bin
from perception.depthmap import DepthMapParams, contact_depth_map, crop_bounds
from perception.errors import DepthMapError, PerceptionError
from perception.gripper_centring import centre_between_gels
from perception.normalisation import denormalise_depth_map
from perception.surface import DEPTH_MAP_METHODS
from workcell.kinematics import GripperGeometry, gel_poses_world, grasp_to_tcp_pose
from workcell.parts import GripperSpec

GEOMETRY = GripperGeometry()
STIFFNESS = GripperSpec().foundation_stiffness_n_per_mm3  # N/mm per mm² of contact
METHODS = list(DEPTH_MAP_METHODS)
NEAREST = "nearest_point"
# Bins of 4.98 mm (z) x 3.72 mm (x), the nearest-point rule: a bin holds its points' minimum y.
SMALL = DepthMapParams(shape=(4, 5), margin_m=0.0, method=NEAREST)
HALF_X, HALF_Z = 0.5 * GEOMETRY.gel_size_m[0], 0.5 * GEOMETRY.gel_size_m[1]
T = GEOMETRY.elastomer_thickness_m


def depth_map(points_gel_m, params=SMALL, gel_to_world=np.eye(4), model_to_world=np.eye(4)):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return contact_depth_map(
            np.asarray(points_gel_m, dtype=np.float64), model_to_world, gel_to_world, GEOMETRY, params
        )


def reference_min_y(points, half_x, half_z, y_range, shape):
    """Brute force: loop over bins with the documented half-open / closed-far-edge rules."""
    rows, cols = shape
    out = np.full(shape, np.nan)
    x_edges = np.linspace(-half_x, half_x, cols + 1)
    z_edges = np.linspace(-half_z, half_z, rows + 1)
    for r in range(rows):
        for c in range(cols):
            x_hi_ok = points[:, 0] <= x_edges[c + 1] if c == cols - 1 else points[:, 0] < x_edges[c + 1]
            z_hi_ok = points[:, 2] <= z_edges[r + 1] if r == rows - 1 else points[:, 2] < z_edges[r + 1]
            mask = (
                (points[:, 0] >= x_edges[c])
                & x_hi_ok
                & (points[:, 2] >= z_edges[r])
                & z_hi_ok
                & (points[:, 1] >= y_range[0])
                & (points[:, 1] <= y_range[1])
            )
            if mask.any():
                out[r, c] = points[mask, 1].min()
    return out


def check_clean(patch, method=NEAREST):
    for array in (patch.depth_map_m, patch.normalised):
        assert array.dtype == np.float32
        assert np.all(np.isfinite(array))
    assert np.all(patch.normalised >= -1) and np.all(patch.normalised <= 1)
    y_near, y_far = patch.y_range_m
    assert np.all(patch.depth_map_m >= np.float32(y_near)) and np.all(patch.depth_map_m <= np.float32(y_far))
    if method == "surface":  # a bin whose surface is not known reads y_far
        assert np.all(patch.depth_map_m[~patch.occupied] == np.float32(y_far))
        return
    # An empty bin reads y_far unless it is a gap inside a sampled surface, filled from its
    # occupied neighbours (at least DepthMapParams.fill_gaps_min_neighbours of 8).
    neighbours = ndimage.convolve(patch.occupied.astype(int), np.ones((3, 3), int), mode="constant") - patch.occupied
    filled = ~patch.occupied & (patch.depth_map_m != np.float32(y_far))
    assert np.all(neighbours[filled] >= DepthMapParams.fill_gaps_min_neighbours)


def test_min_of_points_per_bin_and_empty_bins_read_far():
    points = np.array([[0.0005, 0.001, 0.0005], [0.0006, -0.0005, 0.0006], [-0.008, 0.0015, -0.011]])
    patch = depth_map(points)
    check_clean(patch)
    # x = 0.5 mm is in column 2 (edges at -9.3, -5.58, -1.86, 1.86 mm), z in row 2.
    assert patch.depth_map_m[2, 2] == np.float32(-0.0005)
    assert patch.depth_map_m[0, 0] == np.float32(0.0015)
    assert patch.occupied.sum() == 2 and patch.point_count == 3
    assert np.all(patch.depth_map_m[~patch.occupied] == np.float32(T))


def test_points_exactly_on_bin_edges_go_to_the_upper_bin_and_far_edge_to_the_last():
    x_edges = np.linspace(-HALF_X, HALF_X, 6)
    points = np.array([[x_edges[1], 0.0, 0.0], [x_edges[5], 0.001, HALF_Z], [-HALF_X, -0.001, -HALF_Z]])
    patch = depth_map(points)
    expected = reference_min_y(points, HALF_X, HALF_Z, (-T, T), SMALL.shape)
    np.testing.assert_array_equal(np.isfinite(expected), patch.occupied)
    np.testing.assert_array_equal(patch.depth_map_m[patch.occupied], expected[patch.occupied].astype(np.float32))
    assert patch.occupied[2, 1] and patch.occupied[3, 4] and patch.occupied[0, 0]


@pytest.mark.parametrize("method", METHODS)
def test_crop_boundary_is_inclusive_and_just_outside_is_dropped(method):
    on = [[HALF_X, T, HALF_Z], [-HALF_X, -T, -HALF_Z]]
    outside = [
        [np.nextafter(HALF_X, 1.0), 0.0, 0.0],
        [0.0, np.nextafter(T, 1.0), 0.0],
        [0.0, np.nextafter(-T, -1.0), 0.0],
        [0.0, 0.0, np.nextafter(-HALF_Z, -1.0)],
    ]
    patch = depth_map(on + outside, dataclasses.replace(SMALL, method=method))
    check_clean(patch, method)
    assert patch.point_count == 2
    assert patch.depth_map_m[3, 4] == np.float32(T) and patch.occupied[3, 4]
    assert patch.depth_map_m[0, 0] == np.float32(-T)


@pytest.mark.parametrize("method", METHODS)
def test_every_point_in_one_bin_and_duplicates(method):
    rng = np.random.default_rng(0)
    points = np.column_stack(
        [rng.uniform(0.0001, 0.001, 500), rng.uniform(-T, T, 500), rng.uniform(0.0001, 0.004, 500)]
    )
    points = np.concatenate([points, points])  # every point twice
    patch = depth_map(points, dataclasses.replace(SMALL, method=method))
    check_clean(patch, method)
    assert patch.occupied.sum() == 1 and patch.point_count == 1000
    assert patch.depth_map_m[patch.occupied][0] == np.float32(points[:, 1].min())


@pytest.mark.parametrize("method", METHODS)
def test_one_point(method):
    patch = depth_map([[0.0, 0.0003, 0.0]], dataclasses.replace(SMALL, method=method))
    check_clean(patch, method)
    assert patch.occupied.sum() == 1 and patch.depth_map_m[patch.occupied][0] == np.float32(0.0003)


def test_empty_patch_is_an_error_not_a_flat_map():
    with pytest.raises(DepthMapError, match="no model point in the contact volume"):
        depth_map([[0.0, 0.01, 0.0]], DepthMapParams())
    with pytest.raises(DepthMapError, match="no model point"):
        depth_map(np.zeros((0, 3)), DepthMapParams())


@pytest.mark.parametrize("bad", [[[np.nan, 0, 0]], [[0, np.inf, 0]], [[0, 0, -np.inf]]])
def test_nan_or_inf_model_points_are_refused(bad):
    with pytest.raises(DepthMapError, match="NaN or inf"):
        depth_map(bad, DepthMapParams())


@pytest.mark.parametrize("y_range", [(0.001, 0.001), (0.002, -0.002), (0.0, np.nan), (1.0, 1.0 + 1e-12)])
def test_zero_negative_or_unresolvable_depth_range_is_refused(y_range):
    with pytest.raises(DepthMapError):
        depth_map([[0.0, 0.0, 0.0]], DepthMapParams(y_range_m=y_range))


def test_bin_size_below_float32_resolution_is_refused():
    # 18.6 mm over 10^7 columns: 1.9 nm bins, under 4 float32 steps (4 x 0.93 nm) at 9.3 mm.
    with pytest.raises(DepthMapError, match="below float32 resolution"):
        depth_map([[0.0, 0.0, 0.0]], DepthMapParams(shape=(4, 10**7), margin_m=0.0))
    patch = depth_map([[0.0, 0.0, 0.0]], DepthMapParams(shape=(4, 10**5), margin_m=0.0))  # 0.19 um bins
    check_clean(patch, "surface")


def test_bad_shapes_are_refused():
    for shape in [(0, 10), (10, -1), (2.5, 3)]:
        with pytest.raises(DepthMapError, match="bin shape"):
            depth_map([[0.0, 0.0, 0.0]], DepthMapParams(shape=shape))
    with pytest.raises(DepthMapError, match="positive extent"):
        depth_map([[0.0, 0.0, 0.0]], DepthMapParams(margin_m=-0.05))


@pytest.mark.parametrize("method", METHODS)
def test_scene_a_kilometre_from_the_origin_gives_the_same_map(method):
    """Model and gel poses near (1 km, 1 km, 0): float32 world coordinates would be 61 um apart,
    but the map is computed through one float64 model-to-gel transform."""
    rng = np.random.default_rng(1)
    points_model = np.column_stack(
        [rng.uniform(-0.012, 0.012, 2000), rng.uniform(-0.0015, 0.0015, 2000), rng.uniform(-0.015, 0.015, 2000)]
    )
    params = DepthMapParams(method=method)
    near = depth_map(points_model, params)
    shift = np.eye(4)
    shift[:3, 3] = [1000.0, 1000.0, 0.0]
    rotation = np.eye(4)
    rotation[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix()
    far = depth_map(points_model, params, gel_to_world=shift @ rotation, model_to_world=shift @ rotation)
    check_clean(far, method)
    np.testing.assert_array_equal(near.occupied, far.occupied)
    np.testing.assert_allclose(far.depth_map_m, near.depth_map_m, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_gel_frame_from_kinematics_sees_the_object_it_grasps(method):
    """A 40 mm cube at the origin, grasped at its centre with both gels 1 mm inside its faces."""
    grid = np.linspace(-0.02, 0.02, 201)
    a, b = np.meshgrid(grid, grid)
    faces = [np.column_stack([np.full(a.size, s * 0.02), a.ravel(), b.ravel()]) for s in (-1, 1)]
    faces += [np.column_stack([a.ravel(), np.full(a.size, s * 0.02), b.ravel()]) for s in (-1, 1)]
    cube = np.concatenate(faces)
    tcp = grasp_to_tcp_pose(0.0, 0.0, GEOMETRY.tcp_to_gel_centre_m, 0.0)
    for finger, gel_to_world in gel_poses_world(tcp, 0.038, GEOMETRY).items():
        patch = contact_depth_map(cube, np.eye(4), gel_to_world, GEOMETRY, DepthMapParams((20, 20), method=method))
        check_clean(patch, method)
        assert patch.occupied.all(), finger
        np.testing.assert_allclose(patch.depth_map_m, -0.001, atol=1e-7)


@pytest.mark.parametrize("method", METHODS)
def test_grasp_at_the_object_edge_with_few_points(method):
    """Only a corner of the surface reaches the crop: the rest of the map reads 'far'."""
    points = np.array(
        [[HALF_X - 0.0001, 0.0002, HALF_Z - 0.0001], [HALF_X, -0.0001, HALF_Z], [HALF_X + 0.005, -0.0005, 0.0]]
    )  # last one outside the crop
    patch = depth_map(points, DepthMapParams(shape=(100, 100), margin_m=0.0, method=method))
    check_clean(patch, method)
    assert patch.point_count == 2 and patch.occupied.sum() == 1
    assert patch.depth_map_m[99, 99] == np.float32(-0.0001)


def test_normalisation_round_trip_gives_millimetres_back():
    rng = np.random.default_rng(2)
    points = np.column_stack(
        [rng.uniform(-HALF_X, HALF_X, 3000), rng.uniform(-T, T, 3000), rng.uniform(-HALF_Z, HALF_Z, 3000)]
    )
    patch = depth_map(points, DepthMapParams(shape=(10, 10), margin_m=0.0))
    back = denormalise_depth_map(patch.normalised, patch.y_range_m)
    np.testing.assert_allclose(back, patch.depth_map_m, atol=2 * T * 1e-6)


def test_crop_bounds_and_errors_are_perception_errors():
    half_x, half_z, y_near, y_far = crop_bounds(GEOMETRY, DepthMapParams(margin_m=0.003))
    assert half_x == pytest.approx(0.0093 + 0.003) and half_z == pytest.approx(0.01245 + 0.003)
    assert (y_near, y_far) == (-T, T)
    assert issubclass(DepthMapError, PerceptionError) and issubclass(DepthMapError, ValueError)


finite_coordinate = st.floats(-0.03, 0.03, allow_nan=False, width=64)
special = st.sampled_from([-HALF_X, HALF_X, -HALF_Z, HALF_Z, -T, T, 0.0, np.linspace(-HALF_X, HALF_X, 6)[2]])


@settings(max_examples=150, deadline=None)
@given(
    points=st.lists(
        st.tuples(
            st.one_of(finite_coordinate, special),
            st.one_of(finite_coordinate, special),
            st.one_of(finite_coordinate, special),
        ),
        min_size=1,
        max_size=60,
    ),
    shape=st.tuples(st.integers(1, 7), st.integers(1, 7)),
)
def test_property_matches_brute_force_and_stays_finite(points, shape):
    points = np.array(points, dtype=np.float64)
    params = DepthMapParams(shape=shape, margin_m=0.0, method=NEAREST)
    expected = reference_min_y(points, HALF_X, HALF_Z, (-T, T), shape)
    if np.all(np.isnan(expected)):
        with pytest.raises(DepthMapError):
            depth_map(points, params)
        return
    patch = depth_map(points, params)
    check_clean(patch)
    np.testing.assert_array_equal(patch.occupied, np.isfinite(expected))
    np.testing.assert_array_equal(patch.depth_map_m[patch.occupied], expected[patch.occupied].astype(np.float32))


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 2000), rows=st.integers(1, 50), cols=st.integers(1, 50), seed=st.integers(0, 2**32 - 1))
def test_property_min_y_per_bin_equals_sorting_reference(n, rows, cols, seed):
    rng = np.random.default_rng(seed)
    x, z = rng.uniform(-HALF_X, HALF_X, n), rng.uniform(-HALF_Z, HALF_Z, n)
    y = rng.uniform(-T, T, n)
    min_y, occupied = min_y_per_bin(x, z, y, HALF_X, HALF_Z, (rows, cols))
    col = np.minimum(np.floor((x + HALF_X) / (2 * HALF_X) * cols).astype(int), cols - 1)
    row = np.minimum(np.floor((z + HALF_Z) / (2 * HALF_Z) * rows).astype(int), rows - 1)
    flat = row * cols + col
    order = np.lexsort((y, flat))
    first = np.r_[True, flat[order][1:] != flat[order][:-1]]
    reference = np.full(rows * cols, np.inf)
    reference[flat[order][first]] = y[order][first]
    np.testing.assert_array_equal(min_y.ravel(), reference)
    np.testing.assert_array_equal(occupied.ravel(), np.isfinite(reference))


def test_sampling_gaps_inside_a_surface_are_filled_and_free_space_is_not() -> None:
    depth = np.full((6, 6), 0.002, np.float32)
    occupied = np.zeros((6, 6), bool)
    occupied[:, :3] = True
    depth[:, :3] = -0.001
    occupied[2, 1] = False  # a gap inside the sampled surface
    depth[2, 1] = 0.002
    depth[1, 0] = -0.0015  # its nearest neighbour
    filled = fill_sampling_gaps(depth, occupied, 5)
    assert filled[2, 1] == pytest.approx(-0.0015)
    np.testing.assert_array_equal(filled[:, 4:], depth[:, 4:])  # free space keeps y_far
    with pytest.raises(DepthMapError, match="1..8"):
        fill_sampling_gaps(depth, occupied, 0)


def test_crop_covers_the_sensed_area_plus_margin():
    """A tactile camera that sees less than the whole gel: the crop follows what it sees."""
    sensed = GripperGeometry(sensed_area_m=(0.0199, 0.0149))
    half_x, half_z, _, _ = crop_bounds(sensed, DepthMapParams(margin_m=0.002))
    assert (half_x, half_z) == pytest.approx((0.5 * 0.0199 + 0.002, 0.5 * 0.0149 + 0.002))
    half_x, half_z, _, _ = crop_bounds(GEOMETRY, DepthMapParams(margin_m=0.002))
    assert (half_x, half_z) == pytest.approx((HALF_X + 0.002, HALF_Z + 0.002))


@pytest.mark.parametrize("method", METHODS)
def test_sampling_gaps_are_filled_but_free_space_is_not(method):
    """A plane sampled with a few bins missing: the holes take the plane's y; bins beyond the
    sampled edge stay y_far. Nearest point: the holes stay unoccupied (filled from their
    neighbours, and not at all with gap filling off); surface: the plane is known there."""
    params = DepthMapParams(shape=(10, 10), margin_m=0.0, method=method)
    x_edges = np.linspace(-HALF_X, HALF_X, 11)
    z_edges = np.linspace(-HALF_Z, HALF_Z, 11)
    centres = [
        (0.5 * (x_edges[c] + x_edges[c + 1]), 0.5 * (z_edges[r] + z_edges[r + 1]))
        for r in range(10)
        for c in range(5)
        if (r, c) not in {(3, 2), (6, 1)}
    ]
    points = np.array([[x, -0.0005, z] for x, z in centres])
    patch = depth_map(points, params)
    check_clean(patch, method)
    assert patch.depth_map_m[3, 2] == np.float32(-0.0005) and patch.depth_map_m[6, 1] == np.float32(-0.0005)
    assert np.all(patch.depth_map_m[:, 6:] == np.float32(patch.y_range_m[1]))
    assert not patch.occupied[:, 6:].any()
    if method == "surface":
        assert patch.occupied[3, 2] and patch.occupied[6, 1] and patch.occupied[:, :5].all()
        np.testing.assert_array_equal(patch.depth_map_m[:, :5], np.float32(-0.0005))
        return
    assert not patch.occupied[3, 2]
    exact = depth_map(points, dataclasses.replace(params, fill_gaps_min_neighbours=0))
    assert exact.depth_map_m[3, 2] == np.float32(exact.y_range_m[1])


def _box_points(size_m, spacing_m=0.001):
    """Points on the surface of an axis-aligned box centred on the origin."""
    axes = [np.arange(-h, h + 1e-12, spacing_m) for h in 0.5 * np.asarray(size_m)]
    points = []
    for axis in range(3):
        others = [a for i, a in enumerate(axes) if i != axis]
        grid = np.stack(np.meshgrid(*others, indexing="ij"), -1).reshape(-1, 2)
        for side in (-0.5, 0.5):
            face = np.insert(grid, axis, side * size_m[axis], axis=1)
            points.append(face)
    return np.concatenate(points)


@settings(max_examples=30, deadline=None)
@given(offset_m=st.floats(-0.01, 0.01), along_m=st.floats(-0.005, 0.005), yaw=st.floats(-np.pi, np.pi))
def test_centring_puts_the_object_midway_between_the_gels(offset_m, along_m, yaw):
    """A 40 mm box held at width 39 mm, registered off-centre along the closing axis: its two
    faces are alike, so at any grasp force both gels press it 0.5 mm; nothing moves along the
    gel faces."""
    box = _box_points((0.04, 0.04, 0.06))
    tcp = grasp_to_tcp_pose(0.1, -0.05, 0.03 + GEOMETRY.tcp_to_gel_centre_m, yaw)
    gels = gel_poses_world(tcp, 0.039, GEOMETRY)
    closing = gels["left"][:3, 1]
    along = gels["left"][:3, 0]
    registered = np.eye(4)
    registered[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    registered[:3, 3] = [0.1, -0.05, 0.03]
    registered[:3, 3] += offset_m * closing + along_m * along
    centred = centre_between_gels(box, registered, gels["left"], gels["right"], GEOMETRY, 10.0, STIFFNESS)
    assert centred[:3, :3] == pytest.approx(registered[:3, :3])
    moved = centred[:3, 3] - registered[:3, 3]
    assert moved == pytest.approx(-offset_m * closing, abs=1e-9)
    for finger in ("left", "right"):
        patch = contact_depth_map(box, centred, gels[finger], GEOMETRY, DepthMapParams(margin_m=0.0))
        assert patch.depth_map_m.min() == pytest.approx(-0.0005, abs=1e-6)


def test_centring_leaves_the_pose_when_a_gel_faces_nothing():
    box = _box_points((0.02, 0.02, 0.02))
    gels = gel_poses_world(grasp_to_tcp_pose(0.0, 0.0, 0.01 + GEOMETRY.tcp_to_gel_centre_m, 0.0), 0.03, GEOMETRY)
    far = np.eye(4)
    far[:3, 3] = [0.5, 0.0, 0.01]  # beside the gripper, in front of neither gel
    assert np.array_equal(centre_between_gels(box, far, gels["left"], gels["right"], GEOMETRY, 10.0, STIFFNESS), far)
    with pytest.raises(DepthMapError, match="finite"):
        centre_between_gels(np.array([[0.0, np.nan, 0.0]]), far, gels["left"], gels["right"], GEOMETRY, 10.0, STIFFNESS)


@pytest.mark.parametrize(
    ("force_n", "stiffness", "message"),
    [
        (float("nan"), STIFFNESS, "grasp_force_n"),
        (-1.0, STIFFNESS, "grasp_force_n"),
        (float("inf"), STIFFNESS, "grasp_force_n"),
        (10.0, 0.0, "stiffness"),
        (10.0, float("nan"), "stiffness"),
    ],
)
def test_centring_refuses_a_force_or_stiffness_that_is_no_number(force_n, stiffness, message):
    box = _box_points((0.04, 0.04, 0.06))
    gels = gel_poses_world(grasp_to_tcp_pose(0.0, 0.0, 0.03 + GEOMETRY.tcp_to_gel_centre_m, 0.0), 0.039, GEOMETRY)
    with pytest.raises(DepthMapError, match=message):
        centre_between_gels(box, np.eye(4), gels["left"], gels["right"], GEOMETRY, force_n, stiffness)


# --- the batched, indexed path (contact_depth_maps) and the compiled kernel -----------------------


def numpy_reference_map(points_model, model_to_world, gel_to_world, params):
    """The plain NumPy pipeline (float64 transform, masks, np.searchsorted on the edges,
    np.minimum.at), with the module's nearest-point rules, before gap filling."""
    half_x, half_z, y_near, y_far = crop_bounds(GEOMETRY, params)
    model_to_gel = np.linalg.inv(gel_to_world) @ model_to_world
    gel = np.asarray(points_model, np.float64) @ model_to_gel[:3, :3].T + model_to_gel[:3, 3]
    keep = (gel[:, 1] >= y_near) & (gel[:, 1] <= y_far) & (np.abs(gel[:, 0]) <= half_x) & (np.abs(gel[:, 2]) <= half_z)
    x, y, z = gel[keep].T
    rows, cols = params.shape
    col = np.minimum(np.searchsorted(np.linspace(-half_x, half_x, cols + 1), x, side="right") - 1, cols - 1)
    row = np.minimum(np.searchsorted(np.linspace(-half_z, half_z, rows + 1), z, side="right") - 1, rows - 1)
    out = np.full(rows * cols, np.inf)
    np.minimum.at(out, row * cols + col, y)
    return out.reshape(rows, cols)


def random_pose(rng, offset_m):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    pose[:3, 3] = offset_m + rng.uniform(-0.003, 0.003, 3)
    return pose


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    regions=st.integers(1, 6),
    offset=st.sampled_from([0.0, 1e3, -2e4]),
    dtype=st.sampled_from([np.float32, np.float64]),
    cell=st.sampled_from([0.001, 0.005, 0.05]),
    shape=st.tuples(st.integers(1, 40), st.integers(1, 40)),
    threads=st.integers(1, 3),
    method=st.sampled_from(METHODS),
)
def test_property_batched_maps_equal_one_map_per_gel_and_the_numpy_reference(
    seed, regions, offset, dtype, cell, shape, threads, method
):
    """Gels anywhere around a cloud of a few mm (and a km from the origin): the indexed batch,
    cut on any number of threads, gives each gel exactly contact_depth_map's map (either rule),
    and with the nearest-point rule both the plain NumPy pipeline's."""
    from perception.depthmap import contact_depth_maps
    from perception.pointcloud import VoxelIndex

    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.015, 0.015, (3000, 3)).astype(dtype)
    model_to_world = random_pose(rng, offset)
    gels = np.stack([model_to_world @ random_pose(rng, 0.0) for _ in range(regions)])
    params = DepthMapParams(shape=shape, fill_gaps_min_neighbours=0, method=method)
    try:
        singles = [contact_depth_map(points, model_to_world, gel, GEOMETRY, params) for gel in gels]
    except DepthMapError:
        with pytest.raises(DepthMapError, match="region .*no model point"):
            contact_depth_maps(VoxelIndex(points, cell), model_to_world, gels, GEOMETRY, params, threads=threads)
        return
    batch = contact_depth_maps(VoxelIndex(points, cell), model_to_world, gels, GEOMETRY, params, threads=threads)
    for i, single in enumerate(singles):
        np.testing.assert_array_equal(batch.depth_maps_m[i], single.depth_map_m)
        np.testing.assert_array_equal(batch.occupied[i], single.occupied)
        assert batch.point_counts[i] == single.point_count
        if method != NEAREST:
            continue
        reference = numpy_reference_map(points, model_to_world, gels[i], params)
        np.testing.assert_array_equal(single.occupied, np.isfinite(reference))
        np.testing.assert_allclose(single.depth_map_m[single.occupied], reference[single.occupied], rtol=0, atol=1e-9)


def test_region_groups_split_the_points_to_read_evenly_and_cover_every_region_once():
    from perception.binning import region_groups

    runs = np.array([0, 1, 1, 3, 4, 5])  # 5 regions; the second reads no run
    lengths = np.array([10, 5, 5, 10, 10])
    assert region_groups(lengths, runs, 1) == [(0, 5)]
    assert region_groups(lengths, runs, 2) == [(0, 3), (3, 5)]  # 20 and 20 points
    groups = region_groups(lengths, runs, 8)  # more threads than regions: no empty group
    assert [k for first, stop in groups for k in range(first, stop)] == list(range(5))
    assert region_groups(np.zeros(5, np.int64), runs, 2) == [(0, 5)]  # nothing to read


@pytest.mark.parametrize("method", METHODS)
def test_float32_points_give_the_map_of_their_float64_values(method):
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.012, 0.012, (20000, 3)).astype(np.float32)
    gel = random_pose(rng, 0.0)
    wide, narrow = (
        contact_depth_map(p, np.eye(4), gel, GEOMETRY, DepthMapParams(method=method))
        for p in (points.astype(np.float64), points)
    )
    np.testing.assert_array_equal(wide.depth_map_m, narrow.depth_map_m)
    np.testing.assert_array_equal(wide.occupied, narrow.occupied)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    offset=st.sampled_from([0.0, 1e3, -2e4]),
    cell=st.sampled_from([0.001, 0.005, 0.05]),
)
def test_property_a_planned_cut_keeps_every_cell_that_holds_a_point_of_its_gels_crop(seed, offset, cell):
    """The separating-axis test drops a cell only when no point of it can lie in its gel's crop:
    every point inside a crop (transformed as the cut's kernel does) is in a cell the plan
    keeps for that gel, gels turned every way and a km from the origin; and it drops cells, so
    that the test is one."""
    from perception.binning import cells_meeting_crops
    from perception.pointcloud import VoxelIndex

    rng = np.random.default_rng(seed)
    index = VoxelIndex(offset + rng.uniform(-0.03, 0.03, (20000, 3)), cell)
    gels = np.stack([random_pose(rng, offset) for _ in range(4)])
    model_to_gel = np.linalg.inv(gels)
    half_x, half_z, y_near, y_far = bounds = crop_bounds(GEOMETRY, DepthMapParams())
    owner, starts, ends, corners = index.cells_within_many(gels[:, :3, 3], 0.1)
    meets = cells_meeting_crops(corners, owner, index.cell_m, model_to_gel, bounds)
    assert not meets.all()
    for gel, to_gel in enumerate(model_to_gel):
        points = index.points_m @ to_gel[:3, :3].T + to_gel[:3, 3]
        x, y, z = points.T
        inside = np.flatnonzero((np.abs(x) <= half_x) & (np.abs(z) <= half_z) & (y >= y_near) & (y <= y_far))
        kept = [(s, e) for s, e, m, o in zip(starts, ends, meets, owner) if m and o == gel]
        assert inside.size  # each crop lies within the cloud's cube
        assert all(any(s <= i < e for s, e in kept) for i in inside)


def test_batched_maps_name_the_region_that_misses_and_bound_the_work():
    from perception.depthmap import contact_depth_maps
    from perception.pointcloud import VoxelIndex

    index = VoxelIndex(np.random.default_rng(0).uniform(-0.005, 0.005, (1000, 3)))
    away = np.eye(4)
    away[1, 3] = -1.0
    with pytest.raises(DepthMapError, match="region 1: no model point"):
        contact_depth_maps(index, np.eye(4), np.stack([np.eye(4), away]), GEOMETRY, DepthMapParams())
    with pytest.raises(DepthMapError, match="too much work: 2000 model points near 2 gels > 1999"):
        contact_depth_maps(
            index, np.eye(4), np.stack([np.eye(4)] * 2), GEOMETRY, DepthMapParams(), max_point_visits=1999
        )
    with pytest.raises(DepthMapError, match=r"\(N, 4, 4\)"):
        contact_depth_maps(index, np.eye(4), np.eye(4), GEOMETRY, DepthMapParams())
    with pytest.raises(DepthMapError, match="min_neighbours must be in 1..8, got 9"):
        contact_depth_maps(index, np.eye(4), np.eye(4)[None], GEOMETRY, DepthMapParams(fill_gaps_min_neighbours=9))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    stack=st.integers(0, 3),
    rows=st.integers(1, 12),
    cols=st.integers(1, 12),
    min_neighbours=st.integers(1, 8),
    density=st.floats(0.0, 1.0),
)
def test_property_gap_filling_equals_scipy_filters(seed, stack, rows, cols, min_neighbours, density):
    """The shifted-view neighbourhoods equal scipy.ndimage's 3 x 3 count and minimum, map by map."""
    rng = np.random.default_rng(seed)
    shape = (stack, rows, cols) if stack else (rows, cols)
    occupied = rng.random(shape) < density
    depth = np.where(occupied, rng.uniform(-T, T, shape), T).astype(np.float32)
    got = fill_sampling_gaps(depth, occupied, min_neighbours)
    for index in np.ndindex(*shape[:-2]):
        occ, dep = occupied[index], depth[index]
        neighbours = ndimage.convolve(occ.astype(np.uint8), np.ones((3, 3), np.uint8), mode="constant") - occ
        nearest = ndimage.minimum_filter(np.where(occ, dep, np.inf), size=3, mode="constant", cval=np.inf)
        expected = np.where(~occ & (neighbours >= min_neighbours), nearest, dep).astype(np.float32)
        np.testing.assert_array_equal(got[index], expected)


def test_min_y_per_bin_keeps_values_outside_the_crop_in_the_edge_bins():
    """The crop is the caller's; a value outside it (or NaN) lands in an edge bin, never outside
    the map's memory."""
    x = np.array([-1.0, 1.0, np.nan, 0.0])
    z = np.array([-1.0, 1.0, 0.0, np.nan])
    min_y, occupied = min_y_per_bin(x, z, np.array([0.1, 0.2, 0.3, 0.4]), HALF_X, HALF_Z, (3, 4))
    assert min_y[0, 0] == 0.1 and min_y[2, 3] == 0.2 and occupied.sum() <= 4


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    regions=st.integers(1, 9),
    run=st.tuples(st.integers(0, 8), st.integers(1, 9)),
    threads=st.integers(1, 3),
    on_device=st.booleans(),
    method=st.sampled_from(METHODS),
)
def test_property_any_run_of_a_planned_cut_is_the_whole_cuts_maps(seed, regions, run, threads, on_device, method):
    """A planned cut cut region run by region run (a request pass by pass, nodes.inference),
    on the compiled pass or the tensor one: each run's maps, occupancy and counts are the whole
    cut's rows; a gel that misses is named by its place in the whole cut."""
    from perception.depthmap import plan_contact_cut
    from perception.depthmap_tensor import points_on_device
    from perception.pointcloud import VoxelIndex

    rng = np.random.default_rng(seed)
    index = VoxelIndex(rng.uniform(-0.015, 0.015, (3000, 3)))
    gels = np.stack([random_pose(rng, 0.0) for _ in range(regions)])
    device_points = points_on_device(index.points_m, "cpu") if on_device else None
    params = DepthMapParams(method=method)
    plan = plan_contact_cut(index, np.eye(4), gels, GEOMETRY, params, allow_empty=True, device_points=device_points)
    first, stop = min(run[0], regions - 1), min(max(run), regions)
    stop = max(stop, first + 1)
    whole, part = plan.cut(threads=threads), plan.cut(first, stop, threads=threads)
    np.testing.assert_array_equal(part.depth_maps_m, whole.depth_maps_m[first:stop])
    np.testing.assert_array_equal(part.occupied, whole.occupied[first:stop])
    np.testing.assert_array_equal(part.point_counts, whole.point_counts[first:stop])
    missing = np.flatnonzero(whole.point_counts[first:stop] == 0)
    if missing.size:
        strict = plan_contact_cut(index, np.eye(4), gels, GEOMETRY, params, device_points=device_points)
        with pytest.raises(DepthMapError, match=f"region {first + missing[0]}: no model point"):
            strict.cut(first, stop)


def test_a_planned_cut_refuses_a_run_it_does_not_hold_and_bad_threads():
    from perception.depthmap import plan_contact_cut
    from perception.pointcloud import VoxelIndex

    index = VoxelIndex(np.random.default_rng(0).uniform(-0.005, 0.005, (1000, 3)))
    plan = plan_contact_cut(index, np.eye(4), np.stack([np.eye(4)] * 3), GEOMETRY, DepthMapParams())
    for first, stop in [(0, 4), (2, 2), (-1, 2), (3, 3)]:
        with pytest.raises(DepthMapError, match=rf"regions {first}..{stop - 1} are not a run of this cut's 3"):
            plan.cut(first, stop)
    for threads in (0, 1.5, True):
        with pytest.raises(DepthMapError, match="threads must be an integer >= 1"):
            plan.cut(threads=threads)
