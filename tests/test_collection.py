"""The collection session end to end on the simulated scene: Algorithm 1 through every node,
crash safety under kill -9, a clear stop on an unwritable output, and replay from a bag."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from benchmarks.collect import run_session
from dataset.check import check_dataset
from dataset.format import DatasetReader

SMALL_BAG = Path(__file__).parent / "data" / "session_small.mcap"


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
@pytest.mark.parametrize("node", ["collector", "gripper"])
def test_a_killed_node_is_respawned_and_the_dataset_is_exact(tmp_path: Path, node: str) -> None:
    result = run_session(tmp_path / "session", grasps=6, seed=1, record=False, kill=node)
    assert result["exit_code"] == 0, result.get("collector_log")
    assert result["killed_pid"] is not None and result["respawned"]
    reader = DatasetReader(tmp_path / "session")
    ids = sorted(record.sample_id for record in reader.records)
    assert ids == sorted(f"g{g:05d}_{f}" for g in range(6) for f in ("left", "right"))
    assert check_dataset(tmp_path / "session").ok


def test_an_unwritable_output_stops_the_session_with_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("a file where the dataset should go")
    result = run_session(blocker / "session", grasps=2, seed=0, record=False)
    assert result["exit_code"] != 0
    assert any("cannot create the output directory" in line for line in result["collector_log"])
    assert blocker.read_text() == "a file where the dataset should go"


def replay(bag: Path, out: Path) -> subprocess.CompletedProcess[str]:
    with tempfile.TemporaryDirectory(prefix="dtxr") as bus_dir:
        return subprocess.run([sys.executable, "-m", "dtx.cli", "launch", "launch/replay.yaml", f"bag:={bag}",
                               f"out:={out}"], capture_output=True, text=True, timeout=300,
                              env={**os.environ, "DTX_BUS_DIR": bus_dir})


def test_replaying_the_shipped_bag_twice_gives_identical_datasets(tmp_path: Path) -> None:
    first, second = replay(SMALL_BAG, tmp_path / "a"), replay(SMALL_BAG, tmp_path / "b")
    assert first.returncode == 0, first.stdout[-2000:]
    assert second.returncode == 0, second.stdout[-2000:]
    report = check_dataset(tmp_path / "a")
    assert report.ok and report.samples == 8
    assert tree_digest(tmp_path / "a") == tree_digest(tmp_path / "b")
