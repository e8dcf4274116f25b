"""Running a trained generator outside training: eager PyTorch (fp32 or bf16 autocast) and
the ONNX graph ONNX Runtime loads, in fp32 or with its convolutions in int8, on the CPU or on a
CUDA GPU. The inference node and the inference benchmark share these, so the benchmark measures
the graphs the node serves."""

from __future__ import annotations

import copy
import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dataset.synth import analytic_contact_maps
from models.data import network_input, to_uint8_rgb
from models.networks import UNetGenerator

Runner = Callable[[np.ndarray | torch.Tensor], np.ndarray]

# Where a runner computes: "auto" is CUDA when this machine and the runtime have it, else the CPU.
DEVICES = ("cpu", "cuda", "auto")


class CudaUnavailable(ValueError):
    """CUDA was asked for and this machine or runtime cannot give it; ``code`` names it for
    programs (the inference node's status), the text says why, for people."""

    code = "cuda_unavailable"


def cuda_missing(runtime: str) -> str:
    """Why ``runtime`` (onnxrt | eager) cannot compute on a CUDA GPU here; "" when it can."""
    if runtime == "onnxrt":
        import onnxruntime as ort  # noqa: PLC0415 - only this runtime needs it

        if "CUDAExecutionProvider" not in ort.get_available_providers():
            return (
                f"this ONNX Runtime ({ort.__version__}) has no CUDA provider (its providers: "
                f"{', '.join(ort.get_available_providers())}); install onnxruntime-gpu, or serve with device cpu"
            )
        return ""
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        return f"PyTorch {torch.__version__} ({build}) sees no CUDA GPU; serve with device cpu"
    return ""


def resolve_device(device: str, runtime: str, precision: str) -> str:
    """ "cpu" or "cuda" for a ``device`` of DEVICES: "auto" is CUDA where ``runtime`` has it
    and ``precision`` runs there (int8's kernels are ONNX Runtime's CPU ones), else the CPU.
    CudaUnavailable for "cuda" without it; ValueError for an unknown device or int8 on cuda."""
    if device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "cpu" or (device == "auto" and precision == "int8"):
        return "cpu"
    if precision == "int8":
        raise ValueError("int8 runs on the CPU only (ONNX Runtime's int8 convolutions): serve fp32 on cuda")
    missing = cuda_missing(runtime)
    if missing and device == "cuda":
        raise CudaUnavailable(f"device 'cuda' was asked for, but {missing}")
    return "cpu" if missing else "cuda"


class UncheckedGenerator(nn.Module):
    """The generator without its input check, which graph tracers (FX, ONNX, inductor) cannot follow."""

    def __init__(self, generator: UNetGenerator) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        return self.generator.forward_unchecked(depth)


def eager_runner(module: nn.Module, bf16: bool, device: str = "cpu") -> Runner:
    """N x C x H x W float32 (a NumPy array, or a tensor anywhere) -> the module's float32
    output, under bf16 autocast if asked, the module copied to ``device`` (cpu | cuda;
    resolve_device) and computing there: an input already there is not copied."""
    if device != "cpu":
        module = copy.deepcopy(module).to(device)  # the caller's module stays where it is

    def run(x: np.ndarray | torch.Tensor) -> np.ndarray:
        with torch.inference_mode(), torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            return module(torch.as_tensor(x).to(device)).float().cpu().numpy()

    return run


def export_onnx(generator: UNetGenerator, target: str | os.PathLike[str]) -> None:
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
            str(target),
            dynamo=False,
            input_names=["depth"],
            output_names=["image"],
            dynamic_axes={"depth": {0: "n"}, "image": {0: "n"}},
            opset_version=17,
        )


def onnx_runner(graph: str | os.PathLike[str] | bytes, threads: int, device: str = "cpu") -> Runner:
    """An ONNX Runtime session of ``graph`` (a path or the serialised model) as a runner, with
    the options the inference node serves with, so the benchmark measures what it serves: on
    the CPU provider, or with ``device`` cuda on the CUDA provider (CudaUnavailable when ONNX
    Runtime cannot start it: it would otherwise fall back to the CPU with only a warning)."""
    import onnxruntime as ort  # noqa: PLC0415 - only this runtime needs it

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Threads that spin between runs burn the cores other workers and clients need: on the
    # shared 2-core machine, width 16, 2 threads, it measured 48 -> 184 regions/s without.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    providers = (["CUDAExecutionProvider"] if device == "cuda" else []) + ["CPUExecutionProvider"]
    session = ort.InferenceSession(graph if isinstance(graph, bytes) else str(graph), options, providers=providers)
    if device == "cuda" and "CUDAExecutionProvider" not in session.get_providers():
        raise CudaUnavailable(
            "device 'cuda' was asked for, but ONNX Runtime could not start its CUDA provider "
            "(no GPU, or its CUDA and cuDNN libraries are missing: see its warning above)"
        )
    return lambda x: session.run(None, {"depth": x if isinstance(x, np.ndarray) else x.cpu().numpy()})[0]


def contact_inputs(generator: UNetGenerator, depth_range_m: tuple[float, float], count: int, seed: int) -> np.ndarray:
    """count x C x H x W float32 network inputs of ``generator`` (its physics prior's channels
    included) from random analytic contacts (dataset.synth): what int8 quantisation is
    calibrated on. Contacts of every shape over the whole depth range, not a dataset: a
    checkpoint is served without its dataset, and the objects it is asked about are new."""
    maps = analytic_contact_maps(count, seed, depth_range_m[1], generator.config.image_size)
    return network_input(maps, depth_range_m, generator.config, generator.prior).numpy()


