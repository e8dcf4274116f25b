"""``dtx bench train``: what ``dtx train`` holds in memory and how long its epoch takes, on one
session and on several of the same size, side by side in one run (issue 54's target: ten
demo-size sessions within 1 GiB of one).

Sessions: ``--session DIR ...`` (a lab's own: the first alone, then all of them), or by default
``--synth N`` sessions of ``--pairs`` pairs each, made in ``--work`` by ``dtx dataset library``'s
writer (the scene's own GelSight pressed by analytic contacts, seeds 0..N-1: sessions of one
scene, which a model with a physics prior can mix) and kept there for the next run.

Each row is ``dtx train`` as a user runs it, in its own process, with ``--config`` (default
configs/quick.yaml) cut to one epoch without decay: the process's peak resident memory
(``wait4``'s ru_maxrss), its CPU and wall time (the uncertainty's fit at the end included),
``epoch_s``: the epoch's wall time, validation included (val_log.csv; with ``--max-steps``, the
part of it trained), and ``ms_per_pair``: that over the pairs it trained. A ``--max-steps`` past
what fills the cache (``pair_cache_mib`` / ~100 KB a pair, 4 a step) shows the peak of the whole.
``pair_cache_mib`` (models.pairs) bounds what training keeps; ``--pair-cache-mib`` overrides it.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from dataset.contact_library import write_contact_library
from dataset.reader import DatasetReader
from models.checkpoint import TrainConfig
from models.sessions import open_sessions, session_records

REPO = Path(__file__).resolve().parent.parent


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", nargs="+", default=[], help="sessions to train on (default: synthesised)")
    parser.add_argument("--synth", type=int, default=10, help="sessions to synthesise without --session")
    parser.add_argument("--pairs", type=int, default=2400, help="pairs a synthesised session (the demo's 2,400)")
    parser.add_argument("--scene", default=str(REPO / "scenes" / "ycb_three.yaml"), help="scene of the synthesised")
    parser.add_argument("--work", default="out/bench_train", help="where synthesised sessions are kept")
    parser.add_argument("--config", default=str(REPO / "configs" / "quick.yaml"), help="training config")
    parser.add_argument("--pair-cache-mib", type=float, default=None, help="override the config's pair cache")
    parser.add_argument("--max-steps", type=int, default=0, help="stop each run after this many steps (0: the epoch)")


def synthesised_sessions(work: Path, count: int, pairs: int, scene: str) -> list[Path]:
    """``count`` sessions of ``pairs`` pairs in ``work``: made where missing, resumed where cut
    short, and a complete one taken as it is (whatever code made it)."""
    roots = []
    for seed in range(count):
        root = work / f"session{seed:02d}"
        print(f"session {seed + 1}/{count}: {root}", file=sys.stderr, flush=True)
        if not ((root / "dataset.json").exists() and len(DatasetReader(root).records) == pairs):
            write_contact_library(root, pairs, seed=seed, scene=scene, progress=True)
        roots.append(root)
    return roots


def one_epoch_config(path: str, out: Path, cache_mib: float | None, max_steps: int) -> Path:
    """``path``'s training config cut to one epoch without decay, written to ``out``."""
    config = TrainConfig.load(path).to_dict() | {"epochs": 1, "epochs_decay": 0, "max_steps": max_steps}
    if cache_mib is not None:
        config["pair_cache_mib"] = cache_mib
    TrainConfig.from_dict(config)  # refused here, not in the child, if the override is bad
    out.write_text(yaml.safe_dump(config))
    return out


def train_run(sessions: list[Path], config: Path, out: Path, batch_size: int) -> dict[str, Any]:
    """``dtx train SESSIONS --config CONFIG --out OUT`` in its own process, measured."""
    command = [
        sys.executable,
        "-m",
        "dtx.cli",
        "train",
        *map(str, sessions),
        "--config",
        str(config),
        "--out",
        str(out),
    ]
    log = out.with_suffix(".log")
    started = time.monotonic()
    with open(log, "w") as stream:
        process = subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode:
        tail = log.read_text().splitlines()[-15:]
        raise SystemExit(
            f"dtx train on {len(sessions)} sessions failed (exit {process.returncode}):\n" + "\n".join(tail)
        )
    with open(out / "val_log.csv") as f:
        epoch = list(csv.DictReader(f))[-1]
    opened = open_sessions(sessions)
    train_pairs = sum(len(records) for records in session_records(opened, "train"))
    return {
        "sessions": len(sessions),
        "pairs": sum(len(s.reader.records) for s in opened),
        "train_pairs": train_pairs,
        "steps": int(epoch["step"]),
        "pairs_trained": min(int(epoch["step"]) * batch_size, train_pairs),
        "peak_mib": round(usage.ru_maxrss / 1024, 1),
        "epoch_s": float(epoch["wall_s"]),
        "ms_per_pair": round(1e3 * float(epoch["wall_s"]) / min(int(epoch["step"]) * batch_size, train_pairs), 2),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
        "wall_s": round(time.monotonic() - started, 1),
    }


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="dtxbenchtrain") as tmp:
        config = one_epoch_config(args.config, Path(tmp) / "config.yaml", args.pair_cache_mib, args.max_steps)
        trained = TrainConfig.load(config)
        sessions = [Path(s) for s in args.session] or synthesised_sessions(
            Path(args.work), args.synth, args.pairs, args.scene
        )
        rows = [
            train_run(chosen, config, Path(tmp) / f"run{len(chosen)}", trained.batch_size)
            for chosen in (sessions[:1], sessions)
        ]
    for row in rows:
        row |= {
            "peak_over_one_mib": round(row["peak_mib"] - rows[0]["peak_mib"], 1),
            "pair_cache_mib": trained.pair_cache_mib,
        }
    return rows
