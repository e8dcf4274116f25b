"""Surface depth-maps (perception.surface, ``DepthMapParams.method="surface"``, the default): each
bin holds the object's surface at the bin's centre, along the gel normal.

Checked against analytic truth (tilted planes, spheres, cylinders, a step) and against Open3D
ray casting of a mesh; against the nearest-point rule, which errs by about half a bin times the
slope; under voxel thinning; for what it must not invent (beyond a cloud's extent, a ring's hole,
a cloud too sparse for a plane, an open mesh's hole, a degenerate triangle's surface); and for the
same maps on every path (one map, the indexed batch on 1 or 2 threads or cut in runs, the torch
pass).

Every cloud lies in the gel frame (model and gel poses the identity) unless a test says otherwise.
The measured figures quoted next to the tolerances are those of the 100 x 100 default map
(bins 0.226 mm along x, 0.289 mm along z).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial.transform import Rotation

from perception.binning import bin_centres, bin_edges, cut_kernel, min_y_per_bin
from perception.density import downsample_to_density
from perception.depthmap import (
    DepthMapParams,
    contact_depth_map,
    contact_depth_maps,
    crop_bounds,
    plan_contact_cut,
)
from perception.depthmap_tensor import front_points_on_device, points_on_device
from perception.errors import DepthMapError, OutOfReachError
from perception.pointcloud import VoxelIndex
from perception.registration import RegistrationError, sample_model_cloud
from perception.surface import DEPTH_MAP_METHODS
from workcell.kinematics import GripperGeometry

GEOMETRY = GripperGeometry()
SURFACE = DepthMapParams()  # the default rule, 100 x 100 bins, 2 mm margin, y in +-2 mm
NEAREST = DepthMapParams(method="nearest_point")
HALF_X, HALF_Z, Y_NEAR, Y_FAR = crop_bounds(GEOMETRY, SURFACE)
ROWS, COLS = SURFACE.shape
BIN_X, BIN_Z = 2 * HALF_X / COLS, 2 * HALF_Z / ROWS  # 0.226 mm, 0.289 mm
# Bin centres, (rows, cols) each: the gel x and z where the surface map is read.
CX, CZ = np.meshgrid(bin_centres(HALF_X, COLS), bin_centres(HALF_Z, ROWS))
STEEPEST = np.tan(np.radians(60.0))  # the curved surfaces are compared where they are at most 60 deg steep


def check_curved(surface, nearest, truth, slope, radius):
    """A curved surface of ``radius`` read at the bin centres where it is at most 60 deg steep and
    inside the y range: all known; within 20 um up to 45 deg; within 4e-7 m^2 / radius up to 60
    deg (a plane through the samples around a centre errs by the curvature, steeper the more:
    measured at most 2.4e-7 m^2 / radius, 38 um on a 6 mm cylinder at 60 deg); median under
    12 um and under a third of the nearest point's (measured at most 8 um, 8-20x less)."""
    seen = in_range(truth) & (slope <= STEEPEST)
    # A sampling gap where the surface leaves the y range has samples on one side only: left empty.
    assert surface.occupied[seen].mean() >= 0.995
    seen &= surface.occupied
    error = error_m(surface, truth)
    assert error[seen & (slope <= 1.0)].max() < 20e-6
    assert error[seen].max() < 4e-7 / radius
    assert np.median(error[seen]) < 12e-6
    assert np.median(error[seen]) < np.median(error_m(nearest, truth)[seen]) / 3


DENSE_M = 0.07e-3  # spacing of the "dense" random samples: ~13 points a bin


def both_maps(points, model_to_world=np.eye(4), params=SURFACE):
    """The surface map and the nearest-point map of one cloud (ContactPatch each)."""
    nearest = dataclasses.replace(params, method="nearest_point")
    return (
        contact_depth_map(points, model_to_world, np.eye(4), GEOMETRY, params),
        contact_depth_map(points, model_to_world, np.eye(4), GEOMETRY, nearest),
    )


def error_m(patch, truth):
    return np.abs(patch.depth_map_m.astype(np.float64) - truth)


def holds_a_point(points):
    """(rows, cols) bool: the default map's bins that hold a point of the cloud (gel frame)."""
    y = points[:, 1]
    inside = (y >= Y_NEAR) & (y <= Y_FAR) & (np.abs(points[:, 0]) <= HALF_X) & (np.abs(points[:, 2]) <= HALF_Z)
    return min_y_per_bin(points[inside, 0], points[inside, 2], y[inside], HALF_X, HALF_Z, (ROWS, COLS))[1]


def uniform_xz(rng, count, x_range=(-HALF_X, HALF_X), z_range=(-HALF_Z, HALF_Z)):
    return rng.uniform(*x_range, count), rng.uniform(*z_range, count)


# --- analytic surfaces in the gel frame ---------------------------------------------------------


def tilted_plane(rng, slope_x, slope_z, y0, spacing=DENSE_M):
    """Random points on y = y0 + slope_x x + slope_z z over the crop (uniform by area), and the
    plane's y at the bin centres."""
    stretch = np.sqrt(1 + slope_x**2 + slope_z**2)
    x, z = uniform_xz(rng, int(4 * HALF_X * HALF_Z * stretch / spacing**2))
    y = y0 + slope_x * x + slope_z * z
    near = (y > Y_NEAR - 0.0005) & (y < Y_FAR + 0.0005)  # the rest is cropped anyway
    return np.column_stack([x, y, z])[near], y0 + slope_x * CX + slope_z * CZ


def sphere(rng, radius, centre, spacing=DENSE_M):
    """Random points on the cap of a sphere facing the gel, up to just beyond y_far (uniform by
    area: Archimedes, y uniform), with the sphere's y at the bin centres (+inf off it) and its
    slope there."""
    cx, cy, cz = centre
    height = min(2 * radius, Y_FAR + 0.0005 - (cy - radius))
    count = int(2 * np.pi * radius * height / spacing**2)
    y = rng.uniform(cy - radius, cy - radius + height, count)
    ring = np.sqrt(np.maximum(radius**2 - (y - cy) ** 2, 0.0))
    phi = rng.uniform(0, 2 * np.pi, count)
    points = np.column_stack([cx + ring * np.cos(phi), y, cz + ring * np.sin(phi)])
    points = points[(np.abs(points[:, 0]) < HALF_X + 0.0005) & (np.abs(points[:, 2]) < HALF_Z + 0.0005)]
    d2 = (CX - cx) ** 2 + (CZ - cz) ** 2
    below = radius**2 - d2
    truth = np.where(below > 0, cy - np.sqrt(np.maximum(below, 0.0)), np.inf)
    slope = np.sqrt(d2 / np.maximum(below, 1e-30))
    return points, truth, slope


def cylinder(rng, radius, centre_x, centre_y, azimuth, spacing=DENSE_M):
    """Random points on a cylinder whose axis lies in the gel's x-z plane (``azimuth`` from gel
    z), the side facing the gel up to just beyond y_far; its y and slope at the bin centres."""
    axis = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
    across = np.array([np.cos(azimuth), 0.0, -np.sin(azimuth)])
    height = min(2 * radius, Y_FAR + 0.0005 - (centre_y - radius))
    arc = np.arccos(np.clip((radius - height) / radius, -1.0, 1.0))
    length = 2 * np.hypot(HALF_X + abs(centre_x), HALF_Z) + 0.002  # the whole crop, axis anywhere
    count = int(2 * arc * radius * length / spacing**2)
    theta, along = rng.uniform(-arc, arc, count), rng.uniform(-length / 2, length / 2, count)
    points = (
        np.array([centre_x, centre_y, 0.0])
        + along[:, None] * axis
        + radius * (np.sin(theta)[:, None] * across - np.cos(theta)[:, None] * np.array([0.0, 1.0, 0.0]))
    )
    points = points[(np.abs(points[:, 0]) < HALF_X + 0.0005) & (np.abs(points[:, 2]) < HALF_Z + 0.0005)]
    off = (CX - centre_x) * across[0] + CZ * across[2]
    below = radius**2 - off**2
    truth = np.where(below > 0, centre_y - np.sqrt(np.maximum(below, 0.0)), np.inf)
    return points, truth, np.abs(off) / np.sqrt(np.maximum(below, 1e-30))


