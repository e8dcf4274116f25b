"""The WSG-50 client against the strict firmware simulator: the device behaviours of the public
command set (issue 14, W1 W3 W4 W6) and the firmware's own strictness, byte for byte."""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty

import pytest
import serial

from drivers.gripper import GripperError
from drivers.gripper.firmware import GripperFirmware, Strictness
from drivers.gripper.protocol import (
    Command,
    FrameParser,
    GraspingState,
    Status,
    SystemFlag,
    encode_frame,
    split_response,
)
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper

FAST = 0.4  # m/s


def connect(port: str, **config: float) -> WSG50Gripper:
    client = WSG50Gripper(WSG50Config(port=port, **config))
    client.connect()
    return client


class RawLink:
    """The serial line without the client: send one frame, read answers by command id."""

    def __init__(self, port: str) -> None:
        self.link = serial.Serial(port, timeout=0.05)
        self.parser = FrameParser()

    def ask(self, command: int, payload: bytes = b"", frame: bytes | None = None) -> tuple[int, bytes]:
        self.link.write(frame if frame is not None else encode_frame(command, payload))
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            for command_id, reply in self.parser.feed(self.link.read(64)):
                if command_id == command:
                    return split_response(reply)
        raise AssertionError(f"no answer to {command:#x}")

    def flags(self) -> SystemFlag:
        status, data = self.ask(Command.GET_SYSTEM_STATE, b"\x00\x00\x00")
        assert status == Status.E_SUCCESS
        return SystemFlag(struct.unpack("<I", data)[0])

    def close(self) -> None:
        self.link.close()


class DroppingRelay:
    """client <-> relay <-> firmware, dropping the answers ``drop(command, status)`` names:
    a final status lost on the line, deterministically."""

    def __init__(self, firmware_port: str, drop) -> None:
        self._drop = drop
        self._firmware_side = os.open(firmware_port, os.O_RDWR | os.O_NOCTTY)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._parser = FrameParser()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        while not self._stopping.is_set():
            readable, _, _ = select.select([self._master, self._firmware_side], [], [], 0.05)
            if self._master in readable:
                os.write(self._firmware_side, os.read(self._master, 4096))
            if self._firmware_side in readable:
                for command_id, payload in self._parser.feed(os.read(self._firmware_side, 4096)):
                    if not self._drop(command_id, split_response(payload)[0]):
                        os.write(self._master, encode_frame(command_id, payload))

    def close(self) -> None:
        self._stopping.set()
        self._thread.join()
        for fd in (self._firmware_side, self._master, self._slave):
            os.close(fd)


def run_in_thread(action) -> tuple[threading.Thread, list]:
    outcome: list = []

    def run() -> None:
        try:
            outcome.append(action())
        except GripperError as exc:
            outcome.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    return thread, outcome


# -- W1: homing ends on its own final status ------------------------------------------------
def test_home_waits_for_its_final_status_though_the_state_reads_idle():
    with GripperFirmware(initial_width_m=0.04, homing_speed_m_s=0.05) as firmware:  # 1.4 s of homing
        gripper = connect(firmware.port)
        try:
            state = gripper.home()
            assert state.width_m == pytest.approx(0.110)
            assert state.state == "idle"
            assert gripper.move(0.05, FAST).width_m == pytest.approx(0.05, abs=1e-6)  # not E_ALREADY_RUNNING
        finally:
            gripper.disconnect()


def test_an_unreferenced_gripper_refuses_motion_until_homed():
    with GripperFirmware(
        initial_width_m=0.04, homing_speed_m_s=0.05, strictness=Strictness(referenced=False)
    ) as firmware:
        gripper = connect(firmware.port)
        try:
            with pytest.raises(GripperError, match="not referenced") as refused:
                gripper.preflight()
            assert "home it" in refused.value.fix
            with pytest.raises(GripperError, match="E_ACCESS_DENIED"):
                gripper.move(0.05, FAST)
            assert gripper.home().width_m == pytest.approx(0.110)
            gripper.preflight()
            assert gripper.move(0.05, FAST).state == "idle"
        finally:
            gripper.disconnect()


def test_grasping_state_is_idle_while_homing_and_system_state_says_moving():
    with GripperFirmware(initial_width_m=0.04, homing_speed_m_s=0.05) as firmware:
        link = RawLink(firmware.port)
        try:
            assert link.ask(Command.HOMING, b"\x00")[0] == Status.E_CMD_PENDING
            assert link.ask(Command.GET_GRASPING_STATE, b"\x00\x00\x00")[1] == bytes([GraspingState.IDLE])
            assert link.flags() & SystemFlag.MOVING
            assert link.ask(Command.HOMING, b"\x00")[0] == Status.E_ALREADY_RUNNING
        finally:
            link.close()


# -- W3: an aborted motion is reported aborted ------------------------------------------------
def test_a_stopped_grasp_whose_final_answer_is_lost_is_reported_aborted():
    with GripperFirmware() as firmware:
        relay = DroppingRelay(
            firmware.port, lambda command, status: (command, status) == (Command.GRASP, Status.E_CMD_ABORTED)
        )
        gripper = connect(relay.port)
        try:
            grasping, outcome = run_in_thread(lambda: gripper.grasp(0.02, 0.01, force_n=10.0))  # 9 s
            while gripper.read().state != "moving":
                time.sleep(0.01)
            assert gripper.stop().state == "idle"
            grasping.join()
            assert isinstance(outcome[0], GripperError), f"an aborted grasp returned {outcome[0]}"
            assert "E_CMD_ABORTED" in str(outcome[0])
        finally:
            gripper.disconnect()
            relay.close()


