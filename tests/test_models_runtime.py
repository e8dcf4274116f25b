"""The ONNX graphs the inference node serves: fp32, and int8 with only the encoder quantised."""

from __future__ import annotations

from pathlib import Path

import onnx
import pytest
import torch

from benchmarks.serve import write_checkpoint
from models.checkpoint import load_generator
from models.networks import GeneratorConfig, UNetGenerator
from models.runtime import onnx_graph

DEPTH_RANGE_M = (-0.0015, 0.0025)


def _generator() -> UNetGenerator:
    torch.manual_seed(0)
    return UNetGenerator(GeneratorConfig(ngf=8)).eval()


def _inputs_of(graph: onnx.ModelProto, op_type: str) -> list[list[str]]:
    """For each node of ``op_type``: what feeds each of its inputs (the producing node's type,
    or 'weights' for a stored tensor, or 'graph input')."""
    producers = {output: node.op_type for node in graph.graph.node for output in node.output}
    stored = {tensor.name for tensor in graph.graph.initializer}
    return [
        [producers.get(name, "weights" if name in stored else "graph input") for name in node.input]
        for node in graph.graph.node
        if node.op_type == op_type
    ]


def test_int8_quantises_every_convolution_of_the_encoder_and_leaves_the_decoder_fp32() -> None:
    generator = _generator()
    graph = onnx.load_from_string(onnx_graph(generator, DEPTH_RANGE_M, "int8"))
    convolutions = _inputs_of(graph, "Conv")
    assert len(convolutions) == generator.config.num_downs
    # Activation, weights and bias each come through a DequantizeLinear: int8 kernels.
    assert all(feeds == ["DequantizeLinear"] * 3 for feeds in convolutions)
    transposed = _inputs_of(graph, "ConvTranspose")
    assert len(transposed) == generator.config.num_downs
    assert all("DequantizeLinear" not in feeds and "weights" in feeds for feeds in transposed)
    fp32 = onnx.load_from_string(onnx_graph(generator, DEPTH_RANGE_M, "fp32"))
    assert not _inputs_of(fp32, "QuantizeLinear") and not _inputs_of(fp32, "DequantizeLinear")


def test_a_checkpoint_is_quantised_the_same_way_every_time(tmp_path: Path) -> None:
    """Calibrated on the same contacts, the physics prior's channels included."""
    generator, depth_range_m = load_generator(write_checkpoint(tmp_path / "prior.pt", width=8, prior=True))
    assert onnx_graph(generator, depth_range_m, "int8") == onnx_graph(generator, depth_range_m, "int8")


def test_a_graph_in_another_precision_is_refused() -> None:
    with pytest.raises(ValueError, match="fp32 or int8, not 'bf16'"):
        onnx_graph(_generator(), DEPTH_RANGE_M, "bf16")
