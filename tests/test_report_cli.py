"""``dtx report accuracy-time``: argument errors (nothing is measured here)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import pytest

from report.cli import CALIBRATED_HERE, VECTOR_FLAGS, _cached, add_commands, machine_description
from report.plan import FULL, QUICK, SWEEP_NAMES
from report.workspace import Workspace, training_config


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dtx")
    add_commands(parser.add_subparsers(dest="command"))
    return parser


def _error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        _parser().parse_args(argv)
    assert exit_info.value.code == 2
    return capsys.readouterr().err


def test_out_is_required(capsys: pytest.CaptureFixture[str]) -> None:
    assert "--out" in _error(["report", "accuracy-time", "--quick"], capsys)


def test_out_must_not_be_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    afile = tmp_path / "report.md"
    afile.write_text("")
    assert "not a directory" in _error(["report", "accuracy-time", "--out", str(afile)], capsys)


def test_unknown_sweep_and_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert "invalid choice" in _error(["report", "accuracy-time", "--out", str(tmp_path), "--only", "nope"], capsys)
    assert "unrecognized" in _error(["report", "accuracy-time", "--out", str(tmp_path), "--fast"], capsys)
    assert "invalid choice" in _error(["report", "accuracy-tim", "--out", str(tmp_path)], capsys)


def test_reuse_without_cache_fails_before_measuring(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = _parser().parse_args(["report", "accuracy-time", "--out", str(tmp_path / "new"), "--reuse", "--quick"])
    assert args.func(args) == 2
    assert "nothing cached" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_quick_plan_states_its_reductions() -> None:
    reductions = QUICK.reductions(FULL)
    assert any(r.startswith("samples: 120 (full: 578)") for r in reductions)
    assert FULL.reductions(FULL) == []
    assert len(set(SWEEP_NAMES)) == len(SWEEP_NAMES) >= 12


def test_every_named_sweep_exists() -> None:
    from report.sweeps import SWEEPS

    assert tuple(SWEEPS) == SWEEP_NAMES


def test_reuse_takes_a_cached_sweep_of_the_same_plan(tmp_path: Path) -> None:
    (tmp_path / "cache").mkdir()
    points = [
        {"sweep": "density", "setting": "1 pts/cm³", "time": 0.2, "accuracy": 0.8},
        {"sweep": "density", "setting": "80 pts/cm³", "time": 0.3, "accuracy": None},
    ]
    entry = {
        "plan": dataclasses.asdict(QUICK),
        "training_config": training_config().to_dict(),
        "session": CALIBRATED_HERE,
        "seconds": 5.0,
        "measured_at": "then",
        "points": points,
    }
    (tmp_path / "cache" / "density.json").write_text(json.dumps(entry))
    args = _parser().parse_args(
        ["report", "accuracy-time", "--out", str(tmp_path), "--quick", "--reuse", "--only", "density"]
    )
    assert args.func(args) == 0
    report = (tmp_path / "report.md").read_text()
    assert "density reused (5 s on then)" in report
    assert "measuring 0 of the 1 sweeps (the others cached by an earlier run)" in report
    assert "| 1 pts/cm³ | 0.8 | 0.2 |" in report and "**recommended**" in report
    assert not (tmp_path / "work").exists()  # nothing was measured
    assert "Measured on: not recorded (a sweep cached before machines were)." in report
    entry["machine"] = "2 cores, x86_64, Some CPU, avx512f"
    (tmp_path / "cache" / "density.json").write_text(json.dumps(entry))
    assert args.func(args) == 0
    assert "Measured on: 2 cores, x86_64, Some CPU, avx512f." in (tmp_path / "report.md").read_text()


@pytest.mark.parametrize(
    ("cpuinfo", "named"),
    [
        ("model name\t: Lab CPU\nflags\t\t: fpu sse avx2 avx512f avx512_vnni\n", ", Lab CPU, avx512f avx512_vnni"),
        ("model name\t: Old CPU\nflags\t: fpu sse avx2\n", ", Old CPU, none of " + " ".join(VECTOR_FLAGS)),
        ("", ", processor not named"),  # no /proc/cpuinfo: neither model nor flags claimed
    ],
)
def test_the_machine_is_named_with_the_vector_instructions_precisions_need(cpuinfo: str, named: str) -> None:
    described = machine_description(cpuinfo)
    assert described.startswith(f"{os.cpu_count()} cores, ") and described.endswith(named)


def test_a_cached_sweep_counts_only_for_the_plan_and_training_config_that_made_it(tmp_path: Path) -> None:
    config = training_config().to_dict()
    made_by = json.loads(json.dumps({"plan": dataclasses.asdict(QUICK), "training_config": config}))
    path = tmp_path / "density.json"
    path.write_text(json.dumps({**made_by, "seconds": 1.0, "points": []}))
    assert _cached(path, made_by) is not None
    assert _cached(path, {**made_by, "plan": json.loads(json.dumps(dataclasses.asdict(FULL)))}) is None
    assert _cached(path, {**made_by, "training_config": {**config, "lambda_l1": config["lambda_l1"] / 10}}) is None
    # A config field added since, at its default, is the same config; at another value it is not.
    older = {key: value for key, value in made_by["training_config"].items() if key != "pair_cache_mib"}
    path.write_text(json.dumps({**made_by, "training_config": older, "seconds": 1.0, "points": []}))
    assert _cached(path, made_by) is not None
    assert _cached(path, {**made_by, "training_config": {**config, "pair_cache_mib": 64.0}}) is None
    path.write_text(json.dumps({"plan": made_by["plan"], "seconds": 1.0, "points": []}))  # made before the key
    assert _cached(path, made_by) is None
    path.write_text("{not json")
    assert _cached(path, made_by) is None


def test_only_the_session_models_blur_their_prior_by_the_registration_error(tmp_path: Path) -> None:
    workspace = Workspace(tmp_path, QUICK, [tmp_path / "given"])  # given as it is: not calibrated here
    default = training_config()
    assert default.session_pose_sigma_mm > 0
    session = workspace.config(50, 16, registered=True)
    analytic = workspace.config(50, 16, registered=False)
    assert session.session_pose_sigma_mm == default.session_pose_sigma_mm
    assert analytic.session_pose_sigma_mm == 0.0  # analytic contacts: exact geometry
    assert dataclasses.replace(analytic, session_pose_sigma_mm=session.session_pose_sigma_mm) == session


def test_a_given_session_is_named_by_what_it_holds_never_by_its_path(tmp_path: Path) -> None:
    """The report and its cache are committed: they name a --session by its fingerprint, the same
    session copied elsewhere reuses the same cached sweeps, and a text a sweep wrote with a path of
    the machine in it (a refusal's reason) names it as the command line does."""
    from dataset.splits import session_fingerprint

    session = tmp_path / "somewhere" / "session"
    session.mkdir(parents=True)
    (session / "manifest.jsonl").write_text('{"sample_id": "a"}\n')
    (session / "dataset.json").write_text('{"scene": "scenes/ycb_three.yaml"}\n')
    out = tmp_path / "report"
    (out / "cache").mkdir(parents=True)
    copy = tmp_path / "elsewhere"
    copy.mkdir()
    made_by = {"plan": dataclasses.asdict(QUICK), "training_config": training_config().to_dict()}
    entry = {**made_by, "session": session_fingerprint(session), "seconds": 1.0, "measured_at": "then"}
    refusal = f"{copy.resolve()}: too few touches; {(out / 'work').resolve()} kept"
    points = [{"sweep": "density", "setting": "unfiltered", "time": 1.0, "accuracy": 0.8, "refused": refusal}]
    (out / "cache" / "density.json").write_text(json.dumps({**entry, "points": points}))
    for name in ("manifest.jsonl", "dataset.json"):
        (copy / name).write_bytes((session / name).read_bytes())
    args = _parser().parse_args(
        [
            "report",
            "accuracy-time",
            "--out",
            str(out),
            "--quick",
            "--reuse",
            "--only",
            "density",
            "--session",
            str(copy),
        ]
    )
    assert args.func(args) == 0
    written = (out / "report.md").read_text() + (out / "points.json").read_text()
    assert "density reused" in written and session_fingerprint(session) in written
    assert str(tmp_path) not in written and "elsewhere" not in written
    assert "SESSION: too few touches; DIR/work kept" in written
