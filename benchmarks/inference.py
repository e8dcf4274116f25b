"""``dtx bench inference``: generator width x precision x runtime on this machine's CPU, or
with ``--device cuda`` (or auto) on its GPU: ONNX Runtime's CUDA provider and eager PyTorch on
CUDA (int8 stays on the CPU, the only place its kernels are; ``compile`` too).

For each combination: regions per second with batches of ``--batch`` depth-maps, the median
(p50) latency of one region alone, ``ssim_vs_fp32``: the SSIM of its output against the fp32
eager output of the same weights on the same inputs (how much the faster variant changes the
estimate), and ``ssim``: with ``--dataset``, the paper's SSIM against the ground truth of the
dataset's test split (then ``near_best`` marks the rows within 0.01 of the best row, the
choices the issue asks for), else the same as ``ssim_vs_fp32``.

* widths: the generator's ngf; weights are the trained models of ``--checkpoint`` (one per
  trained width, repeatable) or seeded random ones with PyTorch's default
  initialisation (pix2pix's N(0, 0.02) would make an untrained output nearly constant and
  every SSIM trivially 1);
* precisions: fp32; bf16 (autocast, eager and compiled); int8 (the convolutions of the
  encoder in int8, the decoder in fp32: models.runtime.int8_convolutions, calibrated as the
  inference node calibrates, on a fixed set of analytic contacts other than the synthetic
  rows' inputs). PyTorch's own int8 path,
  torch.ao FX quantisation, is deprecated in torch 2.13 (its successor, torchao, is not a
  dependency) and measured SSIM 0.07-0.39 against fp32 on this generator: left out;
* runtimes: eager PyTorch, ``torch.compile`` (inductor), ONNX Runtime (CPU provider, with the
  inference node's session options: models.runtime.onnx_runner).
Combinations left out: int8 in PyTorch (above), bf16 in ONNX Runtime (no bf16 CPU kernels).
Against the machine's limit: ``gflops`` is what a row computes (regions/s x the generator's
floating-point operations per region, counted by torch.utils.flop_counter: convolutions and
matrix products, 2 per multiply-add), ``share_of_fp32_peak`` that over ``fp32_peak_gflops``, the
fp32 matrix-product rate of PyTorch on the same threads measured in the same run (issue 18's
target: >= 0.75 for the default model in its best runtime). ``fp32_peak_after_gflops``: the same
rate measured again right after the row: on a shared machine a neighbour's job starting or
stopping moves the capacity under a row, and a row whose two peaks differ much has a share that
says more about the neighbour than about the runtime (the share keeps the run's one reference).
Inputs are the test split's depth-maps with ``--dataset``, else depth-maps of synthetic
analytic contacts (dataset.synth).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Any

import numpy as np
import torch

from models.data import to_uint8_rgb
from models.networks import GeneratorConfig, UNetGenerator
from models.runtime import (
    DEVICES,
    CudaUnavailable,
    Runner,
    UncheckedGenerator,
    contact_inputs,
    eager_runner,
    network_runner,
    resolve_device,
)
from perception.ssim import ssim_rgb

DEPTH_RANGE_M = (-0.0015, 0.0025)
OFFERED = {"eager": ("fp32", "bf16"), "compile": ("fp32", "bf16"), "onnxrt": ("fp32", "int8")}


def _measure(run: Runner, inputs: np.ndarray, batch: int, seconds: float) -> tuple[float, float]:
    """(regions per second at ``batch``, p50 ms for one region), each measured ~``seconds``."""
    run(inputs[:batch])  # warm-up: allocation, lazy initialisation
    regions, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or regions == 0:
        run(inputs[:batch])
        regions += batch
    throughput = regions / (time.perf_counter() - started)
    run(inputs[:1])
    latencies: list[float] = []
    started = time.perf_counter()
    while time.perf_counter() - started < seconds or len(latencies) < 5:
        t0 = time.perf_counter()
        run(inputs[len(latencies) % len(inputs)][None])
        latencies.append((time.perf_counter() - t0) * 1e3)
    return throughput, statistics.median(latencies)


def fp32_peak_gflops(seconds: float = 1.0, size: int = 1536) -> float:
    """This machine's fp32 compute limit as PyTorch reaches it: the best rate of size x size
    matrix products (2 n^3 operations each) on the current threads, over ~``seconds``."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)  # warm-up: the BLAS's threads and buffers
    best, started = float("inf"), time.perf_counter()
    while time.perf_counter() - started < seconds or best == float("inf"):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2.0 * size**3 / best / 1e9


def gflop_per_region(generator: UNetGenerator, inputs: np.ndarray) -> float:
    """The generator's floating-point operations for one region (GFLOP), as counted by
    torch.utils.flop_counter (convolutions and matrix products)."""
    from torch.utils.flop_counter import FlopCounterMode

    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        UncheckedGenerator(generator).eval()(torch.from_numpy(inputs[:1]))
    return counter.get_total_flops() / 1e9


def _generator(width: int | None, checkpoint: str | None, seed: int) -> tuple[UNetGenerator, tuple[float, float]]:
    """The trained generator of ``checkpoint``, else a seeded random one of ``width``."""
    if checkpoint:
        from models.checkpoint import load_generator

        return load_generator(checkpoint)
    if width is None:
        raise ValueError("a generator needs a checkpoint or a width")
    torch.manual_seed(seed)
    return UNetGenerator(GeneratorConfig(ngf=width)).eval(), DEPTH_RANGE_M


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The benchmark table: one row per (width, precision, runtime)."""
    torch.set_num_threads(args.threads)
    # Denormal floats (tiny activations) make CPU convolutions orders of magnitude slower;
    # flushing them is process-wide state, so it is switched back off afterwards.
    torch.set_flush_denormal(True)
    try:
        return _run_table(args)
    finally:
        torch.set_flush_denormal(False)


def test_split_inputs(
    dataset: str, generator: UNetGenerator, depth_range_m: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """(network inputs, ground-truth uint8 images) of a dataset's test split."""
    from models.data import load_pairs, reader_for_model, select_records

    reader = reader_for_model(dataset, depth_range_m)
    x, y = load_pairs(reader, select_records(reader, "test"), generator.config, generator.prior)
    return x.numpy(), to_uint8_rgb(y)


