"""The measurements behind the accuracy-time report. Each sweep returns points
``{"sweep", "setting", "time", "accuracy", ...extra figures}``; what "time" and "accuracy"
mean for a sweep is in report.specs. The work is done by the project's own code (a collection
session on the simulated scene, dataset.redepth, dataset.synth contacts, models.train,
perception, sim, benchmarks); this module only chooses settings.

The density and resolution sweeps run on a collected session, since what they change is how
the patch extractor makes depth-maps from registered models; the other learned sweeps compare
networks and GelSight effects on analytic contacts, whose ground truth can be rendered again.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import stats

from benchmarks import inference as inference_bench
from benchmarks.perception import _sweep_cases, _sweep_row
from benchmarks.sim import DEPTH_EFFECTS
from dataset.contact_library import write_contact_library
from dataset.format import DatasetReader, SampleRecord, deformation_map, resize_rgb
from dataset.redepth import depth_map_again, depth_map_params, model_cloud, redepth_dataset
from dataset.synth import gel_gap_from_surface, gelsight_renderer
from models.data import network_input, select_records
from models.evaluate import PAPER, contact_ssim, predict
from models.runtime import sampling_copy
from models.ssim import ssim_rgb
from models.train import TrainConfig, load_checkpoint, load_generator, train
from perception.density import downsample_to_density
from perception.pointcloud import VoxelIndex
from perception.registration import RegistrationParams
from report.contacts import Contact, contacts, write_dataset
from report.plan import Plan
from sim.gelsight import GelSightRenderer
from sim.gelsight_effects import EFFECTS as GELSIGHT_EFFECTS
from sim.gelsight_effects import make_effect
from sim.world import SimWorld
from workcell.scene import load_scene

Point = dict[str, Any]
REPO = Path(__file__).resolve().parent.parent
SCENE = "scenes/ycb_three.yaml"
REFERENCE_SIZE = 100  # the paper's depth-map and image size: every SSIM is taken at it


def _point(sweep: str, setting: str, time_value: float, accuracy: float | None, **extra: Any) -> Point:
    return {
        "sweep": sweep,
        "setting": setting,
        "time": float(time_value),
        "accuracy": float("nan") if accuracy is None else float(accuracy),
        **extra,
    }


def _median_ms(function, runs: int) -> float:
    walls = []
    for _ in range(runs):
        started = time.perf_counter()
        function()
        walls.append((time.perf_counter() - started) * 1e3)
    return statistics.median(walls)


@dataclasses.dataclass(frozen=True)
class SessionTest:
    """The collected session's test split: records and 100 x 100 ground truth."""

    records: list[SampleRecord]
    truth: np.ndarray  # N x 100 x 100 x 3 uint8
    deformation: np.ndarray  # N x 100 x 100, summed |change| from the no-contact image (levels)


def training_config() -> TrainConfig:
    """The config every model of the report is trained with, before a sweep changes its size,
    width or epochs: configs/quick.yaml."""
    return TrainConfig.load(REPO / "configs" / "quick.yaml")


