"""Generator, discriminator, initialisation, SSIM and the network input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from skimage.metrics import structural_similarity

from models.data import depth_input, image_target, to_uint8_rgb
from models.networks import (
    DiscriminatorConfig,
    GeneratorConfig,
    ModelConfigError,
    PatchDiscriminator,
    UNetGenerator,
    init_weights,
)
from perception.normalisation import normalise_depth_map
from perception.ssim import ssim_rgb, ssim_torch

torch.set_num_threads(1)


@pytest.mark.parametrize("num_downs, pad_to, in_channels", [(7, 128, 1), (4, 112, 2), (6, 128, 1)])
def test_generator_maps_100x100_depth_to_rgb_in_tanh_range(num_downs: int, pad_to: int, in_channels: int) -> None:
    torch.manual_seed(0)
    config = GeneratorConfig(
        in_channels=in_channels, ngf=8, num_downs=num_downs, pad_to=pad_to, dropout_blocks=min(3, num_downs - 2)
    )
    generator = UNetGenerator(config)
    init_weights(generator)
    out = generator(torch.randn(2, in_channels, 100, 100))
    assert out.shape == (2, 3, 100, 100) and out.abs().max() <= 1.0
    dropouts = [m for m in generator.modules() if isinstance(m, torch.nn.Dropout)]
    assert len(dropouts) == config.dropout_blocks


def test_generator_output_depends_on_every_input_region_through_the_skips() -> None:
    torch.manual_seed(0)
    generator = UNetGenerator(GeneratorConfig(ngf=8)).eval()
    x = torch.zeros(1, 1, 100, 100, requires_grad=True)
    generator(x)[0, :, 50, 50].sum().backward()
    assert x.grad[0, 0, 50, 50] != 0 and x.grad[0, 0, 0, 0] != 0  # 1 x 1 bottleneck sees everything


def test_discriminator_gives_10x10_patch_logits_and_init_is_n_0_002() -> None:
    torch.manual_seed(0)
    discriminator = PatchDiscriminator(DiscriminatorConfig(in_channels=4, ndf=64))
    init_weights(discriminator)
    logits = discriminator(torch.randn(3, 1, 100, 100), torch.randn(3, 3, 100, 100))
    assert logits.shape == (3, 1, 10, 10)
    weights = torch.cat(
        [m.weight.detach().flatten() for m in discriminator.modules() if isinstance(m, torch.nn.Conv2d)]
    )
    assert abs(float(weights.mean())) < 1e-3 and abs(float(weights.std()) - 0.02) < 1e-3
    strides = [m.stride[0] for m in discriminator.modules() if isinstance(m, torch.nn.Conv2d)]
    assert strides == [2, 2, 2, 1, 1]


@pytest.mark.parametrize(
    "change, message",
    [
        ({"in_channels": 3}, "in_channels"),
        ({"pad_to": 100}, "multiple of"),
        ({"pad_to": 64, "num_downs": 4}, "pad_to"),
        ({"dropout": 1.0}, "dropout"),
        ({"num_downs": 4, "pad_to": 112, "dropout_blocks": 3}, "dropout_blocks"),
    ],
)
def test_bad_generator_config_is_refused(change: dict, message: str) -> None:
    with pytest.raises(ModelConfigError, match=message):
        GeneratorConfig(**change).validate()


def test_generator_refuses_wrong_input_shape_and_unknown_settings() -> None:
    generator = UNetGenerator(GeneratorConfig(ngf=4))
    with pytest.raises(ModelConfigError, match="N x 1 x 100 x 100"):
        generator(torch.zeros(1, 1, 64, 64))
    with pytest.raises(ModelConfigError, match="unknown generator setting"):
        GeneratorConfig.from_dict({"ngf": 8, "width": 3})
    with pytest.raises(ModelConfigError, match="must be int"):
        GeneratorConfig.from_dict({"ngf": "8"})


def _skimage_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=255,
        K1=0.01,
        K2=0.03,
        channel_axis=-1,
    )


@settings(max_examples=25, deadline=None)
@given(a=arrays(np.uint8, (24, 31, 3)), noise=arrays(np.int16, (24, 31, 3), elements=st.integers(-60, 60)))
def test_ssim_equals_skimage_with_the_papers_settings(a: np.ndarray, noise: np.ndarray) -> None:
    b = np.clip(a.astype(np.int16) + noise, 0, 255).astype(np.uint8)
    assert ssim_rgb(a, b) == pytest.approx(_skimage_ssim(a, b), abs=1e-9)


@settings(max_examples=25, deadline=None)
@given(a=arrays(np.uint8, (2, 16, 16, 3)), b=arrays(np.uint8, (2, 16, 16, 3)))
def test_ssim_is_symmetric_at_most_one_and_one_for_identical_images(a: np.ndarray, b: np.ndarray) -> None:
    ab, ba = ssim_rgb(a, b), ssim_rgb(b, a)
    np.testing.assert_allclose(ab, ba, atol=1e-12)
    assert np.all(ab <= 1.0 + 1e-12) and np.allclose(ssim_rgb(a, a), 1.0)


def test_ssim_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="uint8"):
        ssim_rgb(np.zeros((16, 16, 3)), np.zeros((16, 16, 3)))
    with pytest.raises(ValueError, match="at least 11"):
        ssim_rgb(np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="NaN"):
        ssim_torch(torch.full((1, 3, 16, 16), float("nan")), torch.zeros(1, 3, 16, 16))


@settings(max_examples=30, deadline=None)
@given(
    depth=arrays(
        np.float32,
        (2, 12, 12),
        elements=st.one_of(st.floats(-0.0078125, 0.0078125, width=32), st.just(np.nan), st.just(np.inf)),
    )
)
def test_network_input_is_normalised_depth_and_validity_mask(depth: np.ndarray) -> None:
    x = depth_input(depth, (-0.0015, 0.0025), in_channels=2).numpy()
    assert x.shape == (2, 2, 12, 12) and x.dtype == np.float32
    assert np.all(np.abs(x) <= 1.0)
    np.testing.assert_array_equal(x[:, 0], normalise_depth_map(depth, (-0.0015, 0.0025)))
    np.testing.assert_array_equal(x[:, 1] > 0, np.isfinite(depth) & (depth < 0.0025))
    assert np.all(x[:, 0][~np.isfinite(depth)] == 1.0)  # empty bins read as far away


def test_network_input_refuses_bad_depth_maps() -> None:
    with pytest.raises(ModelConfigError, match="N x H x W"):
        depth_input(np.zeros((100, 100), np.float32), (-0.001, 0.001), 1)
    with pytest.raises(ModelConfigError, match="non-empty"):
        depth_input(np.zeros((0, 100, 100), np.float32), (-0.001, 0.001), 1)
    with pytest.raises(ModelConfigError, match="-inf"):
        depth_input(np.full((1, 4, 4), -np.inf, np.float32), (-0.001, 0.001), 1)


@settings(max_examples=30, deadline=None)
@given(images=arrays(np.uint8, (2, 5, 7, 3)))
def test_image_scaling_round_trips(images: np.ndarray) -> None:
    np.testing.assert_array_equal(to_uint8_rgb(image_target(images)), images)


@settings(max_examples=60, deadline=None)
@given(
    units=arrays(
        np.float32,
        st.tuples(st.integers(1, 3), st.integers(1, 4), st.integers(1, 6), st.integers(1, 9)),
        elements=st.one_of(
            st.floats(-1.5, 1.5, width=32),
            st.sampled_from([-1.0, 1.0, 0.0, -0.0, -0.99, 0.99, np.inf, -np.inf, 1e30, -1e30]),
            # Exactly between two levels after the scale: rounding takes the even one.
            st.integers(0, 254).map(lambda level: np.float32((level + 0.5) / 127.5 - 1.0)),
        ),
    )
)
def test_property_images_are_levelled_as_pytorch_levels_them(units: np.ndarray) -> None:
    """The compiled levelling gives PyTorch's round((x + 1) * 127.5), clipped to 0..255, in float32,
    for any channels and sizes: levels, halves, out of range, infinities; channels last."""
    tensor = torch.from_numpy(units)
    expected = ((tensor + 1.0) * 127.5).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
    levels = to_uint8_rgb(tensor)
    assert levels.flags.c_contiguous
    np.testing.assert_array_equal(levels, expected)


def test_learned_background_is_where_the_generator_starts() -> None:
    """With ``background`` the generator draws only the change from a learned image: with its
    last layer silent it returns exactly the image it was started from."""
    generator = UNetGenerator(GeneratorConfig(ngf=4, background=True))
    mean_image = torch.linspace(-0.9, 0.9, 3 * 100 * 100).reshape(3, 100, 100)
    generator.set_background(mean_image)
    last = generator.output[1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    out = generator.eval()(torch.zeros(2, 1, 100, 100))
    torch.testing.assert_close(out, mean_image.expand(2, -1, -1, -1), atol=1e-6, rtol=0)
    with pytest.raises(ModelConfigError, match="no learned background"):
        UNetGenerator(GeneratorConfig(ngf=4)).set_background(mean_image)
