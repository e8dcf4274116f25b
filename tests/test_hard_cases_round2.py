"""Hard cases, round two (issue 31): the numerical code added since the first round gives the
right answer or its module's own error naming the argument, for empty, single, huge and
non-finite inputs, with no RuntimeWarning on the way; the stated bounds hold under a 1 GiB cap.

Families: the physics prior and batch rendering of depth-maps, the most-deformed box, the
real-press evaluation, density thinning, depth-maps made again, the cloud handle's id, the
config loader, PSNR statistics, the points contract of depth-map cutting and the analytic
contacts. Hypothesis runs derandomized, so every run draws the same examples."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import subprocess
import sys
import textwrap
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from bus.inference_client import Cloud, InferenceError, TactileClient
from dataset.records import DatasetError
from dataset.redepth import depth_map_again
from dataset.synth import MAX_CONTACT_MAP_SIZE, MAX_OVERSAMPLE, analytic_contact_maps, depth_map_from_surface
from models.errors import ModelConfigError
from models.evaluate import psnr_statistics, ssim_statistics
from models.networks import GeneratorConfig, UNetGenerator
from models.prior import MAX_POSE_SIGMA_MM, PhysicsPrior, PriorSpec, checked_pose_sigma_mm
from models.real_presses import BALL_RADIUS_RANGE_MM, MAX_BALL_POINTS, ball_cloud_m, evaluate_real_presses
from models.serving import MAX_PREDICT_BATCH, predict
from models.template_match import most_deformed_box, template_match
from msgs.config import ConfigError, config_from_dict
from nodes.inference import cloud_id
from perception.density import MAX_POINTS_PER_CM3, downsample_to_density, voxel_size_for_density
from perception.depthmap import DepthMapParams, contact_depth_map, contact_depth_maps
from perception.errors import DepthMapError, PerceptionError, PointCloudError
from perception.pointcloud import VoxelIndex, check_transforms
from sim.gelsight import GAP_LIMIT_MM, MAX_RENDERED_PIXELS, GelSightRenderError, render_depth_maps
from sim.gelsight_check import press_depth_mm
from workcell.kinematics import ROTATION_TOLERANCE, GripperGeometry, KinematicsError, rigid_transform

pytestmark = pytest.mark.filterwarnings("error")  # a RuntimeWarning on the way fails the case

REPO = Path(__file__).resolve().parent.parent
SCENE = str(REPO / "scenes" / "ycb_three.yaml")
PRESSES = REPO / "assets" / "gelsight" / "ball_presses.npz"
CROP_M = (0.024, 0.015, 0.019)  # wider than the GelSight's 16 x 12 mm field, as a session's crop
BINS = 24
CASES = settings(max_examples=30, deadline=None, derandomize=True)
FEW = settings(max_examples=12, deadline=None, derandomize=True)

# Any float64, the extremes and the non-finite ones drawn often.
ANY_FLOAT = st.one_of(
    st.sampled_from([0.0, -0.0, 1e-300, 5e-324, 1e300, -1e300, 1.7976931348623157e308, math.inf, -math.inf, math.nan]),
    st.floats(allow_nan=True, allow_infinity=True),
)
UNREAL_DTYPES = [np.complex128, np.str_, object]


@pytest.fixture(scope="module")
def prior() -> PhysicsPrior:
    return PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=1.0), BINS)


# --- the physics prior and batch rendering ---------------------------------------------------


def test_zero_depth_maps_give_zero_images(prior: PhysicsPrior) -> None:
    for sigma_mm in (0.0, 1.0):
        images = prior.images(np.zeros((0, BINS, BINS), np.float32), sigma_mm)
        assert images.shape == (0, BINS, BINS, 3) and images.dtype == np.uint8
    assert prior.channels(np.zeros((0, 7, 9))).shape == (0, 3, BINS, BINS)
    assert render_depth_maps(prior.renderer, np.zeros((0, 5, 5)), CROP_M[::2]).shape == (0, BINS, BINS, 3)


@pytest.mark.parametrize("shape", [(1, 0, 0), (1, 0, 5), (2, 5, 0), (5, 5), (1, 1, 1, 1)])
def test_a_map_without_bins_or_of_the_wrong_rank_is_refused(prior: PhysicsPrior, shape: tuple[int, ...]) -> None:
    with pytest.raises(ModelConfigError, match="depth_maps_m"):
        prior.images(np.zeros(shape, np.float32))


@pytest.mark.parametrize("dtype", [np.int64, np.bool_, *UNREAL_DTYPES])
def test_depth_maps_of_a_type_other_than_float_are_refused(prior: PhysicsPrior, dtype: type) -> None:
    with pytest.raises(ModelConfigError, match="depth_maps_m"):
        prior.images(np.zeros((1, 4, 4)).astype(dtype))


def test_one_bin_is_one_gap_everywhere(prior: PhysicsPrior) -> None:
    one = prior.images(np.full((1, 1, 1), -0.0005), 0.0)
    flat = prior.images(np.full((1, BINS, BINS), -0.0005), 0.0)
    np.testing.assert_array_equal(one, flat)


@CASES
@given(
    value=ANY_FLOAT.filter(lambda v: v != -math.inf),
    dtype=st.sampled_from([np.float16, np.float32, np.float64]),
    where=st.tuples(st.integers(0, BINS - 1), st.integers(0, BINS - 1)),
)
def test_any_depth_value_renders_as_its_clipped_gap(
    prior: PhysicsPrior, value: float, dtype: type, where: tuple[int, int]
) -> None:
    """A huge, tiny, NaN or +inf value in a map of contacts renders as the gap it means: NaN and
    +inf are nothing there, and beyond GAP_LIMIT_MM either way the gel cannot tell the difference."""
    maps = np.full((1, BINS, BINS), 0.004, dtype)
    maps[0, 5:12, 5:12] = -0.0008  # a pressed square
    with np.errstate(over="ignore"):  # the test's own cast of the drawn value into float16
        maps[0][where] = value
    if np.isneginf(maps[0][where]):  # a value below float16's range is stored as -inf
        with pytest.raises(ModelConfigError, match="-inf"):
            prior.images(maps, 0.0)
        return
    meant = maps.astype(np.float64)
    meant[np.isnan(meant)] = np.inf
    meant = np.clip(meant, -GAP_LIMIT_MM * 1e-3, GAP_LIMIT_MM * 1e-3).astype(dtype)
    images = prior.images(maps, 0.0)
    assert images.shape == (1, BINS, BINS, 3) and images.dtype == np.uint8
    np.testing.assert_array_equal(images, prior.images(meant, 0.0))


def test_minus_infinity_is_refused(prior: PhysicsPrior) -> None:
    maps = np.zeros((2, 4, 4))
    maps[1, 2, 3] = -np.inf
    with pytest.raises(ModelConfigError, match="depth_maps_m contains -inf"):
        prior.images(maps)


@CASES
@given(sigma_mm=ANY_FLOAT)
def test_any_pose_sigma_is_a_blur_or_refused_naming_it(prior: PhysicsPrior, sigma_mm: float) -> None:
    maps = np.full((1, BINS, BINS), 0.004, np.float32)
    maps[0, 8:14, 8:14] = -0.0005
    if 0 <= sigma_mm <= MAX_POSE_SIGMA_MM:
        images = prior.images(maps, sigma_mm)
        assert images.shape == (1, BINS, BINS, 3)
    else:
        with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
            prior.images(maps, sigma_mm)
        with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
            PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=sigma_mm), BINS)


@pytest.mark.parametrize("sigma", [True, "1.0", None, [1.0], 1e5, 10**400])
def test_a_pose_sigma_that_is_no_number_of_mm_is_refused(sigma: object) -> None:
    with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
        checked_pose_sigma_mm(sigma)  # type: ignore[arg-type]


def test_a_prior_spec_with_an_overflowing_number_is_its_own_error() -> None:
    with pytest.raises(ModelConfigError, match="physics prior"):
        PriorSpec.from_dict({"scene": SCENE, "depth_crop_m": [0.02, 0.01, 10**400]})


@pytest.mark.parametrize(
    ("crop", "size"), [(("a", 1, 1), 8), ((0.02, 0.01), 8), (CROP_M, 0), (CROP_M, 10**6), (CROP_M, 2.5)]
)
def test_a_prior_of_no_crop_or_of_an_image_size_the_renderer_cannot_draw_is_refused(crop: tuple, size: object) -> None:
    with pytest.raises(ModelConfigError, match="depth crop|image size"):
        PhysicsPrior(PriorSpec(SCENE, crop), size)  # type: ignore[arg-type]


def test_too_many_maps_are_refused_before_anything_is_drawn(prior: PhysicsPrior) -> None:
    count = MAX_RENDERED_PIXELS // (BINS * BINS) + 1
    many = np.broadcast_to(np.zeros((1, 1, 1)), (count, 1, 1))  # no memory behind it
    with pytest.raises(GelSightRenderError, match="depth_maps_m"):
        render_depth_maps(prior.renderer, many, CROP_M[::2])


@pytest.mark.parametrize("crop", [(0.0, 0.02), (math.nan, 0.02), (math.inf, 0.02), (0.02,), "ab", (1e300, 1e300)])
def test_a_bad_crop_is_refused_naming_it(prior: PhysicsPrior, crop: object) -> None:
    maps = np.zeros((1, 4, 4))
    if crop == (1e300, 1e300):  # finite and positive: a crop as large as that is a right answer
        assert render_depth_maps(prior.renderer, maps, crop).shape == (1, BINS, BINS, 3)  # type: ignore[arg-type]
        return
    with pytest.raises(GelSightRenderError, match="crop_xz_m"):
        render_depth_maps(prior.renderer, maps, crop)  # type: ignore[arg-type]


# --- the most-deformed box -------------------------------------------------------------------


def _box_sums(values: np.ndarray, size: int) -> dict[tuple[int, int], Fraction]:
    """Exact sum of every size x size box, keyed by its top-left (x, y)."""
    exact = [[Fraction(float(v)) for v in row] for row in values]
    h, w = values.shape
    return {
        (x, y): sum((exact[r][c] for r in range(y, y + size) for c in range(x, x + size)), Fraction(0))
        for y in range(h - size + 1)
        for x in range(w - size + 1)
    }


@CASES
@given(
    values=hnp.arrays(
        np.float64,
        st.tuples(st.integers(1, 7), st.integers(1, 7)),
        elements=st.one_of(st.floats(0, 1e308), st.sampled_from([0.0, 1e300, 1.7976931348623157e308, 5e-324])),
    ),
    size=st.integers(1, 7),
)
def test_the_box_found_holds_the_largest_exact_sum(values: np.ndarray, size: int) -> None:
    h, w = values.shape
    if size > min(h, w):
        with pytest.raises(ModelConfigError, match="size_px"):
            most_deformed_box(values, size)
        return
    sums = _box_sums(values, size)
    best = max(sums.values())
    x, y = most_deformed_box(values, size)
    # Right to rounding: float64 sums of values scaled by the largest (at most 49 of them).
    assert sums[(x, y)] >= best - Fraction(float(np.max(values))) * Fraction(1, 10**12)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.int64, np.uint8])
def test_one_huge_pixel_is_inside_its_box(dtype: type) -> None:
    deformation = np.zeros((9, 9), dtype)
    deformation[6, 2] = np.finfo(dtype).max if np.issubdtype(dtype, np.floating) else np.iinfo(np.int8).max
    deformation[0:3, 0:3] = 1
    x, y = most_deformed_box(deformation, 3)
    assert x <= 2 < x + 3 and y <= 6 < y + 3


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_deformation_is_refused_naming_it(bad: float) -> None:
    deformation = np.zeros((6, 6))
    deformation[4, 4] = bad
    with pytest.raises(ModelConfigError, match="deformation"):
        most_deformed_box(deformation, 2)
    truth = np.zeros((1, 6, 6, 3), np.uint8)
    with pytest.raises(ModelConfigError, match="deformation"):
        template_match(truth, deformation[None], truth, size_px=2)


@pytest.mark.parametrize("size", [0, -1, 2.5, True, "2", None])
def test_a_box_size_that_is_no_whole_number_of_pixels_is_refused(size: object) -> None:
    with pytest.raises(ModelConfigError, match="size_px"):
        most_deformed_box(np.ones((4, 4)), size)  # type: ignore[arg-type]


@pytest.mark.parametrize("deformation", [np.zeros((0, 0)), np.ones(5), np.ones((2, 2), complex), np.array([["1"]])])
def test_an_empty_flat_or_unreal_deformation_is_refused(deformation: np.ndarray) -> None:
    with pytest.raises(ModelConfigError):
        most_deformed_box(deformation, 1)


def test_template_matching_of_no_pairs_is_no_result() -> None:
    empty = np.zeros((0, 8, 8, 3), np.uint8)
    assert template_match(empty, np.zeros((0, 8, 8)), empty, size_px=4) == []


# --- the real-press evaluation ---------------------------------------------------------------


@CASES
@given(radius_mm=ANY_FLOAT)
def test_any_ball_radius_is_a_bounded_cloud_or_refused(radius_mm: float) -> None:
    if not BALL_RADIUS_RANGE_MM[0] <= radius_mm <= BALL_RADIUS_RANGE_MM[1]:
        with pytest.raises(ModelConfigError, match="ball_radius_mm"):
            ball_cloud_m(radius_mm)
        return
    cloud = ball_cloud_m(radius_mm, spacing_m=max(1e-4, radius_mm * 1e-3 / 20))  # keep the examples small
    assert 100 <= len(cloud) <= MAX_BALL_POINTS
    np.testing.assert_allclose(np.linalg.norm(cloud, axis=1), radius_mm * 1e-3, rtol=1e-12)


@pytest.mark.parametrize("spacing_m", [0.0, -1e-4, math.nan, math.inf, 1e-9])
def test_a_spacing_that_would_not_bound_the_ball_is_refused(spacing_m: float) -> None:
    with pytest.raises(ModelConfigError, match="spacing_m"):
        ball_cloud_m(2.0, spacing_m)


@pytest.fixture(scope="module")
def generator() -> UNetGenerator:
    return UNetGenerator(GeneratorConfig(ngf=4))


@pytest.mark.parametrize(
    ("setting", "name"),
    [
        ({"ball_radius_mm": 1000.0}, "ball-radius"),
        ({"ball_radius_mm": 1e300}, "ball-radius"),
        ({"ball_radius_mm": math.nan}, "ball-radius"),
        ({"mm_per_px": 1e300}, "mm-per-px"),
        ({"mm_per_px": 0.0}, "mm-per-px"),
        ({"margin_m": 1.0}, "margin_m"),
        ({"margin_m": -1e-3}, "margin_m"),
        ({"seed": -1}, "seed"),
        ({"depth_range_m": (0.01, -0.01)}, "depth_range_m"),
        ({"depth_range_m": (-1e300, 1e300)}, "depth_range_m"),
    ],
)
def test_absurd_real_press_settings_are_refused_naming_them(generator: UNetGenerator, setting: dict, name: str) -> None:
    arguments = {"depth_range_m": (-0.005, 0.01), **setting}
    with pytest.raises(ModelConfigError, match=name):
        evaluate_real_presses(generator, path=PRESSES, **arguments)


@pytest.mark.parametrize("batch", [0, -1, MAX_PREDICT_BATCH + 1, 2.5, True])
def test_a_forward_batch_out_of_bounds_is_refused(generator: UNetGenerator, batch: object) -> None:
    with pytest.raises(ModelConfigError, match="batch"):
        predict(generator, np.zeros((1, 100, 100), np.float32), (-0.005, 0.01), batch=batch)  # type: ignore[arg-type]


@pytest.mark.parametrize(("contact", "ball"), [(1.0, 1e300), (1.0, math.inf), (math.inf, 2.0), (math.nan, 2.0)])
def test_press_depth_of_an_absurd_ball_is_refused(contact: float, ball: float) -> None:
    with pytest.raises(GelSightRenderError, match="radius"):
        press_depth_mm(contact, ball)


# --- density thinning ------------------------------------------------------------------------


@CASES
@given(density=ANY_FLOAT)
def test_any_density_is_a_voxel_or_refused(density: float) -> None:
    if 0 < density <= MAX_POINTS_PER_CM3:
        voxel = voxel_size_for_density(density)
        assert np.isfinite(voxel) and voxel >= 1e-5
    else:
        with pytest.raises(PerceptionError, match="density"):
            voxel_size_for_density(density)


@CASES
@given(
    points=hnp.arrays(
        np.float64, st.tuples(st.integers(0, 30), st.just(3)), elements=st.floats(-1e300, 1e300, allow_subnormal=True)
    ),
    density=st.sampled_from([1.0, 80.0, 1e6, MAX_POINTS_PER_CM3]),
)
def test_thinning_keeps_at_most_the_points_or_says_the_cloud_is_too_wide(points: np.ndarray, density: float) -> None:
    voxel = voxel_size_for_density(density)
    span = (points.max(axis=0) / 2 - points.min(axis=0) / 2).max() * 2 if len(points) else 0.0
    if span >= voxel * (2**31 - 1) * (1 - 1e-9):
        with pytest.raises(PerceptionError, match="span"):
            downsample_to_density(points, density)
        return
    thinned = downsample_to_density(points, density)
    assert thinned.shape[1] == 3 and len(thinned) <= len(points) and (len(thinned) > 0) == (len(points) > 0)
    assert np.all(np.isfinite(thinned))


def test_one_point_is_itself_and_no_point_is_none() -> None:
    one = np.array([[0.1, -0.2, 0.3]])
    np.testing.assert_allclose(downsample_to_density(one, 10.0), one)
    assert downsample_to_density(np.zeros((0, 3)), 10.0).shape == (0, 3)


@pytest.mark.parametrize("dtype", UNREAL_DTYPES)
def test_thinning_refuses_points_that_are_no_numbers(dtype: type) -> None:
    with pytest.raises(PerceptionError, match="points"):
        downsample_to_density(np.ones((4, 3)).astype(dtype), 10.0)


# --- depth-maps made again, and the points contract of the cutting ---------------------------


@pytest.fixture(scope="module")
def slab() -> VoxelIndex:
    """A 30 x 30 mm slab 0.5 mm thick, 0.2 mm apart, on the gel's x-z plane at y 0..0.5 mm."""
    grid = np.arange(-0.015, 0.015, 0.0002)
    x, z = np.meshgrid(grid, grid)
    return VoxelIndex(np.column_stack([x.ravel(), np.full(x.size, 0.0002), z.ravel()]))


