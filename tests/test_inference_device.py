"""Where the inference node computes (``device``: cpu | cuda | auto) and which precision it
serves when asked for int8 (int8 only where it holds against fp32). On a machine without CUDA
(CI) a node asked for cuda must refuse to start with the code ``cuda_unavailable`` and say
why; on one with a GPU it must serve the generator's estimates from it."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_inference_node import serving

from benchmarks.serve import depth_maps, write_checkpoint
from bus.inference_client import TactileClient
from bus.node import EXIT_DO_NOT_RESPAWN
from bus.pubsub import Bus
from bus.registry import Registry
from models.checkpoint import load_generator
from models.data import network_input, to_uint8_rgb
from models.runtime import (
    CudaUnavailable,
    cuda_missing,
    int8_ssim_loss,
    network_runner,
    onnx_graph,
    onnx_runner,
    resolve_device,
)
from nodes.inference import InferenceNode

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Untrained, width 8, no prior. What its int8 graph loses against fp32 depends on the CPU's
    int8 kernels: 0.33 SSIM on an AMD Zen 3 (no VNNI), 0.0004 on an Intel Xeon with AVX-512 VNNI."""
    return write_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", width=8)


@pytest.fixture(scope="module")
def int8_loss(checkpoint: Path) -> float:
    """The SSIM this machine's int8 graph of ``checkpoint`` loses, measured as the node measures it."""
    generator, depth_range_m = load_generator(checkpoint)
    fp32, int8 = (network_runner(generator, depth_range_m, "onnxrt", p, 2, "cpu") for p in ("fp32", "int8"))
    loss = int8_ssim_loss(generator, depth_range_m, fp32, int8)
    assert loss > 0  # quantising an untrained network's weights changes its images somewhere
    return loss


def estimate(registry: Registry, maps: np.ndarray) -> tuple[np.ndarray, str]:
    with contextlib.closing(Bus("planner", registry)) as bus, TactileClient(bus, timeout_s=30.0) as client:
        images, _ = client.estimate(maps)
        return images, client.last_reply.model if client.last_reply else ""


def graph_images(checkpoint: Path, precision: str, maps: np.ndarray) -> np.ndarray:
    generator, depth_range_m = load_generator(checkpoint)
    run = onnx_runner(onnx_graph(generator, depth_range_m, precision), threads=1)
    x = network_input(maps, depth_range_m, generator.config, generator.prior).numpy()
    return to_uint8_rgb(torch.from_numpy(run(x)))


@pytest.mark.parametrize("runtime", ["onnxrt", "eager"])
def test_devices_resolve_to_the_cpu_or_cuda_as_this_machine_has_them(runtime: str) -> None:
    assert resolve_device("cpu", runtime, "fp32") == "cpu"
    assert resolve_device("auto", runtime, "fp32") == ("cpu" if cuda_missing(runtime) else "cuda")
    assert resolve_device("auto", "onnxrt", "int8") == "cpu"  # int8's kernels are the CPU provider's
    with pytest.raises(ValueError, match="int8 runs on the CPU only"):
        resolve_device("cuda", "onnxrt", "int8")
    with pytest.raises(ValueError, match="device must be one of cpu, cuda, auto, got 'gpu'"):
        resolve_device("gpu", runtime, "fp32")