def in_range(truth):
    return (truth >= Y_NEAR) & (truth <= Y_FAR)


def test_the_default_method_is_the_surface_and_the_two_rules_are_named():
    assert DepthMapParams().method == "surface"
    assert set(DEPTH_MAP_METHODS) == {"surface", "nearest_point"}


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    tilt_deg=st.floats(0.0, 60.0),
    azimuth=st.floats(0.0, 2 * np.pi),
    y0=st.floats(-0.0015, 0.0015),
)
def test_property_a_tilted_plane_is_read_exactly_where_nearest_point_errs_half_a_bin_times_the_slope(
    seed, tilt_deg, azimuth, y0
):
    """A plane up to 60 deg steep: the surface map is the plane at every bin centre whose plane
    lies in the crop's y range (measured: < 0.01 um, float32 rounding), all of them known, save
    an empty bin at the range's ends whose footprint the end cuts: the plane's part in the crop
    there is a sliver beyond its centre, which the rule does not extrapolate to (found by
    hypothesis: a bin 5 um inside y_far); the nearest point lies toward the bin's lowest corner,
    about half a bin times the slope off (measured 21 um at 10 deg, 72 at 30, 131 at 45, 237 at
    60: median)."""
    rng = np.random.default_rng(seed)
    slope = np.tan(np.radians(tilt_deg))
    slope_x, slope_z = slope * np.cos(azimuth), slope * np.sin(azimuth)
    points, truth = tilted_plane(rng, slope_x, slope_z, y0)
    seen = in_range(truth)
    if not seen.any():
        return
    surface, nearest = both_maps(points)
    corner = 0.5 * (abs(slope_x) * BIN_X + abs(slope_z) * BIN_Z)  # the plane's drop to a bin's lowest corner
    whole = (truth >= Y_NEAR + corner) & (truth <= Y_FAR - corner)  # the bin's footprint in the range
    answered = seen & (whole | holds_a_point(points))
    assert surface.occupied[answered].all()
    assert error_m(surface, truth)[answered].max() <= 1e-6
    nearest_error = error_m(nearest, truth)[seen & nearest.occupied]
    assert np.median(nearest_error) <= corner + 1e-9
    if tilt_deg >= 5.0:
        assert np.median(nearest_error) >= 0.5 * corner
        assert np.median(error_m(surface, truth)[seen]) < np.median(nearest_error) / 5


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    radius=st.floats(0.006, 0.03),
    centre_xz=st.tuples(st.floats(-0.003, 0.003), st.floats(-0.003, 0.003)),
    lowest=st.floats(-0.0015, 0.0005),
)
def test_property_a_sphere_is_read_within_microns_of_its_surface(seed, radius, centre_xz, lowest):
    """A sphere of 6-30 mm radius, its lowest point 1.5 mm into the gel to 0.5 mm in front of it,
    as :func:`check_curved` (measured up to 45 deg: at most 13 um at 6 mm radius, 9 at 10, 3 at
    20; median 2-8 um where the nearest point's is 20-100)."""
    rng = np.random.default_rng(seed)
    points, truth, slope = sphere(rng, radius, (centre_xz[0], lowest + radius, centre_xz[1]))
    check_curved(*both_maps(points), truth, slope, radius)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    radius=st.floats(0.006, 0.03),
    centre_x=st.floats(-0.003, 0.003),
    lowest=st.floats(-0.0015, 0.0005),
    azimuth=st.floats(0.0, np.pi),
)
def test_property_a_cylinder_is_read_within_microns_of_its_surface(seed, radius, centre_x, lowest, azimuth):
    """A cylinder of 6-30 mm radius lying along any direction of the gel face, as
    :func:`check_curved` (measured up to 45 deg: at most 16 um at 6 mm radius; median at most
    4 um where the nearest point's is 45 and more)."""
    rng = np.random.default_rng(seed)
    points, truth, slope = cylinder(rng, radius, centre_x, lowest + radius, azimuth)
    check_curved(*both_maps(points), truth, slope, radius)


def small_ball(seed, radius, depth_fraction, centre_xz):
    """A whole ball (its far side inside the y range) sampled by area at the model clouds' 0.1 mm
    (models.real_presses.ball_cloud_m: ~4.5 points a bin, so some bins hold none of its front),
    pressed ``depth_fraction`` of its radius past the gel; its y and slope at the bin centres."""
    from models.real_presses import ball_cloud_m

    centre = np.array([centre_xz[0], radius * (1.0 - depth_fraction), centre_xz[1]])
    points = ball_cloud_m(radius * 1e3, 0.1e-3, seed) + centre
    d2 = (CX - centre[0]) ** 2 + (CZ - centre[2]) ** 2
    below = radius**2 - d2
    truth = np.where(below > 0, centre[1] - np.sqrt(np.maximum(below, 0.0)), np.inf)
    return points, truth, np.sqrt(d2 / np.maximum(below, 1e-30)), centre


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    radius=st.floats(0.0015, 0.003),
    depth=st.floats(0.0005, 0.0018),
    centre_xz=st.tuples(st.floats(-0.003, 0.003), st.floats(-0.003, 0.003)),
)
# Found by this test: at 43 deg on the smallest ball the quadric's correction of the chord is 80
# um, over the quarter bin (72 um) the correction was once held to; the plane stayed 71 um off.
@example(seed=48, radius=0.0015, depth=0.0010615857539590934, centre_xz=(0.0013903754005558885, 0.0))
def test_property_a_small_ball_is_read_within_microns_where_it_is_at_most_45_deg_steep(seed, radius, depth, centre_xz):
    """A 1.5-3 mm ball (the real presses' is 2 mm) pressed 0.5-1.8 mm (its lowest point inside
    the y range), up to its equator, at the model clouds' spacing: where it is at
    most 45 deg steep, the median bin within 3 um and none off by 15 (measured over 60 balls:
    median at most 1.2 um, the worst bin 2-9 um; a plane through the samples read the chord,
    median up to 32 um, the worst bin 31-70 um, and one bin whose front held no point read the
    far side, 3.4 mm off)."""
    points, truth, slope, _ = small_ball(seed, radius, min(depth / radius, 1.0), centre_xz)
    surface, nearest = both_maps(points)
    seen = in_range(truth) & (slope <= 1.0)
    error = error_m(surface, truth)[seen]
    assert np.median(error) < 3e-6 and error.max() < 15e-6
    assert np.median(error) < np.median(error_m(nearest, truth)[seen]) / 10


def test_a_bin_whose_front_holds_no_point_reads_the_front_not_the_far_side():
    """A 2 mm ball pressed to its equator, every front point taken out of one bin inside its
    contact: that bin holds a point of the ball's far side, and reads the front surface from the
    samples around it (the far side is 4 mm behind)."""
    points, truth, _, centre = small_ball(3, 0.002, 1.0, (0.0003, -0.0002))
    row, col = np.unravel_index(np.argmin(np.abs(CX - centre[0] - 0.0005) + np.abs(CZ - centre[2])), CX.shape)
    x_edges, z_edges = bin_edges(HALF_X, COLS), bin_edges(HALF_Z, ROWS)
    in_bin = (
        (points[:, 0] >= x_edges[col])
        & (points[:, 0] < x_edges[col + 1])
        & (points[:, 2] >= z_edges[row])
        & (points[:, 2] < z_edges[row + 1])
    )
    assert (in_bin & (points[:, 1] > centre[1])).any()  # the far side shows through the bin
    points = points[~(in_bin & (points[:, 1] < centre[1]))]
    surface, _ = both_maps(points)
    assert surface.occupied[row, col]
    assert abs(surface.depth_map_m[row, col] - truth[row, col]) < 5e-6


# --- against Open3D's ray casting of a mesh ------------------------------------------------------


