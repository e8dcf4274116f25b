"""The arm's stop under load: ``dtx bench arm`` run many times, quiet and beside CPU hogs, side
by side in one run. Each run is its own process with a deadline; one past it is a hang (it is
killed, and the run goes on). Per load: hangs, failed runs, stops lost (a move that reached
its target after its stop), stops that needed an escalation, and the percentiles of the time
from ``stop()`` to the controller receiving stopJ and to the arm verified at rest, over every
stop of every run (pooled). Targets (issue 55): 0 hangs and 0 lost stops at every load."""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from typing import Any

import numpy as np

from benchmarks._load import cpu_hogs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=int, default=100, help="runs of `dtx bench arm` per load")
    parser.add_argument("--hogs", default="0,2", help="CPU-bound processes beside the runs, one load per number")
    parser.add_argument("--stop-trials", type=int, default=5, help="stops per run")
    parser.add_argument("--rate-seconds", type=float, default=0.3, help="state-rate count per run (s)")
    parser.add_argument("--run-deadline-s", type=float, default=120.0, help="a run longer than this is a hang")


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    if args.runs < 1 or args.stop_trials < 1:
        raise SystemExit("--runs and --stop-trials must be at least 1")
    loads = [int(hogs) for hogs in str(args.hogs).split(",")]
    if any(hogs < 0 for hogs in loads):
        raise SystemExit(f"--hogs takes counts of processes, got {args.hogs!r}")
    rows = []
    for hogs in loads:
        with cpu_hogs(hogs):
            runs = [_one_run(args) for _ in range(args.runs)]
        rows.append(_summary(hogs, runs))
    return rows


def _one_run(args: argparse.Namespace) -> dict[str, Any]:
    """One `dtx bench arm --json` process: its figures, or how it ended ("hang", "failed")."""
    command = [
        sys.executable,
        "-X",
        "faulthandler",  # a hung run's threads are dumped on SIGABRT
        "-m",
        "dtx.cli",
        "bench",
        "arm",
        "--json",
        "--rate-seconds",
        str(args.rate_seconds),
        "--stop-trials",
        str(args.stop_trials),
        "--each-stop",
    ]
    started = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = process.communicate(timeout=args.run_deadline_s)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)
        stdout, stderr = process.communicate()
        return {"outcome": "hang", "where": _innermost_frames(stderr), "seconds": time.monotonic() - started}
    if process.returncode != 0:
        return {"outcome": "failed", "error": stderr.strip().splitlines()[-1:], "seconds": time.monotonic() - started}
    return {"outcome": "ok", "rows": json.loads(stdout), "seconds": time.monotonic() - started}


def _innermost_frames(faulthandler_dump: str) -> list[str]:
    """The line each thread of a faulthandler dump was waiting on."""
    frames, expect_frame = [], False
    for line in faulthandler_dump.splitlines():
        if line.startswith(("Thread 0x", "Current thread 0x")):
            expect_frame = True
        elif expect_frame and line.strip().startswith("File "):
            frames.append(line.strip())
            expect_frame = False
    return frames


def _summary(hogs: int, runs: list[dict[str, Any]]) -> dict[str, Any]:
    finished = [run for run in runs if run["outcome"] == "ok"]

    def figures(name: str) -> list[dict[str, Any]]:
        return [row for run in finished for row in run["rows"] if row["figure"] == name]

    def stop_count(prefix: str) -> int:
        return sum(int(row["value"]) for run in finished for row in run["rows"] if row["figure"].startswith(prefix))

    escalated = stop_count("stops ending with error code") - stop_count("stops ending with error code none")
    received = [value for row in figures("stop() to controller receiving stopJ") for value in row["each"]]
    at_rest = [value for row in figures("stop() to the arm verified at rest") for value in row["each"]]
    return {
        "hogs": hogs,
        "runs": len(runs),
        "hangs": sum(run["outcome"] == "hang" for run in runs),
        "failed": sum(run["outcome"] == "failed" for run in runs),
        "stops": len(at_rest),
        "stops_lost": stop_count("stops lost"),
        "stops_escalated": escalated,
        "stopj_received_p50_ms": _percentile(received, 50),
        "stopj_received_p99_ms": _percentile(received, 99),
        "at_rest_p50_ms": _percentile(at_rest, 50),
        "at_rest_p99_ms": _percentile(at_rest, 99),
        "at_rest_max_ms": max(at_rest, default=None),
        "run_seconds_p50": float(np.median([run["seconds"] for run in runs])),
        "moves_ended_before_their_stop": stop_count("moves that ended before their stop"),
        "errors": sorted({line for run in runs if run["outcome"] == "failed" for line in run["error"]}),
        "hung_at": sorted({frame for run in runs if run["outcome"] == "hang" for frame in run["where"]}),
    }


def _percentile(values_ms: list[float], q: float) -> float | None:
    return float(np.percentile(values_ms, q)) if values_ms else None
