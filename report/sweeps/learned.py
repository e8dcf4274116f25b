"""The learned sweeps on the analytic contacts, whose ground truth can be rendered again:
training length, generator width, GelSight effects, the runtime variants and dropout."""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks import inference as inference_bench
from dataset.reader import DatasetReader
from dataset.synth import gel_gap_from_surface, gelsight_renderer
from models.checkpoint import load_generator
from models.data import network_input, select_records
from models.runtime import sampling_copy
from models.serving import predict
from perception.ssim import ssim_rgb
from report.specs import Point, point
from report.sweeps.common import epoch_s, median_ms, standard_error
from report.workspace import REFERENCE_SIZE, Workspace, epoch_cpu_s
from sim.gelsight import GelSightRenderer
from sim.gelsight_effects import EFFECTS as GELSIGHT_EFFECTS
from sim.gelsight_effects import make_effect


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
        inference_ms = median_ms(lambda: predict(generator, depth, depth_range), 3) / len(depth)
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
    return points


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
        frame_ms = median_ms(lambda: renderer.render(gaps[0]), 5)
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