def ray_cast(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """From each bin centre, 1 mm in front of the crop, along the gel's +y: the y of the first
    hit (+inf: none) and the triangle hit (-1: none), (rows, cols) each."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    start = Y_NEAR - 0.001
    rays = np.zeros((CX.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 4] = CX.ravel(), start, CZ.ravel(), 1.0
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    y = start + hits["t_hit"].numpy().astype(np.float64)
    return y.reshape(CX.shape), hits["primitive_ids"].numpy().astype(np.int64).reshape(CX.shape)


def map_truth(ray_y):
    """What a depth-map should hold where a ray hits at ``ray_y``: the hit clamped to the crop's y
    range, y_far where nothing is hit."""
    return np.clip(np.where(np.isfinite(ray_y), ray_y, Y_FAR), Y_NEAR, Y_FAR)


BOX_SIZE_M = (0.008, 0.006, 0.010)


def _box_cloud(directory: str) -> np.ndarray:
    """A 8 x 6 x 10 mm box, its near face (y = 0) centred on the gel, sampled at 0.05 mm as the
    pipeline samples a model (perception.registration.sample_model_cloud)."""
    path = Path(directory) / "box.ply"
    o3d.io.write_triangle_mesh(str(path), _box_mesh())
    return sample_model_cloud(path, 0.05e-3, seed=0).points_m


def _box_mesh(pose=np.eye(4)):
    mesh = o3d.geometry.TriangleMesh.create_box(*BOX_SIZE_M)
    mesh.translate([-0.5 * BOX_SIZE_M[0], 0.0, -0.5 * BOX_SIZE_M[2]])
    return mesh.transform(pose)


@pytest.fixture(scope="module")
def box_cloud(tmp_path_factory) -> np.ndarray:
    return _box_cloud(str(tmp_path_factory.mktemp("box")))


def box_pose(rotvec, offset=(0.0005, -0.0005, -0.0003)):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = offset
    return pose


def away_from_edges(face, ray_y, reach=2):
    """Bins whose (2 reach + 1)^2 neighbourhood all hit the same face, inside the y range."""
    same = np.ones(face.shape, bool)
    padded = np.pad(face, reach, constant_values=-2)
    for dr in range(2 * reach + 1):
        for dc in range(2 * reach + 1):
            same &= padded[dr : dr + face.shape[0], dc : dc + face.shape[1]] == face
    return same & (face >= 0) & (ray_y > Y_NEAR) & (ray_y < Y_FAR)


# Tilted about the gel's x, its z, both, and turned about its normal as well.
BOX_ROTATIONS = [(0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (0.0, 0.0, 0.6), (0.3, 0.0, 0.2), (0.2, 0.3, -0.4), (0.0, 0.5, 0.35)]


@pytest.mark.parametrize("rotvec", BOX_ROTATIONS)
def test_a_box_is_its_ray_cast_surface_on_every_face_away_from_its_edges(box_cloud, rotvec):
    """Bins two or more bins from any edge of the box's faces (creases and rims), the face inside
    the y range: the surface map is the ray cast (measured: at most 0.001 um); the nearest point
    errs on every tilted face (measured: median 44-76 um, at most 165-651)."""
    pose = box_pose(rotvec)
    ray_y, triangle = ray_cast(_box_mesh(pose))
    face = np.where(triangle >= 0, triangle // 2, -1)  # create_box: two triangles a face
    inner = away_from_edges(face, ray_y)
    assert inner.sum() > 500
    surface, nearest = both_maps(box_cloud, pose)
    assert surface.occupied[inner].all()
    assert error_m(surface, ray_y)[inner].max() < 2e-6
    if any(rotvec):
        assert np.median(error_m(nearest, ray_y)[inner]) > 20e-6


def _rim(ray_y):
    """Bins along the box's outline: a ray hits one of two neighbouring bins and misses the other."""
    hit = np.isfinite(ray_y)
    return ndimage.binary_dilation(hit, np.ones((3, 3))) & ndimage.binary_dilation(~hit, np.ones((3, 3)))


@pytest.mark.parametrize("rotvec", [(0.5, 0.0, 0.0), (0.0, 0.0, 0.6), (-0.3, 0.0, 0.0), (0.0, 0.0, -0.4)])
def test_at_a_tilted_boxs_rim_the_surface_map_is_closer_to_the_ray_cast_than_the_nearest_point(box_cloud, rotvec):
    """A box tilted about the gel's x or z (its outline along the bins): over the bins along its
    outline, the surface map is closer to the ray cast than the nearest point (measured mean
    error, in the order of the parameters: 324 against 454 um, 721/841, 431/471, 733/785; an
    empty-centred bin that holds the face's points reads the face by either rule), and on those
    whose centre the box covers far closer (mean 0.3-3 against 72-108 um, median 0 against
    42-76)."""
    pose = box_pose(rotvec)
    ray_y = ray_cast(_box_mesh(pose))[0]
    truth = map_truth(ray_y)
    rim = _rim(ray_y)
    covered = rim & np.isfinite(ray_y) & (ray_y > Y_NEAR) & (ray_y < Y_FAR)
    surface, nearest = both_maps(box_cloud, pose)
    assert error_m(surface, truth)[rim].mean() < error_m(nearest, truth)[rim].mean()
    assert error_m(surface, truth)[covered].mean() < 0.5 * error_m(nearest, truth)[covered].mean()
    assert np.median(error_m(surface, truth)[covered]) < 2e-6 < np.median(error_m(nearest, truth)[covered])


def test_at_a_turned_boxs_rim_the_surface_map_is_no_farther_from_the_ray_cast_than_the_nearest_point(box_cloud):
    """Turned 0.5 rad about the gel normal: measured mean error over the outline 502 um for the
    surface map against 323 um for the nearest point; 140 bins the box does not cover are known
    surface where the nearest point holds a point in 48."""
    pose = box_pose((0.0, 0.5, 0.35))
    ray_y = ray_cast(_box_mesh(pose))[0]
    truth = map_truth(ray_y)
    rim = _rim(ray_y)
    surface, nearest = both_maps(box_cloud, pose)
    assert error_m(surface, truth)[rim].mean() <= error_m(nearest, truth)[rim].mean()


def test_a_sphere_mesh_is_its_ray_cast_surface(tmp_path):
    """Open3D's 10 mm sphere (a fine triangle mesh), sampled as a model: within 20 um of the ray
    cast wherever it is at most 60 deg steep (measured: at most 10 um, median 4.7), the nearest
    point over three times as far (median 63 um, at most 156)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=0.01, resolution=80)
    mesh.translate([0.0007, 0.01 - 0.0008, -0.0011])
    path = tmp_path / "sphere.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    points = sample_model_cloud(path, 0.07e-3, seed=0).points_m
    ray_y = ray_cast(mesh)[0]
    d2 = (CX - 0.0007) ** 2 + (CZ + 0.0011) ** 2
    gentle = d2 < (0.01 * np.sin(np.radians(60.0))) ** 2
    seen = gentle & np.isfinite(ray_y) & (ray_y > Y_NEAR) & (ray_y < Y_FAR)
    assert seen.sum() > 1000
    surface, nearest = both_maps(points)
    assert surface.occupied[seen].all()
    assert error_m(surface, ray_y)[seen].max() < 20e-6
    assert np.median(error_m(surface, ray_y)[seen]) < np.median(error_m(nearest, ray_y)[seen]) / 3


# --- a step, thinning, and what must stay empty -------------------------------------------------


def step_cloud(rng, low_y, high_y, wall, along_z, spacing=DENSE_M):
    """Two faces of the crop, y = low_y where the across coordinate (x for a wall along z, else z)
    is below ``wall`` and high_y above, joined by a vertical wall sampled as densely."""
    x, z = uniform_xz(rng, int(4 * HALF_X * HALF_Z / spacing**2))
    across = x if along_z else z
    y = np.where(across < wall, low_y, high_y)
    span = 2 * (HALF_Z if along_z else HALF_X)
    count = int(span * abs(high_y - low_y) / spacing**2)
    wall_y, wall_along = (
        rng.uniform(min(low_y, high_y), max(low_y, high_y), count),
        rng.uniform(-span / 2, span / 2, count),
    )
    wall_points = (
        np.column_stack([np.full(count, wall), wall_y, wall_along])
        if along_z
        else np.column_stack([wall_along, wall_y, np.full(count, wall)])
    )
    return np.concatenate([np.column_stack([x, y, z]), wall_points])


def bins_from_the_wall(wall, along_z):
    """(rows, cols): how many bins across each bin is from the bin the wall crosses."""
    edges = bin_edges(HALF_X, COLS) if along_z else bin_edges(HALF_Z, ROWS)
    wall_bin = np.searchsorted(edges, wall, side="right") - 1
    return np.abs((np.arange(COLS)[None, :] if along_z else np.arange(ROWS)[:, None]) - wall_bin) + np.zeros(
        (ROWS, COLS), int
    )


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    faces=st.tuples(st.floats(-0.0015, 0.0015), st.floats(-0.0015, 0.0015)).filter(lambda f: abs(f[0] - f[1]) > 1e-4),
    wall=st.floats(-0.005, 0.005),
    along_z=st.booleans(),
)
def test_property_a_step_reads_each_face_exactly_a_bin_beyond_the_wall(seed, faces, wall, along_z):
    """Two parallel faces 0.1-3 mm apart joined by a vertical wall: every bin known, and each bin
    two or more bins across from the one the wall crosses reads its face's height exactly
    (measured: the one bin beside the wall's is off by up to 1.1 mm on a 2 mm step, xfail below).
    No bin reads farther beyond the faces than a quarter of the step (a plane through both faces,
    read at the wall's bin: measured up to a fifth, 287 um on a 1.42 mm step)."""
    a, b = faces
    points = step_cloud(np.random.default_rng(seed), a, b, wall, along_z)
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    assert patch.occupied.all()
    truth = np.where((CX if along_z else CZ) < wall, a, b)
    far = bins_from_the_wall(wall, along_z) >= 2
    np.testing.assert_array_equal(patch.depth_map_m[far], truth[far].astype(np.float32))
    slack = 0.25 * abs(a - b) + 1e-6
    assert patch.depth_map_m.min() >= min(a, b) - slack and patch.depth_map_m.max() <= max(a, b) + slack


@pytest.mark.parametrize("along_z", [True, False])
def test_a_step_reads_each_face_exactly_beside_the_bins_the_wall_crosses(along_z):
    """A 2 mm step (y -1 mm and +1 mm): every bin wholly on a face reads that face, to 40 um
    beside the wall's bin (measured 1.1 um with the wall along z, 33 um along x, where a plane
    through both faces read 0.6-1 mm off before the far face's samples were dropped), exactly
    beyond."""
    wall = 0.00031
    points = step_cloud(np.random.default_rng(0), -0.001, 0.001, wall, along_z)
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    truth = np.where((CX if along_z else CZ) < wall, -0.001, 0.001)
    away = bins_from_the_wall(wall, along_z)
    error = np.abs(patch.depth_map_m - truth)
    assert error[away == 1].max() <= 40e-6
    np.testing.assert_array_equal(patch.depth_map_m[away >= 2], truth[away >= 2].astype(np.float32))


@pytest.mark.parametrize(
    ("radius", "centre", "known_at_least"),
    [(0.02, (0.0, 0.0185, 0.0), (0.98, 0.93, 0.85)), (0.01, (0.001, 0.0092, -0.001), (0.98, 0.9, 0.75))],
)
def test_a_thinned_sphere_stays_known_and_its_error_grows_gracefully(radius, centre, known_at_least):
    """The sphere's 0.05 mm sample voxel-thinned to 10000, 1000 and 80 points/cm3 (0.46, 1 and
    2.3 mm voxels): most bins whose centre the sphere covers stay known (measured 20 mm radius:
    0.996, 0.992, 0.937; 10 mm: 0.995, 0.958, 0.853), where the nearest point leaves 43 %, 10 %,
    2 % occupied. The median error, an empty bin counted as y_far, grows with the voxels
    (measured 20 mm radius: 2, 3.5, 17, 110 um; 10 mm: 4, 7, 34, 196) and stays under the
    nearest point's (55, 122, 1655, 1802 um; 71, 97, 1369, 1480) at every density."""
    points, truth, _ = sphere(np.random.default_rng(7), radius, centre, spacing=0.05e-3)
    seen = in_range(truth)
    scored_truth = np.where(seen, truth, Y_FAR)
    medians = []
    for density, least in zip((10000.0, 1000.0, 80.0), known_at_least, strict=True):
        thinned = downsample_to_density(points, density)
        surface, nearest = both_maps(thinned)
        assert surface.occupied[seen].mean() >= least, density
        surface_median = np.median(error_m(surface, scored_truth)[seen])
        assert surface_median < np.median(error_m(nearest, scored_truth)[seen]), density
        medians.append(surface_median)
    assert medians == sorted(medians)
    assert medians[0] < 30e-6 and medians[1] < 100e-6 and medians[2] < 500e-6


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    side=st.sampled_from(["x<", "x>", "z<", "z>"]),
    cut=st.floats(-0.006, 0.006),
    density=st.sampled_from([None, 10000.0, 1000.0, 80.0]),
    slopes=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15)),
)
def test_property_a_cloud_on_one_side_of_the_crop_is_not_extended_beyond_its_samples(seed, side, cut, density, slopes):
    """A plane sampled on one side of a line along the bins (dense, or thinned to 10000, 1000 or
    80 points/cm3): no bin beyond its samples' extent is known, whatever the coarser levels
    answer (a known bin's centre is at most half a bin beyond the samples: its own point)."""
    rng = np.random.default_rng(seed)
    points, _ = tilted_plane(rng, *slopes, 0.0003)
    axis = 0 if side[0] == "x" else 2
    keep = points[:, axis] < cut if side[1] == "<" else points[:, axis] > cut
    points = points[keep]
    if density is not None:
        points = downsample_to_density(points, density)
    if not holds_a_point(points).any():
        return
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    centres, half_bin = (CX, 0.5 * BIN_X) if axis == 0 else (CZ, 0.5 * BIN_Z)
    inside = (np.abs(points[:, 0]) <= HALF_X) & (np.abs(points[:, 2]) <= HALF_Z)
    inside &= (points[:, 1] >= Y_NEAR) & (points[:, 1] <= Y_FAR)
    along = points[inside, axis]
    beyond = centres > along.max() + half_bin if side[1] == "<" else centres < along.min() - half_bin
    assert not patch.occupied[beyond].any()
    assert np.all(patch.depth_map_m[beyond] == np.float32(Y_FAR))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    clusters=st.integers(1, 4),
    count=st.integers(1, 400),
    spread=st.sampled_from([0.0002, 0.001, 0.004, 0.02]),
    shape=st.tuples(st.integers(1, 60), st.integers(1, 60)),
)
def test_property_a_bin_is_known_only_on_its_own_points_or_among_them(seed, clusters, count, spread, shape):
    """Any cloud (clusters of points, any size and spread, any bins): a bin holding a point is
    known (its surface at least its own nearest point); a bin holding none is known only inside
    the extent of the cropped points, in x and in z (never extrapolated beyond them); an unknown
    bin reads exactly y_far."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-HALF_X, Y_NEAR, -HALF_Z], [HALF_X, Y_FAR, HALF_Z], (clusters, 3))
    points = np.concatenate([c + rng.normal(0.0, spread, (count, 3)) * [1.0, 0.1, 1.0] for c in centres])
    params = DepthMapParams(shape=shape)
    half_x, half_z, y_near, y_far = crop_bounds(GEOMETRY, params)
    inside = (np.abs(points[:, 0]) <= half_x) & (np.abs(points[:, 2]) <= half_z)
    inside &= (points[:, 1] >= y_near) & (points[:, 1] <= y_far)
    if not inside.any():
        return
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, params)
    cropped = points[inside]
    holds = min_y_per_bin(cropped[:, 0], cropped[:, 2], cropped[:, 1], half_x, half_z, shape)[1]
    assert patch.occupied[holds].all()
    cx, cz = np.meshgrid(bin_centres(half_x, shape[1]), bin_centres(half_z, shape[0]))
    among = (cx >= cropped[:, 0].min()) & (cx <= cropped[:, 0].max())
    among &= (cz >= cropped[:, 2].min()) & (cz <= cropped[:, 2].max())
    assert not (patch.occupied & ~holds & ~among).any()
    assert np.all(patch.depth_map_m[~patch.occupied] == np.float32(y_far))
    known = patch.depth_map_m[patch.occupied]
    assert np.all(known >= np.float32(y_near)) and np.all(known <= np.float32(y_far))


@pytest.mark.parametrize("case", ["three points", "oblique half-plane"])
def test_no_bin_outside_its_samples_is_known(case):
    """A bin that holds no point is known only inside the convex hull of the samples."""
    from matplotlib.path import Path as Polygon

    rng = np.random.default_rng(0)
    if case == "three points":
        points = np.array([[-0.008, 0.0, -0.010], [-0.004, 0.0005, 0.0], [0.008, 0.001, 0.010]])
        hull = Polygon(points[:, [0, 2]])
        inside = hull.contains_points(np.column_stack([CX.ravel(), CZ.ravel()])).reshape(CX.shape)
    else:
        normal = np.array([np.cos(np.radians(38.7)), np.sin(np.radians(38.7))])
        x, z = uniform_xz(rng, int(4 * HALF_X * HALF_Z / DENSE_M**2))
        sampled = x * normal[0] + z * normal[1] < 0.0001
        points = np.column_stack([x, np.full(x.size, -0.0005), z])[sampled]
        inside = CX * normal[0] + CZ * normal[1] < 0.0001
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    invented = patch.occupied & ~holds_a_point(points) & ~inside
    assert not invented.any(), f"{invented.sum()} bins"


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    inner=st.floats(0.0035, 0.007),
    width=st.floats(0.0015, 0.004),
    y=st.floats(-0.001, 0.001),
    centre=st.tuples(st.floats(-0.001, 0.001), st.floats(-0.001, 0.001)),
)
def test_property_a_rings_hole_is_not_filled_as_a_plane(seed, inner, width, y, centre):
    """A dense flat annulus (inner radius 3.5-7 mm, 1.5-4 mm wide): the ring reads its height
    exactly, and the hole stays empty but for a rim along the ring: no bin deeper than 2 mm into
    the hole is known, nor most of the hole (measured: the rim reaches 1.0-1.3 mm into the hole,
    14-38 % of the hole's bins)."""
    rng = np.random.default_rng(seed)
    outer = inner + width
    count = int(np.pi * (outer**2 - inner**2) / DENSE_M**2)
    radius, angle = np.sqrt(rng.uniform(inner**2, outer**2, count)), rng.uniform(0, 2 * np.pi, count)
    points = np.column_stack(
        [centre[0] + radius * np.cos(angle), np.full(count, y), centre[1] + radius * np.sin(angle)]
    )
    patch = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    from_centre = np.hypot(CX - centre[0], CZ - centre[1])
    hole = from_centre < inner
    assert not patch.occupied[from_centre < inner - 0.002].any()
    assert patch.occupied[hole].mean() < 0.5
    ring = (from_centre > inner + 0.5 * BIN_Z) & (from_centre < outer - 0.5 * BIN_Z)
    assert patch.occupied[ring].all()
    np.testing.assert_array_equal(patch.depth_map_m[ring], np.float32(y))


# --- bad input and too little input ------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_points_that_are_no_numbers_are_refused(bad):
    points = np.zeros((5, 3))
    points[2, 1] = bad
    with pytest.raises(DepthMapError, match="NaN or inf"):
        contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)