@pytest.mark.parametrize("method", ["surface", "nearest_point"])
def test_depth_map_again_with_default_params_reaches_or_says_nothing_is_within_reach(
    slab: VoxelIndex, method: str
) -> None:
    geometry, params = GripperGeometry(), DepthMapParams(shape=(16, 16), method=method)
    thickness = geometry.elastomer_thickness_m
    far = np.eye(4)
    far[1, 3] = 1.0
    np.testing.assert_array_equal(
        depth_map_again(slab, far, geometry, params), np.full((16, 16), thickness, np.float32)
    )
    touching = depth_map_again(slab, np.eye(4), geometry, params)
    np.testing.assert_allclose(touching, 0.0002, atol=1e-7)


@pytest.mark.parametrize("pose", [np.zeros((4, 4)), np.full((4, 4), np.nan), np.eye(3)])
def test_depth_map_again_refuses_a_pose_that_is_no_rigid_transform(slab: VoxelIndex, pose: np.ndarray) -> None:
    with pytest.raises(PointCloudError, match="model_to_gel"):
        depth_map_again(slab, pose, GripperGeometry(), DepthMapParams(shape=(16, 16)))


def test_depth_map_again_refuses_bad_params_instead_of_calling_them_out_of_reach(slab: VoxelIndex) -> None:
    with pytest.raises(DepthMapError, match="y_far > y_near"):
        depth_map_again(slab, np.eye(4), GripperGeometry(), DepthMapParams(y_range_m=(0.001, -0.001)))


