"""The training run's config and its checkpoint file (``OUT/checkpoint.pt``).

:class:`TrainConfig` is what a run is trained with, and what its checkpoint records;
:func:`load_checkpoint` reads a checkpoint back (tensors and plain values only) and
:func:`load_generator` the generator that it serves. models.train writes them.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from models.networks import (
    DiscriminatorConfig,
    GeneratorConfig,
    ModelConfigError,
    UNetGenerator,
    config_from_dict,
)
from models.prior import PhysicsPrior, PriorSpec, checked_pose_sigma_mm
from models.uncertainty import ServedUncertainty
from perception.surface import DEPTH_MAP_METHODS

CHECKPOINT = "checkpoint.pt"
# What a checkpoint can serve (models.serving): its generator's image, or its physics prior's.
SERVES = ("network", "prior")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training settings; ``configs/paper.yaml`` and ``configs/quick.yaml`` are examples."""

    seed: int = 0
    epochs: int = 100
    epochs_decay: int = 100
    batch_size: int = 1
    lr: float = 2e-4
    beta1: float = 0.5
    beta2: float = 0.999
    lambda_l1: float = 100.0
    ndf: int = 64
    hold_out_object: str = ""
    max_steps: int = 0
    log_every: int = 10
    threads: int = 0
    # Exponential moving average of the generator's weights (0: off, as the paper). A GAN's
    # generator wanders from step to step; the average is what is validated, saved as
    # ``generator`` and served, while training continues on the raw weights.
    ema_decay: float = 0.0
    # Weight of the contact in the L1 term: a pixel counts 1 + contact_weight * c, where c in
    # [0, 1] is how far its target departs from the mean training image (saturating at
    # CONTACT_SCALE). 0: the paper's plain L1, in which the ~90 % of pixels that show the
    # sensor's own background outweigh the contact.
    contact_weight: float = 0.0
    # Weight r, in [0, 1), of the hold on the correction (models.train.generator_l1): a pixel
    # leaves its physics prior only where over (1 + r) / 2 of the targets that look alike lie on
    # one side of it. 0: the correction is free; 1 or more would pin every pixel to the prior.
    correction_weight: float = 0.0
    # In-plane pose error (mm, per axis) of the session's depth-maps, which come from registered
    # model clouds: the physics prior of a session pair is the image expected over it
    # (models.prior), a library pair's the sharp image of its exact geometry. Stored in the
    # checkpoint as the prior's default for what it is asked; 0: every prior image sharp.
    session_pose_sigma_mm: float = 0.0
    # Each session's own pose error (mm), one a session in the order they are given, where a lab's
    # sessions differ (one redepthed with a touch calibration, one not): its pairs' prior is
    # blurred by it. (): session_pose_sigma_mm for every session. The served default stays
    # session_pose_sigma_mm.
    session_pose_sigmas_mm: tuple[float, ...] = ()
    # The pose uncertainties (mm, [low, high]) the model learns to answer for, so that one
    # checkpoint serves any pose_sigma_mm a planner asks in them (the inference protocol): each
    # library pair, exact geometry, is moved in the gel plane by an offset of a sigma drawn
    # uniformly in the range (seeded by ``seed``), with its prior rendered at that sigma
    # (models.data.load_library). []: library pairs exact, their prior sharp.
    library_pose_sigma_range_mm: tuple[float, ...] = ()
    # What the training depth-maps' bins must hold (perception.surface.DEPTH_MAP_METHODS), checked
    # against the dataset's; "": whatever it holds. The checkpoint records the dataset's, and
    # what it is served is cut by it.
    depth_map: str = ""
    # Memory for the training and validation pairs (MiB, models.pairs): pairs are made from the
    # sessions' files as they are drawn and kept, packed (about 100 KB at 100 x 100 with a prior),
    # until this is full; the rest are made again each time. 512 holds the demo's 3,240 pairs
    # (324 MiB), so a session of its size trains as if loaded at once; ten sessions stay in it.
    pair_cache_mib: float = 512.0
    generator: GeneratorConfig = GeneratorConfig()

    def validate(self) -> "TrainConfig":
        if self.epochs < 0 or self.epochs_decay < 0 or self.epochs + self.epochs_decay == 0:
            raise ModelConfigError(
                f"epochs and epochs_decay must be >= 0 with a positive sum, got {self.epochs}, {self.epochs_decay}"
            )
        for name in ("batch_size", "ndf", "log_every"):
            if getattr(self, name) < 1:
                raise ModelConfigError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.max_steps < 0 or self.threads < 0:
            raise ModelConfigError("max_steps and threads must be >= 0 (0: no limit / torch's default)")
        if not (np.isfinite(self.contact_weight) and self.contact_weight >= 0):
            raise ModelConfigError(f"contact_weight must be a finite number >= 0, got {self.contact_weight}")
        if not (np.isfinite(self.correction_weight) and 0 <= self.correction_weight < 1):
            raise ModelConfigError(f"correction_weight must be in [0, 1), got {self.correction_weight}")
        if self.correction_weight and not self.generator.prior:
            raise ModelConfigError("correction_weight needs a generator with a physics prior (prior: true)")
        checked_pose_sigma_mm(self.session_pose_sigma_mm, "session_pose_sigma_mm")
        for sigma in self.session_pose_sigmas_mm:
            checked_pose_sigma_mm(sigma, "session_pose_sigmas_mm")
        if self.session_pose_sigmas_mm and not self.generator.prior:
            raise ModelConfigError("session_pose_sigmas_mm needs a generator with a physics prior (prior: true)")
        self._check_library_pose_sigma_range()
        if self.depth_map and self.depth_map not in DEPTH_MAP_METHODS:
            raise ModelConfigError(
                f"depth_map must be one of {', '.join(DEPTH_MAP_METHODS)} (or '' for the dataset's), got {self.depth_map!r}"
            )
        if not (np.isfinite(self.pair_cache_mib) and self.pair_cache_mib >= 0):
            raise ModelConfigError(f"pair_cache_mib must be a finite number of MiB >= 0, got {self.pair_cache_mib}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ModelConfigError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if not (self.lr > 0 and 0 <= self.beta1 < 1 and 0 <= self.beta2 < 1 and self.lambda_l1 >= 0):
            raise ModelConfigError(
                f"need lr > 0, betas in [0, 1), lambda_l1 >= 0; got lr={self.lr}, "
                f"betas=({self.beta1}, {self.beta2}), lambda_l1={self.lambda_l1}"
            )
        self.generator.validate()
        return self

    def _check_library_pose_sigma_range(self) -> None:
        sigma_range = self.library_pose_sigma_range_mm
        if not sigma_range:
            return
        if len(sigma_range) != 2:
            raise ModelConfigError(f"library_pose_sigma_range_mm must be [low, high] in mm, got {list(sigma_range)}")
        low, high = (checked_pose_sigma_mm(v, "library_pose_sigma_range_mm") for v in sigma_range)
        if low > high:
            raise ModelConfigError(
                f"library_pose_sigma_range_mm must be [low, high] with low <= high, got {[low, high]}"
            )
        if not self.generator.prior:
            raise ModelConfigError("library_pose_sigma_range_mm needs a generator with a physics prior (prior: true)")

    @property
    def discriminator(self) -> DiscriminatorConfig:
        return DiscriminatorConfig(
            in_channels=self.generator.input_channels + self.generator.out_channels, ndf=self.ndf
        )

    def with_session_pose_sigmas(self, sigmas_mm: Sequence[float], sessions: int) -> "TrainConfig":
        """This config with the sessions' pose errors (mm; ``dtx train --session-pose-sigma-mm``):
        one for all of ``sessions`` sessions or one a session, the first the served default;
        ModelConfigError for another count or a bad value."""
        if len(sigmas_mm) not in (1, sessions):
            raise ModelConfigError(
                f"--session-pose-sigma-mm takes one value or one a session ({sessions}), got {len(sigmas_mm)}"
            )
        several = tuple(sigmas_mm) if len(sigmas_mm) > 1 else ()
        return dataclasses.replace(self, session_pose_sigma_mm=sigmas_mm[0], session_pose_sigmas_mm=several).validate()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> "TrainConfig":
        if not isinstance(data, dict):
            raise ModelConfigError(f"a training config is a mapping, got {type(data).__name__}")
        data = dict(data)
        generator = GeneratorConfig.from_dict(data.pop("generator", {}) or {})
        return dataclasses.replace(
            config_from_dict(TrainConfig, data, "training config"), generator=generator
        ).validate()

    @staticmethod
    def load(path: str | os.PathLike[str]) -> "TrainConfig":
        try:
            data = yaml.safe_load(Path(path).read_text())
        except OSError as err:
            raise ModelConfigError(f"cannot read training config {path}: {err}") from err
        except yaml.YAMLError as err:
            raise ModelConfigError(f"training config {path} is not valid YAML: {err}") from err
        return TrainConfig.from_dict(data or {})


def save_atomic(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` through a temporary file: a crash never leaves half a checkpoint."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The checkpoint dictionary (tensors and plain values only: ``weights_only=True``)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError as err:
        raise ModelConfigError(f"checkpoint {path} does not exist") from err
    except Exception as err:  # torch raises several types for a corrupt or foreign file
        raise ModelConfigError(f"{path} is not a readable dtx checkpoint: {err}") from err
    missing = {"generator", "train_config", "depth_range_m"} - set(state)
    if missing:
        raise ModelConfigError(f"{path} is not a dtx checkpoint: missing {sorted(missing)}")
    return state


def load_generator(path: str | os.PathLike[str]) -> tuple[UNetGenerator, tuple[float, float]]:
    """The trained generator (eval mode, CPU) and the depth_range_m it was trained with."""
    state = load_checkpoint(path)
    config = TrainConfig.from_dict(state["train_config"])
    generator = UNetGenerator(config.generator)
    generator.load_state_dict(state["generator"])
    generator.eval()
    if config.generator.prior:
        if "prior" not in state:
            raise ModelConfigError(f"{path} corrects a physics prior but does not say which (no 'prior' entry)")
        generator.prior = PhysicsPrior(PriorSpec.from_dict(state["prior"]), config.generator.image_size)
    generator.serves = state.get("serves", "network")
    if generator.serves not in SERVES or (generator.serves == "prior" and not config.generator.prior):
        raise ModelConfigError(
            f"{path} serves {generator.serves!r}: a checkpoint serves its network, or the prior it has"
        )
    if "uncertainty" in state:
        generator.uncertainty = ServedUncertainty.from_state(state["uncertainty"])
        floor = generator.uncertainty.floor
        size = config.generator.image_size
        if floor is not None and floor.levels.shape != (size, size):
            raise ModelConfigError(f"{path}: its sensor floor is {floor.levels.shape}, its images {size} x {size}")
    # A checkpoint trained before the surface rule names no method: its maps were nearest points.
    generator.depth_map_method = str(state.get("depth_map_method", "nearest_point"))
    if generator.depth_map_method not in DEPTH_MAP_METHODS:
        raise ModelConfigError(f"{path} was trained on {generator.depth_map_method!r} depth-maps, which no cut makes")
    low, high = state["depth_range_m"]
    return generator, (float(low), float(high))