@pytest.mark.parametrize("method", ["bilinear", "Surface", "", None])
def test_an_unknown_method_is_refused_by_name_before_any_point_is_read(method):
    params = DepthMapParams(method=method)
    with pytest.raises(DepthMapError, match=re.escape(f"method must be one of surface, nearest_point, got {method!r}")):
        crop_bounds(GEOMETRY, params)
    with pytest.raises(DepthMapError, match="method must be one of"):
        contact_depth_map(np.array([[0.0, np.nan, 0.0]]), np.eye(4), np.eye(4), GEOMETRY, params)
    with pytest.raises(DepthMapError, match="method must be one of"):
        plan_contact_cut(VoxelIndex(np.zeros((3, 3))), np.eye(4), np.eye(4)[None], GEOMETRY, params)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    count=st.integers(1, 40),
    line=st.tuples(st.floats(-np.pi, np.pi), st.floats(-0.004, 0.004)),
    single=st.booleans(),
)
def test_property_a_cloud_too_sparse_for_a_plane_is_not_made_into_one(seed, count, line, single):
    """One or two points, or any number on one line across the gel face: no plane can be fitted,
    so only the bins holding a point are known (their nearest point), every other bin is empty:
    occupied False and y_far."""
    rng = np.random.default_rng(seed)
    if single:
        points = np.column_stack(
            [rng.uniform(-HALF_X, HALF_X, 2), rng.uniform(-0.001, 0.001, 2), rng.uniform(-HALF_Z, HALF_Z, 2)]
        )
        points = points[: 1 + count % 2]
    else:
        angle, offset = line
        along = rng.uniform(-0.015, 0.015, count)
        points = np.column_stack(
            [
                offset * -np.sin(angle) + along * np.cos(angle),
                rng.uniform(-0.001, 0.001, count),
                offset * np.cos(angle) + along * np.sin(angle),
            ]
        )
    holds = holds_a_point(points)
    if not holds.any():
        return
    surface, nearest = both_maps(points, params=DepthMapParams(fill_gaps_min_neighbours=0))
    np.testing.assert_array_equal(surface.occupied, holds)
    assert np.all(surface.depth_map_m[~holds] == np.float32(Y_FAR))
    np.testing.assert_array_equal(surface.depth_map_m[holds], nearest.depth_map_m[holds])


