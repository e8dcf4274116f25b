"""The progress of long steps: a bar on a terminal, plain lines at a steady pace anywhere else.

The pacing runs on an injected clock, so nothing here depends on how fast the machine is."""

from __future__ import annotations

import io
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from dtx.demo import COMMAND_WIDTH, shown_command
from msgs.progress import MAX_LINE, TERMINAL_ENV, Progress, duration, track


class FakeClock:
    """A clock that moves only when told."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def no_launcher(monkeypatch: pytest.MonkeyPatch) -> None:
    """As a process started by hand: its own stream says whether it is a terminal."""
    monkeypatch.delenv(TERMINAL_ENV, raising=False)


def run(total: int, seconds_per_update: float, updates: int, **kwargs: object) -> list[str]:
    """The lines a progress of ``total`` prints for ``updates`` updates, the clock moving
    ``seconds_per_update`` before each, and its close."""
    stream, clock = io.StringIO(), FakeClock()
    with Progress("work", total, "items", stream=stream, clock=clock, **kwargs) as progress:  # type: ignore[arg-type]
        for _ in range(updates):
            clock.now += seconds_per_update
            progress.update()
    return stream.getvalue().splitlines()


def test_a_fast_step_prints_a_line_at_each_tenth_and_one_when_done() -> None:
    lines = run(total=100, seconds_per_update=0.01, updates=100)
    assert [line.split()[1] for line in lines] == [f"{done}/100" for done in range(10, 101, 10)]
    assert lines[0] == "work: 10/100 items (10 %), 100.0 items/s, ETA 1 s"
    assert lines[-1] == "work: 100/100 items (100 %), 100.0 items/s, done in 1 s"


def test_a_slow_step_prints_a_line_every_ten_seconds_between_the_tenths() -> None:
    # 3 s per item out of 1000: no tenth is reached, so a line each time 10 s have passed
    lines = run(total=1000, seconds_per_update=3.0, updates=20)
    assert [line.split()[1] for line in lines] == ["4/1000", "8/1000", "12/1000", "16/1000", "20/1000"]
    assert lines[0] == "work: 4/1000 items (0 %), 20.0 items/min, ETA 49 min 48 s"


def test_a_step_stopped_early_says_where_it_got() -> None:
    lines = run(total=100, seconds_per_update=0.5, updates=15)
    assert lines == [
        "work: 10/100 items (10 %), 2.0 items/s, ETA 45 s",
        "work: 15/100 items (15 %), 2.0 items/s, ETA 42 s",
    ]


def test_a_resumed_step_counts_its_rate_from_where_it_resumed() -> None:
    lines = run(total=100, seconds_per_update=1.0, updates=20, initial=80)
    assert lines == [
        "work: 90/100 items (90 %), 1.0 items/s, ETA 10 s",
        "work: 100/100 items (100 %), 1.0 items/s, done in 20 s",
    ]


def test_a_step_with_nothing_to_do_still_says_so() -> None:
    assert run(total=50, seconds_per_update=1.0, updates=0, initial=50) == [
        "work: 50/50 items (100 %), 0.0 items/min, done in 0 s"
    ]


def test_the_note_follows_the_figures_and_no_line_passes_the_limit() -> None:
    stream, clock = io.StringIO(), FakeClock()
    progress = Progress("train", 10, "steps", stream=stream, clock=clock)
    progress.note("g_l1 0.0412")
    clock.now += 2.0
    progress.update()
    progress.note("x" * 1000)
    clock.now += 2.0
    progress.update()
    first, second = stream.getvalue().splitlines()
    assert first == "train: 1/10 steps (10 %), 30.0 steps/min, ETA 18 s | g_l1 0.0412"
    assert len(second) == MAX_LINE and second.endswith("...")


def test_disabled_progress_writes_nothing() -> None:
    assert run(total=10, seconds_per_update=20.0, updates=10, enabled=False) == []


def test_a_terminal_gets_the_bar_and_a_relayed_terminal_a_line_per_update(monkeypatch: pytest.MonkeyPatch) -> None:
    terminal, clock = Tty(), FakeClock()
    with Progress("collect", 3, "grasps", stream=terminal, clock=clock) as progress:
        progress.update(3)
    assert "\r" in terminal.getvalue()  # tqdm's bar, redrawn in place
    # A node under the launcher writes into a pipe; the launcher says its output is a terminal.
    monkeypatch.setenv(TERMINAL_ENV, "1")
    assert len(run(total=100, seconds_per_update=0.01, updates=7, bar_on_terminal=False)) == 7
    # ... or that it is not, whatever the node's own stream is.
    monkeypatch.setenv(TERMINAL_ENV, "0")
    piped = Tty()
    with Progress("collect", 3, "grasps", stream=piped, clock=clock) as progress:
        progress.update(3)
    assert piped.getvalue() == "collect: 3/3 grasps (100 %), 0.0 grasps/min, done in 0 s\n"


def test_track_yields_every_item_and_reports_on_stderr(capsys: pytest.CaptureFixture[str]) -> None:
    assert list(track(range(25), "depth-maps", "samples")) == list(range(25))
    lines = capsys.readouterr().err.splitlines()
    assert {"3/25", "5/25", "8/25", "10/25", "13/25", "15/25", "18/25", "20/25", "23/25", "25/25"} <= {
        line.split()[1] for line in lines
    }
    assert lines[-1].startswith("depth-maps: 25/25 samples (100 %)")


@pytest.mark.parametrize(
    ("seconds", "text"), [(0.4, "0 s"), (42.0, "42 s"), (293.0, "4 min 53 s"), (3725.0, "1 h 02 min")]
)
def test_durations_read_as_a_person_says_them(seconds: float, text: str) -> None:
    assert duration(seconds) == text


def test_bad_counts_are_refused() -> None:
    with pytest.raises(ValueError, match="work: progress needs 0 <= initial <= total, got 5 of 3"):
        Progress("work", 3, "items", initial=5)


def test_a_long_step_into_a_file_writes_plain_short_lines(tmp_path: Path) -> None:
    """``dtx dataset library`` as ``make demo`` runs it, its output into a pipe: no carriage
    return, no line over the limit, and lines that say how far it got."""
    result = subprocess.run(
        [sys.executable, "-m", "dtx.cli", "dataset", "library", str(tmp_path / "library"), "--samples", "20"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    output = result.stdout + result.stderr
    assert "\r" not in output
    assert max(len(line) for line in output.splitlines()) <= MAX_LINE
    progress = [line for line in output.splitlines() if line.startswith("contact library: ")]
    assert {f"{done}/20" for done in range(2, 21, 2)} <= {line.split()[2] for line in progress}
    assert progress[-1].startswith("contact library: 20/20 pairs (100 %)") and "done in" in progress[-1]


def test_the_demo_shows_a_long_command_wrapped_as_a_shell_continues_it() -> None:
    figures = ["--figures", "out/demo/figures", "--real-presses", "assets/gelsight/ball_presses.npz"]
    densities = ["--density", *[str(d) for d in (1, 10, 20, 40, 80, 1000, 10000)]]
    command = [
        "evaluate",
        "out/demo/train/checkpoint.pt",
        "out/demo/session",
        "--json",
        *figures,
        *densities,
        "x" * 150,
    ]
    text = shown_command(command)
    lines = text.splitlines()
    assert len(lines) >= 3 and all(line.endswith(" \\") for line in lines[:-1])
    assert all(len(line) <= COMMAND_WIDTH for line in lines if "x" * 150 not in line)
    assert shlex.split(text.replace("\\\n", " ")) == ["$", "dtx", *command]


def test_a_demo_begun_by_other_code_is_refused_before_any_step_and_left_as_it_is(tmp_path: Path) -> None:
    """``make demo`` again after an update: the calibration and library of the code before would
    be kept unseen or refused halfway, so the demo says so before it runs anything."""
    import dataclasses
    import json

    from dataset.records import DatasetInfo, code_version
    from dtx.demo import begun_by_other_code

    session = tmp_path / "session"
    session.mkdir()
    assert begun_by_other_code(tmp_path) is None  # nothing begun yet
    info = dataclasses.replace(DatasetInfo(), code_version=code_version())
    (session / "dataset.json").write_text(json.dumps(info.to_json()))
    assert begun_by_other_code(tmp_path) is None  # this code's own run resumes
    other = dataclasses.replace(info, code_version="dtx 0.1.0 git 000000000000")
    (session / "dataset.json").write_text(json.dumps(other.to_json()))
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    result = subprocess.run(
        [sys.executable, "-m", "dtx.cli", "demo", "--out", str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 1 and "begun by dtx 0.1.0 git 000000000000" in result.stderr
    assert f"remove {tmp_path}" in result.stderr and "== " not in result.stdout  # no step ran
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