class Workspace:
    """Datasets and trained models under ``root``, made on first use and kept, so a rerun or
    a sweep that needs a model another sweep trained does not train it again."""

    def __init__(self, root: Path, plan: Plan) -> None:
        self.root = root
        self.plan = plan
        self.reused_models: set[str] = set()  # trained by an earlier run: not in this run's time

    @functools.cached_property
    def contacts(self) -> list[Contact]:
        return contacts(self.plan.samples, self.plan.seed)

    def dataset(self, size: int) -> Path:
        return write_dataset(self.root / f"data_{size}", self.contacts, size, self.plan.seed)

    @functools.cached_property
    def session(self) -> Path:
        """A collection session on the simulated scene: launch/collect_sim.yaml, the graph an
        operator runs (Algorithm 1), ``plan.session_grasps`` grasps; resumed if interrupted."""
        out = (self.root / "session").resolve()
        command = [
            sys.executable,
            "-m",
            "dtx.cli",
            "launch",
            "launch/collect_sim.yaml",
            f"out:={out}",
            f"grasps:={self.plan.session_grasps}",
            f"seed:={self.plan.seed}",
            "record:=false",
        ]
        if (out / "manifest.jsonl").exists():
            command.append("resume:=true")
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

    def session_at(self, bins: int) -> Path:
        """The session with its depth-maps made again over ``bins`` x ``bins`` bins."""
        if bins == REFERENCE_SIZE:
            return self.session  # collected at 100 x 100
        return redepth_dataset(self.session, self.root / f"session_{bins}", bins=bins, progress=False).root

    @functools.cached_property
    def session_test(self) -> SessionTest:
        reader = DatasetReader(self.session)
        records = select_records(reader, "test")
        samples = [reader.load(r) for r in records]
        return SessionTest(
            records,
            np.stack([s.tactile_rgb for s in samples]),
            np.stack([deformation_map(s.tactile_diff_rgb) for s in samples]),
        )

    def config(self, size: int, width: int, registered: bool) -> TrainConfig:
        """configs/quick.yaml with the plan's epochs, at ``size`` x ``size``, generator ``width``;
        the physics prior blurred by the registration's pose error only for a ``registered``
        (collected) dataset: the analytic contacts' geometry is exact."""
        base = training_config()
        pad = -(-size // 128) * 128  # the U-Net's 7 halvings need a multiple of 128
        generator = dataclasses.replace(base.generator, image_size=size, pad_to=pad, ngf=width)
        # One thread: on a shared machine extra OpenMP threads mostly wait for a core, and
        # the CPU seconds a sweep reports are then comparable from run to run.
        return dataclasses.replace(
            base,
            seed=self.plan.seed,
            epochs=self.plan.epochs,
            epochs_decay=self.plan.epochs,
            generator=generator,
            threads=1,
            session_pose_sigma_mm=base.session_pose_sigma_mm if registered else 0.0,
        )

    def model(self, size: int = REFERENCE_SIZE, width: int = 16) -> Path:
        """The model trained on the analytic contacts at ``size`` x ``size``: see :meth:`_trained`."""
        return self._trained(
            self.dataset(size), self.config(size, width, registered=False), self.root / f"train_{size}_w{width}"
        )

    def library_at(self, bins: int) -> Path:
        """``plan.library_samples`` contact-library pairs (dataset.contact_library) in the
        session's scene, depth range and crop, at ``bins`` x ``bins``: what the default model
        trains on beside a session (make demo, docs/generalisation.md)."""
        out = self.root / f"library_{bins}"
        if (out / "manifest.jsonl").exists() and len(DatasetReader(out).records) >= self.plan.library_samples:
            return out  # made by an earlier run, whose code version its dataset.json keeps
        session = DatasetReader(self.session)
        params, _ = depth_map_params(session)
        return write_contact_library(
            out,
            self.plan.library_samples,
            self.plan.seed,
            session.info.scene,
            params.y_range_m,
            params.margin_m,
            size=bins,
        ).root

    def session_model(self, bins: int = REFERENCE_SIZE) -> Path:
        """The width-16 model trained as the default is (the session with a contact library)
        at ``bins`` x ``bins``: see :meth:`_trained`."""
        return self._trained(
            self.session_at(bins),
            self.config(bins, 16, registered=True),
            self.root / f"train_session_{bins}",
            libraries=(self.library_at(bins),),
        )

    def _trained(self, dataset: Path, config: TrainConfig, out: Path, libraries: tuple[Path, ...] = ()) -> Path:
        """The trained model's directory (checkpoint.pt, val_log.csv, cpu_s.json: process CPU
        seconds of each epoch, data loading included). Trained one epoch per call so that each
        epoch's CPU time is known; an interrupted training resumes from its checkpoint."""
        cpu_log = out / "cpu_s.json"
        checkpoint = out / "checkpoint.pt"
        if checkpoint.exists() and TrainConfig.from_dict(load_checkpoint(checkpoint)["train_config"]) != config:
            print(f"report: {out.name} was trained with another config; training it again", file=sys.stderr)
            shutil.rmtree(out)
        if len(_cpu_s(out)) >= 2 * self.plan.epochs:
            self.reused_models.add(out.name)
        threads = torch.get_num_threads()
        try:
            while len(_cpu_s(out)) < 2 * self.plan.epochs:
                fresh = not checkpoint.exists()
                started = time.process_time()
                train(dataset, config, out, resume=True, progress=False, stop_after_epochs=1, libraries=libraries)
                cpu = [] if fresh else _cpu_s(out)
                cpu_log.write_text(json.dumps(cpu + [round(time.process_time() - started, 2)]))
        finally:
            torch.set_num_threads(threads)  # train() set one thread for the whole process
        return out

    @functools.cached_property
    def test(self) -> tuple[list[Contact], np.ndarray]:
        """The analytic test split's contacts and their 100 x 100 ground-truth images."""
        reader = DatasetReader(self.dataset(REFERENCE_SIZE))
        records = select_records(reader, "test")
        by_id = {c.sample_id: c for c in self.contacts}
        return [by_id[r.sample_id] for r in records], np.stack([reader.load(r).tactile_rgb for r in records])


def _resize(images: np.ndarray, size: int) -> np.ndarray:
    return np.stack([resize_rgb(image, size, size) for image in images])


def _session_scores(test: SessionTest, estimate: np.ndarray, no_contact: np.ndarray) -> dict[str, float]:
    """SSIM of 100 x 100 estimates against the session's test truth on the contact windows
    (models.evaluate.contact_ssim: the accuracy these sweeps rank by) and over the whole
    image (the paper's figure, which a no-contact estimate scores well on). ``no_contact`` is
    the same model's estimate from an empty depth-map: a setting whose estimates do not beat
    it on the contact windows (one-sided Wilcoxon over the pairs, ``p_vs_no_contact``) gives
    the model nothing it uses."""
    contact = contact_ssim(test.truth, test.deformation, estimate)
    floor = contact_ssim(test.truth, test.deformation, np.repeat(no_contact[None], len(test.truth), axis=0))
    whole = ssim_rgb(test.truth, estimate)
    better = stats.wilcoxon(contact, floor, alternative="greater").pvalue if np.any(contact != floor) else 1.0
    return {
        "contact_ssim": float(contact.mean()),
        "contact_ssim_se": _se(contact),
        "contact_pairs": len(contact),
        "no_contact_ssim": round(float(floor.mean()), 4),
        "p_vs_no_contact": float(better),
        "ssim": round(float(whole.mean()), 4),
        "ssim_se": _se(whole),
    }


def _no_contact_estimate(generator: torch.nn.Module, depth_range: tuple[float, float], size: int) -> np.ndarray:
    """The model's estimate (resized to 100 x 100) from a depth-map with nothing in reach."""
    empty = np.full((1, size, size), depth_range[1], np.float32)
    return _resize(predict(generator, empty, depth_range), REFERENCE_SIZE)[0]


def resolution(ws: Workspace) -> list[Point]:
    """The session's depth-maps made again over 50, 100, 200 bins (tactile images resized to
    match) and a model trained on each -> SSIM of its estimates resized to 100 x 100 against
    the collected 100 x 100 truth, training CPU s/epoch, inference ms per region."""
    test = ws.session_test
    points = []
    for size in ws.plan.resolutions:
        model = ws.session_model(size)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        reader = DatasetReader(ws.session_at(size))
        depth = np.stack([reader.load(r.sample_id).depth_map_m for r in test.records])
        estimate = predict(generator, depth, depth_range)
        inference_ms = _median_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
        scores = _session_scores(
            test, _resize(estimate, REFERENCE_SIZE), _no_contact_estimate(generator, depth_range, size)
        )
        points.append(
            _point(
                "resolution",
                f"{size} x {size}",
                _epoch_s(model),
                scores.pop("contact_ssim"),
                inference_ms_per_region=round(inference_ms, 3),
                **scores,
            )
        )
    return points


def _cpu_s(model: Path) -> list[float]:
    try:
        return json.loads((model / "cpu_s.json").read_text())
    except FileNotFoundError:
        return []


def _epoch_s(model: Path) -> float:
    """The median epoch's CPU seconds: the first training of a process also pays start-up."""
    return float(statistics.median(_cpu_s(model)))


def width(ws: Workspace) -> list[Point]:
    """Generator width (ngf), each trained the same way at 100 x 100 -> test SSIM against the
    truth, and eager fp32 inference time per region (benchmarks.inference has the runtimes)."""
    _, truth = ws.test
    reader = DatasetReader(ws.dataset(REFERENCE_SIZE))
    depth = np.stack([reader.load(r).depth_map_m for r in select_records(reader, "test")])
    points = []
    for ngf in ws.plan.trained_widths:
        model = ws.model(REFERENCE_SIZE, ngf)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        ssim = ssim_rgb(truth, predict(generator, depth, depth_range))
        inference_ms = _median_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
        points.append(
            _point(
                "width",
                f"width {ngf}",
                inference_ms,
                ssim.mean(),
                ssim_se=_se(ssim),
                training_s_per_epoch=round(_epoch_s(model), 2),
                parameters=sum(p.numel() for p in generator.parameters()),
            )
        )
    return points


def _se(values: np.ndarray) -> float:
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else float("nan")


def _val_log(model: Path) -> list[dict[str, float]]:
    with open(model / "val_log.csv", newline="") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def training_length(ws: Workspace) -> list[Point]:
    """Validation SSIM after each epoch of the 100 x 100 model against its training CPU time."""
    model = ws.model()
    return [
        _point("training_length", f"{int(row['epoch']) + 1} epoch(s)", cpu, row["val_ssim"], val_l1=row["val_l1"])
        for row, cpu in zip(_val_log(model), np.cumsum(_cpu_s(model)))
    ]


def density(ws: Workspace) -> list[Point]:
    """The session's test grasps with each object's model cloud (the patch extractor's)
    voxel-thinned to each density and their depth-maps made again from the recorded model
    poses (dataset.redepth), estimated by the model trained on the session -> SSIM; time =
    making one depth-map (the pipeline thins a model cloud once and cuts many depth-maps from
    it, so thinning and indexing are reported beside, not added)."""
    test = ws.session_test
    params, scene = depth_map_params(DatasetReader(ws.session))
    geometry = scene.gripper_geometry()
    generator, depth_range = load_generator(ws.session_model() / "checkpoint.pt")
    no_contact = _no_contact_estimate(generator, depth_range, REFERENCE_SIZE)
    full = {name: model_cloud(scene, name) for name in sorted({r.object_name for r in test.records})}
    points = []
    for value in (None, *ws.plan.densities):
        clouds, thinning = {}, []
        for name, cloud in full.items():
            started = time.perf_counter()
            clouds[name] = VoxelIndex(cloud if value is None else downsample_to_density(cloud, value))
            thinning.append((time.perf_counter() - started) * 1e3)
        maps, walls = [], []
        for record in test.records:
            started = time.perf_counter()
            maps.append(depth_map_again(clouds[record.object_name], np.array(record.model_to_gel), geometry, params))
            walls.append((time.perf_counter() - started) * 1e3)
        scores = _session_scores(test, predict(generator, np.stack(maps), depth_range), no_contact)
        points.append(
            _point(
                "density",
                "unfiltered" if value is None else f"{value:g} pts/cm³",
                statistics.median(walls),
                scores.pop("contact_ssim"),
                points_median=int(np.median([len(c.points_m) for c in clouds.values()])),
                thinning_ms=round(statistics.median(thinning), 3),
                paper_ssim=None if value is None else PAPER["density"].get(int(value)),
                **scores,
            )
        )
    return points


def gelsight_effects(ws: Workspace) -> list[Point]:
    """Test truth rendered with each GelSight effect (and all) on; the model was trained on
    renderings without them. Time = one 100 x 100 frame with the effects."""
    items, _ = ws.test
    generator, depth_range = load_generator(ws.model() / "checkpoint.pt")
    reader = DatasetReader(ws.dataset(REFERENCE_SIZE))
    estimate = predict(
        generator, np.stack([reader.load(r).depth_map_m for r in select_records(reader, "test")]), depth_range
    )
    plain, pitch = gelsight_renderer(REFERENCE_SIZE)
    gaps = [gel_gap_from_surface(c.surface, REFERENCE_SIZE, REFERENCE_SIZE, pitch) for c in items]
    points, ideal = [], None
    for names in ((), *((n,) for n in GELSIGHT_EFFECTS), tuple(GELSIGHT_EFFECTS)):
        renderer = GelSightRenderer(
            plain.config, effects=[make_effect(n) for n in names], rng=np.random.default_rng(ws.plan.seed)
        )
        frame_ms = _median_ms(lambda: renderer.render(gaps[0]), 5)
        ssim = ssim_rgb(np.stack([renderer.render(g) for g in gaps]), estimate)
        ideal = ssim.mean() if ideal is None else ideal
        setting = "none" if not names else ("all" if len(names) > 1 else names[0])
        points.append(
            _point(
                "gelsight_effects",
                setting,
                frame_ms,
                ssim.mean(),
                ssim_se=_se(ssim),
                ssim_lost=round(float(ideal - ssim.mean()), 4),
            )
        )
    return points


def depth_effects(ws: Workspace) -> list[Point]:
    """ycb_three's depth effects off, alone (full plan) and all on -> time per 512 x 424 depth
    frame, and ADD-S of registration (default parameters) on clouds made with them."""
    scene = load_scene(SCENE)
    present = [e for e in DEPTH_EFFECTS if any(s.name == e for s in scene.effects)]
    every = sorted({s.name for s in scene.effects})
    settings: list[tuple[str, ...]] = [()]
    if ws.plan.depth_effects_alone:
        settings += [(e,) for e in present]
    settings.append(tuple(present))
    points = []
    for kept in settings:
        variant = dataclasses.replace(scene, effects=[s for s in scene.effects if s.name in kept])
        world = SimWorld(variant, seed=ws.plan.seed)
        camera = world.camera_names()[0]
        world.render_depth(camera)  # the first frame casts every ray and caches it
        frame_ms = _median_ms(lambda: world.render_depth(camera), ws.plan.depth_frames)
        cases = _sweep_cases(SCENE, ws.plan.registration_poses, ws.plan.seed, [e for e in every if e not in kept])
        row = _sweep_row(cases, RegistrationParams(), {})
        setting = "none" if not kept else ("all" if len(kept) > 1 else kept[0])
        points.append(
            _point(
                "depth_effects",
                setting,
                frame_ms,
                row["add_s_mm_median"],
                accepted_rate=row["accepted_rate"],
                registration_ms=row["ms_median"],
            )
        )
    return points


def _registration_points(sweep: str, cases, settings) -> list[Point]:
    points = []
    for label, params in settings:
        row = _sweep_row(cases, params, {})
        points.append(
            _point(
                sweep,
                label,
                row["ms_median"],
                row["add_s_mm_median"],
                add_s_mm_p90=row["add_s_mm_p90"],
                accepted_rate=row["accepted_rate"],
            )
        )
    return points


def registration(ws: Workspace) -> list[Point]:
    """FPFH + RANSAC + ICP on segmented clusters of the five YCB meshes in ycb_three (with its
    effects): voxel size, RANSAC iterations, ICP distance stages -> ADD-S median and time."""
    cases = _sweep_cases(SCENE, ws.plan.registration_poses, ws.plan.seed, [])
    base = RegistrationParams()
    voxel = [
        (
            f"{v} mm",
            dataclasses.replace(base, voxel_size_m=v * 1e-3, icp_voxel_size_m=min(v * 1e-3, base.icp_voxel_size_m)),
        )
        for v in ws.plan.voxel_mm
    ]
    ransac = [(f"{n:,}", dataclasses.replace(base, ransac_max_iterations=n)) for n in ws.plan.ransac_iterations]
    icp = [
        ("/".join(map(str, stages)) + " mm", dataclasses.replace(base, icp_distances_m=tuple(d * 1e-3 for d in stages)))
        for stages in ws.plan.icp_distances_mm
    ]
    return (
        _registration_points("registration_voxel", cases, voxel)
        + _registration_points("registration_ransac", cases, ransac)
        + _registration_points("registration_icp", cases, icp)
    )


def inference(ws: Workspace) -> list[Point]:
    """benchmarks.inference: width x precision x runtime -> SSIM against fp32 eager of the same
    weights, and time per region at batch 16."""
    threads = torch.get_num_threads()
    args = argparse.Namespace(
        checkpoint=[],
        dataset=None,
        widths=list(ws.plan.widths),
        precisions=list(ws.plan.precisions),
        runtimes=list(ws.plan.runtimes),
        batch=16,
        seconds=ws.plan.inference_seconds,
        threads=threads,
        seed=ws.plan.seed,
        json=True,
    )
    try:
        rows = inference_bench.run(args)
    finally:
        torch.set_num_threads(threads)
    return [
        _point(
            "inference",
            f"width {r['width']} {r['precision']} {r['runtime']}",
            1e3 / r["regions_per_s"],
            r["ssim"],
            regions_per_s=r["regions_per_s"],
            p50_ms=r["p50_ms"],
        )
        for r in rows
    ]


def dropout(ws: Workspace) -> list[Point]:
    """S dropout passes (nodes.inference's sampling copy) -> per-pixel std; calibration =
    Pearson r between that std and the deterministic estimate's actual per-pixel error."""
    items, truth = ws.test
    generator, depth_range = load_generator(ws.model() / "checkpoint.pt")
    reader = DatasetReader(ws.dataset(REFERENCE_SIZE))
    depth = np.stack([reader.load(r).depth_map_m for r in select_records(reader, "test")])
    error = np.abs(predict(generator, depth, depth_range).astype(np.float32) - truth).mean(axis=-1)
    sampled = sampling_copy(generator)
    x = network_input(depth, depth_range, generator.config, generator.prior)
    points = []
    for samples in ws.plan.dropout_samples:
        torch.manual_seed(ws.plan.seed)
        started = time.perf_counter()
        with torch.inference_mode():
            passes = torch.stack([(sampled(x) + 1.0) * 127.5 for _ in range(samples)])
        std = passes.std(dim=0).mean(dim=1).numpy()
        ms = (time.perf_counter() - started) * 1e3 / len(items)
        pixel_r = float(np.corrcoef(std.ravel(), error.ravel())[0, 1])
        image_r = float(np.corrcoef(std.mean(axis=(1, 2)), error.mean(axis=(1, 2)))[0, 1])
        points.append(
            _point(
                "dropout",
                f"{samples} samples",
                ms,
                pixel_r,
                image_r=round(image_r, 4),
                mean_std=round(float(std.mean()), 3),
            )
        )
    return points


SWEEPS = {
    "resolution": resolution,
    "training_length": training_length,
    "width": width,
    "density": density,
    "gelsight_effects": gelsight_effects,
    "dropout": dropout,
    "inference": inference,
    "registration": registration,
    "depth_effects": depth_effects,
}