HOLE_RADIUS_M = 0.003


def _box_with_a_hole(path: Path, degenerate: bool = False) -> Path:
    """A 30 mm box whose near face (y = 0.5 mm, facing the gel) is open: its triangles (legs of
    0.47 mm) within HOLE_RADIUS_M of the gel's centre are taken out, so the mesh is not
    watertight; ``degenerate``: zero-area triangles added (a repeated vertex, three in a line)
    across the hole. Written to ``path`` (returned), as a lab's mesh file would be."""
    box = o3d.geometry.TriangleMesh.create_box(0.03, 0.03, 0.03).subdivide_midpoint(number_of_iterations=6)
    box.translate([-0.015, 0.0005, -0.015])
    vertices, triangles = np.asarray(box.vertices), np.asarray(box.triangles)
    centroids = vertices[triangles].mean(axis=1)
    near_face = np.abs(centroids[:, 1] - 0.0005) < 1e-9
    open_mesh = triangles[~(near_face & (np.hypot(centroids[:, 0], centroids[:, 2]) < HOLE_RADIUS_M))]
    if degenerate:
        extra = len(vertices) + np.arange(4)
        vertices = np.vstack(
            [vertices, [[-0.001, 0.0005, 0.0], [0.0, 0.0005, 0.0], [0.001, 0.0005, 0.0], [0.0, 0.0005, 0.001]]]
        )
        open_mesh = np.vstack([open_mesh, [extra[0], extra[1], extra[2]], [extra[3], extra[3], extra[1]]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(open_mesh))
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def test_an_open_mesh_is_read_where_it_has_surface_and_left_empty_where_it_has_none(tmp_path):
    """A mesh that is not watertight, its near face holed across the gel's centre (the box's far
    side 30 mm behind, out of the crop): every bin half a millimetre outside the hole reads the
    face within 1 um, and every bin 0.6 mm inside it (its edge is jagged by the 0.47 mm triangles)
    is left empty, y_far: no lid is made up over it (measured: empty up to 2.7 mm from the centre,
    exact from 3.3 mm)."""
    points = sample_model_cloud(_box_with_a_hole(tmp_path / "open_box.ply"), 0.1e-3, seed=0).points_m
    surface = contact_depth_map(points, np.eye(4), np.eye(4), GEOMETRY, SURFACE)
    from_centre = np.hypot(CX, CZ)
    face = from_centre > HOLE_RADIUS_M + 0.0005
    hole = from_centre < HOLE_RADIUS_M - 0.0006
    assert face.sum() > 9000 and hole.sum() > 250
    assert surface.occupied[face].all()
    assert np.abs(surface.depth_map_m[face] - 0.0005).max() < 1e-6
    assert not surface.occupied[hole].any()
    assert np.all(surface.depth_map_m[hole] == np.float32(Y_FAR))


def test_degenerate_triangles_add_no_surface_and_a_mesh_of_only_them_is_refused(tmp_path):
    """Zero-area triangles (a repeated vertex, three vertices in a line) across the hole of the
    open box: the model cloud is the same as without them (so is every map cut from it);
    a mesh of nothing else has no surface to sample: RegistrationError naming its area."""
    plain = sample_model_cloud(_box_with_a_hole(tmp_path / "plain.ply"), 0.1e-3, seed=0).points_m
    degenerate = _box_with_a_hole(tmp_path / "degenerate.ply", degenerate=True)
    with_degenerate = sample_model_cloud(degenerate, 0.1e-3, seed=0).points_m
    np.testing.assert_array_equal(with_degenerate, plain)
    only = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.002, 0.0, 0.0]]),
        o3d.utility.Vector3iVector([[0, 1, 2], [0, 0, 1]]),
    )
    o3d.io.write_triangle_mesh(str(tmp_path / "only.ply"), only)
    with pytest.raises(RegistrationError, match="surface area 0.0 m"):
        sample_model_cloud(tmp_path / "only.ply", 0.1e-3)


