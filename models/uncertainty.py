"""The served estimate's uncertainty: per pixel, in image levels (0..255), how far the estimate
is expected to be from what the sensor shows.

What the physics prior cannot draw is the session's residual: the gel's micro-relief, the
sensor's noise, and what is left of the registration's pose error at a contact's rim. A small
convolutional network (:class:`UncertaintyNet`, ~6k weights, a twentieth of the generator's
time) reads the served estimate's input and the estimate itself and answers a per-pixel scale
sigma, fitted to the training split's residuals by the Gaussian negative log-likelihood of
e = |estimate - truth| (the three channels' mean), whose minimum is sigma = RMS(e) given the
input. The network's sigma is then calibrated on the validation split (:class:`Calibration`):
in each decile of the raw sigma, the served value is scaled so that RMS(e) / u = 1.

Dropout sampling (pix2pix's noise z, which the served generator was held to its prior by) gave a
spread uncorrelated with the error (r = -0.002 per pixel on the demo's test split); this replaces it.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
import torch
from torch import nn

from models.errors import ModelConfigError

LEVELS_PER_TANH_UNIT = 127.5  # network images are in [-1, 1]; tactile images in 0..255
DECILES = 10
# The deciles of u that the per-object figures call high: where a contact's error is.
HIGH_DECILES = 3


@dataclasses.dataclass(frozen=True)
class UncertaintyConfig:
    """width: channels of the uncertainty network's layers; the rest is its fit's schedule."""

    width: int = 16
    epochs: int = 6
    batch_size: int = 32
    lr: float = 3e-3
    seed: int = 0

    def validate(self) -> "UncertaintyConfig":
        if min(self.width, self.epochs, self.batch_size) < 1 or not self.lr > 0:
            raise ModelConfigError(f"uncertainty: width, epochs, batch_size must be >= 1 and lr > 0, got {self}")
        return self


class UncertaintyNet(nn.Module):
    """(network input N x C x H x W, estimate N x 3 x H x W in [-1, 1]) -> N x H x W sigma in
    image levels. Computed on a quarter-resolution grid (the inputs averaged over 4 x 4 pixels)
    with four 3 x 3 convolutions, two of them dilated (a 13-cell field: 52 pixels, a contact's
    rim and what surrounds it), and upsampled bilinearly: the error's scale varies smoothly.
    Measured on one loaded core, 64 regions a batch: 0.33 ms a region here, against 2.1 ms at
    half resolution and 7.4 ms for the default generator."""

    DOWNSAMPLE = 4

    def __init__(self, input_channels: int, width: int) -> None:
        super().__init__()
        self.input_channels = input_channels
        self.layers = nn.Sequential(
            nn.Conv2d(input_channels + 3, width, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2),
            nn.ReLU(),
            nn.Conv2d(width, 1, 3, padding=1),
        )

    def forward(self, network_input: torch.Tensor, estimate: torch.Tensor) -> torch.Tensor:
        # Pooled apart, then joined: the same numbers as pooling the joined inputs, without
        # copying the full-resolution channels into one tensor first (0.080 -> 0.066 ms a region).
        coarse = torch.cat(
            [nn.functional.avg_pool2d(part, self.DOWNSAMPLE, ceil_mode=True) for part in (network_input, estimate)],
            dim=1,
        )
        log_sigma = nn.functional.interpolate(
            self.layers(coarse), size=estimate.shape[-2:], mode="bilinear", align_corners=False
        )
        return log_sigma[:, 0].clamp(-4.0, 6.0).exp()


def pixel_error_levels(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """e: |estimate - truth| averaged over the three channels (N x H x W float32, image levels),
    of N x H x W x 3 uint8 images."""
    return np.abs(estimate.astype(np.float32) - truth.astype(np.float32)).mean(axis=-1)


@dataclasses.dataclass(frozen=True)
class Calibration:
    """The raw sigma's deciles on the validation split (``raw_levels``: their mean sigma, rising)
    and what multiplies a raw sigma there (``scale``: RMS(e) / mean sigma of the decile),
    interpolated between deciles and held at the ends."""

    raw_levels: tuple[float, ...]
    scale: tuple[float, ...]

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """u: ``raw`` (any shape, float32 or float64) times its scale, float32: (raw *
        np.interp(raw, raw_levels, scale)).astype(np.float32), to the bit (:func:`_calibrated`)."""
        values = np.ascontiguousarray(raw)
        if values.dtype not in (np.float32, np.float64):
            values = values.astype(np.float64)
        out = np.empty(values.shape, np.float32)
        _calibrated(
            values.reshape(-1),
            np.asarray(self.raw_levels, np.float64),
            np.asarray(self.scale, np.float64),
            out.reshape(-1),
        )
        return out

    def apply_on_device(self, raw: torch.Tensor) -> torch.Tensor:
        """:meth:`apply` as tensor operations where ``raw`` is (a GPU's: only u's float32 leaves
        it, not the raw sigma for a host pass, which took 4.4-4.9 ms of a 64-region request on a
        lent H200's host): the same float64 steps, each its own operation (no fused multiply-add),
        so the same bits (tests/test_models_uncertainty.py)."""
        last = len(self.raw_levels) - 1
        levels = torch.tensor(self.raw_levels, dtype=torch.float64, device=raw.device)
        scale = torch.tensor(self.scale, dtype=torch.float64, device=raw.device)
        slopes = torch.zeros(max(last, 1), dtype=torch.float64, device=raw.device)
        slopes[:last] = (scale[1:] - scale[:-1]) / (levels[1:] - levels[:-1])
        x = raw.double()
        j = (x.unsqueeze(-1) >= levels[1:last]).sum(dim=-1)
        s = slopes[j] * (x - levels[j]) + scale[j]
        s = torch.where(x < levels[0], scale[0], s)
        s = torch.where(x >= levels[last], scale[last], s)
        return (x * s).float()

    @staticmethod
    def fit(raw: np.ndarray, error: np.ndarray) -> "Calibration":
        """From raw sigmas and the errors e at the same pixels (any shape, same size)."""
        raw_flat, error_flat = raw.ravel(), error.ravel()
        # np.interp needs rising knots: deciles of equal mean sigma (ties) are pooled into one.
        pooled: list[np.ndarray] = []
        for group in decile_groups(raw_flat):
            if pooled and raw_flat[group].mean() <= raw_flat[pooled[-1]].mean():
                pooled[-1] = np.concatenate([pooled[-1], group])
            else:
                pooled.append(group)
        levels = [float(raw_flat[g].mean()) for g in pooled]
        scale = [float(np.sqrt(np.mean(np.square(error_flat[g]))) / max(raw_flat[g].mean(), 1e-6)) for g in pooled]
        return Calibration(tuple(levels), tuple(scale))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _calibrated(raw: np.ndarray, levels: np.ndarray, scale: np.ndarray, out: np.ndarray) -> None:
    """out[i] = raw[i] * np.interp(raw[i], levels, scale), rounded once to float32, in
    np.interp's own arithmetic: each knot interval's slope computed once, (scale[j + 1] -
    scale[j]) / (levels[j + 1] - levels[j]), times the value's distance from its lower knot, plus
    that knot's scale; a value on a knot takes its scale, one outside them the end's (NaN stays
    NaN); of equal knots (Calibration.fit can round two deciles' means to one) the last is the
    value's. Why not np.interp: it bisects the knots for each of a served region's 10,000 values,
    0.05 ms a region (0.13 for values spread over its range); with ten knots, counting those at or
    below a value is a compiled pass without a branch: the same bits in half the time."""
    last = levels.shape[0] - 1
    slopes = np.zeros(max(last, 1))
    for j in range(last):
        slopes[j] = (scale[j + 1] - scale[j]) / (levels[j + 1] - levels[j])
    for i in range(raw.shape[0]):
        x = np.float64(raw[i])
        j = 0
        for k in range(1, last):
            j += x >= levels[k]
        s = slopes[j] * (x - levels[j]) + scale[j]
        s = scale[0] if x < levels[0] else s
        s = scale[last] if x >= levels[last] else s
        out[i] = np.float32(x * s)


def decile_groups(values: np.ndarray) -> list[np.ndarray]:
    """The indices of ``values`` (1-D) in each of its ten deciles, lowest first (ties broken by
    position, so that every decile holds a tenth)."""
    order = np.argsort(values, kind="stable")
    return [chunk for chunk in np.array_split(order, DECILES) if len(chunk)]


@dataclasses.dataclass(frozen=True)
class SensorFloor:
    """What a lab's own sensor adds to u (models.sensor_floor fits it from the lab's ball
    presses): per pixel, image levels (H x W float32, >= 0), the served estimate's RMS error on
    the lab's real frames beyond what the checkpoint's u says. ``source``: the presses file and
    how many presses it was fitted on, for the checkpoint to say what it serves."""

    levels: np.ndarray
    source: dict[str, Any]

    def __post_init__(self) -> None:
        levels = self.levels
        shaped = levels.ndim == 2 and levels.size > 0 and levels.dtype == np.float32
        if not (shaped and np.all(np.isfinite(levels)) and levels.min() >= 0):
            raise ModelConfigError(
                f"a sensor floor is an H x W float32 map of finite levels >= 0, got {levels.dtype} {levels.shape}"
            )

    def added(self, u: np.ndarray) -> np.ndarray:
        """sqrt(u^2 + floor^2), float32, of u (N x H x W float32): the sensor's light and what u
        says of the estimate are independent causes of the error, so their variances add. Each
        step in float64, so that :meth:`added_on_device` gives the same bits; in place, half the time
        of a temporary at each step (0.03 against 0.07 ms a region)."""
        floor = self.levels.astype(np.float64)
        wide = u.astype(np.float64)
        wide *= wide
        wide += floor * floor
        return np.sqrt(wide, out=wide).astype(np.float32)

    def added_on_device(self, u: torch.Tensor) -> torch.Tensor:
        """:meth:`added` where ``u`` is (a GPU's), the same float64 steps."""
        wide, floor = u.double(), torch.from_numpy(self.levels).to(u.device).double()
        return torch.sqrt(wide * wide + floor * floor).float()


class ServedUncertainty:
    """The uncertainty a checkpoint serves: the network and its calibration, and the floor of the
    lab's sensor where ``dtx calibrate uncertainty`` gave it one."""

    def __init__(
        self,
        net: UncertaintyNet,
        calibration: Calibration,
        config: UncertaintyConfig,
        floor: SensorFloor | None = None,
    ) -> None:
        self.net, self.calibration, self.config, self.floor = net.eval(), calibration, config, floor

    def to(self, device: str) -> "ServedUncertainty":
        """This uncertainty computing on ``device`` (cpu | cuda), where the network's input is."""
        return ServedUncertainty(copy.deepcopy(self.net).to(device), self.calibration, self.config, self.floor)

    @torch.inference_mode()
    def levels(self, network_input: torch.Tensor, estimate: torch.Tensor, sensor_floor: bool = True) -> np.ndarray:
        """N x H x W float32 u, image levels, for the estimate (N x 3 x H x W, [-1, 1]) of
        ``network_input``, computed where this uncertainty's network is (:meth:`to`); with the
        sensor's floor where there is one, unless ``sensor_floor`` is False (the checkpoint's own u)."""
        device = next(self.net.parameters()).device
        raw = self.net(network_input.float().to(device), estimate.float().to(device))
        floor = self.floor if sensor_floor else None
        if device.type == "cpu":
            u = self.calibration.apply(raw.numpy())
            return u if floor is None else floor.added(u)
        on_device = self.calibration.apply_on_device(raw)
        return (on_device if floor is None else floor.added_on_device(on_device)).cpu().numpy()

    def floor_source(self) -> dict[str, Any] | None:
        """The presses file the sensor floor was fitted on (name, count, SHA-256); None without one."""
        return None if self.floor is None else dict(self.floor.source)

    def reply_note(self) -> str:
        """What a reply's ``model`` adds of this uncertainty: the sensor whose floor it carries."""
        source = self.floor_source()
        return (
            ""
            if source is None
            else f" (its uncertainty with the floor of the sensor of {source.get('file', 'unnamed presses')})"
        )

    def to_state(self) -> dict[str, Any]:
        state = {
            "config": dataclasses.asdict(self.config),
            "weights": self.net.state_dict(),
            "input_channels": self.net.input_channels,
            "calibration": {"raw_levels": list(self.calibration.raw_levels), "scale": list(self.calibration.scale)},
        }
        if self.floor is not None:
            state["sensor_floor"] = {"levels": torch.from_numpy(self.floor.levels), "source": dict(self.floor.source)}
        return state

    @staticmethod
    def from_state(state: dict[str, Any]) -> "ServedUncertainty":
        try:
            config = UncertaintyConfig(**state["config"]).validate()
            net = UncertaintyNet(int(state["input_channels"]), config.width)
            net.load_state_dict(state["weights"])
            calibration = Calibration(
                tuple(float(v) for v in state["calibration"]["raw_levels"]),
                tuple(float(v) for v in state["calibration"]["scale"]),
            )
            floor = state.get("sensor_floor")
            if floor is not None:
                floor = SensorFloor(np.asarray(floor["levels"]), dict(floor["source"]))
        except (KeyError, TypeError, RuntimeError) as err:
            raise ModelConfigError(f"the checkpoint's uncertainty entry is not readable: {err}") from err
        if len(calibration.raw_levels) != len(calibration.scale) or not calibration.raw_levels:
            raise ModelConfigError("the checkpoint's uncertainty calibration has no deciles, or unequal lists")
        return ServedUncertainty(net, calibration, config, floor)


def fit_uncertainty(
    x_train: torch.Tensor,
    estimate_train: torch.Tensor,
    error_train: torch.Tensor,
    x_val: torch.Tensor,
    estimate_val: torch.Tensor,
    error_val: np.ndarray,
    config: UncertaintyConfig,
    log: Any = None,
) -> ServedUncertainty:
    """Fit the network on the training pairs (inputs, estimates in [-1, 1], errors e in levels,
    N x H x W) and calibrate it on the validation pairs'. Seeded: the same data and config give
    the same weights on the CPU."""
    config.validate()
    generator = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    net = UncertaintyNet(x_train.shape[1], config.width)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr)
    steps = config.epochs * -(-len(x_train) // config.batch_size)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, config.lr, total_steps=steps)
    net.train()
    for epoch in range(config.epochs):
        order = torch.randperm(len(x_train), generator=generator)
        total = 0.0
        for start in range(0, len(order), config.batch_size):
            batch = order[start : start + config.batch_size]
            sigma = net(x_train[batch], estimate_train[batch])
            loss = (sigma.log() + 0.5 * (error_train[batch] / sigma).square()).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            total += float(loss.detach()) * len(batch)
        if log is not None:
            log(f"uncertainty epoch {epoch + 1}/{config.epochs}: Gaussian NLL {total / len(x_train):.4f}")
    net.eval()
    with torch.inference_mode():
        raw = np.concatenate(
            [net(x_val[i : i + 64], estimate_val[i : i + 64]).numpy() for i in range(0, len(x_val), 64)]
        )
    return ServedUncertainty(net, Calibration.fit(raw, error_val), config)


def uncertainty_statistics(
    uncertainty: np.ndarray,
    estimate: np.ndarray,
    truth: np.ndarray,
    region_dissimilarity: np.ndarray,
    objects: Sequence[str] | None = None,
) -> dict[str, Any]:
    """How well u (N x H x W, levels) predicts the error of ``estimate`` against ``truth`` (N x H x
    W x 3 uint8): Pearson r(u, e) over pixels; per region r(mean u, ``region_dissimilarity``, 1 -
    SSIM); per decile of u its mean, RMS(e) and their ratio (1: calibrated); and, given the N
    pairs' ``objects`` names, each object's figures (:func:`_per_object`)."""
    if objects is not None and len(objects) != len(uncertainty):
        raise ModelConfigError(f"{len(objects)} object names for {len(uncertainty)} uncertainty maps")
    error = pixel_error_levels(estimate, truth)
    u, e = uncertainty.ravel().astype(np.float64), error.ravel().astype(np.float64)
    groups = decile_groups(u)
    deciles = []
    for group in groups:
        mean_u, rms_e = float(u[group].mean()), _rms(e[group])
        deciles.append({"u_mean": mean_u, "e_rms": rms_e, "ratio": rms_e / mean_u if mean_u > 0 else float("nan")})
    region_u = uncertainty.reshape(len(uncertainty), -1).mean(axis=1)
    figures = {
        "n": len(uncertainty),
        "u_mean_levels": float(u.mean()),
        "e_mean_levels": float(e.mean()),
        "pearson_pixel": _pearson(u, e),
        "pearson_region": _pearson(region_u, np.asarray(region_dissimilarity, np.float64)),
        "deciles": deciles,
        "decile_ratio_min": min(d["ratio"] for d in deciles),
        "decile_ratio_max": max(d["ratio"] for d in deciles),
    }
    if objects is not None:
        high = np.zeros(u.size, bool)
        high[np.concatenate(groups[-HIGH_DECILES:])] = True
        figures["objects"] = _per_object(u, e, high, np.asarray(objects), uncertainty[0].size)
    return figures


def _per_object(
    u: np.ndarray, e: np.ndarray, high: np.ndarray, objects: np.ndarray, pixels_per_pair: int
) -> dict[str, dict[str, Any]]:
    """Whether u tells the objects apart (u, e and ``high`` flat, one entry a pixel, pair by pair;
    ``objects`` the pairs' names): per object, its pairs, r(u, e) over its pixels, and where u is ``high`` (the
    set's top ``HIGH_DECILES`` deciles) its share of those pixels, mean u and RMS(e) there. A u
    that knows each object's error has RMS(e) / mean u near 1 on every object there; one that
    learned the objects' mix says the same u on an object that misses by much and one that
    misses by little."""
    pixel_object = np.repeat(objects, pixels_per_pair)
    figures: dict[str, dict[str, Any]] = {}
    for name in sorted(set(objects)):
        mine = pixel_object == name
        there = mine & high
        row: dict[str, Any] = {
            "n": int(np.count_nonzero(objects == name)),
            "pearson_pixel": _pearson(u[mine], e[mine]),
            "high_u_share": float(np.count_nonzero(there) / np.count_nonzero(high)),
        }
        if not np.isfinite(row["pearson_pixel"]):
            row["pearson_pixel_undefined"] = "u or e is the same at every pixel of the object"
        if there.any():
            row["high_u_mean"], row["high_e_rms"] = float(u[there].mean()), _rms(e[there])
        else:
            row["high_u_mean"] = row["high_e_rms"] = float("nan")
            row["high_u_mean_undefined"] = row["high_e_rms_undefined"] = "no pixel of the object is in u's top deciles"
        figures[name] = row
    return figures


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 2 or np.std(a) == 0 or np.std(b) == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


UNCERTAINTY_ABSENT = "the checkpoint serves no uncertainty (trained before it; dtx fit-serving CHECKPOINT fits one)"


def served_uncertainty_statistics(
    uncertainty: np.ndarray | None,
    estimate: np.ndarray,
    truth: np.ndarray,
    region_dissimilarity: np.ndarray,
    objects: Sequence[str] | None = None,
) -> dict[str, Any]:
    """:func:`uncertainty_statistics` of the served uncertainty; ``absent`` with the reason when
    the checkpoint has none."""
    if uncertainty is None:
        return {"absent": UNCERTAINTY_ABSENT}
    return uncertainty_statistics(uncertainty, estimate, truth, region_dissimilarity, objects)


def uncertainty_table(figures: dict[str, Any]) -> list[str]:
    """The uncertainty's lines of the summary: its correlations and its decile table."""
    if "absent" in figures:
        return [f"uncertainty: absent ({figures['absent']})"]
    floor = figures.get("sensor_floor")
    lines = [] if floor is None else [f"uncertainty with the floor of the sensor of {floor.get('file', '?')}"]
    lines += [
        f"{'uncertainty r (pixel/region)':28s}{figures['pearson_pixel']:>13.3f} / {figures['pearson_region']:.3f}"
        f"   mean u {figures['u_mean_levels']:.2f}, mean e {figures['e_mean_levels']:.2f} levels",
        f"{'  decile of u':28s}" + "".join(f"{i + 1:>7d}" for i in range(len(figures["deciles"]))),
        f"{'  mean u (levels)':28s}" + "".join(f"{d['u_mean']:>7.2f}" for d in figures["deciles"]),
        f"{'  RMS e / mean u':28s}" + "".join(f"{d['ratio']:>7.2f}" for d in figures["deciles"]),
    ]
    if "objects" in figures:
        lines.append(f"  per object: r(u, e); where u is in its top {HIGH_DECILES} deciles, its share, mean u, RMS e")
        lines += [
            f"    {name:24s} r {row['pearson_pixel']:6.3f}   share {row['high_u_share']:.2f}"
            f"   u {row['high_u_mean']:5.2f}   e {row['high_e_rms']:5.2f}"
            for name, row in figures["objects"].items()
        ]
    return lines
