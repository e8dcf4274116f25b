"""The gripper node on the strict firmware simulator: a stop preempts a running grasp (W5),
and a FAST STOP is acknowledged through the service."""

from __future__ import annotations

import threading
import time

import pytest

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from bus.services import ServiceCallError
from drivers.gripper.firmware import GripperFirmware
from nodes.gripper import GripperNode


@pytest.fixture
def firmware():
    with GripperFirmware() as running:
        yield running


@pytest.fixture
def node(registry: Registry, firmware: GripperFirmware):
    gripper = GripperNode(
        "gripper", {"backend": "wsg50", "port": firmware.port, "state_rate_hz": 20.0}, registry=registry
    )
    done = threading.Event()
    spinner = threading.Thread(target=gripper.spin, kwargs={"until": done.is_set})
    spinner.start()
    yield gripper
    done.set()
    spinner.join()
    gripper.close()


def call_in_thread(registry: Registry, command: msgs.GripperCommand, outcome: list) -> threading.Thread:
    def run() -> None:
        bus = Bus("grasper", registry)
        try:
            outcome.append(
                bus.client("/gripper/command", msgs.GripperCommand, msgs.GripperState).call(
                    command, timeout_s=30.0, retries=0
                )
            )
        except ServiceCallError as error:
            outcome.append(error)
        finally:
            bus.close()

    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_stop_through_the_node_preempts_a_running_grasp(registry, node, firmware):
    bus = Bus("operator", registry)
    try:
        command = bus.client("/gripper/command", msgs.GripperCommand, msgs.GripperState)
        assert command.wait_for_service(10.0)
        outcome: list = []
        # 9 s from 110 mm to 20 mm at 10 mm/s, with nothing to find.
        grasping = call_in_thread(
            registry, msgs.GripperCommand(action="grasp", width_m=0.03, speed_m_s=0.01, force_n=10.0), outcome
        )
        while not firmware.moving:
            time.sleep(0.01)
        stopped = command.call(msgs.GripperCommand(action="stop"), timeout_s=10.0, retries=0)
        grasping.join()
        assert stopped.state == "idle"
        assert 0.025 < stopped.width_m < 0.11  # stopped on the way: not queued behind the grasp's end
        assert isinstance(outcome[0], ServiceCallError) and "E_CMD_ABORTED" in outcome[0].text
    finally:
        bus.close()


def test_acknowledge_through_the_node_clears_a_fast_stop(registry, node, firmware):
    bus = Bus("operator", registry)
    try:
        command = bus.client("/gripper/command", msgs.GripperCommand, msgs.GripperState)
        firmware.trip_fast_stop()
        with pytest.raises(ServiceCallError, match="E_ACCESS_DENIED"):
            command.call(msgs.GripperCommand(action="move", width_m=0.05, speed_m_s=0.4), timeout_s=10.0)
        assert command.call(msgs.GripperCommand(action="acknowledge"), timeout_s=10.0).state == "idle"
        moved = command.call(msgs.GripperCommand(action="move", width_m=0.05, speed_m_s=0.4), timeout_s=10.0)
        assert moved.width_m == pytest.approx(0.05, abs=1e-6)
    finally:
        bus.close()


def test_the_simulated_gripper_waits_for_the_arms_place_only_when_its_fingers_may_close(registry):
    """The simulated world needs the arm's pose where the closing fingers may meet the object;
    fingers that open (release, a move to a wider opening) meet nothing and do not wait for it."""
    gripper = GripperNode("gripper", {"backend": "simulated", "state_rate_hz": 20.0}, registry=registry)
    waited: list[int] = []
    gripper.wait_for_arm_state_after = waited.append  # type: ignore[method-assign]
    try:
        gripper.on_command(msgs.GripperCommand(action="home")).result(timeout=30.0)
        for action, width_m, waits in (
            ("move", 0.05, True),
            ("move", 0.08, False),
            ("grasp", 0.03, True),
            ("release", 0.11, False),
        ):
            command = msgs.GripperCommand(action=action, width_m=width_m, speed_m_s=0.4, force_n=10.0)
            command.header.stamp_ns = len(waited) + 1000
            before = list(waited)
            gripper.on_command(command).result(timeout=30.0)
            assert (waited != before) == waits, action
    finally:
        gripper.close()