# --- the front-most point of a bin and its tie rule ----------------------------------------------

TIE_PARAMS = DepthMapParams(shape=(9, 9), margin_m=0.0)


def _tie_setup():
    """Samples at the centres of the 8 bins around bin (4, 4) of a 9 x 9 map, on a tilted plane,
    and two points in bin (4, 4) that tie: the same y, off the plane."""
    half_x, half_z, _, _ = crop_bounds(GEOMETRY, TIE_PARAMS)
    xs, zs = bin_centres(half_x, 9), bin_centres(half_z, 9)
    around = np.array(
        [[xs[c], 0.3 * xs[c] - 0.2 * zs[r], zs[r]] for r in (3, 4, 5) for c in (3, 4, 5) if (r, c) != (4, 4)]
    )
    bin_x, bin_z = xs[1] - xs[0], zs[1] - zs[0]
    return around, xs[4], zs[4], bin_x, bin_z


@settings(max_examples=30, deadline=None)
@given(
    order=st.permutations(range(10)),
    tie=st.sampled_from(["x", "z"]),
    offsets=st.tuples(st.floats(-0.45, 0.45), st.floats(-0.45, 0.45)).filter(lambda o: abs(o[0] - o[1]) > 0.05),
)
def test_property_of_two_points_level_in_a_bin_the_one_of_lesser_x_then_z_is_its_sample(order, tie, offsets):
    """Two points with the same y in one bin: the one of the lesser x (equal x: the lesser z) is
    the bin's sample, whatever the order of the points, on the compiled pass and the torch pass
    alike; the map is the map of the cloud without the other one, and not that without it."""
    around, cx, cz, bin_x, bin_z = _tie_setup()
    y = 0.0008  # off the neighbours' plane: the plane through the bin's sample depends on where it is
    lo, hi = sorted(offsets)
    if tie == "x":
        first, second = [cx + lo * bin_x, y, cz + 0.2 * bin_z], [cx + hi * bin_x, y, cz - 0.3 * bin_z]
    else:
        first, second = [cx + 0.1 * bin_x, y, cz + lo * bin_z], [cx + 0.1 * bin_x, y, cz + hi * bin_z]
    points = np.concatenate([around, [first, second]])[list(order)]

    # The front-most point of the bin, as the kernel and the torch pass keep it.
    bounds = crop_bounds(GEOMETRY, TIE_PARAMS)
    flat = 4 * 9 + 4
    min_y, counts = np.full((1, 81), np.inf), np.zeros(1, np.int64)
    at_x, at_z = np.zeros((1, 81)), np.zeros((1, 81))
    one_run = (np.array([0], np.int64), np.array([len(points)], np.int64), np.array([0, 1], np.int64))
    cut_kernel(
        points,
        *one_run,
        np.ascontiguousarray(np.eye(4)[None, :3, :]),
        np.array(bounds),
        bin_edges(bounds[0], 9),
        bin_edges(bounds[1], 9),
        min_y,
        counts,
        at_x,
        at_z,
        True,
    )
    assert (min_y[0, flat], at_x[0, flat], at_z[0, flat]) == (y, first[0], first[2])
    device = front_points_on_device(torch.from_numpy(points), *one_run, np.eye(4)[None], bounds, (9, 9))
    assert (device[0][0, flat], device[1][0, flat], device[2][0, flat]) == (y, first[0], first[2])

    def surface_map(cloud):
        return contact_depth_map(cloud, np.eye(4), np.eye(4), GEOMETRY, TIE_PARAMS).depth_map_m

    with_both = surface_map(points)
    np.testing.assert_array_equal(with_both, surface_map(np.concatenate([around, [first]])))
    assert with_both[4, 4] != surface_map(np.concatenate([around, [second]]))[4, 4]


# --- the same maps on every path ------------------------------------------------------------------


def random_pose(rng, offset_m):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    pose[:3, 3] = offset_m + rng.uniform(-0.002, 0.002, 3)
    return pose


def every_path(points, model_to_world, gels, params, cell):
    """The maps of every gel by each path: (name, depth-maps, occupied, point counts); a gel that
    reaches no point has an all-y_far map (contact_depth_map: OutOfReachError)."""
    y_far = crop_bounds(GEOMETRY, params)[3]
    singles = []
    for gel in gels:
        try:
            patch = contact_depth_map(points, model_to_world, gel, GEOMETRY, params)
            singles.append((patch.depth_map_m, patch.occupied, patch.point_count))
        except OutOfReachError:
            singles.append((np.full(params.shape, y_far, np.float32), np.zeros(params.shape, bool), 0))
    yield ("contact_depth_map", *(np.stack(part) for part in zip(*singles, strict=True)))
    index = VoxelIndex(points, cell)
    for threads in (1, 2):
        batch = contact_depth_maps(index, model_to_world, gels, GEOMETRY, params, allow_empty=True, threads=threads)
        yield f"contact_depth_maps, {threads} threads", batch.depth_maps_m, batch.occupied, batch.point_counts
    plan = plan_contact_cut(index, model_to_world, gels, GEOMETRY, params, allow_empty=True)
    runs = [plan.cut(first, min(first + 2, len(gels))) for first in range(0, len(gels), 2)]
    yield (
        "planned cut in runs of 2",
        np.concatenate([r.depth_maps_m for r in runs]),
        np.concatenate([r.occupied for r in runs]),
        np.concatenate([r.point_counts for r in runs]),
    )
    on_device = contact_depth_maps(
        index,
        model_to_world,
        gels,
        GEOMETRY,
        params,
        allow_empty=True,
        device_points=points_on_device(index.points_m, "cpu"),
    )
    yield "torch on the CPU", on_device.depth_maps_m, on_device.occupied, on_device.point_counts


def assert_every_path_the_same(points, model_to_world, gels, params, cell=0.005):
    paths = list(every_path(points, model_to_world, gels, params, cell))
    _, maps, occupied, counts = paths[0]
    for name, other_maps, other_occupied, other_counts in paths[1:]:
        np.testing.assert_array_equal(other_maps, maps, err_msg=name)
        np.testing.assert_array_equal(other_occupied, occupied, err_msg=name)
        np.testing.assert_array_equal(other_counts, counts, err_msg=name)
    return maps, occupied


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    regions=st.integers(1, 5),
    offset=st.sampled_from([0.0, 1e3]),
    dtype=st.sampled_from([np.float32, np.float64]),
    cell=st.sampled_from([0.001, 0.005]),
    shape=st.tuples(st.integers(1, 40), st.integers(1, 40)),
    spacing=st.sampled_from([0.1e-3, 0.5e-3, 2e-3]),
)
def test_property_every_path_cuts_the_same_surface_maps(seed, regions, offset, dtype, cell, shape, spacing):
    """A sphere sampled at 0.1-2 mm (dense to sparse: the coarse levels at work) and scattered
    points, seen by gels at any pose around it (a km from the origin or at it), float32 or
    float64 points, any bins: every path cuts the same maps, occupancy and counts, bit for bit."""
    rng = np.random.default_rng(seed)
    ball = rng.normal(size=(int(4 * np.pi * 0.008**2 / spacing**2), 3))
    points = 0.008 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
    points = np.concatenate([points, rng.uniform(-0.01, 0.01, (300, 3))]).astype(dtype)
    model_to_world = random_pose(rng, offset)
    # Gels facing the sphere: +y toward its centre, the face 0-1.5 mm into it.
    gels = []
    for _ in range(regions):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        pose[:3, 3] = -pose[:3, 1] * (0.008 - rng.uniform(0.0, 0.0015))
        gels.append(model_to_world @ pose)
    assert_every_path_the_same(points, model_to_world, np.stack(gels), DepthMapParams(shape=shape), cell)


