"""Launch files (YAML, close to ROS 2's YAML launch) and the process supervisor.

    launch:
      - arg: {name: out, default: out/session}
      - include: {file: sensors.yaml}
      - node:
          name: gripper
          module: nodes.gripper
          params: {backend: simulated, port: $(var port)}
          remaps: {/gripper/state: /left_gripper/state}
          respawn: true
          required: false

Crossing machines: ``transport: tcp`` with ``curve_secret_key``/``curve_authorized_keys``,
``endpoints: {/inference/estimate: "tcp://0.0.0.0:7000"}`` on the serving machine, and
``peers: {/inference/estimate: {address: "tcp://robot-pc:7000", server_key_file: keys/server.key}}``
on the calling one.

Every node runs as its own process; its output is prefixed with its name. A node marked
``respawn`` is restarted ``respawn_delay_s`` after it dies, each on its own clock (nodes that
die together come back together), when it exits non-zero, but not 2 (a node says with 2 that
restarting cannot help)); when a ``required`` node ends otherwise, everything stops. A node with ``if: false`` (e.g. ``if: $(var foxglove)``) is
left out. Every
child gets PR_SET_PDEATHSIG so none outlives the launcher, even one killed with -9, and starts
through ``bus.start``, so a stop that comes while it is still starting ends it quietly.
"""

from __future__ import annotations

import ctypes
import dataclasses
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

import yaml

from bus.node import EXIT_DO_NOT_RESPAWN
from bus.registry import Registry
from bus.start import hold_stops
from msgs.progress import TERMINAL_ENV, on_terminal

NODE_KEYS = {
    "name",
    "module",
    "params",
    "remaps",
    "respawn",
    "respawn_delay_s",
    "required",
    "if",
    "transport",
    "bind_host",
    "curve_secret_key",
    "curve_authorized_keys",
    "endpoints",
    "peers",
}
ENTRY_KEYS = {"arg", "include", "node"}
_VAR = re.compile(r"\$\(var ([A-Za-z_][A-Za-z0-9_]*)\)")


class LaunchError(ValueError):
    """A launch file that cannot be run; the message names the file and line."""


@dataclasses.dataclass
class NodeSpec:
    name: str
    module: str
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    remaps: dict[str, str] = dataclasses.field(default_factory=dict)
    respawn: bool = False
    respawn_delay_s: float = 1.0
    required: bool = False
    transport: str = "ipc"
    bind_host: str = "127.0.0.1"
    curve_secret_key: str = ""
    curve_authorized_keys: str = ""
    endpoints: dict[str, str] = dataclasses.field(default_factory=dict)
    peers: dict[str, dict[str, str]] = dataclasses.field(default_factory=dict)

    def command(self) -> list[str]:
        command = [
            sys.executable,
            "-m",
            "bus.start",  # a stop during start-up ends the node quietly (see there)
            self.module,
            "--name",
            self.name,
            "--params",
            json.dumps(self.params),
            "--transport",
            self.transport,
            "--bind-host",
            self.bind_host,
        ]
        for source, target in self.remaps.items():
            command += ["--remap", f"{source}:={target}"]
        if self.curve_secret_key:
            command += [
                "--curve-secret-key",
                self.curve_secret_key,
                "--curve-authorized-keys",
                self.curve_authorized_keys,
            ]
        if self.endpoints:
            command += ["--endpoints", json.dumps(self.endpoints)]
        if self.peers:
            command += ["--peers", json.dumps(self.peers)]
        return command


@dataclasses.dataclass
class LaunchDescription:
    nodes: list[NodeSpec]
    args: dict[str, str]


def parse_launch_args(items: list[str]) -> dict[str, str]:
    """``key:=value`` pairs from the command line."""
    args = {}
    for item in items:
        if ":=" not in item:
            raise LaunchError(f"launch argument {item!r} must look like name:=value")
        key, value = item.split(":=", 1)
        args[key] = value
    return args


def load_launch(path: str | Path, args: dict[str, str] | None = None) -> LaunchDescription:
    """Read a launch file (and its includes), substitute ``$(var NAME)``, check every node."""
    given = dict(args or {})
    description = LaunchDescription(nodes=[], args={})
    _load_into(Path(path), given, description, stack=())
    unused = sorted(set(given) - set(description.args))
    if unused:
        raise LaunchError(f"{path}: unknown launch argument(s) {unused}; declared: {sorted(description.args)}")
    names = [n.name for n in description.nodes]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise LaunchError(f"{path}: node name(s) used twice: {duplicates}")
    return description


def _where(path: Path, node: yaml.Node) -> str:
    return f"{path}:{node.start_mark.line + 1}"


