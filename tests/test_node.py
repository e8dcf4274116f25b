"""The node base: parameters, timers, background service work, heartbeats."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

import msgs
from benchmarks.fuzz import mutants
from bus.node import Node, ParameterError
from bus.pubsub import Bus
from bus.registry import Registry
from dtx.launch import load_launch


class SlowMover(Node):
    @dataclasses.dataclass
    class Params:
        move_s: float = 0.3
        rate_hz: float = 50.0

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.state = self.create_publisher("/mover/state", msgs.GripperState)
        self.create_service("/mover/move", msgs.GripperCommand, msgs.GripperState, self.on_move)
        self.create_timer(1.0 / self.params.rate_hz, lambda: self.state.publish(msgs.GripperState()))

    def on_move(self, command: msgs.GripperCommand) -> Any:
        def move() -> msgs.GripperState:
            time.sleep(self.params.move_s)
            return msgs.GripperState(width_m=command.width_m, state="holding")

        return self.background.submit(move)


def test_unknown_or_mistyped_parameters_are_refused(registry: Registry) -> None:
    with pytest.raises(ParameterError, match=r"unknown parameter\(s\) \['speed'\]; allowed: \['move_s', 'rate_hz'\]"):
        SlowMover("m", {"speed": 1}, registry=registry)
    with pytest.raises(ParameterError, match="must be float"):
        SlowMover("m", {"move_s": "fast"}, registry=registry)


def test_state_keeps_flowing_while_a_service_works_in_the_background(registry: Registry) -> None:
    node = SlowMover("mover", {"move_s": 1.0}, registry=registry)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: node.spin(until=stop.is_set))
    spinner.start()
    caller = Bus("caller", registry)
    try:
        states = caller.subscriber("/mover/state", msgs.GripperState)
        assert states.receive(5.0) is not None
        asked_ns = time.time_ns()
        reply = caller.client("/mover/move", msgs.GripperCommand, msgs.GripperState).call(
            msgs.GripperCommand(width_m=0.03), timeout_s=5.0
        )
        answered_ns = time.time_ns()
        stamps = [0]
        while stamps[-1] <= answered_ns and (envelope := states.receive(2.0)) is not None:
            stamps.append(envelope.message.header.stamp_ns)
    finally:
        stop.set()
        spinner.join()
        caller.close()
        node.close()
    assert reply.state == "holding" and reply.width_m == pytest.approx(0.03)
    during_the_move = [s for s in stamps if asked_ns < s < answered_ns]
    assert len(during_the_move) >= 2  # the executor kept publishing while the move ran


def test_heartbeat_reaches_the_registry(registry: Registry) -> None:
    node = SlowMover("beating", registry=registry)
    node.spin(until=lambda: any(s["node"] == "beating" for s in registry.node_statuses()))
    status = next(s for s in registry.node_statuses() if s["node"] == "beating")
    node.close()
    assert status["alive"] and "/mover/move" in status["services"] and "/mover/state" in status["publishers"]


def test_a_launch_entry_can_be_switched_off(tmp_path: Path) -> None:
    path = tmp_path / "l.yaml"
    path.write_text(
        "launch:\n  - arg: {name: viewer, default: 'false'}\n"
        "  - node: {name: a, module: nodes.recorder}\n"
        "  - node: {name: b, module: nodes.foxglove_bridge, if: $(var viewer)}\n"
    )
    assert [n.name for n in load_launch(path).nodes] == ["a"]
    assert [n.name for n in load_launch(path, {"viewer": "true"}).nodes] == ["a", "b"]


def test_a_respawned_recorder_never_overwrites_a_bag(tmp_path: Path) -> None:
    from nodes.recorder import free_bag_path

    first = tmp_path / "session.mcap"
    assert free_bag_path(first) == first
    first.write_bytes(b"bag of the first life")
    second = free_bag_path(first)
    assert second.name == "session.1.mcap"
    second.write_bytes(b"bag of the second life")
    assert free_bag_path(first).name == "session.2.mcap"
    assert first.read_bytes() == b"bag of the first life"


class Listener(Node):
    """A node with a subscription whose callback breaks on some values, and a service."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, None, **kwargs)
        self.heard: list[float] = []
        self.create_subscription("/listener/in", msgs.GripperCommand, self.on_command)
        self.create_service(
            "/listener/echo", msgs.GripperCommand, msgs.GripperState, lambda c: msgs.GripperState(width_m=c.width_m)
        )

    def on_command(self, command: msgs.GripperCommand) -> None:
        if command.width_m < 0:
            raise ValueError("a width below zero")  # a bug a message can trigger
        self.heard.append(command.width_m)