def test_points_on_bin_edges_and_crop_faces_cut_the_same_surface_maps_on_every_path():
    """A point on every bin edge of a 7 x 9 map, each at its own depth, a tilted plane's samples
    through them, and points just outside the crop's faces (the gel at the model's origin): every
    path the same, bit for bit, float32 and float64."""
    params = DepthMapParams(shape=(7, 9))
    half_x, half_z, y_near, y_far = crop_bounds(GEOMETRY, params)
    xx, zz = (a.ravel() for a in np.meshgrid(bin_edges(half_x, 9), bin_edges(half_z, 7), indexing="ij"))
    rng = np.random.default_rng(0)
    depths = rng.permutation(np.linspace(y_near, y_far, xx.size))
    x, z = uniform_xz(rng, 3000, (-half_x, half_x), (-half_z, half_z))
    outside = [
        [0.0, np.nextafter(y_near, -np.inf), 0.0],
        [0.0, np.nextafter(y_far, np.inf), 0.0],
        [np.nextafter(half_x, np.inf), 0.0, 0.0],
        [0.0, 0.0, np.nextafter(-half_z, -np.inf)],
    ]
    points = np.concatenate([np.column_stack([xx, depths, zz]), np.column_stack([x, 0.05 * x - 0.03 * z, z]), outside])
    for dtype in (np.float64, np.float32):
        maps, occupied = assert_every_path_the_same(points.astype(dtype), np.eye(4), np.eye(4)[None], params)
        assert occupied.all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_the_cuda_pass_cuts_the_same_surface_maps():
    rng = np.random.default_rng(1)
    points, _, _ = sphere(rng, 0.01, (0.0, 0.0095, 0.0))
    index = VoxelIndex(points)
    gels = np.stack([random_pose(rng, 0.0) for _ in range(4)])
    gels[:, :3, 3] = 0.0
    on_cpu = contact_depth_maps(index, np.eye(4), gels, GEOMETRY, SURFACE, allow_empty=True)
    on_cuda = contact_depth_maps(
        index,
        np.eye(4),
        gels,
        GEOMETRY,
        SURFACE,
        allow_empty=True,
        device_points=points_on_device(index.points_m, "cuda"),
    )
    np.testing.assert_array_equal(on_cuda.depth_maps_m, on_cpu.depth_maps_m)
    np.testing.assert_array_equal(on_cuda.occupied, on_cpu.occupied)


# --- level 0's fast path against the bin-by-bin path ----------------------------------------------


def bin_by_bin_surface_map(samples, centres, bounds):
    """perception.surface._surface_map with every bin answered by _plane_at, level 0's fast path
    (_occupied_planes) left out: the reference the fast path keeps."""
    from perception.surface import _answer_level, _knit, _pooled, level_0_tolerance

    sy = samples[0]
    rows, cols = sy.shape
    bin_size = level_0_tolerance(*centres)
    out, known = np.full(sy.shape, bounds[1]), np.zeros(sy.shape, bool)
    level_samples, unknown, knit_level, level = samples, rows * cols, -1, 0
    while unknown and (knit_level < 0 or level <= knit_level + 1):
        if level > 0:
            if level_samples[0].shape == (1, 1):
                break
            level_samples = _pooled(*level_samples)
        if knit_level < 0 and _knit(level_samples[0]):
            knit_level = level
        tolerance = bin_size * (1 << level)
        unknown -= _answer_level(level_samples, level, sy, centres, tolerance, bounds, out, known)
        if level == 0:
            planar = known & (out != sy)
        level += 1
    return out, known, planar


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(1, 30), st.integers(1, 30)),
    occupancy=st.sampled_from([0.3, 0.7, 0.9, 1.0]),
    slopes=st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)),
    curvature=st.floats(-200.0, 200.0),
    step_m=st.sampled_from([0.0, 2e-4, 3e-3]),
    noise_m=st.sampled_from([0.0, 2e-5, 1e-4]),
    outline=st.tuples(st.floats(0.0, 2 * np.pi), st.floats(-1.0, 1.5)),
)
def test_property_level_0s_fast_path_answers_every_bin_as_the_bin_by_bin_path(
    seed, shape, occupancy, slopes, curvature, step_m, noise_m, outline
):
    """Samples anywhere in their bins of a tilted, curved surface with a step and noise, bins left
    empty at random (sampling gaps, lone bins) and beyond a straight outline (the surface's edge):
    the map with level 0's fast path is the bin-by-bin path's, value and knowledge, bit for bit."""
    from perception.surface import _surface_map, level_0_tolerance

    rng = np.random.default_rng(seed)
    rows, cols = shape
    half_x, half_z, y_near, y_far = 0.012, 0.0095, -0.005, 0.01
    x_edges, z_edges = bin_edges(half_x, cols), bin_edges(half_z, rows)
    sx = x_edges[:-1][None, :] + rng.uniform(0.0, 1.0, shape) * np.diff(x_edges)[None, :]
    sz = z_edges[:-1][:, None] + rng.uniform(0.0, 1.0, shape) * np.diff(z_edges)[:, None]
    sy = slopes[0] * sx + slopes[1] * sz + curvature * (sx**2 + sz**2) + step_m * (sx > 0.3 * half_x)
    sy = sy + rng.normal(0.0, noise_m, shape) if noise_m else sy
    angle, reach = outline
    beyond = np.cos(angle) * sx + np.sin(angle) * sz > reach * half_z
    empty = (rng.uniform(size=shape) >= occupancy) | beyond
    sy[empty], sx[empty], sz[empty] = np.inf, 0.0, 0.0
    centres = (bin_centres(half_x, cols), bin_centres(half_z, rows))
    out, known, planar = np.empty(shape), np.empty(shape, bool), np.empty(shape, bool)
    _surface_map(sy, sx, sz, *centres, y_near, y_far, level_0_tolerance(*centres), out, known, planar)
    reference, reference_known, reference_planar = bin_by_bin_surface_map((sy, sx, sz), centres, (y_near, y_far))
    np.testing.assert_array_equal(known, reference_known)
    np.testing.assert_array_equal(planar, reference_planar)
    np.testing.assert_array_equal(out, reference)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(1, 24), st.integers(1, 24)),
    occupancy=st.sampled_from([0.2, 0.6, 1.0]),
    outline=st.tuples(st.floats(0.0, 2 * np.pi), st.floats(-1.0, 1.0)),
    on_centres=st.sampled_from([0.0, 0.3]),
    level=st.integers(0, 2),
)
def test_property_where_the_samples_around_lie_on_one_side_no_plane_answers_an_empty_bin(
    seed, shape, occupancy, outline, on_centres, level
):
    """The levels skip an empty bin whose samples around lie on one side of its centre in x or z
    (_extent, _one_sided): at every bin and level where that holds, _plane_at's answer for an
    empty bin is NaN, so the skip changes no map; and the level, whose bins of a cell in one row
    share one extent, answers every empty bin as _plane_at asked there does. Samples beyond a
    straight outline are gone (an edge), and some lie exactly on a bin centre's line (the
    boundary case of one side)."""
    from perception.surface import _answer_level, _extent, _one_sided, _plane_at, _pooled, level_0_tolerance

    rng = np.random.default_rng(seed)
    rows, cols = shape
    half_x, half_z = 0.012, 0.0095
    centres = (bin_centres(half_x, cols), bin_centres(half_z, rows))
    x_edges, z_edges = bin_edges(half_x, cols), bin_edges(half_z, rows)
    sx = x_edges[:-1][None, :] + rng.uniform(0.0, 1.0, shape) * np.diff(x_edges)[None, :]
    sz = z_edges[:-1][:, None] + rng.uniform(0.0, 1.0, shape) * np.diff(z_edges)[:, None]
    snapped = rng.uniform(size=shape) < on_centres
    sx = np.where(snapped, np.broadcast_to(centres[0][None, :], shape), sx)
    sz = np.where(rng.uniform(size=shape) < on_centres, np.broadcast_to(centres[1][:, None], shape), sz)
    sy = 0.3 * sx - 0.2 * sz + 50.0 * (sx**2 + sz**2)
    angle, reach = outline
    empty = (rng.uniform(size=shape) >= occupancy) | (np.cos(angle) * sx + np.sin(angle) * sz > reach * half_z)
    sy[empty], sx[empty], sz[empty] = np.inf, 0.0, 0.0
    samples = (sy, sx, sz)
    for _ in range(level):
        samples = _pooled(*samples)
    tolerance = level_0_tolerance(*centres) * (1 << level)
    kept = np.empty((3, 9))
    for r in range(rows):
        for c in range(cols):
            if _one_sided(_extent(samples, r >> level, c >> level), centres[0][c], centres[1][r]):
                y = _plane_at(
                    *samples, r >> level, c >> level, centres[0][c], centres[1][r], tolerance, True, False, kept
                )
                assert np.isnan(y), (r, c)

    # The level's answers for the empty bins (level 0's occupied ones given as known) against
    # _plane_at asked at each of them.
    bounds = (-1.0, 1.0)
    out, known = np.full(shape, bounds[1]), (sy < np.inf) if level == 0 else np.zeros(shape, bool)
    expected, expected_known = out.copy(), known.copy()
    for r, c in zip(*np.nonzero(~known)):
        y = _plane_at(*samples, r >> level, c >> level, centres[0][c], centres[1][r], tolerance, True, False, kept)
        if np.isfinite(y):
            expected[r, c], expected_known[r, c] = min(max(y, bounds[0]), bounds[1]), True
    _answer_level(samples, level, sy, centres, tolerance, bounds, out, known)
    np.testing.assert_array_equal(known, expected_known)
    np.testing.assert_array_equal(out, expected)


