"""The measurements behind the accuracy-time report. Each sweep returns points
``{"sweep", "setting", "time", "accuracy", ...extra figures}``; what "time" and "accuracy"
mean for a sweep is in report.specs. The work is done by the project's own code (a collection
session on the simulated scene, dataset.redepth, dataset.synth contacts, models.train,
perception, sim, benchmarks), on the datasets and models of a report.workspace; this module
only chooses settings.

The density and resolution sweeps run on a collected session, since what they change is how
the patch extractor makes depth-maps from registered models; the other learned sweeps compare
networks and GelSight effects on analytic contacts, whose ground truth can be rendered again.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from scipy import stats

from benchmarks import inference as inference_bench
from benchmarks.perception import _sweep_cases, _sweep_row
from benchmarks.sim import DEPTH_EFFECTS
from dataset.images import resize_rgb
from dataset.reader import DatasetReader
from dataset.redepth import depth_map_again, depth_map_params, model_cloud
from dataset.synth import gel_gap_from_surface, gelsight_renderer
from models.checkpoint import load_generator
from models.data import network_input, select_records
from models.evaluate import PAPER_DENSITY_SSIM, contact_ssim
from models.networks import UNetGenerator
from models.runtime import sampling_copy
from models.serving import predict
from perception.density import downsample_to_density
from perception.pointcloud import VoxelIndex
from perception.registration import RegistrationParams
from perception.ssim import ssim_rgb
from report.calibration_sweep import calibration_grasps
from report.specs import Point, point
from report.workspace import REFERENCE_SIZE, SessionTest, Workspace, epoch_cpu_s
from sim.gelsight import GelSightRenderer
from sim.gelsight_effects import EFFECTS as GELSIGHT_EFFECTS
from sim.gelsight_effects import make_effect
from sim.world import SimWorld
from workcell.scene import load_scene

SCENE = "scenes/ycb_three.yaml"


def _median_ms(function, runs: int) -> float:
    walls = []
    for _ in range(runs):
        started = time.perf_counter()
        function()
        walls.append((time.perf_counter() - started) * 1e3)
    return statistics.median(walls)


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


def _no_contact_estimate(generator: UNetGenerator, depth_range: tuple[float, float], size: int) -> np.ndarray:
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
            point(
                "resolution",
                f"{size} x {size}",
                _epoch_s(model),
                scores.pop("contact_ssim"),
                inference_ms_per_region=round(inference_ms, 3),
                **scores,
            )
        )
    return points


def _epoch_s(model: Path) -> float:
    """The median epoch's CPU seconds: the first training of a process also pays start-up."""
    return float(statistics.median(epoch_cpu_s(model)))


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
            point(
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
        point("training_length", f"{int(row['epoch']) + 1} epoch(s)", cpu, row["val_ssim"], val_l1=row["val_l1"])
        for row, cpu in zip(_val_log(model), np.cumsum(epoch_cpu_s(model)))
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
            point(
                "density",
                "unfiltered" if value is None else f"{value:g} pts/cm³",
                statistics.median(walls),
                scores.pop("contact_ssim"),
                points_median=int(np.median([len(c.points_m) for c in clouds.values()])),
                thinning_ms=round(statistics.median(thinning), 3),
                paper_ssim=None if value is None else PAPER_DENSITY_SSIM.get(int(value)),
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
    # The effects are the simulated GelSight's: its configuration renders again with them.
    if not isinstance(plain, GelSightRenderer):
        raise TypeError(f"the GelSight effects sweep needs the simulated GelSight, not {type(plain).__name__}")
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
            point(
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
            point(
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
            point(
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
        point(
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
            point(
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
    "calibration_grasps": calibration_grasps,
}
