"""``dtx bench serve`` runs the real node in its own process and reports its figures."""
from __future__ import annotations

import argparse

from benchmarks.serve import add_arguments, run


def test_serve_benchmark_reports_latency_and_throughput_of_the_named_weights() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    result = run(parser.parse_args(["--width", "8", "--threads", "1", "--requests", "5", "--regions", "4",
                                    "--seconds", "0.3"]))
    assert result["weights"] == "fresh generator, width 8 (seeded, untrained)"
    assert result["model"].startswith("fresh.pt (ngf 8, onnxrt fp32)")
    assert 0 < result["p50_ms"] <= result["p99_ms"]
    assert result["regions_per_s"] > 0 and result["server_cpu_ms_per_region"] > 0
