"""Launch files and the supervisor, with real node processes."""

from __future__ import annotations

import os
import pty
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from bus.registry import Registry, pid_alive
from dtx.launch import LaunchError, load_launch

FIXTURES = Path(__file__).parent / "launch_fixtures"


@pytest.fixture
def launch_env(bus_dir: Path) -> dict[str, str]:
    path = os.pathsep.join([str(FIXTURES), os.environ.get("PYTHONPATH", "")])
    os.environ["PYTHONPATH"] = path  # load_launch looks modules up in this process too
    sys.path.insert(0, str(FIXTURES))
    return {**os.environ, "DTX_BUS_DIR": str(bus_dir), "PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}


def dtx(*args: str, env: dict[str, str], **kwargs: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "dtx.cli", *args],
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        **kwargs,
    )  # type: ignore[call-overload]


def wait_for_nodes(registry: Registry, names: set[str], timeout_s: float = 30.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = {s["node"]: s["pid"] for s in registry.node_statuses() if s["alive"] and s["status"] == "ok"}
        if names <= set(alive):
            return alive
        time.sleep(0.1)
    raise AssertionError(f"nodes {names} did not come up; registry: {registry.node_statuses()}")


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "launch.yaml"
    path.write_text(text)
    return path


def test_unknown_key_error_names_file_and_line(tmp_path: Path, launch_env: dict[str, str]) -> None:
    path = write(tmp_path, "launch:\n  - node:\n      name: a\n      module: fixture_nodes\n      respwan: true\n")
    with pytest.raises(LaunchError, match=r"launch.yaml:5: unknown key 'respwan'"):
        load_launch(path)


def test_missing_module_error_names_the_line(tmp_path: Path, launch_env: dict[str, str]) -> None:
    path = write(tmp_path, "launch:\n  - arg: {name: x, default: 1}\n  - node: {name: a, module: nodes.no_such_node}\n")
    with pytest.raises(LaunchError, match=r"launch.yaml:3: node 'a': module 'nodes.no_such_node' not found"):
        load_launch(path)


@pytest.mark.parametrize(
    "text, message",
    [
        ("nodes: []\n", "single key 'launch'"),
        ("launch:\n  - group: {}\n", "launch.yaml:2: unknown entry 'group'"),
        ("launch:\n  - node: {name: a, module: fixture_nodes, params: {p: $(var nope)}}\n", "used before its 'arg'"),
        ("launch:\n  - node: {name: a, module: fixture_nodes, params: {p: $(env HOME)}}\n", "unknown substitution"),
        ("launch:\n  - arg: {name: out}\n", "has no default"),
        ("launch:\n  - node: {name: a}\n", "missing key(s) ['module']"),
        ("launch: [\n", "not valid YAML"),
    ],
)
def test_malformed_launch_files_are_refused(
    tmp_path: Path, launch_env: dict[str, str], text: str, message: str
) -> None:
    with pytest.raises(LaunchError, match=__import__("re").escape(message)):
        load_launch(write(tmp_path, text))


def test_quoted_substitution_stays_text(tmp_path: Path, launch_env: dict[str, str]) -> None:
    path = write(
        tmp_path,
        'launch:\n  - arg: {name: serial, default: "003726261447"}\n'
        '  - node: {name: a, module: fixture_nodes, params: {s: "$(var serial)", n: $(var serial)}}\n',
    )
    params = load_launch(path).nodes[0].params
    assert params["s"] == "003726261447"
    assert isinstance(params["n"], int)  # unquoted: YAML reads the value itself (here, as octal)


def test_args_includes_and_typed_substitution(launch_env: dict[str, str]) -> None:
    description = load_launch(FIXTURES / "two_counters.yaml", {"period": "0.2", "finish_after": "7"})
    steady, finisher = description.nodes
    assert steady.params == {"period_s": 0.2} and steady.respawn
    assert finisher.params["finish_after"] == 7 and finisher.required
    assert finisher.remaps == {"/count": "/finisher/count"}
    with pytest.raises(LaunchError, match="unknown launch argument"):
        load_launch(FIXTURES / "two_counters.yaml", {"perod": "1"})


def test_launch_respawns_and_stops_cleanly_on_ctrl_c(registry: Registry, launch_env: dict[str, str]) -> None:
    launcher = dtx("launch", str(FIXTURES / "two_counters.yaml"), env=launch_env)
    try:
        pids = wait_for_nodes(registry, {"steady", "finisher"})
        os.kill(pids["steady"], signal.SIGKILL)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            respawned = wait_for_nodes(registry, {"steady"})
            if respawned["steady"] != pids["steady"]:
                break
            time.sleep(0.2)
        assert respawned["steady"] != pids["steady"]
        launcher.send_signal(signal.SIGINT)
        output, _ = launcher.communicate(timeout=30)
    finally:
        launcher.kill()
    assert launcher.returncode == 0, output
    assert "[steady] counter ready" in output and "respawning" in output
    for pid in (*pids.values(), respawned["steady"]):
        assert not pid_alive(pid)


def test_required_node_finishing_ends_the_launch(registry: Registry, launch_env: dict[str, str]) -> None:
    launcher = dtx("launch", str(FIXTURES / "two_counters.yaml"), "finish_after:=5", env=launch_env)
    output, _ = launcher.communicate(timeout=60)
    assert launcher.returncode == 0, output
    assert "required node finisher ended" in output


def test_required_node_failing_fails_the_launch(registry: Registry, launch_env: dict[str, str]) -> None:
    launcher = dtx("launch", str(FIXTURES / "failing_required.yaml"), env=launch_env)
    output, _ = launcher.communicate(timeout=60)
    assert launcher.returncode == 1, output
    assert "crasher failed (exit 3)" in output


def test_a_second_graph_in_the_same_domain_is_refused(registry: Registry, launch_env: dict[str, str]) -> None:
    """Two graphs on one bus would answer each other's services and mix their data: the second
    launch, or a node started by hand under a taken name, stops before joining; another domain
    is a bus of its own."""
    elsewhere = {**launch_env, "DTX_BUS_DIR": tempfile.mkdtemp(prefix="dtxo")}  # ipc paths stay short
    launcher = dtx("launch", str(FIXTURES / "two_counters.yaml"), env=launch_env)
    try:
        pids = wait_for_nodes(registry, {"steady", "finisher"})
        second = dtx("launch", str(FIXTURES / "two_counters.yaml"), env=launch_env)
        output, _ = second.communicate(timeout=60)
        assert second.returncode == 1, output
        assert f"steady (pid {pids['steady']})" in output and "DTX_DOMAIN" in output and "started" not in output
        by_hand = subprocess.run(
            [sys.executable, "-m", "fixture_nodes", "--name", "steady"],
            env=launch_env,
            text=True,
            capture_output=True,
            timeout=60,
        )
        assert by_hand.returncode == 2 and "a node named 'steady' already runs" in by_hand.stderr
        third = dtx("launch", str(FIXTURES / "two_counters.yaml"), "finish_after:=3", env=elsewhere)
        output, _ = third.communicate(timeout=60)
        assert third.returncode == 0, output
        assert wait_for_nodes(registry, {"steady", "finisher"}) == pids  # the first graph never noticed
    finally:
        launcher.send_signal(signal.SIGINT)
        launcher.communicate(timeout=30)
        shutil.rmtree(elsewhere["DTX_BUS_DIR"], ignore_errors=True)


def test_nodes_die_with_a_killed_launcher(registry: Registry, launch_env: dict[str, str]) -> None:
    launcher = dtx("launch", str(FIXTURES / "two_counters.yaml"), env=launch_env)
    pids = wait_for_nodes(registry, {"steady", "finisher"})
    launcher.kill()
    launcher.wait()
    deadline = time.monotonic() + 10
    while any(pid_alive(p) for p in pids.values()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(pid_alive(p) for p in pids.values())


def test_command_line_tools_see_the_running_graph(registry: Registry, launch_env: dict[str, str]) -> None:
    launcher = dtx("launch", str(FIXTURES / "two_counters.yaml"), env=launch_env)
    try:
        wait_for_nodes(registry, {"steady", "finisher"})

        def run(*args: str) -> str:
            result = subprocess.run(
                [sys.executable, "-m", "dtx.cli", *args], env=launch_env, text=True, capture_output=True, timeout=60
            )
            assert result.returncode == 0, result.stderr
            return result.stdout

        assert "steady" in run("node", "list") and "finisher" in run("node", "list")
        topics = run("topic", "list")
        assert "/count" in topics and "/finisher/count" in topics and "/heartbeat" in topics
        echoed = run("topic", "echo", "/finisher/count", "--count", "1", "--timeout", "10")
        assert "node: finisher" in echoed
        assert "average rate" in run("topic", "hz", "/count", "--duration", "1.5")
        assert "MB/s" in run("topic", "bw", "/count", "--duration", "1.5")
        assert "state: echo" in run("service", "call", "/echo", "{width_m: 0.03}")
        assert "/echo" in run("service", "list")
    finally:
        launcher.send_signal(signal.SIGINT)
        launcher.communicate(timeout=30)


def test_nodes_that_die_together_are_respawned_together(
    registry: Registry, launch_env: dict[str, str], tmp_path: Path
) -> None:
    """Each crashed node waits its own respawn delay while the launcher watches the others:
    both deaths are seen before either respawn (they were served one after the other, each
    waiting out its delay while the other stayed dead)."""
    path = write(
        tmp_path,
        "launch:\n"
        "  - node: {name: one, module: fixture_nodes, respawn: true, respawn_delay_s: 3}\n"
        "  - node: {name: two, module: fixture_nodes, respawn: true, respawn_delay_s: 3,\n"
        "           remaps: {/count: /two/count, /echo: /two/echo, /hold: /two/hold}}\n",
    )
    launcher = dtx("launch", str(path), env=launch_env)
    try:
        pids = wait_for_nodes(registry, {"one", "two"})
        for pid in pids.values():
            os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            respawned = wait_for_nodes(registry, {"one", "two"})
            if not set(respawned.values()) & set(pids.values()):
                break
            time.sleep(0.2)
        launcher.send_signal(signal.SIGINT)
        output, _ = launcher.communicate(timeout=30)
    finally:
        launcher.kill()
    lines = output.splitlines()
    deaths = [i for i, line in enumerate(lines) if "exited with -9; respawning" in line]
    starts = [i for i, line in enumerate(lines) if line.startswith("[launch] started ")]
    assert len(deaths) == 2 and len(starts) == 4, output
    assert max(deaths) < min(starts[2:]), output  # both deaths seen before either respawn
    assert launcher.returncode == 0, output


def limit_file_size(limit_bytes: int) -> Callable[[], None]:
    """A preexec_fn under which no file grows past ``limit_bytes``: writes beyond fail (EFBIG;
    Python ignores SIGXFSZ), as on a full disk, without needing root to mount a small one."""

    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return apply


def test_a_recorder_the_disk_refuses_stops_cleanly_and_is_not_respawned(
    registry: Registry, launch_env: dict[str, str], tmp_path: Path
) -> None:
    """It crash-looped: each respawn opened one more bag (session.1.mcap, ...) that the disk
    refused in turn. Now it stops with the do-not-respawn status and its bag reads."""
    from bus.bag import bag_info

    bag = tmp_path / "session.mcap"
    path = write(
        tmp_path,
        "launch:\n"
        "  - node: {name: talker, module: fixture_nodes, params: {period_s: 0.02, text_bytes: 4000}}\n"
        "  - node:\n      name: recorder\n      module: nodes.recorder\n      respawn: true\n"
        f"      params: {{bag: {bag}, compression: none, foxglove: false}}\n",
    )
    launcher = dtx("launch", str(path), env=launch_env, preexec_fn=limit_file_size(1024 * 1024))
    try:
        deadline = time.monotonic() + 60  # the recorder may fill its file before the talker is seen up

        def recorder_ended() -> bool:
            return any(s["node"] == "recorder" and not s["alive"] for s in registry.node_statuses())

        while not recorder_ended() and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(5.0)  # time for a respawn, if the launcher wrongly made one
        launcher.send_signal(signal.SIGINT)
        output, _ = launcher.communicate(timeout=30)
    finally:
        launcher.kill()
    assert "[launch] recorder failed (exit 2)" in output and "recorder exited with" not in output, output
    assert "the disk refused the data" in output and "the recorder stops" in output, output
    assert sorted(p.name for p in tmp_path.glob("session*")) == ["session.mcap"]
    info = bag_info(bag)
    assert info.truncated and info.topics.get("/count", {}).get("count", 0) > 0, info


def test_a_loaded_graph_stops_within_the_grace_time_without_a_kill(
    registry: Registry, launch_env: dict[str, str], tmp_path: Path
) -> None:
    """Ctrl-C while a node waits on a long call (the collector during a registration), beside a
    flooding talker and a recorder: every node exits by itself, status 0; none is killed after
    the grace time (the caller used to wait out its call's time-out). The server is outside the
    graph and keeps holding the request, so only the caller's own stop can end the wait."""
    server = subprocess.Popen(
        [sys.executable, "-m", "fixture_nodes", "--name", "server", "--params", '{"hold_s": 600}'],
        env=launch_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    path = write(
        tmp_path,
        "launch:\n"
        "  - node: {name: caller, module: fixture_nodes, params: {period_s: 0.5, call_hold: true},\n"
        "           remaps: {/count: /caller/count, /echo: /caller/echo, /hold: /caller/hold,"
        " /target/hold: /hold}}\n"
        "  - node: {name: talker, module: fixture_nodes, params: {period_s: 0.005, text_bytes: 2000},\n"
        "           remaps: {/count: /talker/count, /echo: /talker/echo, /hold: /talker/hold}}\n"
        f"  - node: {{name: recorder, module: nodes.recorder, params: {{bag: {tmp_path / 'b.mcap'}}}}}\n",
    )
    launcher = dtx("launch", str(path), env=launch_env)
    try:
        wait_for_nodes(registry, {"server", "talker", "recorder"}, timeout_s=60)
        time.sleep(3.0)  # the caller's first call is in flight, held by the server (its executor is
        # blocked in the call, as the collector's is: no heartbeat to wait for)
        launcher.send_signal(signal.SIGINT)
        output, _ = launcher.communicate(timeout=60)
    finally:
        launcher.kill()
        server.kill()
        server.wait()
    assert output.count("killing it") == 0, output
    assert "[caller] call ended: cancelled" in output, output
    assert launcher.returncode == 0, output


def test_nodes_learn_whether_the_launchers_output_is_a_terminal(tmp_path: Path, launch_env: dict[str, str]) -> None:
    """A node writes into the launcher's pipe; how it shows progress follows the launcher's own
    output (DTX_TERMINAL): plain paced lines into a file or pipe, a terminal's form on a terminal."""
    path = write(tmp_path, "launch:\n  - node: {name: probe, module: terminal_probe, required: true}\n")
    launch_env.pop("DTX_TERMINAL", None)
    piped = dtx("launch", str(path), env=launch_env)
    output, _ = piped.communicate(timeout=60)
    assert piped.returncode == 0 and "[probe] progress on a terminal: False" in output, output
    controller, terminal = pty.openpty()
    with open(controller, "rb", buffering=0) as reader:
        process = subprocess.Popen(
            [sys.executable, "-m", "dtx.cli", "launch", str(path)], env=launch_env, stdout=terminal, stderr=terminal
        )
        os.close(terminal)
        chunks = []
        while True:
            try:
                chunk = reader.read(4096)
            except OSError:  # the last writer closed the terminal
                break
            if not chunk:
                break
            chunks.append(chunk)
        assert process.wait(timeout=60) == 0
    assert "[probe] progress on a terminal: True" in b"".join(chunks).decode(errors="replace")


def _read_until(process: subprocess.Popen[str], wanted: set[str]) -> str:
    """The process's output up to the line that completes ``wanted`` (substrings), as read."""
    assert process.stdout is not None
    seen = ""
    while not all(text in seen for text in wanted):
        line = process.stdout.readline()
        assert line, f"the output ended before {wanted} appeared: {seen}"
        seen += line
    return seen


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize(
    ("module", "params", "line"),
    [("slow_import", {}, "importing"), ("fixture_nodes", {"start_s": 60.0}, "starting")],
    ids=["while-importing", "while-being-made"],
)
def test_a_node_stopped_while_it_starts_exits_quietly_with_status_0(
    launch_env: dict[str, str], signum: int, module: str, params: dict[str, float], line: str
) -> None:
    """A stop while a node loads its module or is being made, started as the launcher starts it:
    status 0 and no traceback (a KeyboardInterrupt's was printed; SIGTERM gave -15)."""
    from dtx.launch import NodeSpec, _prepare_child

    process = subprocess.Popen(
        NodeSpec("starter", module, params).command(),
        env=launch_env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        preexec_fn=_prepare_child,
    )
    try:
        _read_until(process, {line})
        process.send_signal(signum)
        _, errors = process.communicate(timeout=60)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0, errors
    assert "Traceback" not in errors and "KeyboardInterrupt" not in errors, errors


def test_ctrl_c_while_nodes_start_stops_the_graph_without_a_traceback(
    tmp_path: Path, launch_env: dict[str, str]
) -> None:
    path = write(
        tmp_path,
        "launch:\n"
        "  - node: {name: loading, module: slow_import}\n"
        "  - node: {name: making, module: fixture_nodes, params: {start_s: 60}}\n",
    )
    launcher = dtx("launch", str(path), env=launch_env)
    try:
        seen = _read_until(launcher, {"[loading] importing", "[making] starting"})
        launcher.send_signal(signal.SIGINT)
        output, _ = launcher.communicate(timeout=60)
    finally:
        launcher.kill()
    output = seen + output
    assert launcher.returncode == 0, output
    assert "Traceback" not in output and "KeyboardInterrupt" not in output, output
    assert "killing it" not in output, output  # each stopped at once, within the grace time