@pytest.mark.parametrize("dtype", UNREAL_DTYPES)
def test_point_arrays_that_are_no_numbers_are_refused(dtype: type) -> None:
    points = np.zeros((5, 3)).astype(dtype)
    with pytest.raises(DepthMapError, match="real numbers"):
        contact_depth_map(points, np.eye(4), np.eye(4))
    with pytest.raises(PointCloudError, match="real numbers"):
        VoxelIndex(points)


@CASES
@given(value=ANY_FLOAT, where=st.tuples(st.integers(0, 3), st.integers(0, 3)), count=st.integers(1, 3))
def test_a_pose_with_any_one_entry_is_rigid_or_refused_the_same_way(
    value: float, where: tuple[int, int], count: int
) -> None:
    """One entry of the identity set to anything (1e308 in the rotation overflowed R^T R): the
    single and the batched check agree, and what they pass is rigid."""
    pose = np.eye(4)
    pose[where] = value
    try:
        checked = rigid_transform(pose, "pose")
    except KinematicsError:
        with pytest.raises(PointCloudError, match=r"poses\[0\]"):
            check_transforms(np.repeat(pose[None], count, axis=0), "poses")
        return
    rotation = checked[:3, :3]
    assert np.abs(rotation.T @ rotation - np.eye(3)).max() <= ROTATION_TOLERANCE and np.linalg.det(rotation) > 0
    np.testing.assert_array_equal(
        check_transforms(np.repeat(pose[None], count, axis=0)), np.repeat(checked[None], count, 0)
    )


