"""The suite's own deadline (pyproject's pytest-timeout settings): a test past its deadline
fails, and the tests after it still run, so one hung device call cannot end a CI run."""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

HUNG_THEN_FINE = """
import threading
import time

import pytest


@pytest.mark.timeout(1)
def test_hangs_waiting_on_a_device() -> None:
    threading.Event().wait(60)


@pytest.mark.timeout(1)
def test_hangs_sleeping() -> None:
    time.sleep(60)


def test_after_the_hung_ones() -> None:
    assert True
"""


def test_a_hung_test_fails_and_the_run_goes_on(tmp_path: Path) -> None:
    (tmp_path / "test_hung.py").write_text(HUNG_THEN_FINE)
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-c",
            str(ROOT / "pyproject.toml"),
            "--rootdir",
            str(tmp_path),
            "--junitxml",
            str(tmp_path / "report.xml"),
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "2 failed, 1 passed" in run.stdout, run.stdout + run.stderr
    # The report, not the terminal: how many times a message is printed depends on its width.
    failures = {
        case.get("name"): failure.get("message", "")
        for case in ET.parse(tmp_path / "report.xml").iter("testcase")
        for failure in case.iter("failure")
    }
    assert sorted(failures) == ["test_hangs_sleeping", "test_hangs_waiting_on_a_device"]
    assert all("Timeout (>1.0s) from pytest-timeout" in m for m in failures.values()), failures