def _load_into(path: Path, given: dict[str, str], out: LaunchDescription, stack: tuple[Path, ...]) -> None:
    path = path.resolve()
    if path in stack:
        raise LaunchError(f"{path}: included from itself ({' -> '.join(map(str, stack))})")
    try:
        root = yaml.compose(path.read_text())
    except OSError as exc:
        raise LaunchError(f"launch file {path} cannot be read: {exc}") from exc
    except yaml.YAMLError as exc:
        raise LaunchError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(root, yaml.MappingNode) or [k.value for k, _ in root.value] != ["launch"]:
        raise LaunchError(f"{path}:1: a launch file is a mapping with the single key 'launch'")
    entries = root.value[0][1]
    if not isinstance(entries, yaml.SequenceNode):
        raise LaunchError(f"{_where(path, entries)}: 'launch' must be a list of entries")
    for entry in entries.value:
        if not isinstance(entry, yaml.MappingNode) or len(entry.value) != 1:
            raise LaunchError(f"{_where(path, entry)}: each entry is one of {sorted(ENTRY_KEYS)}")
        key_node, body = entry.value[0]
        kind = key_node.value
        if kind not in ENTRY_KEYS:
            raise LaunchError(f"{_where(path, key_node)}: unknown entry {kind!r}; allowed: {sorted(ENTRY_KEYS)}")
        fields = _mapping(path, body)
        values = {k: _substitute(path, v, out.args) for k, v in fields.items()}
        if kind == "arg":
            _check_keys(path, body, fields, {"name", "default", "description"}, required={"name"})
            name = str(values["name"])
            if name in given:
                out.args[name] = given[name]
            elif "default" in values:
                out.args[name] = str(values["default"])
            else:
                raise LaunchError(f"{_where(path, body)}: argument {name!r} has no default; pass {name}:=VALUE")
        elif kind == "include":
            _check_keys(path, body, fields, {"file"}, required={"file"})
            _load_into(path.parent / str(values["file"]), given, out, (*stack, path))
        else:
            _check_keys(path, body, fields, NODE_KEYS, required={"name", "module"})
            enabled = values.pop("if", True)
            if not isinstance(enabled, bool):
                raise LaunchError(f"{_where(path, body)}: 'if' must be true or false, got {enabled!r}")
            if not enabled:
                continue
            spec = NodeSpec(**values)
            if importlib.util.find_spec(spec.module) is None:
                raise LaunchError(f"{_where(path, body)}: node {spec.name!r}: module {spec.module!r} not found")
            out.nodes.append(spec)


def _mapping(path: Path, node: yaml.Node) -> dict[str, yaml.Node]:
    if not isinstance(node, yaml.MappingNode):
        raise LaunchError(f"{_where(path, node)}: expected a mapping")
    return {k.value: v for k, v in node.value}


def _check_keys(
    path: Path, body: yaml.Node, fields: dict[str, yaml.Node], allowed: set[str], required: set[str]
) -> None:
    for key_node, _ in body.value:  # type: ignore[union-attr]
        if key_node.value not in allowed:
            raise LaunchError(f"{_where(path, key_node)}: unknown key {key_node.value!r}; allowed: {sorted(allowed)}")
    missing = sorted(required - set(fields))
    if missing:
        raise LaunchError(f"{_where(path, body)}: missing key(s) {missing}")


def _substitute(path: Path, node: yaml.Node, args: dict[str, str]) -> Any:
    """Python value of a YAML node with ``$(var NAME)`` replaced; an unquoted whole-value
    substitution is re-read as YAML so that ``grasps: $(var grasps)`` stays an integer."""
    if isinstance(node, yaml.MappingNode):
        return {k.value: _substitute(path, v, args) for k, v in node.value}
    if isinstance(node, yaml.SequenceNode):
        return [_substitute(path, v, args) for v in node.value]
    text = node.value
    if isinstance(text, str) and "$(" in text:

        def replace(match: re.Match[str]) -> str:
            name = match.group(1)
            if name not in args:
                raise LaunchError(f"{_where(path, node)}: $(var {name}) used before its 'arg' entry")
            return args[name]

        replaced = _VAR.sub(replace, text)
        if "$(" in replaced:
            raise LaunchError(f"{_where(path, node)}: unknown substitution in {text!r} (only $(var NAME))")
        plain = node.style is None  # a quoted "$(var serial)" stays text: 003726261447 is no octal number
        return yaml.safe_load(replaced) if plain and _VAR.fullmatch(text) else replaced
    return yaml.safe_load(yaml.serialize(node))


# -- supervision -------------------------------------------------------------------------

_PR_SET_PDEATHSIG = 1


def _prepare_child() -> None:
    # SIGKILL: a node stuck in a blocking call must not outlive a launcher that was killed.
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    hold_stops()  # a stop during the interpreter's start-up waits for bus.start's handler