@pytest.mark.parametrize("dtype", UNREAL_DTYPES)
def test_poses_that_are_no_numbers_are_refused(dtype: type) -> None:
    with pytest.raises(KinematicsError, match="real numbers"):
        rigid_transform(np.eye(4).astype(dtype))
    with pytest.raises(PointCloudError, match="real numbers"):
        check_transforms(np.eye(4).astype(dtype)[None])


@pytest.mark.parametrize("threads", [0, -1, 1.5, True])
def test_a_thread_count_that_is_no_whole_positive_number_is_refused(slab: VoxelIndex, threads: object) -> None:
    with pytest.raises(DepthMapError, match="threads"):
        contact_depth_maps(slab, np.eye(4), np.eye(4)[None], threads=threads)  # type: ignore[arg-type]


# --- the cloud handle's id, the config loader, PSNR statistics, analytic contacts -----------


@FEW
@given(
    points=hnp.arrays(
        st.sampled_from([np.float32, np.float64]),
        st.tuples(st.integers(0, 20), st.just(3)),
        elements=st.floats(allow_nan=True, allow_infinity=True, width=32),
    )
)
def test_the_cloud_id_is_the_hash_of_dtype_shape_and_bytes(points: np.ndarray) -> None:
    expected = hashlib.sha256(f"{points.dtype.str} {points.shape}".encode() + points.tobytes()).hexdigest()
    assert cloud_id(points) == expected
    assert cloud_id(np.asfortranarray(points)) == expected  # the C-order bytes, whatever the layout


