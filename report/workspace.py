"""The datasets and trained models the accuracy-time report measures (report.sweeps): the
analytic contacts at each size, a collection session on the simulated scene, its depth-maps
made again at other resolutions, a contact library, and the models trained on them, each made
on first use under the workspace's root and kept."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from benchmarks.collect import collect_sim_command
from dataset.contact_library import write_contact_library
from dataset.images import deformation_map
from dataset.reader import DatasetReader
from dataset.records import SampleRecord
from dataset.redepth import depth_map_params, redepth_dataset
from dataset.touch_calibration import (
    CALIBRATED_POSE_SIGMA_MM,
    REGISTRATION_FRAMES_TOPIC,
    TouchCalibration,
    calibrate_touches,
)
from models.checkpoint import TrainConfig, load_checkpoint
from models.data import select_records
from models.serving import fit_serving
from models.train import train
from perception.touch_calibration import TouchCalibrationError
from report.contacts import Contact, contacts, write_dataset
from report.plan import Plan

REPO = Path(__file__).resolve().parent.parent
REFERENCE_SIZE = 100  # the paper's depth-map and image size: every SSIM is taken at it


@dataclasses.dataclass(frozen=True)
class SessionTest:
    """The sessions' test splits, one after another: records and 100 x 100 ground truth."""

    records: list[SampleRecord]
    truth: np.ndarray  # N x 100 x 100 x 3 uint8
    deformation: np.ndarray  # N x 100 x 100, summed |change| from the no-contact image (levels)
    session_of: np.ndarray  # N ints: which of the workspace's sessions each record is of

    def part(self, session: int) -> SessionTest:
        """The records of the workspace's ``session``-th session alone."""
        rows = np.flatnonzero(self.session_of == session)
        return SessionTest(
            [self.records[i] for i in rows], self.truth[rows], self.deformation[rows], self.session_of[rows]
        )

    def depth_maps(self, datasets: Sequence[Path]) -> np.ndarray:
        """The records' depth-maps (N x H x W, m) read from ``datasets``, one a session in the
        workspace's order (the sessions themselves, or their maps made again: session_at)."""
        readers = [DatasetReader(dataset) for dataset in datasets]
        return np.stack([readers[s].load(r.sample_id).depth_map_m for r, s in zip(self.records, self.session_of)])


def training_config() -> TrainConfig:
    """The config every model of the report is trained with, before a sweep changes its size,
    width or epochs: configs/quick.yaml."""
    return TrainConfig.load(REPO / "configs" / "quick.yaml")


