"""The inference benchmark produces the table the issue asks for."""
from __future__ import annotations

import argparse

from benchmarks.inference import add_arguments, run


def test_benchmark_rows_have_the_required_fields_and_fp32_eager_is_the_reference() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--widths", "8", "--precisions", "fp32", "int8", "--runtimes", "eager", "onnxrt",
                              "--batch", "4", "--seconds", "0.05", "--threads", "1"])
    rows = run(args)
    assert [(r["precision"], r["runtime"]) for r in rows] == [("fp32", "eager"), ("fp32", "onnxrt"),
                                                              ("int8", "onnxrt")]
    for row in rows:
        assert set(row) == {"width", "precision", "runtime", "ssim", "regions_per_s", "p50_ms"}
        assert row["width"] == 8 and row["regions_per_s"] > 0 and row["p50_ms"] > 0
    assert rows[0]["ssim"] == 1.0 and rows[1]["ssim"] > 0.99  # ONNX Runtime computes the same function
