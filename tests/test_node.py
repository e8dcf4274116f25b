"""The node base: parameters, timers, background service work, heartbeats."""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Any

import pytest

import msgs
from dtx.launch import load_launch
from nodes.bus import Bus
from nodes.node import Node, ParameterError
from nodes.registry import Registry


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
            msgs.GripperCommand(width_m=0.03), timeout_s=5.0)
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
    path.write_text("launch:\n  - arg: {name: viewer, default: 'false'}\n"
                    "  - node: {name: a, module: nodes.recorder}\n"
                    "  - node: {name: b, module: nodes.foxglove_bridge, if: $(var viewer)}\n")
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
