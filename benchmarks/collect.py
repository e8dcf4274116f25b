"""The simulated collection session, timed, and the kill -9 test.

Runs ``dtx launch launch/collect_sim.yaml`` as an operator would and reports wall time,
grasps per minute and the median time per stage of a grasp (from the collector's
session.json). With ``--kill NODE ...`` it runs one more session per node, kills that node
with SIGKILL a third of the way through (the launcher respawns it), and checks the dataset
that comes out: complete, exactly the requested size, sound by ``dtx dataset check``. With
``--recorder-kills N`` it records one more session and kills the recorder at N seeded random
moments of it: per kill, the seconds of messages its file lost before the kill (the kill time
less the last message the file holds) and the gap until the respawned recorder's first message,
whether any file is empty, and whether the dataset is still complete.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bus.bag import iter_envelopes
from bus.bag_format import BagError
from bus.registry import Registry
from dataset.check import check_dataset

NODES = [
    "collector",
    "patch_extractor",
    "arm",
    "gripper",
    "gelsight_left",
    "gelsight_right",
    "camera_left",
    "camera_right",
    "recorder",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grasps", type=int, default=289)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--kill",
        nargs="*",
        default=[],
        choices=NODES + ["all"],
        help="nodes to kill -9 mid-session, one session each ('all': every node)",
    )
    parser.add_argument("--kill-grasps", type=int, default=30, help="session size for the kill -9 runs")
    parser.add_argument("--record", action="store_true", help="record the session bag too")
    parser.add_argument(
        "--recorder-kills",
        type=int,
        default=0,
        metavar="N",
        help="one more recorded session of --grasps grasps, its recorder killed at N random moments",
    )


def collect_sim_command(
    out: Path, grasps: int, seed: int, record: bool, resume: bool = False, scene: str = ""
) -> list[str]:
    """``dtx launch launch/collect_sim.yaml`` with the session's arguments, as an operator types it
    (``scene``: the launch file's own unless given)."""
    command = [sys.executable, "-m", "dtx.cli", "launch", "launch/collect_sim.yaml"]
    command += [f"out:={out}", f"grasps:={grasps}", f"seed:={seed}", f"record:={'true' if record else 'false'}"]
    return command + (["resume:=true"] if resume else []) + ([f"scene:={scene}"] if scene else [])


def launch_collection(
    out: Path, grasps: int, seed: int, record: bool, bus_dir: str, capture: bool = True, scene: str = ""
) -> subprocess.Popen[str]:
    """``dtx launch launch/collect_sim.yaml`` writing to ``out``, as an operator runs it, on the
    private bus ``bus_dir``; its output (every node's log lines) on a pipe, or discarded without
    ``capture``."""
    env = {**os.environ, "DTX_BUS_DIR": bus_dir, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        collect_sim_command(out, grasps, seed, record, scene=scene),
        env=env,
        stdout=subprocess.PIPE if capture else subprocess.DEVNULL,
        stderr=subprocess.STDOUT if capture else subprocess.DEVNULL,
        text=True,
    )


def run_session(out: Path, grasps: int, seed: int, record: bool, kill: str = "", scene: str = "") -> dict:
    with tempfile.TemporaryDirectory(prefix="dtxc") as bus_dir:
        started = time.monotonic()
        launcher = launch_collection(out, grasps, seed, record, bus_dir, scene=scene)
        killed = None
        if kill:
            killed = _kill_when_a_third_is_done(Registry(Path(bus_dir)), out, grasps, kill, launcher)
        output, _ = launcher.communicate(timeout=1800)
        wall_s = time.monotonic() - started
    report = check_dataset(out)
    session = json.loads((out / "session.json").read_text()) if (out / "session.json").exists() else {}
    result = {
        "grasps": grasps,
        "exit_code": launcher.returncode,
        "wall_s": round(wall_s, 1),
        "pairs": report.samples,
        "dataset_check_ok": report.ok,
        "session": session,
    }
    if kill:
        result.update(killed=kill, killed_pid=killed, respawned=f"[launch] {kill} exited with -9; respawning" in output)
    collector_log = [line for line in output.splitlines() if line.startswith("[collector]")]
    result["collector_last_line"] = collector_log[-1] if collector_log else ""
    result["collector_warnings"] = [line for line in collector_log if " WARNING " in line]
    if launcher.returncode != 0 or not report.ok:
        result["collector_log"] = collector_log[-15:]
    return result


def _kill_when_a_third_is_done(
    registry: Registry, out: Path, grasps: int, node: str, launcher: subprocess.Popen[str]
) -> int | None:
    manifest = out / "manifest.jsonl"
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and launcher.poll() is None:
        written = len(manifest.read_text().splitlines()) if manifest.exists() else 0
        if written >= 2 * grasps // 3:
            for status in registry.node_statuses():
                if status["node"] == node and status["alive"]:
                    os.kill(status["pid"], signal.SIGKILL)
                    return int(status["pid"])
        time.sleep(0.05)
    return None


def _bag_files(out: Path) -> list[Path]:
    """The session's bag files in the order the recorders wrote them: session.mcap, session.1.mcap, ..."""
    numbered = sorted(out.glob("session.*.mcap"), key=lambda p: int(p.suffixes[0][1:]))
    return [out / "session.mcap", *numbered] if (out / "session.mcap").exists() else numbered


def _log_times_ns(path: Path) -> list[int]:
    try:
        return [log_time for log_time, _ in iter_envelopes(path)]
    except BagError:
        return []


def run_recorder_kills(out: Path, grasps: int, seed: int, kills: int, last_share: float = 0.9) -> dict:
    """A recorded session whose recorder is killed at ``kills`` moments drawn (seeded) between
    10 % and ``last_share`` of the grasps; each kill waits until the respawned recorder has a
    message on disk, so every kill cuts a file that was being written. A kill near the end may
    leave the session no time to respawn the recorder (``respawn_delay_s`` and its start)."""
    moments = sorted(random.Random(seed).sample(range(grasps // 10, int(last_share * grasps)), kills))
    with tempfile.TemporaryDirectory(prefix="dtxk") as bus_dir:
        launcher = launch_collection(out, grasps, seed, True, bus_dir, capture=False)
        killed_ns = _kill_recorder_at(moments, launcher, Registry(Path(bus_dir)), out)
        launcher.wait(timeout=1800)
    files = _bag_files(out)
    per_kill = _kill_losses(files, killed_ns)
    report = check_dataset(out)
    losses = [k["lost_before_kill_s"] for k in per_kill if k["lost_before_kill_s"] is not None]
    return {
        "grasps": grasps,
        "kills": len(killed_ns),
        "exit_code": launcher.returncode,
        "dataset_check_ok": report.ok,
        "pairs": report.samples,
        "files": len(files),
        "empty_files": sum(p.stat().st_size == 0 for p in files),
        "lost_before_kill_s_max": max(losses, default=None),
        "lost_before_kill_s_median": sorted(losses)[len(losses) // 2] if losses else None,
        "per_kill": per_kill,
    }


def _kill_recorder_at(moments: list[int], launcher: subprocess.Popen[str], registry: Registry, out: Path) -> list[int]:
    """SIGKILL the recorder once each of ``moments`` grasps is written and the newest bag file
    holds a message; the kill times (ns since the epoch)."""
    killed_ns: list[int] = []
    manifest = out / "manifest.jsonl"
    for moment in moments:
        while launcher.poll() is None:
            written = len(manifest.read_text().splitlines()) // 2 if manifest.exists() else 0
            files = _bag_files(out)
            # The newest file must hold a message: the respawned recorder is writing.
            if written >= moment and len(files) == len(killed_ns) + 1 and _log_times_ns(files[-1]):
                pids = [s["pid"] for s in registry.node_statuses() if s["node"] == "recorder" and s["alive"]]
                if pids:
                    killed_ns.append(time.time_ns())
                    os.kill(pids[0], signal.SIGKILL)
                    break
            time.sleep(0.02)
    return killed_ns


def _kill_losses(files: list[Path], killed_ns: list[int]) -> list[dict]:
    """Per kill: the file it cut (name, bytes), the seconds of messages lost before the kill and
    the gap until the respawned recorder's first message (None where a file is missing or empty)."""
    per_kill = []
    for index, kill_ns in enumerate(killed_ns):
        cut = _log_times_ns(files[index]) if index < len(files) else []
        after = _log_times_ns(files[index + 1]) if index + 1 < len(files) else []
        per_kill.append(
            {
                "file": files[index].name if index < len(files) else None,
                "bytes": files[index].stat().st_size if index < len(files) else 0,
                "lost_before_kill_s": round((kill_ns - max(cut)) / 1e9, 3) if cut else None,
                "gap_until_respawned_s": round((min(after) - kill_ns) / 1e9, 3) if after else None,
            }
        )
    return per_kill


def run(args: argparse.Namespace) -> dict:
    kills = NODES if "all" in args.kill else args.kill
    with tempfile.TemporaryDirectory(prefix="dtxsession") as tmp:
        main = run_session(Path(tmp) / "main", args.grasps, args.seed, args.record)
        grasps_per_min = (
            main["session"].get("stats", {}).get("grasps_done", 0) / max(main["session"].get("wall_s", 1e9), 1e-9) * 60
        )
        results = {
            "session": main,
            "grasps_per_min_collector": round(grasps_per_min, 1),
            "grasps_per_min_wall": round(args.grasps / main["wall_s"] * 60, 1),
            "kill_tests": [],
        }
        for node in kills:
            outcome = run_session(
                Path(tmp) / f"kill_{node}", args.kill_grasps, args.seed, record=node == "recorder", kill=node
            )
            outcome["complete"] = (
                outcome["dataset_check_ok"]
                and outcome["exit_code"] == 0
                and len((Path(tmp) / f"kill_{node}" / "manifest.jsonl").read_text().splitlines())
                == 2 * args.kill_grasps
            )
            results["kill_tests"].append(outcome)
        if args.recorder_kills:
            results["recorder_kills"] = run_recorder_kills(
                Path(tmp) / "recorder_kills", args.grasps, args.seed, args.recorder_kills
            )
    return results
