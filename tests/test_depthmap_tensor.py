"""The depth-map cut on a torch device (perception.depthmap_tensor) against the compiled CPU
pass: the same maps, occupancy and point counts, bit for bit, on the CPU here and on CUDA where
a GPU is present, by either rule (the nearest point: depth_maps_on_device; the surface: each
bin's front-most point, front_points_on_device, then perception.surface)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_perception_depthmap import GEOMETRY, METHODS, random_pose

import perception.depthmap_tensor as depthmap_tensor
from perception.depthmap import DepthMapParams, contact_depth_maps, crop_bounds
from perception.depthmap_tensor import points_on_device
from perception.errors import DepthMapError
from perception.pointcloud import VoxelIndex

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _both(index, model_to_world, gels, params, device, **kwargs):
    on_cpu = contact_depth_maps(index, model_to_world, gels, GEOMETRY, params, allow_empty=True, **kwargs)
    on_device = contact_depth_maps(
        index,
        model_to_world,
        gels,
        GEOMETRY,
        params,
        allow_empty=True,
        device_points=points_on_device(index.points_m, device),
        **kwargs,
    )
    return on_cpu, on_device


def _assert_same(a, b) -> None:
    np.testing.assert_array_equal(a.depth_maps_m, b.depth_maps_m)
    np.testing.assert_array_equal(a.occupied, b.occupied)
    np.testing.assert_array_equal(a.point_counts, b.point_counts)
    assert a.crop_m == b.crop_m and a.y_range_m == b.y_range_m


@pytest.mark.parametrize("device", DEVICES)
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    regions=st.integers(1, 8),
    offset=st.sampled_from([0.0, 1e3, -2e4]),
    dtype=st.sampled_from([np.float32, np.float64]),
    cell=st.sampled_from([0.001, 0.005, 0.05]),
    shape=st.tuples(st.integers(1, 40), st.integers(1, 40)),
    fill=st.sampled_from([0, 1, 3, 5, 8]),
    method=st.sampled_from(METHODS),
)
def test_property_device_cut_equals_the_compiled_pass(device, seed, regions, offset, dtype, cell, shape, fill, method):
    """Gels anywhere around a cloud of a few mm, a km from the origin or at it, any bins, float32
    or float64 points, either rule: every map, bin and count the same as the compiled pass's."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.015, 0.015, (3000, 3)).astype(dtype)
    model_to_world = random_pose(rng, offset)
    gels = np.stack([model_to_world @ random_pose(rng, 0.0) for _ in range(regions)])
    params = DepthMapParams(shape=shape, fill_gaps_min_neighbours=fill, method=method)
    _assert_same(*_both(VoxelIndex(points, cell), model_to_world, gels, params, device))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("device", DEVICES)
def test_points_on_bin_edges_and_crop_faces_fall_as_the_compiled_pass_puts_them(device, method):
    """A point exactly on every bin edge, each at its own depth from the near face to the far one
    (so the bin a point falls in shows in the map), and points just outside the crop's faces, with
    the gel at the model's origin: the edge rule, not a rounding of it."""
    params = DepthMapParams(shape=(7, 9), fill_gaps_min_neighbours=0, method=method)
    half_x, half_z, y_near, y_far = crop_bounds(GEOMETRY, params)
    x = np.linspace(-half_x, half_x, params.shape[1] + 1)
    z = np.linspace(-half_z, half_z, params.shape[0] + 1)
    xx, zz = (a.ravel() for a in np.meshgrid(x, z, indexing="ij"))
    depths = np.random.default_rng(0).permutation(np.linspace(y_near, y_far, xx.size))
    outside = [
        [0.0, np.nextafter(y_near, -np.inf), 0.0],
        [0.0, np.nextafter(y_far, np.inf), 0.0],
        [np.nextafter(half_x, np.inf), y_near, 0.0],
        [0.0, y_near, np.nextafter(-half_z, -np.inf)],
    ]
    index = VoxelIndex(np.concatenate([np.column_stack([xx, depths, zz]), outside]))
    on_cpu, on_device = _both(index, np.eye(4), np.eye(4)[None], params, device)
    _assert_same(on_cpu, on_device)
    assert on_cpu.point_counts[0] == xx.size  # every edge point inside, nothing outside


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("device", DEVICES)
def test_a_cut_split_into_chunks_gives_the_same_maps(device, method, monkeypatch):
    """Runs spread over many chunks (a region's points in several): the minimum, the front-most
    points and the counts gather across them."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.012, 0.012, (20000, 3))
    gels = np.stack([random_pose(rng, 0.0) for _ in range(5)])
    index = VoxelIndex(points, 0.002)
    params = DepthMapParams(method=method)
    on_cpu, whole = _both(index, np.eye(4), gels, params, device)
    _assert_same(on_cpu, whole)
    monkeypatch.setattr(depthmap_tensor, "CHUNK_POINTS", 37)
    _assert_same(whole, _both(index, np.eye(4), gels, params, device)[1])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("device", DEVICES)
def test_a_gel_that_reaches_nothing_and_a_cloud_of_no_point(device, method):
    params = DepthMapParams(method=method)
    away = np.eye(4)
    away[1, 3] = -1.0
    index = VoxelIndex(np.random.default_rng(0).uniform(-0.005, 0.005, (1000, 3)))
    on_cpu, on_device = _both(index, np.eye(4), np.stack([np.eye(4), away]), params, device)
    _assert_same(on_cpu, on_device)
    assert on_device.point_counts[1] == 0 and not on_device.occupied[1].any()
    np.testing.assert_array_equal(on_device.depth_maps_m[1], np.float32(on_device.y_range_m[1]))
    with pytest.raises(DepthMapError, match="region 1: no model point"):
        contact_depth_maps(
            index,
            np.eye(4),
            np.stack([np.eye(4), away]),
            GEOMETRY,
            params,
            device_points=points_on_device(index.points_m, device),
        )
    empty = VoxelIndex(np.zeros((0, 3)))
    _assert_same(*_both(empty, np.eye(4), np.eye(4)[None], params, device))


def test_points_of_another_cloud_are_refused():
    index = VoxelIndex(np.zeros((10, 3)))
    with pytest.raises(DepthMapError, match=r"device_points \(9, 3\) are not the index's \(10, 3\)"):
        contact_depth_maps(
            index, np.eye(4), np.eye(4)[None], GEOMETRY, DepthMapParams(), device_points=torch.zeros(9, 3)
        )


def test_read_only_points_as_a_message_carries_them_are_copied_without_a_warning():
    points = np.arange(12, dtype=np.float32).reshape(4, 3)
    points.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        on_device = points_on_device(points, "cpu")
    assert on_device.dtype == torch.float32
    np.testing.assert_array_equal(on_device.numpy(), points)