@pytest.mark.parametrize("value", [1e300, -1e39, math.nan, math.inf])
def test_the_client_refuses_maps_that_would_not_survive_float32(value: float) -> None:
    """A float64 value beyond float32 overflowed the client's cast (RuntimeWarning) into an inf
    the server then refused; the client now says so before sending."""
    maps = np.zeros((1, 100, 100))
    maps[0, 3, 4] = value
    with TactileClient(timeout_s=1.0) as client, pytest.raises(InferenceError) as refused:
        client.estimate(maps)
    assert refused.value.code == "bad_request" and "depth_maps" in refused.value.text


@pytest.mark.parametrize("dtype", UNREAL_DTYPES)
def test_a_cloud_handle_of_points_that_are_no_numbers_is_refused(dtype: type) -> None:
    with pytest.raises(InferenceError, match="real numbers"):
        Cloud(np.zeros((4, 3)).astype(dtype))


def test_the_id_of_an_empty_cloud_is_the_hash_of_no_points() -> None:
    empty = np.zeros((0, 3), np.float32)
    assert cloud_id(empty) == hashlib.sha256(b"<f4 (0, 3)").hexdigest()


@dataclasses.dataclass
class _Settings:
    gain: float = 1.0
    count: int = 0


@CASES
@given(value=st.one_of(st.integers(), st.integers(-(10**400), 10**400), st.sampled_from([10**309, -(10**309)])))
def test_any_integer_for_a_float_key_is_that_float_or_an_error_naming_the_key(value: int) -> None:
    if abs(value) <= sys.float_info.max:
        assert config_from_dict(_Settings, {"gain": value}).gain == float(value)
    else:
        with pytest.raises(ConfigError, match="gain"):
            config_from_dict(_Settings, {"gain": value})


