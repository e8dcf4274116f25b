"""Training the cGAN (``dtx train SESSION [SESSION ...] --config CONFIG``).

Paper settings by default: vanilla cGAN loss on logits (BCE), L1 weighted by lambda = 100,
Adam lr 2e-4, betas (0.5, 0.999); the learning rate is constant for ``epochs`` and then
decays linearly to zero over ``epochs_decay`` (as in pix2pix: a LambdaLR per optimiser,
stepped after every epoch).

The parts, as in pix2pix's reference implementation: :func:`build_state` (data, networks,
optimisers, schedule: a :class:`TrainState`), :func:`resume_state`, :func:`train_step` (one
discriminator step and one generator step: the paper's objective), :class:`TrainLog` and
:func:`save_checkpoint`; :func:`train` runs them. The config (``TrainConfig``) and reading a
checkpoint back are models.checkpoint's; the data, models.data's.

Reproducible: the seed fixes the initial weights, the sample order of every epoch (a
permutation seeded by seed and epoch) and dropout; on CPU the same seed gives the same
weights, and a resumed run continues exactly where the checkpoint left off.

Runs unchanged under ``torchrun``: with WORLD_SIZE > 1 it joins the process group (NCCL on
CUDA, gloo on CPU), wraps both networks in DistributedDataParallel and gives each rank every
WORLD_SIZE-th sample of the epoch's permutation, made from the sessions' files as its batches
draw them (models.pairs: no rank loads every session); rank 0 alone logs and saves. BatchNorm
statistics stay per rank, as in pix2pix.

Outputs in ``--out``: ``checkpoint.pt`` (state dicts of the networks, optimisers and
learning-rate schedulers, configs and progress, loadable with ``torch.load(weights_only=True)``;
one from before the schedulers were saved resumes with the schedule rebuilt at its epoch),
``train_log.csv`` (losses every ``log_every`` steps), ``val_log.csv`` (validation L1 and SSIM
after every epoch), and the same scalars as TensorBoard events in ``tensorboard/``
(``tensorboard --logdir OUT/tensorboard``).
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.optim.lr_scheduler import LambdaLR
from torch.utils.tensorboard import SummaryWriter

from models.checkpoint import CHECKPOINT, TrainConfig, load_checkpoint, save_atomic
from models.networks import ModelConfigError, PatchDiscriminator, UNetGenerator, init_weights
from models.pairs import PairSet
from models.sessions import PathLike, checkpoint_sessions, load_training_data
from msgs.progress import Progress
from perception.ssim import ssim_torch

# A target pixel this far from the mean training image (tanh units; 0.1 = 12.75 levels of 255)
# counts as fully contact in the contact-weighted L1.
CONTACT_SCALE = 0.1


def contact_weights(target: torch.Tensor, mean_image: torch.Tensor, contact_weight: float) -> torch.Tensor:
    """Per-pixel L1 weights (N x 1 x H x W): 1 on the background, up to 1 + ``contact_weight``
    where the target (N x 3 x H x W, [-1, 1]) departs from ``mean_image`` (3 x H x W)."""
    change = (target - mean_image).abs().mean(dim=1, keepdim=True)
    return 1.0 + contact_weight * (change / CONTACT_SCALE).clamp(max=1.0)


def lr_factor(config: TrainConfig, epoch: int) -> float:
    """Learning-rate multiplier for a 0-based epoch: 1 for ``epochs``, then linear to 0."""
    if epoch < config.epochs:
        return 1.0
    return 1.0 - (epoch - config.epochs + 1) / (config.epochs_decay + 1)


@dataclasses.dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")


def _setup_distributed() -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return _Dist(device=torch.device("cuda" if torch.cuda.is_available() else "cpu"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if torch.cuda.is_available():
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return _Dist(rank=torch.distributed.get_rank(), world=world, device=device)


def _unwrap(module: nn.Module) -> nn.Module:
    return module.module if isinstance(module, nn.parallel.DistributedDataParallel) else module


@torch.no_grad()
def _update_average(average: nn.Module, model: nn.Module, decay: float) -> None:
    """average <- decay * average + (1 - decay) * model, weights only; BatchNorm statistics are
    the model's own (they describe activations, not a direction of descent)."""
    for mean, value in zip(average.parameters(), model.parameters()):
        mean.lerp_(value, 1.0 - decay)
    for average_buffer, buffer in zip(average.buffers(), model.buffers()):
        average_buffer.copy_(buffer)