@pytest.mark.skipif(not cuda_missing("onnxrt"), reason="this machine's ONNX Runtime has CUDA")
def test_a_node_asked_for_cuda_without_it_refuses_to_start_with_a_code_and_the_reason(
    checkpoint: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    registry = Registry(tmp_path / "bus")
    with caplog.at_level(logging.ERROR), pytest.raises(CudaUnavailable, match="device 'cuda' was asked for, but"):
        InferenceNode("gpu_worker", {"checkpoint": str(checkpoint), "device": "cuda"}, registry=registry)
    assert CudaUnavailable.code == "cuda_unavailable"
    [status] = registry.node_statuses()
    assert status["node"] == "gpu_worker" and status["status"] == "cuda_unavailable"
    assert "no CUDA provider" in status["text"]
    assert any(r.getMessage().startswith("cuda_unavailable: device 'cuda' was asked for") for r in caplog.records)


@pytest.mark.skipif(not cuda_missing("onnxrt"), reason="this machine's ONNX Runtime has CUDA")
def test_the_launched_process_exits_without_a_respawn_and_leaves_the_code(checkpoint: Path, tmp_path: Path) -> None:
    bus_dir = tmp_path / "bus"
    params = json.dumps({"checkpoint": str(checkpoint), "device": "cuda"})
    done = subprocess.run(
        [sys.executable, "-m", "nodes.inference", "--name", "gpu_worker", "--params", params],
        cwd=REPO,
        env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == EXIT_DO_NOT_RESPAWN
    assert "cuda_unavailable: device 'cuda' was asked for, but" in done.stderr
    [status] = Registry(bus_dir).node_statuses()
    assert status["status"] == "cuda_unavailable" and not status["alive"]


@pytest.mark.parametrize("runtime", ["onnxrt", "eager"])
def test_auto_serves_on_what_the_machine_has_and_says_so(registry: Registry, checkpoint: Path, runtime: str) -> None:
    maps = depth_maps(2, seed=5)
    with serving(registry, checkpoint, runtime=runtime, device="auto"):
        images, model = estimate(registry, maps)
    device = "cpu" if cuda_missing(runtime) else "cuda"
    assert f"{runtime} fp32, {device}" in model
    assert np.abs(images.astype(int) - graph_images(checkpoint, "fp32", maps)).max() <= 1


@pytest.mark.parametrize("runtime", ["onnxrt", "eager"])
def test_on_cuda_the_estimates_are_the_generators(registry: Registry, checkpoint: Path, runtime: str) -> None:
    if cuda_missing(runtime):  # a GPU host may have PyTorch's CUDA and an ONNX Runtime without its provider
        pytest.skip(cuda_missing(runtime))
    maps = depth_maps(3, seed=6)
    with serving(registry, checkpoint, runtime=runtime, device="cuda"):
        images, model = estimate(registry, maps)
    assert f"{runtime} fp32, cuda" in model
    # A GPU's convolutions sum in another order: a level here and there.
    assert np.abs(images.astype(int) - graph_images(checkpoint, "fp32", maps)).max() <= 2


def test_int8_that_loses_more_than_allowed_is_served_in_fp32_with_a_log_line_saying_why(
    registry: Registry, checkpoint: Path, int8_loss: float, caplog: pytest.LogCaptureFixture
) -> None:
    maps = depth_maps(3, seed=7)
    allowed = round(0.5 * int8_loss, 8)
    with (
        caplog.at_level(logging.WARNING),
        serving(registry, checkpoint, precision="int8", int8_max_ssim_loss=allowed),
    ):
        images, model = estimate(registry, maps)
    assert "onnxrt fp32, cpu" in model
    np.testing.assert_array_equal(images, graph_images(checkpoint, "fp32", maps))
    [refusal] = [r.getMessage() for r in caplog.records if "int8 refused" in r.getMessage()]
    assert f"it loses {int8_loss:.4f} SSIM" in refusal
    assert f"more than int8_max_ssim_loss {allowed:g}; serving fp32" in refusal


def test_int8_within_the_allowed_loss_is_served_in_int8_and_its_loss_logged(
    registry: Registry, checkpoint: Path, int8_loss: float, caplog: pytest.LogCaptureFixture
) -> None:
    maps = depth_maps(3, seed=8)
    allowed = round(2 * int8_loss, 8)
    with (
        caplog.at_level(logging.INFO),
        serving(registry, checkpoint, precision="int8", int8_max_ssim_loss=allowed),
    ):
        images, model = estimate(registry, maps)
    assert "onnxrt int8, cpu" in model
    np.testing.assert_array_equal(images, graph_images(checkpoint, "int8", maps))
    [held] = [r.getMessage() for r in caplog.records if r.getMessage().startswith("int8 holds: ")]
    assert held == f"int8 holds: {int8_loss:.5f} SSIM lost against fp32 (at most {allowed:g})"


def test_the_ssim_loss_of_a_graph_against_itself_is_none(checkpoint: Path) -> None:
    generator, depth_range_m = load_generator(checkpoint)
    fp32 = onnx_runner(onnx_graph(generator, depth_range_m, "fp32"), threads=1)
    assert int8_ssim_loss(generator, depth_range_m, fp32, fp32) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("loss", [-0.1, 1.5])
def test_an_allowed_int8_loss_outside_0_to_1_is_refused(checkpoint: Path, tmp_path: Path, loss: float) -> None:
    params = {"checkpoint": str(checkpoint), "precision": "int8", "int8_max_ssim_loss": loss}
    with pytest.raises(ValueError, match=r"int8_max_ssim_loss in \[0, 1\]"):
        InferenceNode("refused", params, registry=Registry(tmp_path / "bus"))
