"""Running a trained generator outside training: eager PyTorch (fp32 or bf16 autocast) and
the ONNX graph ONNX Runtime loads. The inference node and the inference benchmark share these,
so the benchmark measures the graphs the node serves."""

from __future__ import annotations

import copy
import io
import os
import warnings
from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from models.networks import UNetGenerator

Runner = Callable[[np.ndarray], np.ndarray]


class UncheckedGenerator(nn.Module):
    """The generator without its input check, which graph tracers (FX, ONNX, inductor) cannot follow."""

    def __init__(self, generator: UNetGenerator) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        return self.generator.forward_unchecked(depth)


def eager_runner(module: nn.Module, bf16: bool) -> Runner:
    """N x C x H x W float32 -> the module's float32 output, under bf16 autocast if asked."""

    def run(x: np.ndarray) -> np.ndarray:
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            return module(torch.from_numpy(x)).float().numpy()

    return run


def export_onnx(generator: UNetGenerator, target: str | os.PathLike[str] | io.BytesIO) -> None:
    """The generator (eval mode, batch dimension dynamic) as an ONNX graph: inputs ``depth``,
    outputs ``image``."""
    size = generator.config.image_size
    with warnings.catch_warnings():
        # The torch.export-based exporter needs onnxscript, which is not a dependency; the
        # TorchScript one still works but warns about its deprecation and about shape
        # arithmetic it handles, none of which concerns the exported model.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            UncheckedGenerator(generator).eval(),
            (torch.zeros(1, generator.config.input_channels, size, size),),
            target if isinstance(target, io.BytesIO) else str(target),
            dynamo=False,
            input_names=["depth"],
            output_names=["image"],
            dynamic_axes={"depth": {0: "n"}, "image": {0: "n"}},
            opset_version=17,
        )


def onnx_runner(graph: str | os.PathLike[str] | bytes, threads: int) -> Runner:
    """An ONNX Runtime (CPU) session of ``graph`` (a path or the serialised model) as a runner,
    with the options the inference node serves with, so the benchmark measures what it serves."""
    import onnxruntime as ort  # noqa: PLC0415 - only this runtime needs it

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Threads that spin between runs burn the cores other workers and clients need: on the
    # shared 2-core machine, width 16, 2 threads, it measured 48 -> 184 regions/s without.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(
        graph if isinstance(graph, bytes) else str(graph), options, providers=["CPUExecutionProvider"]
    )
    return lambda x: session.run(None, {"depth": x})[0]


class SampledDropout(nn.Module):
    """Dropout that stays on at inference. Written with rand_like because the ONNX exporter
    removes nn.Dropout from an eval graph, and an eval graph keeps BatchNorm's running stats."""

    def __init__(self, p: float) -> None:
        super().__init__()
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        keep = (torch.rand_like(x) >= self.p).to(x.dtype)
        return x * keep * (1.0 / (1.0 - self.p))


def sampling_copy(generator: UNetGenerator) -> UNetGenerator:
    """A copy in eval mode whose dropout still samples: several passes give the spread the
    inference node reports as per-pixel uncertainty."""
    sampled = copy.deepcopy(generator).eval()
    for block in sampled.modules():
        for name, child in block.named_children():
            if isinstance(child, nn.Dropout):
                setattr(block, name, SampledDropout(child.p))
    return sampled