@dataclasses.dataclass
class _Running:
    spec: NodeSpec
    process: subprocess.Popen[bytes]
    respawns: int = 0
    relay: threading.Thread | None = None


class Launcher:
    """Starts, watches and stops the nodes of one launch description."""

    def __init__(
        self, description: LaunchDescription, output: TextIO = sys.stdout, stop_timeout_s: float = 5.0
    ) -> None:
        self.description = description
        self.output = output
        self.stop_timeout_s = stop_timeout_s
        self.running: dict[str, _Running] = {}
        # Crashed nodes waiting for their respawn: name -> (when, spec, respawns so far). Each
        # waits its own delay while the launcher watches the others, so nodes that died together
        # come back together.
        self.respawning: dict[str, tuple[float, NodeSpec, int]] = {}
        self._print_lock = threading.Lock()
        self._stop = threading.Event()
        self.failures: list[str] = []
        self.registry = Registry()  # the bus of the graph

    def say(self, text: str) -> None:
        with self._print_lock:
            print(text, file=self.output, flush=True)

    def _start(self, spec: NodeSpec, respawns: int = 0) -> None:
        # DTX_RESPAWN tells a node it is being restarted (a collector then resumes its dataset);
        # DTX_TERMINAL whether the relay ends on a terminal (how the node should show progress).
        process = subprocess.Popen(
            spec.command(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=_prepare_child,
            env={
                **os.environ,
                "PYTHONUNBUFFERED": "1",
                "DTX_RESPAWN": str(respawns),
                TERMINAL_ENV: "1" if on_terminal(self.output) else "0",
            },
        )
        relay = threading.Thread(target=self._relay, args=(spec.name, process), daemon=True)
        self.running[spec.name] = _Running(spec, process, respawns, relay)
        relay.start()
        self.say(f"[launch] started {spec.name} (pid {process.pid})")

    def _relay(self, name: str, process: subprocess.Popen[bytes]) -> None:
        assert process.stdout is not None
        for raw in process.stdout:
            self.say(f"[{name}] {raw.decode(errors='replace').rstrip()}")

    def run(self) -> int:
        """Run until Ctrl-C, a required node ends, or every node has ended. Exit status."""
        registry = self.registry
        taken = {spec.name: registry.live_node_pid(spec.name) for spec in self.description.nodes}
        taken = {name: pid for name, pid in taken.items() if pid is not None}
        if taken:
            self.say(
                f"[launch] error: {', '.join(f'{n} (pid {p})' for n, p in taken.items())} already run on bus "
                f"{registry.root}: another graph is live in this domain. Stop it, or run this one on a bus of "
                "its own with DTX_DOMAIN=NAME"
            )
            return 1
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: self._stop.set())
        for spec in self.description.nodes:
            self._start(spec)
        try:
            while not self._stop.is_set() and (self.running or self.respawning):
                self._watch()
                self._respawn_due()
                self._stop.wait(0.1)
        finally:
            self.shutdown()
        return 1 if self.failures else 0

    def _watch(self) -> None:
        for name, run in list(self.running.items()):
            code = run.process.poll()
            if code is None:
                continue
            spec = run.spec
            del self.running[name]
            self.registry.forget_process(run.process.pid)  # a node killed with -9 could not
            if code not in (0, EXIT_DO_NOT_RESPAWN) and spec.respawn:
                self.say(f"[launch] {name} exited with {code}; respawning in {spec.respawn_delay_s} s")
                self.respawning[name] = (time.monotonic() + spec.respawn_delay_s, spec, run.respawns + 1)
                continue
            if code != 0:
                self.failures.append(f"{name} exited with {code}")
                self.say(f"[launch] {name} failed (exit {code})")
            else:
                self.say(f"[launch] {name} finished")
            if spec.required:
                self.say(f"[launch] required node {name} ended; stopping everything")
                self._stop.set()

    def _respawn_due(self) -> None:
        now = time.monotonic()
        for name, (due, spec, respawns) in list(self.respawning.items()):
            if due <= now and not self._stop.is_set():
                del self.respawning[name]
                self._start(spec, respawns)

    def shutdown(self) -> None:
        self.respawning.clear()
        for run in self.running.values():
            if run.process.poll() is None:
                run.process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + self.stop_timeout_s
        for name, run in self.running.items():
            try:
                run.process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.say(f"[launch] {name} did not stop in {self.stop_timeout_s} s; killing it")
                run.process.kill()
                run.process.wait()
        for run in self.running.values():  # a node's last lines (why it stopped) are still in the pipe
            if run.relay is not None:
                run.relay.join(timeout=1.0)
        self.running.clear()