def _pairs(n: int, size: int = 16) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(n)
    return tuple(rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8) for _ in range(2))  # type: ignore[return-value]


@pytest.mark.parametrize("n", [0, 1])
def test_psnr_statistics_of_fewer_than_two_pairs_say_why(n: int) -> None:
    truth, estimate = _pairs(n)
    for statistics in (psnr_statistics, ssim_statistics):
        with pytest.raises(ModelConfigError, match="at least 2 pairs"):
            statistics(truth, estimate)


def test_psnr_statistics_of_images_without_pixels_or_of_another_type_are_refused() -> None:
    empty = np.zeros((2, 0, 16, 3), np.uint8)
    with pytest.raises(ModelConfigError, match="at least one pixel"):
        psnr_statistics(empty, empty)
    truth, estimate = _pairs(3)
    with pytest.raises(ModelConfigError, match="uint8"):
        psnr_statistics(truth.astype(np.float64), estimate.astype(np.float64))


def test_psnr_statistics_of_identical_and_of_two_pairs_are_finite() -> None:
    truth, estimate = _pairs(2)
    same = psnr_statistics(truth, truth)
    assert same["psnr_db_model_mean"] == 100.0 and all(np.isfinite(v) for v in same.values())
    assert all(np.isfinite(v) for v in psnr_statistics(truth, estimate).values())