def test_stop_while_holding_lets_go():
    with GripperFirmware(lambda: 0.04) as firmware:
        gripper = connect(firmware.port)
        try:
            assert gripper.grasp(0.04, FAST, force_n=20.0).state == "holding"
            stopped = gripper.stop()
            assert stopped.state == "idle"
            assert stopped.force_n == 0.0
        finally:
            gripper.disconnect()


# -- W4: fast stop, faults, acknowledge --------------------------------------------------------
def test_fast_stop_is_refused_by_the_preflight_and_cleared_by_acknowledge():
    with GripperFirmware() as firmware:
        gripper = connect(firmware.port)
        try:
            gripper.preflight()
            firmware.trip_fast_stop()
            with pytest.raises(GripperError, match="FAST STOP") as refused:
                gripper.preflight()
            assert "acknowledge" in refused.value.fix
            with pytest.raises(GripperError, match="E_ACCESS_DENIED"):
                gripper.move(0.05, FAST)
            assert gripper.read().state == "error"
            assert gripper.acknowledge().state == "idle"
            gripper.preflight()
            assert gripper.move(0.05, FAST).width_m == pytest.approx(0.05, abs=1e-6)
        finally:
            gripper.disconnect()


def test_fast_stop_command_aborts_a_running_motion():
    with GripperFirmware() as firmware:
        link = RawLink(firmware.port)
        try:
            assert link.ask(Command.PREPOSITION, struct.pack("<Bff", 0, 10.0, 10.0))[0] == Status.E_CMD_PENDING
            assert link.ask(Command.FAST_STOP)[0] == Status.E_SUCCESS
            assert link.flags() & SystemFlag.FAST_STOP
            assert link.ask(Command.PREPOSITION, struct.pack("<Bff", 0, 50.0, 10.0))[0] == Status.E_ACCESS_DENIED
            assert link.ask(Command.ACK_FAST_STOP, b"no")[0] == Status.E_CMD_FORMAT_ERROR
            assert link.ask(Command.ACK_FAST_STOP, b"ack")[0] == Status.E_SUCCESS
            assert not link.flags() & SystemFlag.FAST_STOP
        finally:
            link.close()


# -- the firmware's strictness, on the wire ----------------------------------------------------
def test_grasp_finds_the_part_only_within_the_clamping_travel():
    with GripperFirmware(lambda: 0.04) as firmware:
        gripper = connect(firmware.port)
        try:
            assert gripper.grasp(0.0, FAST, force_n=10.0).state == "no_part"  # nominal 0 on a 40 mm part
            gripper.release(0.1, FAST)
            assert gripper.grasp(0.045, FAST, force_n=10.0).state == "holding"
        finally:
            gripper.disconnect()


def test_out_of_range_targets_are_clamped_by_the_device():
    with GripperFirmware(initial_width_m=0.05) as firmware:
        link = RawLink(firmware.port)
        try:
            assert link.ask(Command.PREPOSITION, struct.pack("<Bff", 0, 200.0, 400.0))[0] == Status.E_CMD_PENDING
            deadline = time.monotonic() + 5.0
            while link.flags() & SystemFlag.MOVING and time.monotonic() < deadline:
                time.sleep(0.01)
            status, data = link.ask(Command.GET_WIDTH, b"\x00\x00\x00")
            assert struct.unpack("<f", data)[0] == pytest.approx(110.0)
        finally:
            link.close()


def test_a_bad_checksum_is_answered():
    with GripperFirmware() as firmware:
        link = RawLink(firmware.port)
        try:
            frame = bytearray(encode_frame(Command.GET_WIDTH, b"\x00\x00\x00"))
            frame[-1] ^= 0xFF
            assert link.ask(Command.GET_WIDTH, frame=bytes(frame))[0] == Status.E_CHECKSUM_ERROR
        finally:
            link.close()


def test_configuration_commands_answer_like_the_device():
    with GripperFirmware() as firmware:
        link = RawLink(firmware.port)
        try:
            assert link.ask(Command.SET_ACCELERATION, struct.pack("<f", 500.0))[0] == Status.E_SUCCESS
            status, data = link.ask(Command.GET_ACCELERATION, b"\x00\x00\x00")
            assert struct.unpack("<f", data)[0] == pytest.approx(500.0)
            assert link.ask(Command.SET_FORCE_LIMIT, struct.pack("<f", 30.0))[0] == Status.E_SUCCESS
            status, data = link.ask(Command.GET_FORCE_LIMIT, b"\x00\x00\x00")
            assert struct.unpack("<f", data)[0] == pytest.approx(30.0)
            assert link.ask(Command.TARE_FORCE)[0] == Status.E_SUCCESS
            assert link.flags() & SystemFlag.REFERENCED
            assert link.ask(Command.DISCONNECT)[0] == Status.E_SUCCESS
        finally:
            link.close()
