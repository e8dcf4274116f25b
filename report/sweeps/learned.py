"""The learned sweeps on the analytic contacts, whose ground truth can be rendered again:
training length, generator width (down to the physics prior alone), GelSight effects and the
runtime variants."""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import torch

from benchmarks import inference as inference_bench
from dataset.reader import DatasetReader
from dataset.synth import gel_gap_from_surface, gelsight_renderer
from models.checkpoint import load_generator
from models.data import select_records
from models.serving import predict
from perception.ssim import ssim_rgb
from report.specs import Point, point
from report.sweeps.common import epoch_s, median_cpu_ms, standard_error
from report.sweeps.serving import serving_as
from report.workspace import REFERENCE_SIZE, Workspace, epoch_cpu_s
from sim.gelsight import GelSightRenderer
from sim.gelsight_effects import EFFECTS as GELSIGHT_EFFECTS
from sim.gelsight_effects import make_effect


def width(ws: Workspace) -> list[Point]:
    """Generator width (ngf), each trained the same way at 100 x 100, its network served (not
    the prior a checkpoint may have chosen to serve; no uncertainty) -> test SSIM against the
    truth, and eager fp32 inference time per region (benchmarks.inference has the runtimes);
    then the physics prior alone, which every width draws the same and no network computes."""
    _, truth = ws.test
    reader = DatasetReader(ws.dataset(REFERENCE_SIZE))
    depth = np.stack([reader.load(r).depth_map_m for r in select_records(reader, "test")])
    points = []
    for ngf in ws.plan.trained_widths:
        model = ws.model(REFERENCE_SIZE, ngf)
        generator, depth_range = load_generator(model / "checkpoint.pt")
        with serving_as(generator, "network", None):
            ssim = ssim_rgb(truth, predict(generator, depth, depth_range))
            inference_ms = median_cpu_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
        points.append(
            point(
                "width",
                f"width {ngf}",
                inference_ms,
                ssim.mean(),
                ssim_se=standard_error(ssim),
                training_s_per_epoch=round(epoch_s(model), 2),
                parameters=sum(p.numel() for p in generator.parameters()),
            )
        )
    return points + [_prior_alone(ws.model(REFERENCE_SIZE, min(ws.plan.trained_widths)), depth, truth)]


def _prior_alone(model: Path, depth: np.ndarray, truth: np.ndarray) -> Point:
    """The width table's floor: the model's physics prior served alone (models.serving.served_images
    "prior"), timed from the same depth-maps; no weights, nothing trained."""
    generator, depth_range = load_generator(model / "checkpoint.pt")
    with serving_as(generator, "prior", None):
        ssim = ssim_rgb(truth, predict(generator, depth, depth_range))
        inference_ms = median_cpu_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
    return point("width", "prior alone", inference_ms, ssim.mean(), ssim_se=standard_error(ssim), parameters=0)


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
        frame_ms = median_cpu_ms(lambda: renderer.render(gaps[0]), 5)
        ssim = ssim_rgb(np.stack([renderer.render(g) for g in gaps]), estimate)
        ideal = ssim.mean() if ideal is None else ideal
        setting = "none" if not names else ("all" if len(names) > 1 else names[0])
        points.append(
            point(
                "gelsight_effects",
                setting,
                frame_ms,
                ssim.mean(),
                ssim_se=standard_error(ssim),
                ssim_lost=round(float(ideal - ssim.mean()), 4),
            )
        )
    return points


def inference(ws: Workspace) -> list[Point]:
    """benchmarks.inference: width x precision x runtime -> SSIM against fp32 eager of the same
    weights, and time per region at batch 16."""
    threads = torch.get_num_threads()
    # The bench's own parser, so that every option it gains has its default here too.
    parser = argparse.ArgumentParser()
    inference_bench.add_arguments(parser)
    args = parser.parse_args(
        [
            "--widths",
            *map(str, ws.plan.widths),
            "--precisions",
            *ws.plan.precisions,
            "--runtimes",
            *ws.plan.runtimes,
            "--batch=16",
            f"--seconds={ws.plan.inference_seconds}",
            f"--threads={threads}",
            f"--seed={ws.plan.seed}",
        ]
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