# What int8 graphs are calibrated on: a fixed set of contacts, so that a checkpoint served twice
# is quantised the same way (the seed is other than the benchmarks' inputs').
CALIBRATION_CONTACTS = 64
CALIBRATION_SEED = 2020


def onnx_graph(generator: UNetGenerator, depth_range_m: tuple[float, float], precision: str) -> bytes:
    """The generator's ONNX graph in ``precision``: fp32, or int8 (:func:`int8_convolutions`,
    calibrated on the fixed contacts)."""
    # torch.onnx.export writes to a path (the file holds the same bytes a file object got).
    with tempfile.TemporaryDirectory(prefix="dtx-onnx") as tmp:
        path = Path(tmp) / "generator.onnx"
        export_onnx(generator, path)
        graph = path.read_bytes()
    if precision == "fp32":
        return graph
    if precision == "int8":
        calibration = contact_inputs(generator, depth_range_m, CALIBRATION_CONTACTS, CALIBRATION_SEED)
        return int8_convolutions(graph, calibration)
    raise ValueError(f"ONNX graphs are fp32 or int8, not {precision!r}")


# The contacts int8 is judged on: drawn as the calibration's are, but others (a graph is not
# judged on what it was calibrated on).
JUDGING_CONTACTS = 64
JUDGING_SEED = 2021


def int8_ssim_loss(generator: UNetGenerator, depth_range_m: tuple[float, float], fp32: Runner, int8: Runner) -> float:
    """What serving ``int8`` instead of ``fp32`` (runners of ``generator``'s two graphs) costs:
    1 - the mean SSIM of int8's images against fp32's on the checkpoint's own kind of
    calibration contacts (:func:`contact_inputs`, JUDGING_CONTACTS of them, JUDGING_SEED)."""
    from perception.ssim import ssim_rgb  # noqa: PLC0415 - torch-heavy, only this check needs it

    inputs = contact_inputs(generator, depth_range_m, JUDGING_CONTACTS, JUDGING_SEED)

    def images(run: Runner) -> np.ndarray:
        return to_uint8_rgb(
            torch.from_numpy(np.concatenate([run(inputs[i : i + 16]) for i in range(0, len(inputs), 16)]))
        )

    return 1.0 - float(ssim_rgb(images(fp32), images(int8)).mean())


def int8_convolutions(graph: bytes, calibration: np.ndarray) -> bytes:
    """``graph`` with its convolutions in int8: ONNX Runtime's static post-training
    quantisation (QDQ; weights int8 per tensor, activations uint8 with the min/max ranges seen on
    ``calibration``, N x C x H x W network inputs). Only ``Conv``: the encoder. The decoder's
    transposed convolutions stay fp32, because ONNX Runtime has no faster int8 kernel for them
    and quantising them too lost 0.007 SSIM and ran slower than fp32 (dtx bench inference, the
    default model: encoder-only int8 1.1-1.2x fp32's regions/s at the same test-split SSIM)."""
    from onnxruntime import quantization  # noqa: PLC0415 - only this precision needs it

    class Batches(quantization.CalibrationDataReader):
        def __init__(self) -> None:
            self.batches = iter([{"depth": calibration[i : i + 16]} for i in range(0, len(calibration), 16)])

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.batches, None)

    with tempfile.TemporaryDirectory(prefix="dtx-int8") as tmp:
        fp32, prepared, int8 = Path(tmp) / "fp32.onnx", Path(tmp) / "prepared.onnx", Path(tmp) / "int8.onnx"
        fp32.write_bytes(graph)
        # Shapes inferred and BatchNorms folded first, as quantize_static asks.
        quantization.quant_pre_process(fp32, prepared)
        quantization.quantize_static(
            prepared,
            int8,
            Batches(),
            quant_format=quantization.QuantFormat.QDQ,
            op_types_to_quantize=["Conv"],
            activation_type=quantization.QuantType.QUInt8,
            weight_type=quantization.QuantType.QInt8,
        )
        return int8.read_bytes()


def network_runner(
    generator: UNetGenerator,
    depth_range_m: tuple[float, float],
    runtime: str,
    precision: str,
    threads: int,
    device: str,
) -> Runner:
    """N x C x H x W float32 -> N x 3 x H x W float32 in [-1, 1]: ``generator`` on ``runtime``
    (onnxrt | eager) in ``precision`` on ``device`` (cpu | cuda), as the inference node serves it."""
    if runtime == "eager":
        return eager_runner(UncheckedGenerator(generator).eval(), bf16=precision == "bf16", device=device)
    return onnx_runner(onnx_graph(generator, depth_range_m, precision), threads, device)


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
    """A copy in eval mode whose dropout still samples: several passes give the spread that the
    report's uncertainty sweep (report/sweeps/serving.py) sets against the learned uncertainty.
    The inference node no longer serves it (protocol v4): that spread was ~0 and uncorrelated
    with the error; models.uncertainty serves a calibrated one instead."""
    sampled = copy.deepcopy(generator).eval()
    for block in sampled.modules():
        for name, child in block.named_children():
            if isinstance(child, nn.Dropout):
                setattr(block, name, SampledDropout(child.p))
    return sampled