def _run_table(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    peak = fp32_peak_gflops()
    print(f"fp32 matrix-product peak on {args.threads} thread(s): {peak:.1f} GFLOP/s", file=sys.stderr, flush=True)
    models: list[tuple[int | None, str | None]] = (  # (width, checkpoint): one of the two
        [(None, c) for c in args.checkpoint] if args.checkpoint else [(w, None) for w in args.widths]
    )
    for width, checkpoint in models:
        generator, depth_range_m = _generator(width, checkpoint, args.seed)
        if args.dataset:
            inputs, truth = test_split_inputs(args.dataset, generator, depth_range_m)
        else:
            inputs = contact_inputs(generator, depth_range_m, max(args.batch, 16), args.seed)
            truth = None
        reference = to_uint8_rgb(torch.from_numpy(eager_runner(generator, bf16=False)(inputs)))
        gflop = gflop_per_region(generator, inputs)
        for runtime in args.runtimes:
            for precision in args.precisions:
                if precision not in OFFERED[runtime]:
                    continue
                device = _device(args.device, runtime, precision)
                if runtime == "compile":
                    compiled = torch.compile(UncheckedGenerator(generator))
                    # torch.compile of a module returns a module (an OptimizedModule); its
                    # annotation says only "a callable".
                    if not isinstance(compiled, torch.nn.Module):
                        raise TypeError(f"torch.compile returned {type(compiled).__name__}, not a module")
                    runner = eager_runner(compiled, bf16=precision == "bf16")
                else:  # the node's runners, graphs and session options
                    runner = network_runner(generator, depth_range_m, runtime, precision, args.threads, device)
                output = to_uint8_rgb(torch.from_numpy(runner(inputs)))
                throughput, p50 = _measure(runner, inputs, args.batch, args.seconds)
                peak_after = fp32_peak_gflops()  # did the machine's capacity change meanwhile?
                vs_fp32 = round(float(ssim_rgb(reference, output).mean()), 4)
                rows.append(
                    {
                        "width": generator.config.ngf,
                        "precision": precision,
                        "runtime": runtime,
                        "device": device,
                        "ssim": vs_fp32 if truth is None else round(float(ssim_rgb(truth, output).mean()), 4),
                        "ssim_vs_fp32": vs_fp32,
                        "regions_per_s": round(throughput, 1),
                        "p50_ms": round(p50, 2),
                        "gflop_per_region": round(gflop, 4),
                        "gflops": round(throughput * gflop, 1),
                        "fp32_peak_gflops": round(peak, 1),
                        "share_of_fp32_peak": round(throughput * gflop / peak, 3),
                        "fp32_peak_after_gflops": round(peak_after, 1),
                    }
                )
                # Progress on stderr: ``dtx bench`` prints the table (or JSON) on stdout.
                print(_format_row(rows[-1]), file=sys.stderr, flush=True)
    if args.dataset:
        best = max(row["ssim"] for row in rows)
        for row in rows:
            row["near_best"] = row["ssim"] >= best - 0.01
    return rows


def _device(asked: str, runtime: str, precision: str) -> str:
    """Where a row computes (models.runtime.resolve_device; torch.compile and int8 rows on the CPU);
    a clear exit when cuda is asked for and absent."""
    if runtime == "compile" or precision == "int8":
        return "cpu"
    try:
        return resolve_device(asked, runtime, precision)
    except CudaUnavailable as exc:
        raise SystemExit(f"dtx bench inference: {exc.code}: {exc}") from exc


def _format_row(row: dict[str, Any]) -> str:
    return (
        f"width {row['width']:3d}  {row['precision']:5s} {row['runtime']:8s} ssim {row['ssim']:.4f}  "
        f"{row['regions_per_s']:8.1f} regions/s  p50 {row['p50_ms']:7.2f} ms  "
        f"{row['gflops']:6.1f} GFLOP/s ({row['share_of_fp32_peak']:.0%} of the fp32 peak; "
        f"peak {row['fp32_peak_gflops']:.0f} before the rows, {row['fp32_peak_after_gflops']:.0f} after this one)"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``dtx bench inference`` (which adds ``--json`` itself)."""
    parser.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        help="benchmark this trained generator (repeat for each trained width) instead of seeded random widths",
    )
    parser.add_argument("--dataset", help="take inputs and ground truth from this dataset's test split")
    parser.add_argument("--widths", type=int, nargs="+", default=[16, 32, 64])
    parser.add_argument("--precisions", nargs="+", default=["fp32", "bf16", "int8"], choices=["fp32", "bf16", "int8"])
    # torch.compile is opt-in: compiling one model takes about a minute on 2 cores, and it
    # measured slower than ONNX Runtime here (width 16 fp32: 72 vs 110-140 regions/s).
    parser.add_argument("--runtimes", nargs="+", default=["eager", "onnxrt"], choices=["eager", "compile", "onnxrt"])
    parser.add_argument("--batch", type=int, default=32, help="regions per batch for the throughput")
    parser.add_argument("--seconds", type=float, default=1.5, help="measuring time per figure")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", choices=list(DEVICES), default="cpu", help="where the rows compute")
    parser.add_argument("--seed", type=int, default=0)
