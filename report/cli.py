"""``dtx report accuracy-time --out DIR [--quick] [--reuse] [--session DIR [DIR ...]]``: what
accuracy costs in time, across the pipeline, in DIR/report.md with a plot per sweep and
DIR/points.json.

Each sweep's points are cached in DIR/cache/<sweep>.json with the plan and the training
config (configs/quick.yaml) that made them; --reuse takes a cached sweep made by the same plan
and config instead of measuring it again. Datasets and trained models live in DIR/work/<plan>
and are reused by later runs either way (a model only if trained with the current config).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from dataset.splits import session_fingerprint
from report.plan import FULL, QUICK, SWEEP_NAMES, Plan
from report.write import dumps, loads, write_report

if TYPE_CHECKING:  # torch and Open3D load only when a sweep runs
    from report.workspace import Workspace


# What a sweep's cache names as its session when none is given: the report's own, collected and
# cut again with its touch calibration (sweeps cached before it was calibrated are not reused).
CALIBRATED_HERE = "collected here, cut again with its touch calibration"


def _out_dir(value: str) -> Path:
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{value} exists and is not a directory")
    return path


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """The ``report`` group and its ``accuracy-time`` command."""
    group = subparsers.add_parser("report", help="reports measured across the pipeline")
    commands = group.add_subparsers(dest="report_command", required=True, metavar="REPORT")
    p = commands.add_parser(
        "accuracy-time",
        help="what accuracy costs in time: sweeps, Pareto fronts, defaults",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, type=_out_dir, metavar="DIR", help="where report.md, plots, points go")
    p.add_argument("--quick", action="store_true", help="every table at lower counts (<= 30 min on 2 cores)")
    p.add_argument(
        "--reuse", action="store_true", help="take sweeps cached in DIR/cache by the same plan and training config"
    )
    p.add_argument(
        "--only",
        action="append",
        choices=SWEEP_NAMES,
        metavar="SWEEP",
        help=f"measure only these sweeps (repeatable): {', '.join(SWEEP_NAMES)}",
    )
    p.add_argument(
        "--session",
        type=_session_dir,
        nargs="+",
        default=[],
        metavar="DIR",
        help="measure the session sweeps on these collected simulated sessions, e.g. make demo's "
        "out/demo/session_calibrated, instead of collecting the plan's grasps: their models train on all "
        "of them and are scored on each one's test split and the whole; the pipeline, registration and "
        "calibration tables measure the first",
    )
    p.add_argument(
        "--session-pose-sigma-mm",
        type=float,
        nargs="+",
        default=[],
        metavar="MM",
        help="the given sessions' pose errors, as dtx train takes them (one for all or one a session; e.g. 0.1 "
        "for sessions cut again with a touch calibration, as make demo trains); default: the training config's",
    )
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run_accuracy_time)


def _short(sessions: str) -> str:
    """A workspace's name for the sessions' fingerprints joined by "+": one session's own
    fingerprint (as before sessions were several), a digest of several."""
    return sessions if "+" not in sessions else hashlib.sha256(sessions.encode()).hexdigest()[:16]


def _session_dir(value: str) -> Path:
    path = Path(value)
    missing = [name for name in ("manifest.jsonl", "dataset.json") if not (path / name).is_file()]
    if missing:
        raise argparse.ArgumentTypeError(f"{value} is not a collected session (no {' or '.join(missing)})")
    return path


def _without_machine_paths(points: list[dict], places: dict[str, str]) -> list[dict]:
    """``points`` with each of ``places`` (a path on this machine: the report's directory, a given
    session) named by what it is in every text they hold, such as a refusal's reason: the report
    and its cache are committed, and read on other machines."""

    longest_first = sorted(places.items(), key=lambda place: -len(place[0]))  # /s10 before /s1

    def named(value: object) -> object:
        if not isinstance(value, str):
            return value
        for path, name in longest_first:
            value = value.replace(path, name)
        return value

    return [{key: named(value) for key, value in point.items()} for point in points]


# CPU flags (/proc/cpuinfo) that decide what the reduced precisions cost: the inference table's
# bf16 and int8 rows are fast only where the processor has them.
VECTOR_FLAGS = ("avx512f", "avx512_bf16", "amx_bf16", "avx512_vnni", "avx_vnni")


def machine_description(cpuinfo: str | None = None) -> str:
    """This machine as a sweep's cache records it: cores, architecture, the processor's model name
    and which of VECTOR_FLAGS it has (``cpuinfo``: /proc/cpuinfo's text, read where None; a
    machine without it is described without them)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    flags = set(fields.get("flags", "").split())
    has = [flag for flag in VECTOR_FLAGS if flag in flags]
    vector = (", " + " ".join(has)) if has else (", none of " + " ".join(VECTOR_FLAGS) if flags else "")
    return f"{os.cpu_count()} cores, {platform.machine()}, {fields.get('model name') or 'processor not named'}{vector}"


