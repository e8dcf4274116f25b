"""Depth images to point clouds: back-projection with distortion, and merging cameras in world.

A depth pixel holds the z coordinate (metres) of the surface point in the camera's optical
frame (z forward, x right, y down), as the Kinect v2 / OpenNI report it — not the range
along the ray.
"""
from __future__ import annotations

import functools
from collections.abc import Sequence

import cv2
import open3d as o3d
import numpy as np

from msgs.sensors import CameraIntrinsics, DepthImage
from perception.errors import PointCloudError

# Kinect v2 working range; returns outside it are unreliable or spurious.
DEFAULT_RANGE_M = (0.5, 4.5)


def check_transform(a_to_b: np.ndarray, name: str = "transform") -> np.ndarray:
    """Return ``a_to_b`` as a float64 4x4 rigid transform, or raise PointCloudError."""
    matrix = np.asarray(a_to_b, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise PointCloudError(f"{name} must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) or np.linalg.det(rotation) <= 0:
        raise PointCloudError(f"{name} rotation block is not a proper rotation")
    if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
        raise PointCloudError(f"{name} last row must be [0, 0, 0, 1], got {matrix[3]}")
    return matrix


def transform_points(points_a_m: np.ndarray, a_to_b: np.ndarray) -> np.ndarray:
    """Map (N, 3) points from frame a to frame b; computed and returned in float64."""
    points = np.asarray(points_a_m, dtype=np.float64).reshape(-1, 3)
    matrix = check_transform(a_to_b)
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _intrinsics_key(intrinsics: CameraIntrinsics) -> tuple:
    distortion = tuple(float(d) for d in intrinsics.distortion)
    return (int(intrinsics.width), int(intrinsics.height), float(intrinsics.fx), float(intrinsics.fy),
            float(intrinsics.cx), float(intrinsics.cy), distortion)


@functools.lru_cache(maxsize=16)
def _normalised_rays(key: tuple) -> np.ndarray:
    # Undistorting 200k pixels costs tens of ms; a camera's rays never change, so cache them.
    width, height, fx, fy, cx, cy, distortion = key
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    camera_matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    undistorted = cv2.undistortPoints(pixels, camera_matrix, np.asarray(distortion, dtype=np.float64))
    rays = undistorted.reshape(height, width, 2)
    rays.setflags(write=False)
    return rays


def pixel_rays(intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H, W, 2) undistorted normalised image coordinates (x/z, y/z) of every pixel centre."""
    if intrinsics.width <= 0 or intrinsics.height <= 0:
        raise PointCloudError(f"image size must be positive, got {intrinsics.width}x{intrinsics.height}")
    if not (intrinsics.fx > 0 and intrinsics.fy > 0):
        raise PointCloudError(f"focal lengths must be positive, got fx={intrinsics.fx} fy={intrinsics.fy}")
    if len(intrinsics.distortion) not in (4, 5, 8, 12, 14):
        raise PointCloudError(f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {len(intrinsics.distortion)}")
    key = _intrinsics_key(intrinsics)
    if not all(np.isfinite(v) for v in key[2:6] + key[6]):
        raise PointCloudError("intrinsics must be finite")
    return _normalised_rays(key)


def depth_to_points_camera(depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                           range_m: tuple[float, float] = DEFAULT_RANGE_M) -> np.ndarray:
    """Back-project a depth image (H, W, metres, NaN = no return) to (N, 3) float64 points in
    the camera frame. NaN, inf and depths outside ``range_m`` (inclusive) are dropped."""
    depth = np.asarray(depth_m)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise PointCloudError(f"depth image is {depth.shape}, intrinsics say "
                              f"{(intrinsics.height, intrinsics.width)}")
    near, far = float(range_m[0]), float(range_m[1])
    if not (0.0 < near < far and np.isfinite(far)):
        raise PointCloudError(f"depth range must satisfy 0 < near < far < inf, got {range_m}")
    rays = pixel_rays(intrinsics)
    z = depth.astype(np.float64, copy=False)
    with np.errstate(invalid="ignore"):  # NaN compares False, which is what drops it
        valid = (z >= near) & (z <= far)
    z_valid = z[valid]
    rays_valid = rays[valid]
    return np.column_stack([rays_valid[:, 0] * z_valid, rays_valid[:, 1] * z_valid, z_valid])


def depth_images_to_world(images: Sequence[DepthImage],
                          range_m: tuple[float, float] = DEFAULT_RANGE_M) -> list[np.ndarray]:
    """One (N_i, 3) float64 world cloud per depth image, using each image's ``camera_to_world``."""
    if len(images) == 0:
        raise PointCloudError("no depth images given")
    return [transform_points(depth_to_points_camera(image.depth_m(), image.intrinsics, range_m),
                             image.camera_to_world)
            for image in images]


def merge_depth_images(images: Sequence[DepthImage],
                       range_m: tuple[float, float] = DEFAULT_RANGE_M) -> np.ndarray:
    """All cameras' points merged in ``world``, (N, 3) float64."""
    return np.concatenate(depth_images_to_world(images, range_m), axis=0)


def seed_open3d(*keys: int) -> None:
    """Seed Open3D's global RNG (RANSAC, sampling) from any integers; it takes only 31 bits."""
    state = np.random.SeedSequence([abs(int(k)) for k in keys]).generate_state(1)[0]
    o3d.utility.random.seed(int(state >> 1))