def test_a_live_node_survives_malformed_messages_and_failing_callbacks(registry: Registry) -> None:
    from msgs.codec import encode

    node = Listener("listener", registry=registry)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: node.spin(until=stop.is_set))
    spinner.start()
    fuzzer = Bus("fuzzer", registry)
    try:
        publisher = fuzzer.publisher("/listener/in", msgs.GripperCommand)
        assert publisher.wait_for_subscribers(1, timeout_s=10.0)
        client = fuzzer.client("/listener/echo", msgs.GripperCommand, msgs.GripperState)
        assert client.call(msgs.GripperCommand(width_m=0.01), timeout_s=5.0).width_m == pytest.approx(0.01)
        publisher.publish(msgs.GripperCommand(width_m=-1.0))
        good = [bytes(memoryview(f)) for f in encode("/listener/in", msgs.GripperCommand(width_m=0.02), "fuzzer")]
        for frames in mutants(good, 500, seed=1):
            publisher.sock.send_multipart(frames)
        good_request = [bytes(memoryview(f)) for f in encode("/listener/echo", msgs.GripperCommand(), "fuzzer")]
        for frames in mutants(good_request, 500, seed=2):
            client.sock.send_multipart(frames)
        publisher.publish(msgs.GripperCommand(width_m=0.03))
        reply = client.call(msgs.GripperCommand(width_m=0.04), timeout_s=10.0)
        deadline = time.monotonic() + 10.0
        while 0.03 not in node.heard and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        spinner.join()
        fuzzer.close()
    counters = node.counters()
    node.close()
    assert spinner is not None and reply.width_m == pytest.approx(0.04)
    assert 0.03 in node.heard and -1.0 not in node.heard
    assert counters["handler_errors"] == 1 and counters["malformed"] >= 400


def test_a_service_answers_every_call_in_time_through_a_20000_message_flood(registry: Registry) -> None:
    """A node in its own process gets 20,000 mutated requests on its service socket while a
    client keeps calling it: every call is answered within its time-out, the node lives on."""
    from msgs.codec import encode

    fixtures = Path(__file__).parent / "launch_fixtures"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fixtures), os.environ.get("PYTHONPATH", "")])}
    server = subprocess.Popen(
        [sys.executable, "-m", "fixture_nodes", "--name", "flooded"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    bus = Bus("flooder", registry)
    try:
        client = bus.client("/echo", msgs.GripperCommand, msgs.GripperState)
        flooder = bus.client("/echo", msgs.GripperCommand, msgs.GripperState)  # its socket sends the garbage
        assert client.wait_for_service(60) and flooder.wait_for_service(60)
        good = [bytes(memoryview(f)) for f in encode("/echo", msgs.GripperCommand(width_m=0.02), "flooder")]
        flood_frames = mutants(good, 20_000, seed=3)
        sent = refused = 0

        def flood() -> None:
            nonlocal sent, refused
            for frames in flood_frames:
                flooder.sock.send_multipart(frames)
                sent += 1
                while flooder.sock.poll(0):  # the bad_request replies, read so none backs up
                    flooder.sock.recv_multipart()
                    refused += 1

        thread = threading.Thread(target=flood, daemon=True)
        thread.start()
        answered = 0
        while thread.is_alive() or answered == 0:
            width = 0.001 * (answered % 50)
            reply = client.call(msgs.GripperCommand(width_m=width), timeout_s=5.0, retries=0)
            assert reply.width_m == pytest.approx(width) and reply.state == "echo"
            answered += 1
        thread.join()
        while flooder.sock.poll(2000):  # the replies to the last of the flood
            flooder.sock.recv_multipart()
            refused += 1
        assert sent == 20_000 and answered >= 1
        assert refused > 10_000  # the flood reached the server: most mutants are answered bad_request
        assert server.poll() is None  # alive
        print(
            f"flood: {sent} mutated requests ({refused} answered with an error), "
            f"{answered} calls answered within 5 s each"
        )
    finally:
        server.kill()
        server.wait()
        bus.close()