class Workspace:
    """Datasets and trained models under ``root``, made on first use and kept, so a rerun or
    a sweep that needs a model another sweep trained does not train it again."""

    def __init__(
        self, root: Path, plan: Plan, sessions: Sequence[Path] = (), pose_sigmas_mm: Sequence[float] = ()
    ) -> None:
        """``sessions``: collected simulated sessions the session sweeps use instead of one
        collected here (make demo's is larger than any plan's, so its p-values mean more; a lab's
        several days train one model, as ``dtx train A B`` does), with their pose errors
        ``pose_sigmas_mm`` as ``dtx train --session-pose-sigma-mm`` takes them (none: the
        training config's)."""
        self.root = root
        self.plan = plan
        self.given_sessions = tuple(sessions)
        self.pose_sigmas_mm = tuple(pose_sigmas_mm)
        self.reused_models: set[str] = set()  # trained by an earlier run: not in this run's time
        self.trained_models: set[str] = set()  # trained, or found trained, by this run

    @functools.cached_property
    def contacts(self) -> list[Contact]:
        return contacts(self.plan.samples, self.plan.seed)

    def dataset(self, size: int) -> Path:
        return write_dataset(self.root / f"data_{size}", self.contacts, size, self.plan.seed)

    @functools.cached_property
    def sessions(self) -> tuple[Path, ...]:
        """The sessions the session sweeps' models train on together and are scored on: the
        given ones as given, else the one collected here with its depth-maps cut again by its
        own touch calibration (:meth:`_calibrated`), as ``make demo`` trains on."""
        if self.given_sessions:
            return self.given_sessions
        try:
            return (self._calibrated(),)
        except TouchCalibrationError:  # too few touches: the pipeline's table says why
            return (self.collected,)

    @property
    def calibrated(self) -> bool:
        """Whether the session sweeps run on a session this workspace calibrated (:attr:`sessions`)."""
        return not self.given_sessions and self.session != self.collected

    @property
    def session(self) -> Path:
        """The first of :attr:`sessions`."""
        return self.sessions[0]

    @functools.cached_property
    def collected(self) -> Path:
        """The collection whose stages the pipeline, registration and touch-calibration sweeps
        measure: the first given session, else the one collected here (:meth:`_collected`). Its
        records are :attr:`session`'s, its depth-maps as its patch extractor cut them."""
        return self.given_sessions[0] if self.given_sessions else self._collected()

    def _calibrated(self) -> Path:
        """The collected session's depth-maps cut again with its objects where its touch
        calibration's joint fit placed them (what ``dtx calibrate touches`` then ``dtx dataset
        redepth --calibration`` make, make demo's session_calibrated); resumed if torn."""
        calibration, _ = self.touch_calibration
        out = self.root / "session_calibrated"
        return redepth_dataset(self.collected, out, progress=False, registered=calibration.cell.objects).root

    def _collected(self) -> Path:
        """A collection session on the simulated scene: launch/collect_sim.yaml, the graph an
        operator runs (Algorithm 1), ``plan.session_grasps`` grasps, its registrations' camera
        frames recorded; resumed if interrupted, left as it is when complete (a resumed run
        would write its session.json again, with no stage times for the grasps it did not make)."""
        out = (self.root / "session").resolve()
        if _grasps_done(out) >= self.plan.session_grasps:
            return out
        resume = (out / "manifest.jsonl").exists()
        command = collect_sim_command(out, self.plan.session_grasps, self.plan.seed, record=True, resume=resume)
        # The registrations' camera frames, which the touch calibration needs (dtx calibrate touches).
        command.append(f"record_topics:=[{REGISTRATION_FRAMES_TOPIC}]")
        # A bus of its own, so that a graph the lab is running meanwhile is never touched; the
        # graph's progress goes to stderr with the report's own.
        bus = tempfile.mkdtemp(prefix="dtxr")  # ipc socket paths must stay short
        try:
            result = subprocess.run(command, cwd=REPO, stdout=sys.stderr, env={**os.environ, "DTX_BUS_DIR": bus})
        finally:
            shutil.rmtree(bus, ignore_errors=True)
        if result.returncode != 0:
            raise RuntimeError(
                f"the collection session for the report failed (exit {result.returncode}): dtx {' '.join(command[3:])}"
            )
        return out

    @functools.cached_property
    def touch_calibration(self) -> tuple[TouchCalibration, float]:
        """``dtx calibrate touches`` on the whole session, and the CPU s it took (made once a
        run: the pipeline's table times it, the registration tables register with it);
        perception.touch_calibration.TouchCalibrationError where its touches cannot."""
        started = time.process_time()
        calibration = calibrate_touches(self.collected)
        return calibration, time.process_time() - started

    def session_at(self, bins: int, method: str = "surface") -> tuple[Path, ...]:
        """The sessions with their depth-maps made again over ``bins`` x ``bins`` bins, each bin
        holding what ``method`` says (perception.surface.DEPTH_MAP_METHODS)."""
        made = []
        for index, session in enumerate(self.sessions):
            if bins == REFERENCE_SIZE and method == DatasetReader(session).info.depth_map_method:
                made.append(session)  # collected at 100 x 100 by that rule
                continue
            # The first session's name as before sessions were several: a workspace made then is reused.
            name = f"session{'' if index == 0 else index + 1}_{bins}{_method_suffix(method)}"
            made.append(redepth_dataset(session, self.root / name, bins=bins, progress=False, method=method).root)
        return tuple(made)

    @functools.cached_property
    def session_test(self) -> SessionTest:
        records, samples, session_of = [], [], []
        for index, session in enumerate(self.sessions):
            reader = DatasetReader(session)
            test = select_records(reader, "test")
            records += test
            samples += [reader.load(r) for r in test]
            session_of += [index] * len(test)
        return SessionTest(
            records,
            np.stack([s.tactile_rgb for s in samples]),
            np.stack([deformation_map(s.tactile_diff_rgb) for s in samples]),
            np.array(session_of),
        )

    @functools.cached_property
    def first_test(self) -> SessionTest:
        """The first session's test split alone: what the sweeps of its collection (pipeline,
        touch calibration) score against."""
        return self.session_test.part(0)

    def config(self, size: int, width: int, registered: bool) -> TrainConfig:
        """configs/quick.yaml with the plan's epochs, at ``size`` x ``size``, generator ``width``;
        the physics prior blurred by the registration's pose error only for a ``registered``
        (collected) dataset: the analytic contacts' geometry is exact. A session calibrated here
        is left with the touch calibration's error (CALIBRATED_POSE_SIGMA_MM, as make demo
        trains), given ones with their ``pose_sigmas_mm`` or else the config's."""
        base = training_config()
        pad = -(-size // 128) * 128  # the U-Net's 7 halvings need a multiple of 128
        generator = dataclasses.replace(base.generator, image_size=size, pad_to=pad, ngf=width)
        # One thread: on a shared machine extra OpenMP threads mostly wait for a core, and
        # the CPU seconds a sweep reports are then comparable from run to run.
        config = dataclasses.replace(
            base,
            seed=self.plan.seed,
            epochs=self.plan.epochs,
            epochs_decay=self.plan.epochs,
            generator=generator,
            threads=1,
            session_pose_sigma_mm=0.0,  # analytic contacts: exact geometry
        )
        if not registered:
            return config
        if self.pose_sigmas_mm:
            return config.with_session_pose_sigmas(self.pose_sigmas_mm, len(self.given_sessions))
        return dataclasses.replace(
            config, session_pose_sigma_mm=CALIBRATED_POSE_SIGMA_MM if self.calibrated else base.session_pose_sigma_mm
        )

    def model(self, size: int = REFERENCE_SIZE, width: int = 16) -> Path:
        """The model trained on the analytic contacts at ``size`` x ``size``: see :meth:`_trained`."""
        return self._trained(
            self.dataset(size), self.config(size, width, registered=False), self.root / f"train_{size}_w{width}"
        )

    def library_at(self, bins: int, method: str = "surface") -> Path:
        """``plan.library_samples`` contact-library pairs (dataset.contact_library) in the
        session's scene, depth range and crop, at ``bins`` x ``bins`` binned by ``method``: what
        the default model trains on beside a session (make demo, docs/generalisation.md)."""
        out = self.root / f"library_{bins}{_method_suffix(method)}"
        if (out / "manifest.jsonl").exists() and len(DatasetReader(out).records) >= self.plan.library_samples:
            return out  # made by an earlier run, whose code version its dataset.json keeps
        session = DatasetReader(self.session)
        params, _ = depth_map_params(session)
        return write_contact_library(
            out,
            self.plan.library_samples,
            self.plan.seed,
            session.info.scene,
            session.info.depth_range_m,  # the session's depth-maps' y range (depth_map_params)
            params.margin_m,
            size=bins,
            method=method,
        ).root

    def session_model(self, bins: int = REFERENCE_SIZE, method: str = "surface") -> Path:
        """The width-16 model trained as the default is (the session with a contact library)
        at ``bins`` x ``bins`` on depth-maps binned by ``method``: see :meth:`_trained`."""
        config = self.config(bins, 16, registered=True)
        if method != "surface":
            # The default's config is left as configs/quick.yaml has it ("": the dataset's rule),
            # so that models an earlier run trained match it and are kept.
            config = dataclasses.replace(config, depth_map=method)
        return self._trained(
            list(self.session_at(bins, method)),
            config,
            self.root / f"train_session_{bins}{_method_suffix(method)}",
            libraries=(self.library_at(bins, method),),
        )

    def _trained(
        self, dataset: Path | list[Path], config: TrainConfig, out: Path, libraries: tuple[Path, ...] = ()
    ) -> Path:
        """The trained model's directory (checkpoint.pt, val_log.csv, cpu_s.json: process CPU
        seconds of each epoch, data loading included; serving_cpu_s.json: choosing what it
        serves and fitting its uncertainty). Trained one epoch per call so that each epoch's CPU
        time is known; an interrupted training resumes from its checkpoint. Then served as ``dtx
        train`` serves a model (models.serving.fit_serving), so that every figure is the path a
        planner calls."""
        cpu_log = out / "cpu_s.json"
        checkpoint = out / "checkpoint.pt"
        if checkpoint.exists() and TrainConfig.from_dict(load_checkpoint(checkpoint)["train_config"]) != config:
            print(f"report: {out.name} was trained with another config; training it again", file=sys.stderr)
            shutil.rmtree(out)
        if len(epoch_cpu_s(out)) >= 2 * self.plan.epochs and out.name not in self.trained_models:
            self.reused_models.add(out.name)
        self.trained_models.add(out.name)
        threads = torch.get_num_threads()
        try:
            while len(epoch_cpu_s(out)) < 2 * self.plan.epochs:
                fresh = not checkpoint.exists()
                started = time.process_time()
                train(dataset, config, out, resume=True, progress=False, stop_after_epochs=1, libraries=libraries)
                cpu = [] if fresh else epoch_cpu_s(out)
                cpu_log.write_text(json.dumps(cpu + [round(time.process_time() - started, 2)]))
        finally:
            torch.set_num_threads(threads)  # train() set one thread for the whole process
        if "serves" not in load_checkpoint(checkpoint):
            started = time.process_time()
            fit_serving(checkpoint, log=lambda line: None)
            (out / "serving_cpu_s.json").write_text(json.dumps(round(time.process_time() - started, 2)))
        return out

    @functools.cached_property
    def test(self) -> tuple[list[Contact], np.ndarray]:
        """The analytic test split's contacts and their 100 x 100 ground-truth images."""
        reader = DatasetReader(self.dataset(REFERENCE_SIZE))
        records = select_records(reader, "test")
        by_id = {c.sample_id: c for c in self.contacts}
        return [by_id[r.sample_id] for r in records], np.stack([reader.load(r).tactile_rgb for r in records])


def _method_suffix(method: str) -> str:
    """What a directory made by depth-map rule ``method`` adds to its name: nothing for the
    default rule, so that a workspace made before the rule was a setting is reused."""
    return "" if method == "surface" else f"_{method}"


def _grasps_done(session: Path) -> int:
    """The grasps a collection session's collector counted (its session.json; 0 before one)."""
    try:
        return int(json.loads((session / "session.json").read_text())["stats"]["grasps_done"])
    except (FileNotFoundError, ValueError, KeyError, TypeError):
        return 0


def epoch_cpu_s(model: Path) -> list[float]:
    """The CPU seconds of each epoch ``model`` has trained (its cpu_s.json; none before the first)."""
    try:
        return json.loads((model / "cpu_s.json").read_text())
    except FileNotFoundError:
        return []
