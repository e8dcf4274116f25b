"""`dtx perception register-check` on the simulated scene, and the benchmark's binning figures."""

from __future__ import annotations

import argparse
import json

from benchmarks import perception as benchmark
from perception.cli import add_commands

REPORT_KEYS = {"success_rate", "add_s_mm_median", "add_s_mm_p90", "add_mm_median", "time_ms_median"}


def parse(argv):
    parser = argparse.ArgumentParser(prog="dtx")
    add_commands(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def test_register_check_prints_one_json_object_keyed_by_mesh_stem(capsys):
    args = parse(
        ["perception", "register-check", "assets/ycb/GelatinBox.obj", "--trials", "2", "--seed", "4", "--json"]
    )
    assert args.func(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert list(report) == ["GelatinBox"]
    row = report["GelatinBox"]
    assert REPORT_KEYS <= set(row) and row["trials"] == 2
    assert row["success_rate"] == 1.0
    # The scene's camera calibration offset (4-6 mm per camera) bounds what registration can reach.
    assert 0.5 < row["add_s_mm_median"] < 10.0


def test_register_check_refuses_a_missing_mesh(capsys):
    args = parse(["perception", "register-check", "no/such/mesh.obj", "--trials", "1"])
    assert args.func(args) == 2
    assert "mesh not found: no/such/mesh.obj" in capsys.readouterr().err


def test_register_check_refuses_zero_trials(capsys):
    args = parse(["perception", "register-check", "assets/ycb/GelatinBox.obj", "--trials", "0"])
    assert args.func(args) == 2
    assert "trials must be >= 1" in capsys.readouterr().err


def test_benchmark_binning_methods_agree_with_ours():
    parser = argparse.ArgumentParser()
    benchmark.add_arguments(parser)
    rows = benchmark.run(parser.parse_args(["--only", "binning"]))
    compared = [row for row in rows if row["same_as_ours"] is not None]
    assert {row["points"] for row in compared} == {10_000, 100_000, 1_000_000}
    assert all(row["same_as_ours"] for row in compared)
    assert all(row["mpoints_per_s"] > 0 for row in rows)
