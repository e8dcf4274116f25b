"""The WSG-50 client against the firmware simulator on a pty: every command, end to end."""

from __future__ import annotations

import os
import struct
import threading
import time
import tty

import pytest
import serial

from drivers import DeviceTimeoutError
from drivers.gripper import GripperError, make_backend
from drivers.gripper.firmware import GripperFirmware
from drivers.gripper.protocol import Command, FrameParser, Status, encode_frame, split_response
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper

FAST = 0.4  # m/s: keeps every motion below a few hundred milliseconds


class World:
    """Stands in for the simulated world: what lies between the fingers (m)."""

    def __init__(self) -> None:
        self.object_width_m: float | None = None

    def contact_width_m(self) -> float | None:
        return self.object_width_m


@pytest.fixture
def world():
    return World()


@pytest.fixture
def firmware(world):
    with GripperFirmware(world.contact_width_m) as running:
        yield running


@pytest.fixture
def gripper(firmware):
    client = WSG50Gripper(WSG50Config(port=firmware.port, response_timeout_s=0.3))
    client.connect()
    yield client
    client.disconnect()


def test_read_reports_initial_opening(gripper):
    state = gripper.read()
    assert state.width_m == pytest.approx(0.110)
    assert state.force_n == 0.0
    assert state.state == "idle"
    assert state.header.frame_id == "tcp"


def test_home_opens_fully(gripper):
    gripper.move(0.04, FAST)
    assert gripper.home().width_m == pytest.approx(0.110)


def test_move_reaches_width(gripper):
    state = gripper.move(0.0625, FAST)
    assert state.width_m == pytest.approx(0.0625, abs=1e-6)
    assert state.state == "idle"


def test_move_blocked_by_object(gripper, world):
    world.object_width_m = 0.05
    with pytest.raises(GripperError, match="blocked at 50.0 mm"):
        gripper.move(0.02, FAST)


def test_grasp_stops_at_contact_and_holds_force(gripper, world):
    world.object_width_m = 0.0385
    state = gripper.grasp(0.04, FAST, force_n=25.0)  # nominal width, within the clamping travel
    assert state.state == "holding"
    assert state.width_m == pytest.approx(0.0385, abs=1e-6)
    assert state.force_n == pytest.approx(25.0)
    assert state.status_code == Status.E_SUCCESS


def test_grasp_with_nothing_between_fingers(gripper):
    state = gripper.grasp(0.03, FAST, force_n=10.0)
    assert state.state == "no_part"
    assert state.width_m == pytest.approx(0.02, abs=1e-6)  # nominal less the 10 mm travel
    assert state.status_code == Status.E_CMD_FAILED


def test_release_opens_and_drops_force(gripper, world):
    world.object_width_m = 0.05
    gripper.grasp(0.05, FAST, force_n=20.0)
    state = gripper.release(0.09, FAST)
    assert state.state == "idle"
    assert state.force_n == 0.0
    assert state.width_m == pytest.approx(0.09, abs=1e-6)


def test_force_limit_beyond_gripper_is_refused(gripper):
    with pytest.raises(GripperError, match="force limit 120.0 N is outside"):
        gripper.set_force_limit(120.0)


def test_out_of_range_move_is_refused_before_the_device_clamps_it(gripper):
    """W6: the device clamps 200 mm to its 110 mm stroke and succeeds; the driver must not
    call that "blocked … something between the fingers"."""
    with pytest.raises(GripperError, match="outside the gripper's range"):
        gripper.move(0.2, FAST)
    with pytest.raises(GripperError, match="outside the gripper's range"):
        gripper.grasp(0.04, 1.0, force_n=10.0)


def test_release_cannot_close(gripper):
    gripper.move(0.05, FAST)
    with pytest.raises(GripperError, match="release opens"):
        gripper.release(0.03, FAST)


def test_stop_interrupts_a_grasp(gripper):
    outcome: list[BaseException] = []

    def slow_grasp() -> None:
        try:
            gripper.grasp(0.01, 0.01, force_n=10.0)  # 11 s at 10 mm/s if never stopped
        except GripperError as exc:
            outcome.append(exc)

    grasping = threading.Thread(target=slow_grasp)
    grasping.start()
    while gripper.read().state != "moving":
        time.sleep(0.01)
    stopped = gripper.stop()
    grasping.join()
    assert stopped.state == "idle"
    assert 0.0 < stopped.width_m < 0.110
    assert "E_CMD_ABORTED" in str(outcome[0])


