"""SSIM as the paper evaluates it (Wang et al. 2004), batched in torch.

Gaussian window 11 x 11 with sigma 1.5, K1 = 0.01, K2 = 0.03, data range 255, population
(not sample) covariances, computed per RGB channel and averaged; only windows that lie
fully inside the image count. This equals ``skimage.metrics.structural_similarity(a, b,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255,
channel_axis=-1)``, which also discards the 5-pixel border.

One SSIM for the whole system: the models' evaluation and validation and the renderer's check
against real frames (``sim.gelsight_check``) all score with it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from perception.errors import ImageComparisonError

WINDOW = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03
DATA_RANGE = 255.0


def _gaussian_window(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The normalised 11-tap window, built in float64 and then cast to ``dtype`` (a float type):
    built in an integer dtype its weights would truncate to 0."""
    offsets = torch.arange(WINDOW, dtype=torch.float64, device=device) - (WINDOW - 1) / 2
    g = torch.exp(-0.5 * (offsets / SIGMA) ** 2)
    return (g / g.sum()).to(dtype)


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype SSIM is computed in for inputs of ``dtype``: float32 and float64 as given;
    bool and integers in float64 (exact for 0..255); float16 and bfloat16 in float32, since
    their range (65504) cannot hold the blurred squares of 8-bit levels."""
    if dtype in (torch.float32, torch.float64):
        return dtype
    if dtype in (torch.float16, torch.bfloat16):
        return torch.float32
    if dtype.is_complex:
        raise ImageComparisonError(f"SSIM compares real images, got {dtype}")
    return torch.float64


def _band_matrix(size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(size - 10) x size matrix whose row i holds the Gaussian window at columns i..i+10."""
    g = _gaussian_window(dtype, device)
    band = torch.zeros(size - WINDOW + 1, size, dtype=dtype, device=device)
    for i in range(size - WINDOW + 1):
        band[i, i : i + WINDOW] = g
    return band


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM of two N x C x H x W batches in image units (0..255); returns N values.

    N >= 0, C >= 1, H and W at least 11; every value finite in [0, 255] (the data range the
    constants assume); any real dtype, the two may differ. Computed in ``compute_dtype(a.dtype)``
    (float64 inputs match skimage to 1e-6). Anything else raises ImageComparisonError."""
    return ssim_map_torch(a, b).mean(dim=(2, 3)).mean(dim=1)


def ssim_map_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The SSIM of every 11 x 11 window: N x C x (H - 10) x (W - 10); window (i, j) is centred
    on pixel (i + 5, j + 5). Inputs as :func:`ssim_torch`."""
    if a.shape != b.shape or a.ndim != 4 or a.shape[1] < 1:
        raise ImageComparisonError(
            f"SSIM needs two N x C x H x W batches of one shape (C >= 1), got {tuple(a.shape)} and {tuple(b.shape)}"
        )
    if min(a.shape[2:]) < WINDOW:
        raise ImageComparisonError(f"SSIM needs images of at least {WINDOW} x {WINDOW}, got {tuple(a.shape[2:])}")
    dtype = compute_dtype(a.dtype)
    a, b = a.to(dtype), b.to(dtype=dtype, device=a.device)
    if a.numel():
        for name, x in (("a", a), ("b", b)):
            low, high = torch.aminmax(x)  # NaN propagates and fails both comparisons
            if not (low >= 0 and high <= DATA_RANGE):
                raise ImageComparisonError(
                    f"SSIM input {name} must be finite levels in [0, {DATA_RANGE:g}], "
                    f"got values in [{low.item()}, {high.item()}] (NaN or inf?)"
                )
    blur = _blur(a.shape[2:], dtype, a.device)
    return _ssim_map(blur(a), blur(a * a), blur(b), blur(b * b), blur(a * b))


