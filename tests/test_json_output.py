"""Every JSON a ``dtx`` command prints is strict RFC 8259 JSON (msgs.strict_json): no NaN or
Infinity, an undefined figure is null beside its reason, and a reader in another language
(Node's ``JSON.parse``) takes it as it is.

Each command runs once on small inputs through ``dtx.cli.main`` and its output is parsed by a
parser that refuses NaN and Infinity (the three that need a whole collection session are
checked where tests/test_collection.py runs one); the list of commands is checked against the
command line itself, so a new ``--json`` command or benchmark must be added here."""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dtx.cli import build_parser, main
from msgs import strict_json

ROOT = Path(__file__).resolve().parent.parent
BALL_PRESSES = "assets/gelsight/ball_presses.npz"
NODE = shutil.which("node")


def refuse(constant: str) -> None:
    raise AssertionError(f"not strict JSON: {constant}")


def strict_loads(text: str) -> Any:
    return json.loads(text, parse_constant=refuse)


class Inputs:
    """Small inputs the commands read, made once for the module."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def bag(self) -> Path:
        from bus.bag import BagWriter
        from msgs import GripperState, Header
        from msgs.codec import decode, encode

        path = self.root / "small.mcap"
        if not path.exists():
            writer = BagWriter(path)
            for i in range(3):
                frames = encode("/gripper/state", GripperState(header=Header(stamp_ns=1_000 * (i + 1))), "test")
                writer.write(decode(frames), frames, log_time_ns=1_000 * (i + 1))
            writer.close()
        return path

    def checkpoint(self) -> Path:
        from benchmarks.serve import write_checkpoint

        path = self.root / "fresh.pt"
        return path if path.exists() else write_checkpoint(path, width=8)

    def tiny_training_config(self) -> Path:
        path = self.root / "tiny.yaml"
        path.write_text(
            "epochs: 1\nepochs_decay: 0\nbatch_size: 2\nndf: 8\nthreads: 1\n"
            "generator: {ngf: 8, prior: true, background: false}\n"
        )
        return path

    def presses(self) -> Path:
        from sim.gelsight_check import load_ball_presses

        path = self.root / "presses.npz"
        if not path.exists():
            presses = load_ball_presses(ROOT / BALL_PRESSES)
            np.savez(
                path,
                background=presses.background,
                frames=presses.frames[:3],
                touch_center=presses.centers_xy_px[:3],
                touch_radius=presses.radii_px[:3],
            )
        return path


# Command -> its arguments on small inputs (the JSON flag included).
COMMANDS: dict[str, Callable[[Inputs], list[str]]] = {
    "bag info": lambda i: ["bag", "info", str(i.bag()), "--json"],
    "bag play": lambda i: ["bag", "play", str(i.bag()), "--fast", "--wait", "0"],
    "bag record": lambda i: ["bag", "record", "-o", str(i.root / "recorded.mcap"), "--duration", "0.3"],
    # Its output on a dataset (a minute to predict here) is parsed as strictly where
    # tests/test_models_evaluate.py runs it.
    "evaluate": lambda i: ["evaluate", str(i.checkpoint()), "--real-presses", str(i.presses()), "--json"],
    "perception register-check": lambda i: [
        "perception",
        "register-check",
        "assets/ycb/GelatinBox.obj",
        "--trials",
        "1",
        "--json",
    ],
    "sim gelsight-check": lambda i: ["sim", "gelsight-check", str(i.presses()), "--json"],
    "bench arm": lambda i: ["bench", "arm", "--json", "--rate-seconds", "0.3", "--stop-trials", "2"],
    "bench arm_stress": lambda i: [
        "bench",
        "arm_stress",
        "--json",
        "--runs",
        "1",
        "--hogs",
        "0",
        "--stop-trials",
        "1",
    ],
    "bench bus": lambda i: [
        "bench",
        "bus",
        "--json",
        "--latency-messages",
        "20",
        "--throughput-mb",
        "1",
        "--transports",
        "ipc",
        "--repeats",
        "1",
    ],
    "bench hardware": lambda i: [
        "bench",
        "hardware",
        "--json",
        "--gripper-commands",
        "5",
        "--stop-samples",
        "2",
        "--completion-samples",
        "1",
    ],
    "bench inference": lambda i: [
        "bench",
        "inference",
        "--json",
        "--widths",
        "8",
        "--precisions",
        "fp32",
        "--runtimes",
        "eager",
        "--batch",
        "2",
        "--seconds",
        "0.05",
        "--threads",
        "1",
    ],
    # One part, the quickest: every part's rows go through the same printing.
    "bench perception": lambda i: ["bench", "perception", "--json", "--only", "binning"],
    "bench record": lambda i: ["bench", "record", "--json", "--duration", "0.5", "--out-dir", str(i.root)],
    "bench serve": lambda i: [
        "bench",
        "serve",
        "--json",
        "--width",
        "8",
        "--threads",
        "1",
        "--requests",
        "3",
        "--regions",
        "2",
        "--seconds",
        "0.2",
    ],
    "bench sim": lambda i: ["bench", "sim", "--json", "--frames", "2", "--skip-check"],
    "bench train": lambda i: [
        "bench",
        "train",
        "--json",
        "--synth",
        "1",
        "--pairs",
        "20",
        "--work",
        str(i.root / "bench_train"),
        "--config",
        str(i.tiny_training_config()),
        "--max-steps",
        "1",
    ],
}
# These need whole collection sessions or a fit (minutes here): tests/test_collection.py,
# tests/test_touch_calibration.py, tests/test_sim_gelsight_fit.py, tests/test_models_uncertainty.py
# and tests/test_models_sensor_floor.py (a trained checkpoint with its uncertainty), which run them
# anyway, parse each one's output as strictly.
IN_COLLECTION_TESTS = {
    "sim ceiling",
    "bench collect",
    "bench fuzz",
    "calibrate touches",
    "calibrate gelsight",
    "calibrate uncertainty",
    "fit-serving",
}
# Commands that print JSON whether asked or not.
ALWAYS_JSON = {"bag play", "bag record"}


def json_commands() -> set[str]:
    """Every command of the command line that takes --json, and every benchmark."""
    found: set[str] = set()

    def walk(parser: argparse.ArgumentParser, words: tuple[str, ...]) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, (*words, name))
            elif "--json" in action.option_strings:
                found.add(" ".join(words))
            elif words == ("bench",) and action.dest == "name":
                found.update(f"bench {name}" for name in action.choices)

    walk(build_parser([]), ())
    return found


def test_the_list_holds_every_command_that_prints_json() -> None:
    assert json_commands() | ALWAYS_JSON == set(COMMANDS) | IN_COLLECTION_TESTS


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Inputs:
    return Inputs(tmp_path_factory.mktemp("json_inputs"))


@pytest.fixture
def bus_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A bus of its own (ipc paths must stay short), and the signal handlers a command sets
    undone afterwards."""
    handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    with tempfile.TemporaryDirectory(prefix="dtxj") as directory:
        monkeypatch.setenv("DTX_BUS_DIR", directory)
        yield
    for signum, handler in handlers.items():
        signal.signal(signum, handler)


