"""Shared fixtures: every test gets its own bus directory, so tests never hear each other."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from bus.context import OPEN_BUSES
from bus.registry import Registry


@pytest.fixture(autouse=True)
def close_leftover_buses() -> Iterator[None]:
    """A test that fails half-way leaves its buses open; close them now rather than let the
    garbage collector meet a ZeroMQ context in the middle of a later test."""
    yield
    for bus in list(OPEN_BUSES):
        bus.close()


@pytest.fixture
def bus_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    # ipc socket paths must stay short, so not pytest's long tmp_path.
    path = Path(tempfile.mkdtemp(prefix="dtxt"))
    monkeypatch.setenv("DTX_BUS_DIR", str(path))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture
def registry(bus_dir: Path) -> Registry:
    return Registry(bus_dir)
