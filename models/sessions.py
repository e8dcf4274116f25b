"""The sessions a model learns from: ``dtx train SESSION [SESSION ...]``.

A lab collects a session a day (a dataset directory: a new calibration, sometimes another object
set or another GelSight); one model learns from all of them. Each pair keeps its own session's
depth-maps (cut with that session's calibration and crop) and its own tactile image. Sessions
are mixed only where their pairs mean the same to the network; otherwise the run is refused
(:func:`open_sessions`):

* the same depth range (the network's input normalisation), image size and depth-map method
  (what a bin holds);
* scenes (the GelSight each session saw) may differ, but a session that records none cannot be
  mixed with sessions of another: nothing says which sensor it saw;
* a generator with a physics prior renders every pair with the one prior its checkpoint
  stores and serves: its sessions must share the depth crop and the GelSight as the prior
  draws it, whatever objects their scenes hold (:func:`check_one_prior`). Each session's
  prior is blurred by its own pose error (the config's ``session_pose_sigmas_mm``, one a
  session, or ``session_pose_sigma_mm`` for all: a dataset records none of its own).

The splits are dataset.splits.split_sessions' (one session: its own split, exactly as alone).
The checkpoint records each session (:meth:`Session.entry`: name, path, fingerprint).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.splits import SPLITS, session_fingerprint, split_sessions
from models.checkpoint import TrainConfig
from models.data import select_records, session_prior
from models.networks import GeneratorConfig, ModelConfigError
from models.pairs import PairCache, PairSet, SessionPairs, library_pairs
from models.prior import PhysicsPrior
from sim.gelsight import scene_renderer
from workcell.scene import SceneError, load_scene

PathLike = str | os.PathLike[str]


def session_paths(datasets: PathLike | Sequence[PathLike]) -> list[PathLike]:
    """One dataset directory or several, as a list; ModelConfigError for none."""
    paths: list[PathLike] = [datasets] if isinstance(datasets, (str, os.PathLike)) else list(datasets)
    if not paths:
        raise ModelConfigError("no session given: name at least one dataset directory")
    return paths


@dataclasses.dataclass(frozen=True)
class Session:
    """An opened session: its reader, its name (its directory's, or its path where two share
    one) and its fingerprint (SHA-256 of dataset.json and the manifest: the data it holds)."""

    reader: DatasetReader
    name: str
    fingerprint: str

    def entry(self, pose_sigma_mm: float | None = None) -> dict[str, Any]:
        """What a checkpoint records of this session (with the pose error its prior was blurred by)."""
        info = self.reader.info
        return {
            "name": self.name,
            "path": str(self.reader.root.resolve()),
            "fingerprint": self.fingerprint,
            "samples": len(self.reader.records),
            "scene": info.scene,
            "depth_crop_m": None if info.depth_crop_m is None else list(info.depth_crop_m),
            "split_seed": info.split_seed,
            **({} if pose_sigma_mm is None else {"pose_sigma_mm": pose_sigma_mm}),
        }


def open_sessions(
    datasets: PathLike | Sequence[PathLike], depth_range_m: tuple[float, float] | None = None
) -> list[Session]:
    """The sessions at ``datasets``, refused (ModelConfigError naming the first that differs)
    unless they can be mixed (module docstring), and, given ``depth_range_m``, unless they
    normalise depth as the model was trained."""
    readers = [DatasetReader(path) for path in session_paths(datasets)]
    if depth_range_m is not None:
        for reader in readers:
            if tuple(reader.info.depth_range_m) != tuple(depth_range_m):
                raise ModelConfigError(
                    f"{reader.root} normalises depth with {reader.info.depth_range_m}, "
                    f"the model was trained with {depth_range_m}"
                )
    first = readers[0].info
    for reader in readers[1:]:
        info = reader.info
        for what, mine, theirs in (
            ("depth range (m)", info.depth_range_m, first.depth_range_m),
            ("image size", (info.image_height, info.image_width), (first.image_height, first.image_width)),
            ("depth-map method", info.depth_map_method, first.depth_map_method),
        ):
            if tuple(np.atleast_1d(mine)) != tuple(np.atleast_1d(theirs)):
                raise ModelConfigError(
                    f"sessions {readers[0].root} and {reader.root} cannot be mixed: {what} {theirs} "
                    f"against {mine} (make them alike: dtx dataset redepth)"
                )
    scenes = {r.info.scene for r in readers}
    if len(scenes) > 1 and "" in scenes:
        unnamed = next(r.root for r in readers if not r.info.scene)
        raise ModelConfigError(
            f"session {unnamed} records no scene, so nothing says which GelSight it saw: "
            "it cannot be mixed with sessions of a scene"
        )
    names = [r.root.resolve().name for r in readers]
    if len(set(names)) < len(names):
        names = [str(r.root.resolve()) for r in readers]
    return [Session(r, name, session_fingerprint(r.root)) for r, name in zip(readers, names)]


def check_one_prior(sessions: Sequence[Session], config: GeneratorConfig) -> None:
    """A generator with a physics prior: every session must share the first's depth crop and
    its GelSight as the prior draws it (the scene's renderer without effects: the objects may
    differ), the one prior its checkpoint stores (the first session's scene) and serves;
    ModelConfigError otherwise."""
    if not config.prior:
        return
    first = sessions[0].reader.info
    for session in sessions[1:]:
        info = session.reader.info
        if first.depth_crop_m is None or info.depth_crop_m is None or info.scene == first.scene:
            same = info.depth_crop_m == first.depth_crop_m
        else:
            same = np.allclose(info.depth_crop_m, first.depth_crop_m, rtol=0, atol=1e-9) and _same_gelsight(
                first.scene, info.scene, config.image_size
            )
        if not same:
            raise ModelConfigError(
                f"sessions {sessions[0].reader.root} and {session.reader.root} have another GelSight or depth crop "
                f"({first.scene!r} {first.depth_crop_m} against {info.scene!r} {info.depth_crop_m}): "
                "a checkpoint serves one physics prior, so a prior model cannot mix them: train one model a "
                "GelSight, or one without a prior on both (prior: false, e.g. configs/variants/session_only.yaml)"
            )


def _same_gelsight(scene: str, other: str, size: int) -> bool:
    """Whether two scenes' GelSights draw the same prior (models.prior); False where either
    scene cannot be read."""
    try:
        mine, theirs = (scene_renderer(load_scene(s), size=(size, size), effects=False) for s in (scene, other))
    except (SceneError, OSError):
        return False
    return repr(mine.config) == repr(theirs.config)


def session_records(sessions: Sequence[Session], split: str, hold_out_object: str = "") -> list[list[SampleRecord]]:
    """Each session's records of ``split`` ("all": every record): one session's own split
    (models.data.select_records, as alone), several sessions' dataset.splits.split_sessions,
    ordered by their fingerprints (the order they are given in changes nothing)."""
    if split == "all":
        return [s.reader.records for s in sessions]
    if len(sessions) == 1:
        return [select_records(sessions[0].reader, split, hold_out_object)]
    if split not in SPLITS:
        raise ModelConfigError(f"unknown split {split!r}; known: {sorted(SPLITS)}")
    splits = split_sessions(
        [s.reader.records for s in sessions],
        [s.reader.info.split_seed for s in sessions],
        hold_out_object,
        [s.fingerprint for s in sessions],
    )
    return [chosen[split] for chosen in splits]


def session_sources(
    sessions: Sequence[Session],
    split: str,
    hold_out_object: str,
    config: GeneratorConfig,
    prior: PhysicsPrior | None,
    pose_sigmas_mm: Sequence[float | None] = (),
) -> list[SessionPairs]:
    """The pairs of ``split`` in each session that has some, in the order given (models.pairs:
    made from the files on demand), each session's prior blurred by its ``pose_sigmas_mm``
    (one a session; none given: the prior's default); ModelConfigError where no session has one."""
    chosen = session_records(sessions, split, hold_out_object)
    if not any(chosen):
        where = f"any of the {len(sessions)} sessions" if len(sessions) > 1 else str(sessions[0].reader.root)
        raise ModelConfigError(f"no samples of the {split} split in {where}")
    sigmas = list(pose_sigmas_mm) or [None] * len(sessions)
    if len(sigmas) != len(sessions):
        raise ModelConfigError(
            f"{len(sigmas)} pose uncertainties given for {len(sessions)} sessions: give one a session"
        )
    return [
        SessionPairs(s.reader, records, config, prior, sigma)
        for s, records, sigma in zip(sessions, chosen, sigmas)
        if records
    ]


def load_training_data(
    datasets: PathLike | Sequence[PathLike],
    config: TrainConfig,
    libraries: Sequence[PathLike],
    device: torch.device,
) -> tuple[PairSet, PairSet, dict[str, Any]]:
    """The train pairs (the sessions' train splits, then every library sample) and validation
    pairs, streamed onto ``device`` and sharing the config's pair cache, and the checkpoint's
    record of the data (depth range, sessions, libraries, physics prior); nothing is written."""
    sessions = open_sessions(datasets)
    for session in sessions:
        reader = session.reader
        if config.depth_map and config.depth_map != reader.info.depth_map_method:
            held, wanted = reader.info.depth_map_method, config.depth_map
            raise ModelConfigError(
                f"{reader.root} holds {held} depth-maps, the config asks for {wanted}: dtx dataset redepth"
            )
    check_one_prior(sessions, config.generator)
    first = sessions[0].reader
    prior = session_prior(first, config.generator, config.session_pose_sigma_mm)
    library = library_pairs(
        libraries,
        [s.reader for s in sessions],
        config.generator,
        prior,
        config.library_pose_sigma_range_mm,
        config.seed,
    )
    hold_out, channels, cache = config.hold_out_object, config.generator.in_channels, PairCache(config.pair_cache_mib)
    sigmas = config.session_pose_sigmas_mm
    train = session_sources(sessions, "train", hold_out, config.generator, prior, sigmas)
    val = session_sources(sessions, "val", hold_out, config.generator, prior, sigmas)
    train_pairs = PairSet([*train, *library], channels, cache, device)
    val_pairs = PairSet(val, channels, cache, device)
    meta = {
        "depth_range_m": list(first.info.depth_range_m),
        "depth_map_method": first.info.depth_map_method,
        # One session: its path, as every checkpoint before sessions recorded it.
        **({"dataset": str(first.root.resolve())} if len(sessions) == 1 else {}),
        "sessions": [s.entry(sigma) for s, sigma in zip(sessions, sigmas or [None] * len(sessions))],
        "libraries": [str(Path(library).resolve()) for library in libraries],
        **({"prior": prior.spec.to_dict()} if prior is not None else {}),
    }
    return train_pairs, val_pairs, meta


def checkpoint_sessions(state: dict[str, Any]) -> list[str]:
    """The session paths a checkpoint was trained on: its ``sessions``, or the single
    ``dataset`` of a checkpoint trained before sessions; [] where it names none."""
    if state.get("sessions"):
        return [str(entry["path"]) for entry in state["sessions"]]
    return [str(state["dataset"])] if state.get("dataset") else []