@pytest.mark.usefixtures("bus_dir")
@pytest.mark.parametrize("command", COMMANDS)
def test_every_json_output_is_strict(command: str, inputs: Inputs, capsys: pytest.CaptureFixture[str]) -> None:
    argv = COMMANDS[command](inputs)
    capsys.readouterr()
    assert main(argv) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    # A command that prints JSON prints nothing else on stdout.
    assert isinstance(strict_loads(out), (dict, list)), out


def undefined_ratio_output() -> str:
    """What dtx evaluate prints for a split whose truths are one frame, estimated exactly: the
    dissimilarity ratio is undefined (ssim_statistics says why)."""
    from models.evaluate import ssim_statistics

    frame = np.random.default_rng(0).integers(0, 256, (1, 32, 32, 3), dtype=np.uint8)
    frames = np.repeat(frame, 3, axis=0)
    return strict_json.dumps(ssim_statistics(frames, frames.copy(), baseline_draws=2), indent=2)


def test_an_undefined_figure_is_null_beside_its_reason() -> None:
    result = strict_loads(undefined_ratio_output())
    assert isinstance(result, dict)
    assert result["dissimilarity_ratio"] is None
    assert "no dissimilarity to compare with" in result["dissimilarity_ratio_undefined"]


def test_a_non_finite_figure_without_its_reason_fails_loudly() -> None:
    with pytest.raises(ValueError, match=r"\$\.rows\[1\]\.mb_per_s is nan with no '_undefined' reason"):
        strict_json.dumps({"rows": [{"mb_per_s": 1.0}, {"mb_per_s": float("nan")}]})
    with pytest.raises(ValueError, match=r"\$\.p99_ms is inf"):
        strict_json.dumps({"p99_ms": np.float64("inf")})
    assert strict_json.dumps({"ratio": [np.float32(0.5), float("-inf")], "ratio_undefined": "why"}) == (
        '{"ratio": [0.5, null], "ratio_undefined": "why"}'
    )


@pytest.mark.skipif(NODE is None, reason="node (Node.js) is not installed")
def test_the_node_client_reads_an_undefined_figure_with_json_parse() -> None:
    done = subprocess.run(
        [str(NODE), str(ROOT / "clients" / "node" / "undefined_figures.mjs")],
        input=undefined_ratio_output(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    (figure,) = json.loads(done.stdout)
    assert figure["path"] == "$.dissimilarity_ratio"
    assert "no dissimilarity to compare with" in figure["reason"]