def _cached(path: Path, made_by: dict) -> dict | None:
    """The sweep cached at ``path`` if ``made_by`` made it: the same plan and session, and the same
    training config as read (a field added since, at its default, is the same config)."""
    from models.checkpoint import TrainConfig
    from models.errors import ModelConfigError

    try:
        entry = json.loads(path.read_text())
        same_config = TrainConfig.from_dict(entry["training_config"]) == TrainConfig.from_dict(
            made_by["training_config"]
        )
    except (OSError, ValueError, KeyError, TypeError, ModelConfigError):
        return None
    same = all(entry.get(key) == value for key, value in made_by.items() if key != "training_config")
    return entry if same and same_config else None


def _header(
    plan: Plan,
    elapsed_s: float,
    entries: list[dict],
    timings: list[str],
    sessions: list[Path],
    workspace: Workspace,
) -> list[str]:
    """The report's opening lines: the mode, the machine, the times, the machines the sweeps
    (``entries``, as cached) were measured on, and what was not measured as the full plan measures
    it."""
    measured_s = sum(entry["seconds"] for entry in entries)
    machines = {entry.get("machine", "not recorded (a sweep cached before machines were)") for entry in entries}
    reused = sum(" reused (" in timing for timing in timings)
    measured = len(timings) - reused
    header = [
        f"Mode: **{plan.name}**, seed {plan.seed}; this run took **{elapsed_s / 60:.1f} min** of wall time on "
        f"{os.cpu_count()} cores ({platform.machine()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})"
        + (
            f", measuring {measured} of the {len(timings)} sweeps (the others cached by an earlier run)"
            if reused
            else ""
        )
        + f"; measuring every sweep shown took **{measured_s / 60:.1f} min**.",
        "",
        "Sweep times: " + "; ".join(timings) + ".",
        "",
        "Measured on: " + "; ".join(sorted(machines)) + ".",
    ]
    header += ["", _sessions_line(sessions, workspace)]
    if workspace.reused_models:
        header += [
            "",
            f"Trained models reused from an earlier run in this report's work/{workspace.root.name} (their "
            f"training is not in the times above; its CPU seconds per epoch are in the tables): "
            f"{', '.join(sorted(workspace.reused_models))}.",
        ]
    if plan.name != FULL.name:
        header += [
            "",
            "Reduced from the full report: " + "; ".join(plan.reductions(FULL)) + ". These figures check "
            "the pipeline end to end; with so few contacts and epochs, SSIM differences within a few standard "
            "errors are noise, so take the defaults from the full report.",
        ]
    return header


def _sessions_line(sessions: list[Path], workspace: Workspace) -> str:
    """The header's line on the sessions the session sweeps ran on: the report's own, or those given."""
    if not sessions:
        return (
            "The session sweeps ran on the report's own session with its depth-maps cut again by its touch "
            "calibration, as make demo trains (as collected where its touches cannot calibrate: the pipeline "
            "table says why); the pipeline, registration and calibration tables measure its collection."
        )
    if len(sessions) == 1:
        return (
            f"The session sweeps ran on a collected session given with --session (fingerprint "
            f"{session_fingerprint(sessions[0])}), not on one of the plan's size{_told(workspace)}."
        )
    return (
        f"The session sweeps ran on {len(sessions)} collected sessions given with --session (fingerprints "
        f"{', '.join(session_fingerprint(s) for s in sessions)}){_told(workspace)}: their models trained on all "
        "of them, scored on the test splits together, each session's contact SSIM beside in that order; the "
        "pipeline, registration and calibration tables measure the first session's collection."
    )