def _append_csv(path: Path, header: list[str], row: list[Any]) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        writer = csv.writer(f)
        if new:
            writer.writerow(header)
        writer.writerow(row)


@torch.no_grad()
def _validate(generator: nn.Module, pairs: PairSet, batch: int = 32) -> tuple[float, float]:
    """Mean L1 (in [-1, 1] image units) and mean SSIM (0..255 images) of eval-mode output."""
    was_training = generator.training
    generator.eval()
    l1, ssim = [], []
    for chunk in pairs.chunks(batch):
        x, real = pairs.batch(chunk)
        fake = generator(x)
        l1.append((fake - real).abs().mean(dim=(1, 2, 3)))
        ssim.append(
            ssim_torch(((fake + 1) * 127.5).round().clamp(0, 255).double(), ((real + 1) * 127.5).round().double())
        )
    generator.train(was_training)
    return float(torch.cat(l1).mean()), float(torch.cat(ssim).mean())


@dataclasses.dataclass
class TrainState:
    """A training run: the networks (``generator`` and ``discriminator`` are wrapped in
    DistributedDataParallel once training starts on several ranks), their optimisers and
    learning-rate schedulers, the data (streamed: models.pairs) and the schedule; ``epoch`` is the next epoch to
    run and ``step`` the optimiser steps taken. ``meta`` is what every checkpoint records
    about the data."""

    config: TrainConfig
    dist: _Dist
    generator: nn.Module
    discriminator: nn.Module
    average: nn.Module | None  # the weight average of the generator (ema_decay), or None
    opt_g: torch.optim.Optimizer
    opt_d: torch.optim.Optimizer
    schedulers: list[LambdaLR]  # one per optimiser: generator's, discriminator's
    train: PairSet
    val: PairSet
    mean_image: torch.Tensor | None  # the mean training target, where the config uses it
    per_rank: int  # training samples of each rank per epoch
    total_steps: int
    meta: dict[str, Any]
    epoch: int = 0
    step: int = 0
    bce: nn.Module = dataclasses.field(default_factory=nn.BCEWithLogitsLoss)

    @property
    def served(self) -> nn.Module:
        """The generator that is validated, saved as ``generator`` and served."""
        return self.average if self.average is not None else _unwrap(self.generator)


SCHEDULER_KEYS = ("scheduler_generator", "scheduler_discriminator")


def lr_schedulers(config: TrainConfig, optimizers: Sequence[torch.optim.Optimizer], epoch: int = 0) -> list[LambdaLR]:
    """One LambdaLR per optimiser, setting lr * lr_factor(config, epoch) for each epoch and
    stepped once at the end of it, positioned at ``epoch`` (the next epoch to run; above 0 it
    rebuilds the schedule of a checkpoint that did not save one)."""
    if epoch:
        for optimizer in optimizers:
            for group in optimizer.param_groups:
                group["initial_lr"] = config.lr

    def factor(e: int) -> float:
        return lr_factor(config, e)

    return [LambdaLR(optimizer, factor, last_epoch=epoch - 1) for optimizer in optimizers]