def test_zero_analytic_contacts_are_zero_maps_and_absurd_sizes_are_refused() -> None:
    assert analytic_contact_maps(0, 0, 0.004).shape == (0, 100, 100)
    assert analytic_contact_maps(1, 0, 0.004, size=1).shape == (1, 1, 1)
    for arguments in (
        {"count": -1},
        {"count": 2.0},
        {"size": 0},
        {"size": MAX_CONTACT_MAP_SIZE + 1},
        {"count": 10**6},
        {"crop_mm": math.inf},
        {"y_far_m": math.nan},
    ):
        with pytest.raises(DatasetError, match=next(iter(arguments)).split("_")[0]):
            analytic_contact_maps(**{"count": 1, "seed": 0, "y_far_m": 0.004, **arguments})
    for oversample in (0, MAX_OVERSAMPLE + 1, 1.5):
        with pytest.raises(DatasetError, match="oversample"):
            depth_map_from_surface(lambda x, z: x + z, 8, 24.0, 0.004, oversample)  # type: ignore[arg-type]


# --- the stated bounds under a memory cap ----------------------------------------------------


def test_the_stated_bounds_hold_under_a_1_gib_cap() -> None:
    """In a fresh interpreter capped at 1 GiB of address space above its imports, every absurd
    parameter of the issue is refused before it allocates, and each bound itself (the largest
    pose blur on a 256 x 256 prior, the largest ball's cloud, the densest grid) answers."""
    script = textwrap.dedent(f"""
        import math, resource, warnings
        import numpy as np
        from models.errors import ModelConfigError
        from models.prior import MAX_POSE_SIGMA_MM, PhysicsPrior, PriorSpec
        from models.real_presses import BALL_RADIUS_RANGE_MM, ball_cloud_m
        from perception.density import MAX_POINTS_PER_CM3, downsample_to_density
        from perception.errors import PerceptionError
        from sim.gelsight import GelSightRenderError, render_depth_maps
        from dataset.synth import analytic_contact_maps
        from dataset.records import DatasetError
        warnings.simplefilter("error")
        small = PhysicsPrior(PriorSpec({SCENE!r}, {CROP_M!r}), 32)
        large = PhysicsPrior(PriorSpec({SCENE!r}, {CROP_M!r}), 256)
        with open("/proc/self/status") as status:
            vm = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (vm + (1 << 30), vm + (1 << 30)))
        refused = 0
        cases = [
            (ModelConfigError, lambda: small.images(np.full((1, 32, 32), 0.004, np.float32), 1e6)),
            (ModelConfigError, lambda: small.images(np.full((1, 32, 32), 0.004, np.float32), 1e5)),
            (ModelConfigError, lambda: ball_cloud_m(1000.0)),
            (ModelConfigError, lambda: ball_cloud_m(1e300)),
            (PerceptionError, lambda: downsample_to_density(np.random.default_rng(0).random((1000, 3)), 1e30)),
            (GelSightRenderError, lambda: render_depth_maps(
                small.renderer, np.broadcast_to(np.zeros((1, 1, 1)), (10 ** 8, 1, 1)), (0.024, 0.019))),
            (DatasetError, lambda: analytic_contact_maps(10 ** 6, 0, 0.004)),
        ]
        for error, case in cases:
            try:
                case()
            except error:
                refused += 1
        maps = np.full((1, 256, 256), 0.004, np.float32)
        maps[0, 100:140, 100:140] = -0.0005
        assert large.images(maps, MAX_POSE_SIGMA_MM).shape == (1, 256, 256, 3)
        assert len(ball_cloud_m(BALL_RADIUS_RANGE_MM[1])) > 750_000
        cloud = np.random.default_rng(0).uniform(-0.5, 0.5, (200_000, 3))  # no two in one voxel
        assert len(downsample_to_density(cloud, MAX_POINTS_PER_CM3)) == len(cloud)
        print("refused", refused, "of", len(cases))
    """)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=REPO, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "refused 7 of 7" in done.stdout, done.stdout[-2000:]