def _told(workspace: Workspace) -> str:
    """What the header says of the pose errors the given sessions' models were told."""
    sigmas = workspace.pose_sigmas_mm
    return (
        f", told pose errors of {' / '.join(f'{s:g}' for s in sigmas)} mm (--session-pose-sigma-mm)" if sigmas else ""
    )


def _sessions_refused(args: argparse.Namespace, fingerprints: list[str]) -> str:
    """Why the given sessions and their pose errors cannot be measured ("" where they can)."""
    from models.errors import ModelConfigError
    from report.workspace import training_config

    if len(set(fingerprints)) < len(fingerprints):
        return "--session: the same session given twice"
    sigmas = args.session_pose_sigma_mm
    if sigmas and not args.session:
        return "--session-pose-sigma-mm is for given sessions (the report calibrates its own)"
    try:
        if sigmas:
            training_config().with_session_pose_sigmas(sigmas, len(args.session))
    except ModelConfigError as err:
        return str(err)
    return ""


def run_accuracy_time(args: argparse.Namespace) -> int:
    plan = dataclasses.replace(QUICK if args.quick else FULL, seed=args.seed)
    cache = args.out / "cache"
    if args.reuse and not cache.is_dir():
        print(f"dtx report: error: --reuse: nothing cached in {cache}", file=sys.stderr)
        return 2
    from report.sweeps import SWEEPS
    from report.workspace import Workspace, training_config

    fingerprints = [session_fingerprint(session) for session in args.session]
    refusal = _sessions_refused(args, fingerprints)
    if refusal:
        print(f"dtx report: error: {refusal}", file=sys.stderr)
        return 2
    sigmas = args.session_pose_sigma_mm
    # Given sessions get a workspace of their own: their re-cut datasets and trained models are theirs.
    session = "+".join(fingerprints) or CALIBRATED_HERE
    work = f"{plan.name}-{_short(session)}" if args.session else plan.name
    workspace = Workspace(args.out / "work" / work, plan, args.session, sigmas)
    made_by = {"plan": dataclasses.asdict(plan), "training_config": training_config().to_dict(), "session": session}
    if sigmas:  # only then: sweeps cached before the option still count for the config's pose error
        made_by["session_pose_sigmas_mm"] = sigmas
    made_by = json.loads(json.dumps(made_by))
    cache.mkdir(parents=True, exist_ok=True)
    # Named as the command line names them: --out DIR, --session SESSION (SESSION1, SESSION2 ... for several).
    names = ["SESSION"] if len(args.session) == 1 else [f"SESSION{i + 1}" for i in range(len(args.session))]
    places = {**{str(s.resolve()): name for s, name in zip(args.session, names)}, str(args.out.resolve()): "DIR"}
    started = time.monotonic()
    points, timings, entries = [], [], []
    for name, sweep in SWEEPS.items():
        if args.only and name not in args.only:
            continue
        entry = _cached(cache / f"{name}.json", made_by) if args.reuse else None
        if entry is None:
            print(f"report: measuring {name} ...", file=sys.stderr, flush=True)
            sweep_started = time.monotonic()
            measured = sweep(workspace)
            entry = {
                **made_by,
                "seconds": round(time.monotonic() - sweep_started, 1),
                "measured_at": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                "machine": machine_description(),
                "points": json.loads(dumps(_without_machine_paths(measured, places))),
            }
            (cache / f"{name}.json").write_text(json.dumps(entry, indent=1) + "\n")
            timings.append(f"{name} {entry['seconds']:.0f} s")
        else:
            timings.append(f"{name} reused ({entry['seconds']:.0f} s on {entry['measured_at']})")
        points += loads(json.dumps(_without_machine_paths(entry["points"], places)))
        entries.append(entry)
    elapsed = time.monotonic() - started
    header = _header(plan, elapsed, entries, timings, args.session, workspace)
    path = write_report(args.out, points, header)
    print(f"report: {path} ({elapsed:.0f} s)")
    return 0