def build_state(
    dataset: PathLike | Sequence[PathLike],
    config: TrainConfig,
    libraries: Sequence[str | os.PathLike[str]] = (),
    dist: _Dist | None = None,
) -> TrainState:
    """A fresh run on one session or several (models.sessions): data, seeded and initialised
    networks, Adam optimisers, their learning-rate schedulers at epoch 0, and the number of steps."""
    dist = dist or _Dist()
    train_pairs, val_pairs, meta = load_training_data(dataset, config, libraries, dist.device)
    per_rank = len(train_pairs) // dist.world
    if per_rank == 0:
        raise ModelConfigError(f"{len(train_pairs)} training samples cannot be shared by {dist.world} ranks")
    total_steps = (config.epochs + config.epochs_decay) * -(-per_rank // config.batch_size)
    if config.max_steps:
        total_steps = min(total_steps, config.max_steps)

    torch.manual_seed(config.seed)
    generator = UNetGenerator(config.generator).to(dist.device)
    discriminator = PatchDiscriminator(config.discriminator).to(dist.device)
    init_weights(generator)
    init_weights(discriminator)
    # A pass over every training target, so only where the background or the contact weights need it.
    mean_image = train_pairs.mean_target() if config.generator.background or config.contact_weight else None
    if mean_image is not None and config.generator.background:
        generator.set_background(mean_image)
    average = copy.deepcopy(generator).requires_grad_(False) if config.ema_decay else None
    betas = (config.beta1, config.beta2)
    opt_g = torch.optim.Adam(generator.parameters(), lr=config.lr, betas=betas)
    opt_d = torch.optim.Adam(discriminator.parameters(), lr=config.lr, betas=betas)
    return TrainState(
        config=config,
        dist=dist,
        generator=generator,
        discriminator=discriminator,
        average=average,
        opt_g=opt_g,
        opt_d=opt_d,
        schedulers=lr_schedulers(config, (opt_g, opt_d)),
        train=train_pairs,
        val=val_pairs,
        mean_image=mean_image,
        per_rank=per_rank,
        total_steps=total_steps,
        meta=meta,
    )


def resume_state(state: TrainState, path: Path) -> None:
    """Continue ``state`` where checkpoint ``path`` left off: weights, optimisers, learning-rate
    schedule, progress and the CPU random state. A checkpoint saved before the schedule was
    (no scheduler entries) gets it rebuilt at its epoch."""
    checkpoint = load_checkpoint(path)
    if TrainConfig.from_dict(checkpoint["train_config"]) != state.config:
        raise ModelConfigError(
            f"{path} was trained with a different config; resume with the same config or train into a new --out"
        )
    # A checkpoint from before sessions were recorded resumes as it always did.
    trained_on, given = checkpoint_sessions(checkpoint), checkpoint_sessions(state.meta)
    if "sessions" in checkpoint and trained_on != given:
        raise ModelConfigError(f"{path} was trained on {trained_on}; resume on the same sessions, or train a new --out")
    average = state.average
    state.generator.load_state_dict(checkpoint["generator_raw"] if average is not None else checkpoint["generator"])
    if average is not None:
        average.load_state_dict(checkpoint["generator"])
    state.discriminator.load_state_dict(checkpoint["discriminator"])
    state.opt_g.load_state_dict(checkpoint["opt_generator"])
    state.opt_d.load_state_dict(checkpoint["opt_discriminator"])
    state.epoch, state.step = int(checkpoint["epoch"]), int(checkpoint["step"])
    if all(key in checkpoint for key in SCHEDULER_KEYS):
        for scheduler, key in zip(state.schedulers, SCHEDULER_KEYS):
            scheduler.load_state_dict(checkpoint[key])
    else:
        state.schedulers = lr_schedulers(state.config, (state.opt_g, state.opt_d), state.epoch)
    torch.set_rng_state(checkpoint["rng_cpu"])


def _distribute(state: TrainState) -> None:
    """Wrap both networks in DistributedDataParallel when training on several ranks."""
    if state.dist.world > 1:
        device_ids = [state.dist.device.index] if state.dist.device.type == "cuda" else None
        state.generator = nn.parallel.DistributedDataParallel(state.generator, device_ids=device_ids)
        state.discriminator = nn.parallel.DistributedDataParallel(state.discriminator, device_ids=device_ids)


def generator_l1(
    fake: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    prior: torch.Tensor | None = None,
    correction_weight: float = 0.0,
) -> torch.Tensor:
    """The G step's L1 term (images N x 3 x H x W in [-1, 1], ``weights`` N x 1 x H x W):
    mean |G - y|, plus ``correction_weight`` r times mean |G - prior|, each pixel weighted.

    A pixel that looks the same in many samples is left at its prior unless the targets lie
    above it (or below) in over (1 + r) / 2 of them: the correction moves only what the
    training targets say consistently, and stays out of what they disagree on."""
    l1 = ((fake - target).abs() * weights).mean()
    if correction_weight:
        if prior is None:
            raise ModelConfigError("correction_weight needs the physics prior's images")
        l1 = l1 + correction_weight * ((fake - prior).abs() * weights).mean()
    return l1 / weights.mean()


def train_step(state: TrainState, batch: tuple[torch.Tensor, torch.Tensor]) -> dict[str, float]:
    """One pix2pix iteration on a batch of inputs x (depth-maps) and targets y (tactile images):

    * D step: minimise (BCE(D(x, y), 1) + BCE(D(x, G(x)), 0)) / 2, real pairs against
      generated ones (the generated image detached);
    * G step: minimise BCE(D(x, G(x)), 1) + lambda_l1 * :func:`generator_l1` (the paper's L1
      with contact_weight and correction_weight 0);
    * the weight average (ema_decay) follows the generator.

    Returns the four losses, in that order."""
    config, bce = state.config, state.bce
    x, y = batch
    fake = state.generator(x)

    # Discriminator: real pairs -> 1, generated pairs -> 0. One backward per forward, so that
    # DistributedDataParallel reduces each pass cleanly.
    state.discriminator.requires_grad_(True)
    state.opt_d.zero_grad(set_to_none=True)
    pred_real = state.discriminator(x, y)
    loss_d_real = bce(pred_real, torch.ones_like(pred_real))
    (0.5 * loss_d_real).backward()
    pred_fake = state.discriminator(x, fake.detach())
    loss_d_fake = bce(pred_fake, torch.zeros_like(pred_fake))
    (0.5 * loss_d_fake).backward()
    state.opt_d.step()

    # Generator: fool the discriminator (its unwrapped module: no gradient reduction for D
    # here) and stay close to the target in L1.
    state.discriminator.requires_grad_(False)
    state.opt_g.zero_grad(set_to_none=True)
    pred = _unwrap(state.discriminator)(x, fake)
    loss_g_gan = bce(pred, torch.ones_like(pred))
    # All 1 without contact weights: the paper's L1.
    weights = (
        torch.ones_like(y[:, :1])
        if state.mean_image is None
        else contact_weights(y, state.mean_image, config.contact_weight)
    )
    prior = x[:, config.generator.in_channels :] if config.generator.prior else None
    loss_g_l1 = generator_l1(fake, y, weights, prior, config.correction_weight)
    (loss_g_gan + config.lambda_l1 * loss_g_l1).backward()
    state.opt_g.step()
    if state.average is not None:
        _update_average(state.average, _unwrap(state.generator), config.ema_decay)
    losses = {"loss_d_real": loss_d_real, "loss_d_fake": loss_d_fake, "loss_g_gan": loss_g_gan, "loss_g_l1": loss_g_l1}
    return {name: loss.item() for name, loss in losses.items()}


def _epoch_batches(state: TrainState, epoch: int) -> Iterator[torch.Tensor]:
    """This rank's sample indices of ``epoch``, batch by batch: a permutation seeded by the seed
    and the epoch, of which each rank takes every world-th sample."""
    config, dist = state.config, state.dist
    order = torch.randperm(len(state.train), generator=torch.Generator().manual_seed(config.seed * 100003 + epoch))
    mine = order[: state.per_rank * dist.world][dist.rank :: dist.world]
    for start in range(0, state.per_rank, config.batch_size):
        yield mine[start : start + config.batch_size]


class TrainLog:
    """The progress (``msgs.progress``), ``train_log.csv`` (window means of the losses every ``log_every``
    steps), ``val_log.csv`` and TensorBoard scalars; only rank 0 writes files."""

    def __init__(self, out_dir: Path, state: TrainState, resumed: bool, progress: bool = True) -> None:
        self.out_dir, self.log_every, self.total_steps = out_dir, state.config.log_every, state.total_steps
        rank0 = state.dist.rank == 0
        if rank0 and not resumed:
            out_dir.mkdir(parents=True, exist_ok=True)
            for log in ("train_log.csv", "val_log.csv"):
                (out_dir / log).unlink(missing_ok=True)
            shutil.rmtree(out_dir / "tensorboard", ignore_errors=True)
        # purge_step: a resumed run drops events a crashed run wrote after its last checkpoint.
        self.board = SummaryWriter(out_dir / "tensorboard", purge_step=state.step) if rank0 else None
        self.progress = Progress("train", state.total_steps, "steps", initial=state.step, enabled=progress and rank0)
        self.window: list[list[float]] = []
        self.started = time.monotonic()

    def losses(self, epoch: int, step: int, lr: float, losses: dict[str, float]) -> None:
        """Step ``step``'s losses; their means since the last entry every ``log_every`` steps."""
        self.progress.update(1)
        self.window.append(list(losses.values()))
        if step % self.log_every and step != self.total_steps:
            return
        means = np.mean(self.window, axis=0)
        self.window.clear()
        self.progress.note(f"d_real {means[0]:.3f}, d_fake {means[1]:.3f}, g_gan {means[2]:.3f}, g_l1 {means[3]:.4f}")
        if self.board is not None:
            names = list(losses)
            _append_csv(
                self.out_dir / "train_log.csv",
                ["epoch", "step", "lr", *names],
                [epoch, step, lr, *[f"{m:.6g}" for m in means]],
            )
            for name, value in zip(names, means):
                self.board.add_scalar(f"train/{name}", value, step)
            self.board.add_scalar("train/lr", lr, step)

    def validation(self, epoch: int, step: int, generator: nn.Module, pairs: PairSet) -> None:
        """Validate ``generator`` on ``pairs`` after ``epoch``; rank 0 alone calls this."""
        if self.board is None:
            raise RuntimeError("TrainLog.validation is rank 0's: this rank writes no logs")
        val_l1, val_ssim = _validate(generator, pairs)
        _append_csv(
            self.out_dir / "val_log.csv",
            ["epoch", "step", "val_l1", "val_ssim", "wall_s"],
            [epoch, step, f"{val_l1:.6g}", f"{val_ssim:.6g}", f"{time.monotonic() - self.started:.1f}"],
        )
        self.board.add_scalar("val/l1", val_l1, step)
        self.board.add_scalar("val/ssim", val_ssim, step)
        self.board.flush()

    def close(self) -> None:
        self.progress.close()
        if self.board is not None:
            self.board.close()


def save_checkpoint(state: TrainState, path: Path) -> None:
    """Write ``state`` to ``path`` atomically: the served generator (and the raw one when it is
    a weight average), the discriminator, both optimisers and learning-rate schedulers,
    progress, the CPU random state, the config and the record of the data."""
    raw = {"generator_raw": _unwrap(state.generator).state_dict()} if state.average is not None else {}
    save_atomic(
        {
            "generator": state.served.state_dict(),
            **raw,
            "discriminator": _unwrap(state.discriminator).state_dict(),
            "opt_generator": state.opt_g.state_dict(),
            "opt_discriminator": state.opt_d.state_dict(),
            **{key: scheduler.state_dict() for key, scheduler in zip(SCHEDULER_KEYS, state.schedulers)},
            "epoch": state.epoch,
            "step": state.step,
            "rng_cpu": torch.get_rng_state(),
            "train_config": state.config.to_dict(),
            **state.meta,
        },
        path,
    )


def train(
    dataset: PathLike | Sequence[PathLike],
    config: TrainConfig,
    out: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
    stop_after_epochs: int | None = None,
    libraries: Sequence[str | os.PathLike[str]] = (),
) -> Path:
    """Train on the dataset's train split (or, with ``hold_out_object``, on the other
    objects; given several sessions, on their train splits together: models.sessions), joined by every sample of the ``libraries`` (contact libraries: they add kinds of
    contact, never a session's validation or test pairs); returns the checkpoint path.
    ``stop_after_epochs`` ends this run early (the checkpoint can be resumed) without changing
    the schedule."""
    config.validate()
    checkpoint_path = Path(out) / CHECKPOINT
    dist = _setup_distributed()
    try:
        if config.threads:
            torch.set_num_threads(config.threads)
        state = build_state(dataset, config, libraries, dist)
        resumed = resume and checkpoint_path.exists()
        if resumed:
            resume_state(state, checkpoint_path)
        log = TrainLog(Path(out), state, resumed, progress)
        _distribute(state)
        total_epochs = config.epochs + config.epochs_decay
        last_epoch = total_epochs if stop_after_epochs is None else min(total_epochs, state.epoch + stop_after_epochs)
        for epoch in range(state.epoch, last_epoch):
            if state.step >= state.total_steps:
                break
            for index in _epoch_batches(state, epoch):
                if state.step >= state.total_steps:
                    break
                losses = train_step(state, state.train.batch(index))
                state.step += 1
                log.losses(epoch, state.step, state.opt_g.param_groups[0]["lr"], losses)
            state.epoch = epoch + 1
            for scheduler in state.schedulers:
                scheduler.step()
            if dist.rank == 0:
                log.validation(epoch, state.step, state.served, state.val)
                save_checkpoint(state, checkpoint_path)
        log.close()
        if dist.world > 1:
            # Every rank returns the checkpoint only once rank 0 has written it, and the ranks
            # leave the group together. A rank that left first returned a path not yet written; a
            # CI run of this job once aborted in gloo too, cause unknown (docs/measurements.md).
            torch.distributed.barrier()
        return checkpoint_path
    finally:
        if dist.world > 1:
            torch.distributed.destroy_process_group()
