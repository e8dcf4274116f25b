"""`dtx bench sim` runs end to end and reports every figure (a short run)."""

from __future__ import annotations

import argparse
import json

from benchmarks import sim as bench


def test_bench_sim_short_run() -> None:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    rows = bench.run(parser.parse_args(["--frames", "2", "--skip-check"]))
    json.dumps(rows)
    figures = {r["figure"] for r in rows}
    assert "depth frame 512x424, no effects" in figures
    assert "depth frame 512x424, ycb_three default effects" in figures
    for name in bench.DEPTH_EFFECTS:
        assert f"depth frame 512x424, {name} alone" in figures
    assert any(f.startswith("gelsight frame 120x160") for f in figures)
    assert any(f.startswith("gelsight frame 480x640") for f in figures)
    assert all(r["value"] > 0 for r in rows)
