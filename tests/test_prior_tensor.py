"""The physics prior as batched tensor operations (models.prior_tensor), which the inference node
draws on CUDA, against the renderer's own NumPy and OpenCV images (sim.gelsight, what training
and ``dtx evaluate`` see), within the module's stated tolerance; run here on the CPU, the same
operations PyTorch runs on a GPU."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from dataset.synth import analytic_contact_maps
from models.data import network_input
from models.errors import ModelConfigError
from models.networks import GeneratorConfig
from models.prior import PhysicsPrior, PriorSpec
from models.prior_tensor import TensorPrior
from sim.gelsight import camera_pixels_on_map

REPO = Path(__file__).resolve().parent.parent
SCENE = str(REPO / "scenes" / "ycb_three.yaml")
CROP_M = (0.02392, 0.015, 0.01894)  # the demo's checkpoint's crop (x, y, z)
FAR_M = 0.0025
# The stated tolerance (models/prior_tensor.py): a level apart at most, except where a pixel's
# slope lies within float rounding of an edge of the calibration's slope bins, whose neighbouring
# polynomials differ by up to ~50 levels; such pixels are rare in contacts (99.9 % of pixels
# equal), though a map of noise that hypothesis draws can be full of them.
# Float32 rounding of the gel's depth (~1e-7 of ~1 mm, the blurs summed in another order) over
# the central difference's 0.3 mm: a slope (mm/mm) is known to about 1e-6.
SLOPE_ROUNDING = 2e-6
MIN_EQUAL = 0.999


@pytest.fixture(scope="module")
def prior() -> PhysicsPrior:
    return PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=0.5), 100)


def tensor_images(prior: PhysicsPrior, maps: np.ndarray, sigma_mm: float) -> np.ndarray:
    drawn = TensorPrior(prior.renderer, (CROP_M[0], CROP_M[2])).images(torch.from_numpy(maps), sigma_mm)
    return drawn.permute(0, 2, 3, 1).numpy()


def near_a_bin_edge(prior: PhysicsPrior, depth_map_m: np.ndarray) -> np.ndarray:
    """H x W: where the renderer's slope of the gel under ``depth_map_m`` is within its float
    rounding (SLOPE_ROUNDING) of a slope bin's edge (magnitude or direction) or of the tilt
    threshold."""
    renderer = prior.renderer
    map_u, map_v = camera_pixels_on_map(renderer, depth_map_m.shape, (CROP_M[0], CROP_M[2]))
    gap_mm = np.clip(np.nan_to_num(depth_map_m, nan=np.inf), -1.0, 1.0).astype(np.float32) * np.float32(1e3)
    depth = renderer._work_depth(cv2.remap(gap_mm, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    row_mm, col_mm = renderer.grid.pitch_mm
    slope_x = cv2.Sobel(depth, cv2.CV_64F, 1, 0, ksize=1, scale=0.5 / col_mm, borderType=cv2.BORDER_REPLICATE)
    slope_y = cv2.Sobel(depth, cv2.CV_64F, 0, 1, ksize=1, scale=0.5 / row_mm, borderType=cv2.BORDER_REPLICATE)
    magnitude = np.hypot(slope_x, slope_y)
    near = np.abs(magnitude - renderer.grid.tilted_tan) < SLOPE_ROUNDING
    # Each bin position with how far the slope's rounding can move it, in bins.
    for position, rounding in (
        (np.arctan(magnitude) / renderer.grid.mag_step, SLOPE_ROUNDING / (1 + magnitude**2) / renderer.grid.mag_step),
        (
            (np.arctan2(slope_y, slope_x) + np.pi) / renderer.grid.dir_step,
            SLOPE_ROUNDING / np.maximum(magnitude, 1e-12) / renderer.grid.dir_step,
        ),
    ):
        near |= np.abs(position - np.rint(position)) < rounding
    return near


def assert_within_tolerance(
    prior: PhysicsPrior, maps: np.ndarray, sigma_mm: float, got: np.ndarray, min_equal: float = 0.0
) -> None:
    """``got`` (the tensor form's images of ``maps``) against the renderer's: sharp, a level apart
    at most except at bin edges; blurred over ``sigma_mm``, at most what the pose blur spreads of
    the sharp images' differences, and a level for each image's rounding; at least ``min_equal``
    of the pixels equal."""
    want = prior.images(maps, sigma_mm)
    assert got.shape == want.shape
    apart = np.abs(got.astype(np.int16) - want.astype(np.int16)).max(axis=-1)
    sharp = np.abs(tensor_images(prior, maps, 0.0).astype(np.int16) - prior.images(maps, 0.0).astype(np.int16))
    for depth_map_m, sharp_apart in zip(maps, sharp.max(axis=-1)):
        off = sharp_apart > 1
        assert not np.any(off & ~near_a_bin_edge(prior, depth_map_m)), "more than a level apart away from a bin edge"
    if sigma_mm > 0:
        pitch_rows_mm, pitch_cols_mm = prior.renderer.pixel_pitch_mm
        for pixels_apart, sharp_apart in zip(apart, sharp):
            spread = cv2.GaussianBlur(
                sharp_apart.astype(np.float32),
                (0, 0),
                sigmaX=sigma_mm / pitch_cols_mm,
                sigmaY=sigma_mm / pitch_rows_mm,
                borderType=cv2.BORDER_REPLICATE,
            ).max(axis=-1)
            assert np.all(pixels_apart <= np.ceil(spread + 1e-3) + 1)
    assert np.mean(apart == 0) >= min_equal, f"{np.mean(apart == 0):.6f} of pixels equal"


@pytest.mark.parametrize("sigma_mm", [0.0, 0.5, 2.0])
def test_a_batch_of_contacts_is_the_renderers_images(prior: PhysicsPrior, sigma_mm: float) -> None:
    maps = analytic_contact_maps(48, seed=5, y_far_m=FAR_M)
    got = tensor_images(prior, maps, sigma_mm)
    assert np.all(got == np.round(got)) and got.min() >= 0 and got.max() <= 255  # levels
    assert_within_tolerance(prior, maps, sigma_mm, got, MIN_EQUAL)


@settings(max_examples=12, deadline=None)
@given(
    maps=hnp.arrays(
        np.float32,
        st.tuples(st.integers(1, 3), st.integers(4, 60), st.integers(4, 60)),
        elements=st.one_of(
            st.floats(-(2.0**-8), 2.0**-8, width=32), st.just(np.float32(np.nan)), st.just(np.float32(np.inf))
        ),
    ),
    sigma_mm=st.sampled_from([0.0, 0.7]),
)
def test_any_map_of_any_size_within_tolerance(prior: PhysicsPrior, maps: np.ndarray, sigma_mm: float) -> None:
    """Maps of any bins, with NaN and +inf (nothing there) and presses past the gel's thickness."""
    assert_within_tolerance(prior, maps, sigma_mm, tensor_images(prior, maps, sigma_mm))


def test_the_prior_on_a_device_draws_with_the_tensor_form_and_checks_its_input(prior: PhysicsPrior) -> None:
    moved = prior.on("cpu")
    assert moved._tensor is None and moved.device == "cpu"  # "cpu" stays the renderer's own path
    tensor = PhysicsPrior.on(prior, "cpu")
    tensor._tensor = TensorPrior(prior.renderer, (CROP_M[0], CROP_M[2]))  # the cuda form, on the CPU
    maps = analytic_contact_maps(6, seed=1, y_far_m=FAR_M)
    assert_within_tolerance(prior, maps, prior.spec.pose_sigma_mm, tensor.images(maps), MIN_EQUAL)
    assert tensor.images(maps[:0]).shape == (0, 100, 100, 3)
    with pytest.raises(ModelConfigError, match="-inf"):
        tensor.images(np.full((1, 10, 10), -np.inf, np.float32))
    with pytest.raises(ModelConfigError, match="N x rows x cols float"):
        tensor.images(np.zeros((10, 10), np.float32))
    with pytest.raises(ModelConfigError, match="pose_sigma_mm"):
        tensor.images(maps, pose_sigma_mm=float("nan"))


def test_on_a_device_the_network_input_is_built_there_from_the_same_levels(prior: PhysicsPrior) -> None:
    """The tensor form's channels are its images' levels in the network's units, each exactly
    the CPU's conversion of that level (IMAGE_UNITS), and network_input joins them to the depth
    channels where they are: the CPU path's input wherever the levels agree."""
    tensor = PhysicsPrior.on(prior, "cpu")
    tensor._tensor = TensorPrior(prior.renderer, (CROP_M[0], CROP_M[2]))  # the cuda form, on the CPU
    maps = analytic_contact_maps(5, seed=2, y_far_m=FAR_M)
    images = tensor.images(maps)
    channels = tensor.channels(maps)
    expected = images.transpose(0, 3, 1, 2).astype(np.float32) / 127.5 - 1.0
    np.testing.assert_array_equal(channels.numpy(), expected)
    config = GeneratorConfig(image_size=100, prior=True)
    on_device = network_input(maps, (-0.005, FAR_M), config, tensor)
    on_cpu = network_input(maps, (-0.005, FAR_M), config, prior)
    np.testing.assert_array_equal(on_device[:, :-3].numpy(), on_cpu[:, :-3].numpy())  # the depth channels
    np.testing.assert_array_equal(on_device[:, -3:].numpy(), expected)
    assert tensor.channels(maps[:0]).shape == (0, 3, 100, 100)


def test_a_renderer_that_spreads_on_a_coarser_grid_is_refused() -> None:
    """At 256 x 256 the renderer computes the gel's elastic spread on a coarser grid: the tensor
    form does not draw that, and says so (the node keeps such a prior on the CPU)."""
    large = PhysicsPrior(PriorSpec(SCENE, CROP_M), 256)
    with pytest.raises(ModelConfigError, match="coarser grid"):
        large.on("cuda")


def test_a_prior_drawn_at_the_sensors_pixels_is_the_same_on_a_device() -> None:
    """Drawn at the GelSight's 120 x 160 pixels and area-averaged to the grid: the tensor form's
    average (OpenCV's INTER_AREA as two matrices) gives the CPU's levels within the stated
    tolerance, a level apart where the two round an average differently."""
    sensor = PhysicsPrior(PriorSpec(SCENE, CROP_M, pose_sigma_mm=0.5, drawn_at="sensor"), 100)
    assert sensor.renderer.config.shape == (120, 160)
    tensor = PhysicsPrior.on(sensor, "cpu")
    tensor._tensor = TensorPrior(sensor.renderer, (CROP_M[0], CROP_M[2]))  # the cuda form, on the CPU
    maps = analytic_contact_maps(12, seed=3, y_far_m=FAR_M)
    for sigma_mm in (0.0, 0.5):
        cpu, device = sensor.images(maps, sigma_mm), tensor.images(maps, sigma_mm)
        assert device.shape == cpu.shape == (12, 100, 100, 3)
        apart = np.abs(cpu.astype(int) - device.astype(int))
        assert np.mean(apart == 0) >= 0.99 and np.mean(apart <= 1) >= MIN_EQUAL
