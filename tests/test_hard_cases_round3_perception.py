"""Hard cases of issue 52 in perception: a depth-map cut on a torch device takes only a copy of
the index's points in the index's own dtype (so it cuts the NumPy path's maps, bit for bit), and
planar ICP reports the fitness and RMSE of the pose it returns, not of the pose before its last
step (the sweep and the turn judge rank poses by them)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from test_perception_depthmap import GEOMETRY, random_pose
from test_perception_planar_icp import box_surface, seen

from perception.depthmap import DepthMapParams, contact_depth_maps, plan_contact_cut
from perception.depthmap_tensor import points_on_device
from perception.errors import DepthMapError
from perception.planar_icp import (
    PlanarPose,
    planar_icp,
    planar_icp_to_plane,
    sweep_yaws,
    turned_about_centre,
    upright_refined,
)
from perception.pointcloud import VoxelIndex

TORCH_DTYPES = [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.int32, torch.int64]


def _cloud(seed: int, dtype: type) -> tuple[VoxelIndex, np.ndarray]:
    """A few mm of points around the origin, and gels posed anywhere in them."""
    rng = np.random.default_rng(seed)
    index = VoxelIndex(rng.uniform(-0.015, 0.015, (2000, 3)).astype(dtype), 0.005)
    return index, np.stack([random_pose(rng, 0.0) for _ in range(4)])


@settings(derandomize=True, deadline=None, max_examples=30)
@given(
    seed=st.integers(0, 2**32 - 1),
    index_dtype=st.sampled_from([np.float32, np.float64]),
    device_dtype=st.sampled_from(TORCH_DTYPES),
)
def test_property_a_device_copy_cuts_the_numpy_maps_or_is_refused(seed, index_dtype, device_dtype):
    """Any dtype of device points: refused, naming the argument and both dtypes, unless it is the
    index's own; then every map, bin and count is the NumPy cut's."""
    index, gels = _cloud(seed, index_dtype)
    device_points = torch.from_numpy(index.points_m.copy()).to(device_dtype)
    on_cpu = contact_depth_maps(index, np.eye(4), gels, GEOMETRY, DepthMapParams(), allow_empty=True)
    if device_points.dtype != points_on_device(index.points_m, "cpu").dtype:
        with pytest.raises(DepthMapError, match=rf"device_points are {device_dtype}, not the index's"):
            contact_depth_maps(
                index, np.eye(4), gels, GEOMETRY, DepthMapParams(), allow_empty=True, device_points=device_points
            )
        return
    on_device = contact_depth_maps(
        index, np.eye(4), gels, GEOMETRY, DepthMapParams(), allow_empty=True, device_points=device_points
    )
    np.testing.assert_array_equal(on_cpu.depth_maps_m, on_device.depth_maps_m)
    np.testing.assert_array_equal(on_cpu.occupied, on_device.occupied)
    np.testing.assert_array_equal(on_cpu.point_counts, on_device.point_counts)


@pytest.mark.parametrize(
    ("index_dtype", "device_dtype"),
    [(np.float64, torch.float16), (np.float64, torch.float32), (np.float32, torch.float64)],
)
def test_the_probes_copies_are_refused_where_the_cut_is_planned(index_dtype, device_dtype):
    """The probe's float16 copy (maps 3.5-4 mm off) and float32 copy of float64 points (not bit
    for bit), and a float64 copy of float32 points: refused when the cut is planned, before any
    region is cut, the message naming the way to copy them."""
    index, gels = _cloud(0, index_dtype)
    device_points = torch.from_numpy(index.points_m.copy()).to(device_dtype)
    expected = "torch.float32" if index_dtype == np.float32 else "torch.float64"
    with pytest.raises(
        DepthMapError, match=rf"device_points are {device_dtype}, not .* {expected}: .*points_on_device"
    ):
        plan_contact_cut(index, np.eye(4), gels, GEOMETRY, DepthMapParams(), device_points=device_points)


def test_device_points_that_are_not_a_tensor_are_refused():
    index, gels = _cloud(1, np.float64)
    with pytest.raises(DepthMapError, match=r"device_points must be a torch.Tensor .*, got ndarray"):
        plan_contact_cut(
            index,
            np.eye(4),
            gels,
            GEOMETRY,
            DepthMapParams(),
            device_points=index.points_m,  # type: ignore[arg-type]
        )


def fresh_figures(observed_m: np.ndarray, model_m: np.ndarray, pose: PlanarPose, z_m: float, distance_m: float):
    """(fitness, RMSE m) of the model at ``pose`` against the observed points, worked out anew:
    the model moved into the observed frame, each observed point paired with its nearest model
    point within ``distance_m``."""
    yaw, x_m, y_m = pose
    c, s = np.cos(yaw), np.sin(yaw)
    moved = model_m @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + [x_m, y_m, z_m]
    gap_m, _ = cKDTree(moved).query(observed_m, distance_upper_bound=distance_m)
    paired = np.isfinite(gap_m)
    return float(paired.mean()), float(np.sqrt(np.mean(gap_m[paired] ** 2))) if paired.any() else np.inf


def _pose_of(model_to_world: np.ndarray) -> PlanarPose:
    return float(np.arctan2(model_to_world[1, 0], model_to_world[0, 0])), *map(float, model_to_world[:2, 3])


MODEL, NORMALS = box_surface(0.008)
TREE = cKDTree(MODEL)
truths = st.tuples(st.floats(-np.pi, np.pi), st.floats(-0.1, 0.1), st.floats(-0.1, 0.1))
offsets = st.tuples(st.floats(-0.3, 0.3), st.floats(-0.02, 0.02), st.floats(-0.02, 0.02))


def _start(truth: PlanarPose, offset: PlanarPose) -> PlanarPose:
    return (truth[0] + offset[0], truth[1] + offset[1], truth[2] + offset[2])


@settings(derandomize=True, deadline=None, max_examples=25)
@given(
    truth=truths,
    offset=offsets,
    iterations=st.integers(0, 4),
    distances=st.sampled_from([(0.016, 0.008), (0.008,), (0.03,)]),
)
def test_property_planar_icp_reports_the_figures_of_the_pose_it_returns(truth, offset, iterations, distances):
    """The box seen at a known pose, ICP started off it and stopped after a few steps (while it
    still moves, or at once): fitness and RMSE those of the returned pose at the last distance."""
    observed = seen(truth, noise_m=0.001, seed=0)
    pose, fitness, rmse = planar_icp(observed, TREE, MODEL, _start(truth, offset), 0.0, distances, iterations)
    assert (fitness, rmse) == pytest.approx(fresh_figures(observed, MODEL, pose, 0.0, distances[-1]), rel=1e-9)


@settings(derandomize=True, deadline=None, max_examples=25)
@given(truth=truths, offset=offsets, iterations=st.integers(0, 4))
def test_property_point_to_plane_and_turns_report_the_figures_of_the_pose_they_return(truth, offset, iterations):
    """The point-to-plane step and the upright search's last step (and so the turn judge's turned
    poses): fitness and RMSE of the pose returned, however few the steps."""
    observed = seen(truth, noise_m=0.001, seed=1)
    start = _start(truth, offset)
    pose, fitness, rmse = planar_icp_to_plane(observed, TREE, MODEL, NORMALS, start, 0.0, 0.008, iterations)
    assert (fitness, rmse) == pytest.approx(fresh_figures(observed, MODEL, pose, 0.0, 0.008), rel=1e-9)
    model_to_world, fitness, rmse = upright_refined(observed, TREE, MODEL, NORMALS, start, 0.0, 0.008, iterations)
    assert (fitness, rmse) == pytest.approx(
        fresh_figures(observed, MODEL, _pose_of(model_to_world), 0.0, 0.008), rel=1e-9
    )
    turned, fitness, rmse = turned_about_centre(observed, TREE, MODEL, NORMALS, model_to_world, np.pi, 0.008, 2)
    assert (fitness, rmse) == pytest.approx(fresh_figures(observed, MODEL, _pose_of(turned), 0.0, 0.008), rel=1e-9)


def test_each_sweep_row_ranks_its_own_pose():
    """A sweep of one ICP step a yaw (each still moving): every row's fitness and RMSE are those
    of the pose in the row, so ranking the rows ranks the poses."""
    truth = (0.7, 0.03, -0.02)
    observed = seen(truth, noise_m=0.001, seed=2)
    rows = sweep_yaws(observed, TREE, MODEL, MODEL[:, :2].mean(axis=0), 0.0, 12, (0.016,), 1)
    for fitness, minus_rmse, pose in rows:
        assert (fitness, -minus_rmse) == pytest.approx(fresh_figures(observed, MODEL, pose, 0.0, 0.016), rel=1e-9)


def test_from_the_truth_itself_no_step_reports_the_truths_fit():
    """No step taken (no iterations): the figures of the start, here the truth, not zeros."""
    truth = (0.3, -0.05, 0.04)
    observed = seen(truth, noise_m=0.0, seed=3)
    pose, fitness, rmse = planar_icp(observed, TREE, MODEL, truth, 0.0, (0.008,), 0)
    assert pose == truth
    assert (fitness, rmse) == pytest.approx(fresh_figures(observed, MODEL, truth, 0.0, 0.008), rel=1e-9)
    assert fitness > 0.99


def test_planar_icp_without_a_distance_is_refused_naming_it():
    """No distance leaves no pairing to judge the returned pose by (it reported zeros before)."""
    with pytest.raises(ValueError, match="distances_m must hold at least one"):
        planar_icp(MODEL, TREE, MODEL, (0.0, 0.0, 0.0), 0.0, (), 5)