def test_second_motion_while_running_is_refused(gripper):
    outcome: list[BaseException] = []

    def slow_move() -> None:
        try:
            gripper.move(0.0, 0.02)  # 5.5 s unless stopped
        except GripperError as exc:
            outcome.append(exc)

    mover = threading.Thread(target=slow_move)
    mover.start()
    while gripper.read().state != "moving":
        time.sleep(0.01)
    with pytest.raises(GripperError, match="another motion is running"):
        gripper.grasp(0.02, FAST, force_n=10.0)
    gripper.stop()
    mover.join()
    assert "E_CMD_ABORTED" in str(outcome[0])


def test_motion_answers_pending_then_final_status(firmware, world):
    """The raw protocol: E_CMD_PENDING at once, the final status when the fingers stop."""
    world.object_width_m = 0.03
    with serial.Serial(firmware.port, timeout=0.05) as link:
        link.write(encode_frame(Command.GRASP, struct.pack("<ff", 30.0, 400.0)))
        parser, frames = FrameParser(), []
        deadline = time.monotonic() + 5.0
        while len(frames) < 2 and time.monotonic() < deadline:
            frames += parser.feed(link.read(64))
    statuses = [(command_id, split_response(payload)[0]) for command_id, payload in frames]
    assert statuses == [(Command.GRASP, Status.E_CMD_PENDING), (Command.GRASP, Status.E_SUCCESS)]


def test_unknown_command_is_answered(firmware):
    with serial.Serial(firmware.port, timeout=0.05) as link:
        link.write(encode_frame(0x7E))
        parser, frames = FrameParser(), []
        deadline = time.monotonic() + 5.0
        while not frames and time.monotonic() < deadline:
            frames += parser.feed(link.read(64))
    assert split_response(frames[0][1])[0] == Status.E_CMD_UNKNOWN


def test_gripper_that_never_answers():
    master, slave = os.openpty()  # a serial line with nothing on the other end
    tty.setraw(slave)
    try:
        client = WSG50Gripper(WSG50Config(port=os.ttyname(slave), response_timeout_s=0.05, retries=1))
        with pytest.raises(GripperError, match="no answer to GET_GRASPING_STATE .* after 2 tries") as raised:
            client.connect()
        assert isinstance(raised.value, DeviceTimeoutError)  # the device contract's deadline error
    finally:
        os.close(master)
        os.close(slave)


def test_missing_serial_port_names_what_exists(tmp_path):
    client = WSG50Gripper(WSG50Config(port=str(tmp_path / "ttyUSB9")))
    with pytest.raises(GripperError, match="cannot open the gripper's serial port .*Serial ports found"):
        client.connect()


def test_simulated_backend_is_the_client_on_the_firmware(world):
    world.object_width_m = 0.06
    gripper = make_backend({"backend": "simulated", "initial_width_m": 0.08}, contact_width_m=world.contact_width_m)
    gripper.connect()
    try:
        assert gripper.read().width_m == pytest.approx(0.08)
        assert gripper.grasp(0.06, FAST, 15.0).width_m == pytest.approx(0.06, abs=1e-6)
    finally:
        gripper.disconnect()


def test_make_backend_rejects_unknown_backend_and_keys():
    with pytest.raises(ValueError, match=r"unknown backend 'robotiq'; allowed: \['simulated', 'wsg50'\]"):
        make_backend({"backend": "robotiq"})
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['baud'\]; allowed: .*'baudrate'"):
        make_backend({"backend": "wsg50", "baud": 9600})


def test_speed_is_reported_while_moving(firmware):
    """GET_SPEED (0x44), which the client does not need, still answers like the device."""
    with serial.Serial(firmware.port, timeout=0.05) as link:
        parser = FrameParser()

        def ask(command: int, payload: bytes) -> tuple[int, bytes]:
            link.write(encode_frame(command, payload))
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                for command_id, reply in parser.feed(link.read(64)):
                    if command_id == command:
                        return split_response(reply)
            raise AssertionError(f"no answer to {command:#x}")

        assert ask(Command.PREPOSITION, struct.pack("<Bff", 0, 10.0, 20.0))[0] == Status.E_CMD_PENDING
        status, data = ask(Command.GET_SPEED, b"\x00\x00\x00")
        assert status == Status.E_SUCCESS
        assert struct.unpack("<f", data)[0] == pytest.approx(20.0)
        assert ask(Command.STOP, b"")[0] == Status.E_SUCCESS


def test_round_trip_benchmark_measures_every_command():
    import argparse

    from benchmarks import hardware

    figures = hardware.run(argparse.Namespace(gripper_commands=20, stop_samples=2, completion_samples=1))
    assert [figure["samples"] for figure in figures] == [20, 2, 1, 1, 1]
    assert all(0.0 < figure["p99"] and figure["p50"] <= figure["p99"] for figure in figures[:2])
    assert figures[1]["preempted"] == 2
    assert all(figure["completed"] == 1 for figure in figures[2:])
