"""pix2pix networks for 100 x 100 depth-maps: U-Net generator and 70 x 70 PatchGAN.

Generator size: the stock pix2pix U-Nets halve the image down to 1 x 1 (7 times for 128 x 128,
8 for 256 x 256) and cannot take 100 x 100, which is divisible by 2 only twice. ``UNetGenerator`` therefore
replicate-pads the input to ``pad_to`` (a multiple of 2 ** num_downs; edge bins
repeat, i.e. "no new surface there") and crops the output back to 100 x 100. The default,
``num_downs=7, pad_to=128``, keeps the stock depth (1 x 1 bottleneck, whole-patch receptive
field); ``num_downs=4, pad_to=112`` is the shallow alternative (7 x 7 bottleneck, 1.3x fewer
pixels). Measured after one epoch on the 578-sample synthetic dataset (ngf 32, batch 8,
same seed, 2 shared CPU cores): 128/7 gave validation SSIM 0.745 and L1 0.066 in 287 s,
112/4 gave 0.720 and 0.124 in 250 s. The stock depth learns much faster for 13 % more
time, so it is the default (``configs/*.yaml``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import torch
from torch import nn

from models.errors import ModelConfigError
from msgs import config as typed_config

C = TypeVar("C")


@dataclasses.dataclass(frozen=True)
class GeneratorConfig:
    """in_channels: 1 (depth) or 2 (depth + validity mask); ngf: width of the first layer;
    background: add a learned image (the sensor's no-contact frame, in tanh's input units)
    to the last layer's output, so the network draws only what the contact changes;
    prior: the input carries 3 more channels, the physics prior's image of the same depth-map
    (models.prior), which is also added to the output (in tanh's input units): the network
    learns the correction to physics; prior_drawn_at: where the prior's renderer draws
    (models.prior.PRIOR_DRAWN_AT), and prior_drawn_rows the rows of square pixels it draws the
    sensor's field on (0: the sensor's own; models.prior.PriorSpec)."""

    in_channels: int = 1
    out_channels: int = 3
    ngf: int = 64
    num_downs: int = 7
    pad_to: int = 128
    image_size: int = 100
    dropout: float = 0.5
    dropout_blocks: int = 3
    background: bool = False
    prior: bool = False
    prior_drawn_at: str = "grid"
    prior_drawn_rows: int = 0

    @property
    def input_channels(self) -> int:
        """Channels of the network's input: the depth channels, and the prior's image if any."""
        return self.in_channels + (3 if self.prior else 0)

    def validate(self) -> "GeneratorConfig":
        if self.in_channels not in (1, 2):
            raise ModelConfigError(f"in_channels must be 1 (depth) or 2 (depth + mask), got {self.in_channels}")
        if self.out_channels < 1 or self.ngf < 1:
            raise ModelConfigError(f"out_channels and ngf must be positive, got {self.out_channels}, {self.ngf}")
        if self.num_downs < 2:
            raise ModelConfigError(f"num_downs must be at least 2, got {self.num_downs}")
        if self.pad_to < self.image_size or self.pad_to % (2**self.num_downs):
            raise ModelConfigError(
                f"pad_to={self.pad_to} must be >= image_size={self.image_size} and a "
                f"multiple of 2**num_downs={2**self.num_downs}"
            )
        if self.prior_drawn_at not in ("grid", "sensor"):
            raise ModelConfigError(f"prior_drawn_at must be 'grid' or 'sensor', got {self.prior_drawn_at!r}")
        rows = self.prior_drawn_rows
        if not (isinstance(rows, int) and not isinstance(rows, bool) and rows >= 0):
            raise ModelConfigError(f"prior_drawn_rows must be an integer >= 0 (0: the sensor's own), got {rows!r}")
        if rows and self.prior_drawn_at != "sensor":
            raise ModelConfigError(
                f"prior_drawn_rows ({rows}) draws the sensor's field: it needs prior_drawn_at 'sensor'"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ModelConfigError(f"dropout must be in [0, 1), got {self.dropout}")
        if not 0 <= self.dropout_blocks <= self.num_downs - 2:
            raise ModelConfigError(
                f"dropout_blocks must be in [0, num_downs - 2] (decoder blocks between the "
                f"bottleneck and the output), got {self.dropout_blocks}"
            )
        return self

    @staticmethod
    def from_dict(data: dict[str, Any]) -> "GeneratorConfig":
        return config_from_dict(GeneratorConfig, data, "generator").validate()


@dataclasses.dataclass(frozen=True)
class DiscriminatorConfig:
    """in_channels: the conditioning channels (depth [+ mask]) plus the 3 image channels."""

    in_channels: int = 4
    ndf: int = 64

    def validate(self) -> "DiscriminatorConfig":
        if self.in_channels < 2 or self.ndf < 1:
            raise ModelConfigError(
                f"discriminator needs in_channels >= 2 and ndf >= 1, got {self.in_channels}, {self.ndf}"
            )
        return self


def config_from_dict(cls: type[C], data: dict[str, Any], what: str) -> C:
    """A config dataclass from a mapping (e.g. YAML), checked by msgs.config; any problem is a
    ModelConfigError naming ``what`` ("generator", "training config") and the key."""
    try:
        return typed_config.config_from_dict(cls, data, noun=f"{what} setting")
    except typed_config.ConfigError as exc:
        raise ModelConfigError(f"{what}: {exc}") from None


class UNetGenerator(nn.Module):
    """Depth-map (N x C x 100 x 100, normalised to [-1, 1]) -> RGB (N x 3 x 100 x 100, [-1, 1]).

    Encoder blocks: LeakyReLU(0.2) - conv 4x4 stride 2 - BatchNorm (the first block has no
    activation before and no norm; the innermost no norm). Decoder blocks: ReLU - transposed
    conv 4x4 stride 2 - BatchNorm, with dropout in the ``dropout_blocks`` blocks right above
    the bottleneck (pix2pix's noise z); each decoder block after the first takes its input
    concatenated with the mirrored encoder output (skip connection); tanh at the end.

    With ``config.background`` a learned 3 x 100 x 100 image is added before the tanh. A
    GelSight frame is mostly the sensor's own colour gradient, the same in every sample; the
    stock U-Net must rebuild it at every pixel from a depth-map that says nothing about it, and
    what it gets wrong there is noise in every estimate. :meth:`set_background` starts it at
    the mean training image.
    """

    def __init__(self, config: GeneratorConfig = GeneratorConfig()) -> None:
        super().__init__()
        self.config = config.validate()
        widths = [config.ngf * min(2**i, 8) for i in range(config.num_downs)]
        self.encoder = nn.ModuleList()
        for i, width in enumerate(widths):
            conv = nn.Conv2d(
                config.input_channels if i == 0 else widths[i - 1], width, 4, 2, 1, bias=i in (0, len(widths) - 1)
            )
            if i == 0:
                self.encoder.append(conv)
            elif i == len(widths) - 1:
                self.encoder.append(nn.Sequential(nn.LeakyReLU(0.2), conv))
            else:
                self.encoder.append(nn.Sequential(nn.LeakyReLU(0.2), conv, nn.BatchNorm2d(width)))
        self.decoder = nn.ModuleList()
        for depth in range(config.num_downs - 1, 0, -1):
            # Decoder block for level `depth` outputs the width of encoder level depth-1.
            in_width = widths[depth] * (1 if depth == config.num_downs - 1 else 2)
            layers: list[nn.Module] = [
                nn.ReLU(),
                nn.ConvTranspose2d(in_width, widths[depth - 1], 4, 2, 1, bias=False),
                nn.BatchNorm2d(widths[depth - 1]),
            ]
            if 1 <= config.num_downs - 1 - depth <= config.dropout_blocks and config.dropout > 0:
                layers.append(nn.Dropout(config.dropout))
            self.decoder.append(nn.Sequential(*layers))
        self.output = nn.Sequential(nn.ReLU(), nn.ConvTranspose2d(widths[0] * 2, config.out_channels, 4, 2, 1))
        if config.background:
            self.background = nn.Parameter(torch.zeros(config.out_channels, config.image_size, config.image_size))
        # The models.prior.PhysicsPrior whose images this generator's input carries
        # (config.prior): set by models.checkpoint.load_generator from the checkpoint, never learned.
        self.prior: Any = None
        # What the checkpoint serves (models.serving: "network" or "prior") and the
        # models.uncertainty.ServedUncertainty served beside it (None: absent); set by load_generator.
        self.serves = "network"
        self.uncertainty: Any = None
        # What its input's bins hold (perception.surface.DEPTH_MAP_METHODS); set by load_generator.
        self.depth_map_method = "surface"

    @torch.no_grad()
    def set_background(self, mean_image: torch.Tensor) -> None:
        """Start the learned background at ``mean_image`` (C x H x W in [-1, 1])."""
        if not self.config.background:
            raise ModelConfigError("this generator has no learned background (config.background is false)")
        self.background.copy_(torch.atanh(mean_image.clamp(-0.99, 0.99)))

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        size = self.config.image_size
        if depth.ndim != 4 or depth.shape[1] != self.config.input_channels or depth.shape[2:] != (size, size):
            raise ModelConfigError(
                f"generator input must be N x {self.config.input_channels} x {size} x {size}, got {tuple(depth.shape)}"
            )
        return self.forward_unchecked(depth)

    def forward_unchecked(self, depth: torch.Tensor) -> torch.Tensor:
        """``forward`` without the input check, which graph tracers (FX, ONNX) cannot follow."""
        size, pad = self.config.image_size, self.config.pad_to - self.config.image_size
        x = nn.functional.pad(depth, (pad // 2, pad - pad // 2, pad // 2, pad - pad // 2), mode="replicate")
        skips = []
        for block in self.encoder:
            x = block(x)
            skips.append(x)
        for i, block in enumerate(self.decoder):
            x = block(x if i == 0 else torch.cat([x, skips[-1 - i]], dim=1))
        x = self.output(torch.cat([x, skips[0]], dim=1))[:, :, pad // 2 : pad // 2 + size, pad // 2 : pad // 2 + size]
        if self.config.background:
            x = x + self.background
        if self.config.prior:
            prior = depth[:, self.config.in_channels :].clamp(-0.99, 0.99)
            x = x + 0.5 * torch.log((1 + prior) / (1 - prior))  # atanh, which the ONNX exporter lacks
        return torch.tanh(x)


class PatchDiscriminator(nn.Module):
    """70 x 70 PatchGAN on the depth-map and an image, concatenated along channels.

    Three stride-2 4x4 convolutions (ndf, 2ndf, 4ndf), one stride-1 (8ndf), then a stride-1
    convolution to one logit per patch (N x 1 x 10 x 10 for 100 x 100 input); each logit
    sees a 70 x 70 window. LeakyReLU(0.2), BatchNorm except after the first layer.
    """

    def __init__(self, config: DiscriminatorConfig = DiscriminatorConfig()) -> None:
        super().__init__()
        self.config = config.validate()
        ndf = config.ndf
        self.layers = nn.Sequential(
            nn.Conv2d(config.in_channels, ndf, 4, 2, 1),
            nn.LeakyReLU(0.2),
            nn.Conv2d(ndf, ndf * 2, 4, 2, 1, bias=False),
            nn.BatchNorm2d(ndf * 2),
            nn.LeakyReLU(0.2),
            nn.Conv2d(ndf * 2, ndf * 4, 4, 2, 1, bias=False),
            nn.BatchNorm2d(ndf * 4),
            nn.LeakyReLU(0.2),
            nn.Conv2d(ndf * 4, ndf * 8, 4, 1, 1, bias=False),
            nn.BatchNorm2d(ndf * 8),
            nn.LeakyReLU(0.2),
            nn.Conv2d(ndf * 8, 1, 4, 1, 1),
        )

    def forward(self, depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        return self.layers(torch.cat([depth, image], dim=1))


def init_weights(module: nn.Module, std: float = 0.02) -> None:
    """pix2pix initialisation: conv weights N(0, std), BatchNorm scale N(1, std), biases 0."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.normal_(m.weight, 0.0, std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, std)
            nn.init.zeros_(m.bias)