def _blur(shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Callable[[torch.Tensor], torch.Tensor]:
    """The window's separable blur of ... x H x W images, 'valid' only (the result is exactly the
    border-cropped SSIM map), written as two band-matrix products: far faster on CPU than
    grouped convolutions."""
    rows = _band_matrix(shape[0], dtype, device)
    cols = _band_matrix(shape[1], dtype, device)
    return lambda x: rows @ x @ cols.T


def _ssim_map(
    mu_a: torch.Tensor, sq_a: torch.Tensor, mu_b: torch.Tensor, sq_b: torch.Tensor, blurred_ab: torch.Tensor
) -> torch.Tensor:
    """SSIM per window from the blurred images (``mu``), their blurred squares (``sq``) and the
    blurred product of the two."""
    var_a = sq_a - mu_a * mu_a
    var_b = sq_b - mu_b * mu_b
    cov = blurred_ab - mu_a * mu_b
    c1, c2 = (K1 * DATA_RANGE) ** 2, (K2 * DATA_RANGE) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def _rgb_pair(a: np.ndarray, b: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``a`` and ``b`` as arrays: two uint8 (N x) H x W x 3 images of one shape, or
    ImageComparisonError (a ValueError) naming the function ``what``."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != np.uint8 or b.dtype != np.uint8:
        raise ImageComparisonError(f"{what} compares uint8 images, got {a.dtype} and {b.dtype}")
    if a.shape != b.shape or a.ndim not in (3, 4) or a.shape[-1] != 3:
        raise ImageComparisonError(f"{what} needs two (N x) H x W x 3 arrays of one shape, got {a.shape}, {b.shape}")
    return a, b


def ssim_rgb(a: np.ndarray, b: np.ndarray, windows: np.ndarray | None = None) -> np.ndarray:
    """SSIM of uint8 RGB images: H x W x 3 pairs -> scalar array, N x H x W x 3 -> N values.

    ``windows`` ((N x) H x W bool) restricts the mean to the windows centred on True pixels
    (an image with none gets NaN); the 5-pixel border has no windows. Views of any strides
    (flipped, sliced) are accepted; other dtypes or shapes raise ImageComparisonError."""
    a, b = _rgb_pair(a, b, "ssim_rgb")
    mask = None if windows is None else _window_mask(windows, a.shape[:-1])
    flat_a, flat_b = a.reshape((-1,) + a.shape[-3:]), b.reshape((-1,) + b.shape[-3:])
    values = torch.empty(len(flat_a), dtype=torch.float64)
    for start in range(0, len(flat_a), _IMAGES_PER_BLUR):
        batch_a = _rgb_batch(flat_a[start : start + _IMAGES_PER_BLUR])
        batch_b = _rgb_batch(flat_b[start : start + _IMAGES_PER_BLUR])
        values[start : start + len(batch_a)] = (
            ssim_torch(batch_a, batch_b)
            if mask is None
            else _masked_mean(ssim_map_torch(batch_a, batch_b).mean(dim=1), mask[start : start + len(batch_a)])
        )
    return values.numpy().reshape(a.shape[:-3])


def ssim_pairs_rgb(a: np.ndarray, b: np.ndarray, pairs: np.ndarray, windows: np.ndarray | None = None) -> np.ndarray:
    """SSIM of ``a[i]`` against ``b[j]`` for each row (i, j) of ``pairs`` (K x 2 indices), as
    ``ssim_rgb(a[i], b[j], windows[i])`` gives each: ``a`` and ``b`` N x H x W x 3 and M x H x W x 3
    uint8 images of one size, ``windows`` (N x H x W bool) belonging to ``a``. Each image's blur
    and blurred square are computed once, not once a pair: a random-truth baseline compares each
    estimate with 15 truths. Bad input raises ImageComparisonError."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != np.uint8 or b.dtype != np.uint8:
        raise ImageComparisonError(f"ssim_pairs_rgb compares uint8 images, got {a.dtype} and {b.dtype}")
    if a.ndim != 4 or a.shape[1:] != b.shape[1:] or a.shape[-1] != 3:
        raise ImageComparisonError(
            f"ssim_pairs_rgb needs N x H x W x 3 stacks of one image size, got {a.shape}, {b.shape}"
        )
    if min(a.shape[1:3]) < WINDOW:
        raise ImageComparisonError(f"SSIM needs images of at least {WINDOW} x {WINDOW}, got {a.shape[1:3]}")
    pairs = np.asarray(pairs)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.dtype.kind not in "iu":
        raise ImageComparisonError(f"pairs must be K x 2 integer indices, got {pairs.dtype} {pairs.shape}")
    if not len(pairs):
        return np.empty(0)
    if pairs.min() < 0 or pairs[:, 0].max() >= len(a) or pairs[:, 1].max() >= len(b):
        raise ImageComparisonError(f"pairs index images that are not there ({len(a)} and {len(b)} images)")
    mask = None if windows is None else _window_mask(windows, a.shape[:-1])
    blur = _blur(a.shape[1:3], torch.float64, torch.device("cpu"))
    mu_a, sq_a = _blurred_moments(a, blur)
    mu_b, sq_b = _blurred_moments(b, blur)
    values = torch.empty(len(pairs), dtype=torch.float64)
    for start in range(0, len(pairs), _IMAGES_PER_BLUR):
        i, j = pairs[start : start + _IMAGES_PER_BLUR, 0], pairs[start : start + _IMAGES_PER_BLUR, 1]
        ssim_map = _ssim_map(mu_a[i], sq_a[i], mu_b[j], sq_b[j], blur(_rgb_batch(a[i]) * _rgb_batch(b[j])))
        chunk = ssim_map.mean(dim=(2, 3)).mean(dim=1) if mask is None else _masked_mean(ssim_map.mean(dim=1), mask[i])
        values[start : start + len(i)] = chunk
    return values.numpy()


# Images (or pairs) compared in one batch by ssim_rgb and ssim_pairs_rgb: small enough to stay in
# the caches (the demo's 360 test pairs in one batch took 2.1 s; its baseline's 5,400 pairs in
# batches of 64 7.9 s, of 256 22.8 s).
_IMAGES_PER_BLUR = 64


def _blurred_moments(
    images: np.ndarray, blur: Callable[[torch.Tensor], torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The blurred N x H x W x 3 uint8 ``images`` and their blurred squares, N x 3 x (H - 10) x (W - 10)."""
    mu, sq = [], []
    for start in range(0, len(images), _IMAGES_PER_BLUR):
        batch = _rgb_batch(images[start : start + _IMAGES_PER_BLUR])
        mu.append(blur(batch))
        sq.append(blur(batch * batch))
    return torch.cat(mu), torch.cat(sq)


def _rgb_batch(images: np.ndarray) -> torch.Tensor:
    """(N x) H x W x 3 uint8 images as an N x 3 x H x W float64 batch."""
    # torch.from_numpy refuses negative strides; ascontiguousarray copies only such views.
    flat = np.ascontiguousarray(images).reshape((-1,) + images.shape[-3:])
    return torch.from_numpy(flat).permute(0, 3, 1, 2).double()


def _window_mask(windows: np.ndarray, shape: tuple[int, ...]) -> torch.Tensor:
    """``windows`` ((N x) H x W bool, of ``shape``) as N x (H - 10) x (W - 10): the windows
    that lie inside the border, by their centres."""
    windows = np.asarray(windows)
    if windows.dtype != bool or windows.shape != shape:
        raise ImageComparisonError(f"windows must be bool of shape {shape}, got {windows.dtype} {windows.shape}")
    half = WINDOW // 2
    return torch.from_numpy(np.ascontiguousarray(windows).reshape((-1,) + shape[-2:]))[:, half:-half, half:-half]


def _masked_mean(per_window: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Each image's mean over its masked windows; NaN for an image with none."""
    counts = mask.sum(dim=(1, 2))
    sums = (per_window * mask).sum(dim=(1, 2))
    return torch.where(counts > 0, sums / counts.clamp(min=1), torch.tensor(float("nan"), dtype=sums.dtype))


# PSNR of identical images is infinite; the cap keeps means and JSON finite (an 8-bit image one
# level off everywhere scores 48 dB, so the cap is never reached by a real difference).
PSNR_MAX_DB = 100.0


def psnr_rgb(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """PSNR (dB, peak 255) of uint8 RGB images over all pixels and channels: H x W x 3 pairs ->
    scalar array, N x H x W x 3 -> N values; capped at :data:`PSNR_MAX_DB`. Images of no pixel
    have no mean error: ImageComparisonError, as for other dtypes or shapes."""
    a, b = _rgb_pair(a, b, "psnr_rgb")
    if a.shape[-3] * a.shape[-2] == 0:
        raise ImageComparisonError(f"psnr_rgb needs images of at least one pixel, got {a.shape}")
    mse = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).reshape((-1,) + a.shape[-3:]).mean(axis=(1, 2, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        psnr = 10.0 * np.log10(DATA_RANGE**2 / mse)
    return np.minimum(psnr, PSNR_MAX_DB).reshape(a.shape[:-3])