def least_squares_bend(samples, centres, bin_size, out, planar, bounds):
    """perception.surface_bend.bend_corrected's rule written plainly with NumPy's least squares,
    bin by bin: the reference its vector loop keeps."""
    from perception.surface import MAX_SLOPE
    from perception.surface_bend import (
        FLAT_BEND_M,
        MAX_BEND_CORRECTION,
        QUADRIC_FIT_FRACTION,
    )

    sy, sx, sz = samples
    planes = np.where(planar, out, np.nan)
    corrected = out.copy()
    fit = QUADRIC_FIT_FRACTION * bin_size
    for r in range(1, sy.shape[0] - 1):
        for c in range(1, sy.shape[1] - 1):
            around = planes[r - 1 : r + 2, c - 1 : c + 2]
            ends = around.ravel()[[3, 1, 0, 2]] + around.ravel()[[5, 7, 8, 6]]  # a row, a column, two diagonals
            if np.isnan(planes[r, c]) or not (np.abs(ends - 2.0 * planes[r, c]) > FLAT_BEND_M).any():
                continue
            y, x, z = (grid[r - 1 : r + 2, c - 1 : c + 2].ravel() for grid in (sy, sx, sz))
            dx, dz, dy = x - centres[0][c], z - centres[1][r], y - planes[r, c]
            step = np.abs(dy) - bin_size
            keep = np.isfinite(y) & ((step <= 0.0) | (step**2 <= MAX_SLOPE**2 * (dx**2 + dz**2)))
            u, v, dy = dx[keep] / bin_size, dz[keep] / bin_size, dy[keep]
            terms = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
            if keep.sum() < 7 or np.linalg.matrix_rank(terms) < 6:
                continue
            solution = np.linalg.lstsq(terms, dy, rcond=None)[0]
            fits = np.all(np.abs(dy - terms @ solution) <= fit)
            if fits and dy.min() - fit <= solution[0] <= dy.max() + fit:
                if abs(solution[0]) <= MAX_BEND_CORRECTION * bin_size:
                    corrected[r, c] = np.clip(planes[r, c] + solution[0], *bounds)
    return corrected


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(3, 24), st.integers(3, 24)),
    radius_m=st.floats(0.0008, 0.005),
    occupancy=st.sampled_from([0.8, 1.0]),
    step_m=st.sampled_from([0.0, 1e-4, 1.2e-3]),
    noise_m=st.sampled_from([0.0, 3e-6, 3e-5]),
)
def test_property_the_bend_pass_reads_each_bending_bin_as_the_least_squares_quadric(
    seed, shape, radius_m, occupancy, step_m, noise_m
):
    """A ball's cap, with a step, noise and empty bins at random: the bend pass (its bins' quadrics
    solved side by side in one vector loop) gives each bin what a bin-by-bin least-squares fit
    with its rules gives (the samples it keeps, the fit, the heights, the largest correction)."""
    from perception.surface import MAX_SLOPE, _surface_map, level_0_tolerance
    from perception.surface_bend import bend_corrected

    rng = np.random.default_rng(seed)
    rows, cols = shape
    half_x, half_z, bounds = 0.012 * cols / 100, 0.0095 * rows / 100, (-0.005, 0.01)
    centres = (bin_centres(half_x, cols), bin_centres(half_z, rows))
    x_edges, z_edges = bin_edges(half_x, cols), bin_edges(half_z, rows)
    sx = x_edges[:-1][None, :] + rng.uniform(0.0, 1.0, shape) * np.diff(x_edges)[None, :]
    sz = z_edges[:-1][:, None] + rng.uniform(0.0, 1.0, shape) * np.diff(z_edges)[:, None]
    flat = np.minimum(sx**2 + sz**2, 0.8 * radius_m**2)
    sy = radius_m - np.sqrt(radius_m**2 - flat) + step_m * (sx > 0.0) + rng.normal(0.0, noise_m, shape)
    empty = rng.uniform(size=shape) >= occupancy
    sy[empty], sx[empty], sz[empty] = np.inf, 0.0, 0.0
    bin_size = level_0_tolerance(*centres)
    out, known, planar = np.empty(shape), np.empty(shape, bool), np.empty(shape, bool)
    _surface_map(sy, sx, sz, *centres, *bounds, bin_size, out, known, planar)
    expected = least_squares_bend((sy, sx, sz), centres, bin_size, out, planar, bounds)
    bend_corrected((sy, sx, sz), centres, (bin_size, MAX_SLOPE), bounds, out, planar)
    np.testing.assert_allclose(out, expected, rtol=0.0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    dropped=st.lists(st.integers(0, 8), max_size=2, unique=True),
    scale=st.sampled_from([1e-6, 1e-4, 1e-2]),
)
def test_property_the_quadric_is_the_least_squares_quadric_of_its_samples(seed, dropped, scale):
    """The bend pass's solve (normal equations of the nine samples, a dropped one weighing 0, then
    LDL^T in scalars) gives the least-squares quadric of seven to nine samples spread over the
    3 x 3 bins (u, v in bins, y in m at any scale), as NumPy's least squares does; samples on one
    line do not pin six terms."""
    from perception.surface_bend import _normal_equations, _solved

    rng = np.random.default_rng(seed)
    cells = [cell for cell in range(9) if cell not in dropped]
    u = np.array([cell % 3 - 1.0 for cell in cells]) + rng.uniform(-0.5, 0.5, len(cells))
    v = np.array([cell // 3 - 1.0 for cell in cells]) + rng.uniform(-0.5, 0.5, len(cells))
    terms = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
    y = terms @ rng.normal(0.0, scale, 6) + rng.normal(0.0, 0.01 * scale, len(cells))

    def nine(u: np.ndarray, v: np.ndarray) -> tuple:
        kept = dict(zip(cells, zip(u.tolist(), v.tolist(), y.tolist(), [1.0] * len(cells))))
        return tuple(kept.get(cell, (0.0, 0.0, 0.0, 0.0)) for cell in range(9))

    pinned, solution = _solved(_normal_equations(nine(u, v)))
    assert pinned
    expected = np.linalg.lstsq(terms, y, rcond=None)[0]
    np.testing.assert_allclose(solution, expected, rtol=0.0, atol=1e-9 * scale)
    assert not _solved(_normal_equations(nine(u, 0.5 * u + 0.25)))[0]  # every sample on one line
