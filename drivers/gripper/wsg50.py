"""WSG-50 client over a serial line (pyserial); the frame format is in ``protocol``.

A reader thread cuts incoming bytes into frames and files each under its command id, so a
``stop()`` from another thread can interrupt a running grasp. A request that gets no answer
(lost or corrupted on the line) is sent again; a motion command that was already started by
an earlier copy answers E_ALREADY_RUNNING, which the client treats as "wait for the end".
If the final status of a motion is lost, the system state's SF_MOVING tells when the fingers
stopped (the grasping state cannot: it stays IDLE while the gripper homes), and a stop sent
meanwhile makes the motion's outcome E_CMD_ABORTED. Targets are checked against the
gripper's limits before sending, because the device clamps them silently.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import queue
import struct
import threading
import time

import serial
from serial.tools import list_ports

from drivers import requires_connection
from drivers.gripper.base import Gripper
from drivers.gripper.protocol import (
    ACK_PAYLOAD,
    FAULT_FLAGS,
    Command,
    FrameParser,
    GraspingState,
    GripperError,
    GripperTimeoutError,
    Status,
    SystemFlag,
    encode_frame,
    split_response,
    status_name,
)
from msgs import GripperState, Header

_STATE_NAMES = {
    GraspingState.IDLE: "idle",
    GraspingState.GRASPING: "moving",
    GraspingState.RELEASING: "moving",
    GraspingState.POSITIONING: "moving",
    GraspingState.HOLDING: "holding",
    GraspingState.NO_PART_FOUND: "no_part",
    GraspingState.PART_LOST: "no_part",
    GraspingState.ERROR: "error",
}
# Outcome of a motion whose final status frame was lost, judged from where it ended.
_OUTCOME_OF_STATE = {
    GraspingState.IDLE: Status.E_SUCCESS,
    GraspingState.HOLDING: Status.E_SUCCESS,
    GraspingState.NO_PART_FOUND: Status.E_CMD_FAILED,
}
# How far (m) a finished move may end from its target before it counts as blocked.
_WIDTH_TOLERANCE_M = 0.5e-3


@dataclasses.dataclass
class WSG50Config:
    """Serial port and time-outs (s) of a WSG-50 in its serial (RS-232/USB) mode."""

    port: str = "/dev/ttyUSB0"
    baudrate: int = 115200
    response_timeout_s: float = 0.3
    motion_timeout_s: float = 10.0
    retries: int = 4
    frame_id: str = "tcp"
    # The gripper's limits (WSG 50-110 data sheet); the device clamps what lies beyond them.
    max_width_m: float = 0.110
    max_speed_m_s: float = 0.42
    max_force_n: float = 80.0


class WSG50Gripper(Gripper):
    """Commands take and return SI units; the wire carries mm, mm/s and N."""

    def __init__(self, config: WSG50Config) -> None:
        self.config = config
        self._link: serial.Serial | None = None
        self._parser = FrameParser()
        self._replies: dict[int, queue.Queue[tuple[int, bytes]]] = collections.defaultdict(queue.Queue)
        self._command_locks: dict[int, threading.Lock] = collections.defaultdict(threading.Lock)
        self._table_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._closing = threading.Event()
        self._link_error: str | None = None
        self._reader: threading.Thread | None = None
        self._sequence = itertools.count(1)  # next() is atomic: commands run in several threads
        self._stops = 0  # stops sent so far: a motion that saw one go out was aborted

    # -- life cycle ------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port and check that a WSG answers on it."""
        try:
            self._link = serial.Serial(self.config.port, self.config.baudrate, timeout=0.05)
        except serial.SerialException as exc:
            found = [port.device for port in list_ports.comports()] or "none"
            raise GripperError(
                f"cannot open the gripper's serial port {self.config.port}: {exc}. "
                f"Serial ports found: {found}; set `port` to the WSG's."
            ) from exc
        self._closing.clear()
        self._reader = threading.Thread(target=self._read_loop, name="wsg50-reader", daemon=True)
        self._reader.start()
        try:
            self._grasping_state()
        except GripperError:
            self.disconnect()
            raise

    def disconnect(self) -> None:
        self._closing.set()
        if self._reader is not None:
            self._reader.join()
            self._reader = None
        if self._link is not None:
            self._link.close()
            self._link = None

    @property
    def is_connected(self) -> bool:
        return self._link is not None

    @property
    def discarded_bytes(self) -> int:
        """Bytes the client skipped as garbage or corrupted frames since it was made."""
        return self._parser.discarded_bytes

    # -- commands --------------------------------------------------------------------------
    @requires_connection
    def read(self) -> GripperState:
        """Current opening, grasping force and grasping state."""
        return self._state(Status.E_SUCCESS)

    @requires_connection
    def preflight(self) -> None:
        """Refuse a gripper that answers but cannot move: in FAST STOP, faulted, not
        referenced (every motion would get E_ACCESS_DENIED; system state 0x40), or in the
        grasping state ERROR (0x41). GripperError with the fix."""
        flags = self._system_flags()
        if flags & SystemFlag.FAST_STOP:
            raise GripperError(
                "the gripper is in FAST STOP",
                "clear its cause, then `dtx hw acknowledge LAUNCHFILE` (or /gripper/command action acknowledge)",
            )
        if flags & FAULT_FLAGS:
            raise GripperError(
                f"the gripper reports a fault ({SystemFlag(flags & FAULT_FLAGS)!r})",
                "see its web interface, let it cool or check the power, then power-cycle it",
            )
        if not flags & SystemFlag.REFERENCED:
            raise GripperError(
                "the gripper is not referenced",
                "home it: `dtx hw acknowledge LAUNCHFILE` (or /gripper/command action home)",
            )
        if self._grasping_state() == GraspingState.ERROR:
            raise GripperError(
                "the gripper's grasping state is ERROR",
                "see its web interface for the cause, then `dtx hw acknowledge LAUNCHFILE`",
            )

    @requires_connection
    def acknowledge(self) -> GripperState:
        """Acknowledge a FAST STOP (0x24 "ack") once its cause is cleared, so motions run again;
        nothing is sent when the gripper is not in FAST STOP."""
        status: int = Status.E_SUCCESS
        if self._system_flags() & SystemFlag.FAST_STOP:
            status, _ = self._request(Command.ACK_FAST_STOP, ACK_PAYLOAD)
        if status != Status.E_SUCCESS:
            raise GripperError(f"acknowledging the fast stop failed: {status_name(status)}")
        return self._state(status)

    @requires_connection
    def referenced(self) -> bool:
        """Whether the gripper has been homed since it powered up."""
        return bool(self._system_flags() & SystemFlag.REFERENCED)

    @requires_connection
    def home(self) -> GripperState:
        """Reference the fingers (they open fully); needed after the gripper powers up.
        Returns when homing's own final status comes (the grasping state says IDLE throughout)."""
        status = self._motion(Command.HOMING, b"\x00")
        if status != Status.E_SUCCESS:
            raise GripperError(
                f"homing failed: {status_name(status)}; clear the fingers' path "
                "and check the gripper's web interface for a fault"
            )
        return self._state(status)

    @requires_connection
    def move(self, width_m: float, speed_m_s: float) -> GripperState:
        """Move the fingers to ``width_m`` at ``speed_m_s`` without force control."""
        self._check_range("move", width_m, speed_m_s)
        payload = struct.pack("<Bff", 0x02, width_m * 1e3, speed_m_s * 1e3)  # stop on block
        status = self._motion(Command.PREPOSITION, payload)
        self._raise_on_refusal(status, "move")
        state = self._state(status)
        if status == Status.E_AXIS_BLOCKED or (
            status == Status.E_SUCCESS and abs(state.width_m - width_m) > _WIDTH_TOLERANCE_M
        ):
            raise GripperError(
                f"move to {width_m * 1e3:.1f} mm blocked at {state.width_m * 1e3:.1f} mm: "
                "something is between the fingers; use grasp() to close on it"
            )
        if status != Status.E_SUCCESS:
            raise GripperError(f"move to {width_m * 1e3:.1f} mm failed: {status_name(status)}")
        return state

    @requires_connection
    def grasp(self, width_m: float, speed_m_s: float, force_n: float) -> GripperState:
        """Close towards ``width_m`` until contact, then hold at ``force_n``.

        ``width_m`` is the part's nominal width: a WSG looks for the part only within its
        clamping travel (set on the web interface) around it, so pass the expected width.
        Returns the state: ``holding`` with the object's width, or ``no_part`` if the fingers
        found nothing in that window.
        """
        self._check_range("grasp", width_m, speed_m_s)
        self.set_force_limit(force_n)
        status = self._motion(Command.GRASP, struct.pack("<ff", width_m * 1e3, speed_m_s * 1e3))
        self._raise_on_refusal(status, "grasp")
        state = self._state(status)
        if status == Status.E_SUCCESS or state.state == "no_part":
            return state
        raise GripperError(f"grasp failed: {status_name(status)} (gripper state {state.state})")

    @requires_connection
    def release(self, width_m: float, speed_m_s: float) -> GripperState:
        """Open to ``width_m`` (wider than now) at ``speed_m_s``, letting go of the part."""
        self._check_range("release", width_m, speed_m_s)
        status = self._motion(Command.RELEASE, struct.pack("<ff", width_m * 1e3, speed_m_s * 1e3))
        self._raise_on_refusal(status, "release")
        if status != Status.E_SUCCESS:
            raise GripperError(f"release failed: {status_name(status)}")
        return self._state(status)

    @requires_connection
    def stop(self) -> GripperState:
        """Stop the fingers where they are; a running command ends with E_CMD_ABORTED (and
        is reported so even if its final answer is lost). The gripper lets go of a held part."""
        self._stops += 1
        status, _ = self._request(Command.STOP, b"")
        if status != Status.E_SUCCESS:
            raise GripperError(f"stop failed: {status_name(status)}")
        return self._state(status)

    @requires_connection
    def set_force_limit(self, force_n: float) -> None:
        """Grasping force (N) the next grasp holds with."""
        if not 0.0 < force_n <= self.config.max_force_n:
            raise GripperError(
                f"force limit {force_n} N is outside the gripper's range (up to {self.config.max_force_n} N)"
            )
        status, _ = self._request(Command.SET_FORCE_LIMIT, struct.pack("<f", force_n))
        if status == Status.E_RANGE_ERROR:
            raise GripperError(f"force limit {force_n} N is outside the gripper's range")
        if status != Status.E_SUCCESS:
            raise GripperError(f"setting the force limit failed: {status_name(status)}")

    # -- state -----------------------------------------------------------------------------
    def _state(self, status: int) -> GripperState:
        header = Header.now(self.config.frame_id)
        header.seq = next(self._sequence)
        width_m = self._value(Command.GET_WIDTH) * 1e-3
        force_n = self._value(Command.GET_FORCE)
        name = _STATE_NAMES[self._grasping_state()]
        if name == "idle" and self._system_flags() & SystemFlag.MOVING:
            name = "moving"  # homing: the grasping state has no name for it
        return GripperState(header=header, width_m=width_m, force_n=force_n, state=name, status_code=int(status))

    def _system_flags(self) -> SystemFlag:
        status, data = self._request(Command.GET_SYSTEM_STATE, b"\x00\x00\x00")
        if status != Status.E_SUCCESS or len(data) != 4:
            raise GripperError(f"reading the system state failed: {status_name(status)}")
        return SystemFlag(struct.unpack("<I", data)[0])

    def _moving(self) -> bool:
        return bool(self._system_flags() & SystemFlag.MOVING)

    def _value(self, command: Command) -> float:
        # Payload 0,0,0: no automatic updates, answer once.
        status, data = self._request(command, b"\x00\x00\x00")
        if status != Status.E_SUCCESS or len(data) != 4:
            raise GripperError(f"{command.name} failed: {status_name(status)}")
        return struct.unpack("<f", data)[0]

    def _grasping_state(self) -> GraspingState:
        status, data = self._request(Command.GET_GRASPING_STATE, b"\x00\x00\x00")
        if status != Status.E_SUCCESS or len(data) != 1 or data[0] not in GraspingState._value2member_map_:
            raise GripperError(f"reading the grasping state failed: {status_name(status)}")
        return GraspingState(data[0])

    def _check_range(self, what: str, width_m: float, speed_m_s: float) -> None:
        """Refuse what the device would clamp without saying so (nothing is sent)."""
        config = self.config
        if not (0.0 <= width_m <= config.max_width_m and 0.0 < speed_m_s <= config.max_speed_m_s):
            raise GripperError(
                f"{what} to {width_m * 1e3:.1f} mm at {speed_m_s * 1e3:.0f} mm/s is outside "
                f"the gripper's range (width 0-{config.max_width_m * 1e3:.0f} mm, speed up "
                f"to {config.max_speed_m_s * 1e3:.0f} mm/s)"
            )

    def _raise_on_refusal(self, status: int, what: str) -> None:
        if status == Status.E_RANGE_ERROR:
            raise GripperError(f"{what} refused (E_RANGE_ERROR): grasp closes, release opens")
        if status == Status.E_ACCESS_DENIED:
            raise GripperError(
                f"{what} refused (E_ACCESS_DENIED): the gripper is in FAST STOP or not referenced",
                "acknowledge the fast stop or home the gripper (`dtx hw acknowledge LAUNCHFILE`)",
            )

    # -- request / response ----------------------------------------------------------------
    def _motion(self, command: Command, payload: bytes) -> int:
        """Run a motion command to its end; return its final status code."""
        with self._lock_for(command):
            replies = self._queue_for(command)
            stops_before = self._stops
            status, _ = self._send_until_answered(command, payload, replies, motion=True)
            if status not in (Status.E_CMD_PENDING, Status.E_ALREADY_RUNNING):
                return status
            status = self._await_final(command, replies, stops_before)
            # A command sent again after its answer was lost can run twice: the first run's
            # final reply then comes while the second still moves, so wait for the second's.
            while self._moving():
                status = self._await_final(command, replies, stops_before)
            return status

    def _request(self, command: Command, payload: bytes) -> tuple[int, bytes]:
        """Send a command that answers at once; return (status, data)."""
        with self._lock_for(command):
            return self._send_until_answered(command, payload, self._queue_for(command), motion=False)

    def _send_until_answered(
        self, command: Command, payload: bytes, replies: queue.Queue[tuple[int, bytes]], motion: bool
    ) -> tuple[int, bytes]:
        while not replies.empty():  # answers that came after an earlier time-out
            replies.get_nowait()
        frame = encode_frame(command, payload)
        for attempt in range(self.config.retries + 1):
            self._write(frame)
            reply = self._wait(replies, self.config.response_timeout_s)
            if reply is None or reply[0] == Status.E_CHECKSUM_ERROR:
                continue
            if motion and attempt == 0 and reply[0] == Status.E_ALREADY_RUNNING:
                raise GripperError(f"{command.name} refused: another motion is running; stop() it first")
            return reply
        raise GripperTimeoutError(
            f"no answer to {command.name} from the gripper on {self.config.port} after "
            f"{self.config.retries + 1} tries of {self.config.response_timeout_s} s: check that it is "
            f"powered, the cable, and the baud rate ({self.config.baudrate}; the WSG default is 115200)"
        )

    def _await_final(self, command: Command, replies: queue.Queue[tuple[int, bytes]], stops_before: int) -> int:
        """The motion's final status; after a silence, ask SF_MOVING whether it still runs.
        Stopped without its final answer: E_CMD_ABORTED if a stop went out meanwhile (a
        stopped grasp also ends IDLE), else judged from the grasping state."""
        deadline = time.monotonic() + self.config.motion_timeout_s
        while time.monotonic() < deadline:
            reply = self._wait(replies, self.config.response_timeout_s)
            if reply is not None and reply[0] != Status.E_CMD_PENDING:
                return reply[0]
            if reply is None and not self._moving():
                late = self._wait(replies, 0.0)  # the answer may have come with the stop
                if late is not None and late[0] != Status.E_CMD_PENDING:
                    return late[0]
                if self._stops != stops_before:
                    return Status.E_CMD_ABORTED
                return _OUTCOME_OF_STATE.get(self._grasping_state(), Status.E_CMD_FAILED)
        raise GripperTimeoutError(
            f"{command.name} did not finish within {self.config.motion_timeout_s} s; "
            "the fingers may still be moving: call stop()"
        )

    def _wait(self, replies: queue.Queue[tuple[int, bytes]], timeout_s: float) -> tuple[int, bytes] | None:
        try:
            return replies.get(timeout=timeout_s)
        except queue.Empty:
            if self._link_error is not None:
                raise GripperError(f"serial link to the gripper lost: {self._link_error}") from None
            return None

    def _lock_for(self, command: Command) -> threading.Lock:
        with self._table_lock:
            return self._command_locks[command]

    def _queue_for(self, command: Command) -> queue.Queue[tuple[int, bytes]]:
        with self._table_lock:
            return self._replies[command]

    def _write(self, frame: bytes) -> None:
        if self._link is None:  # disconnect() ran while a command was under way
            raise self.NOT_CONNECTED("the gripper was disconnected during the command")
        if self._link_error is not None:
            raise GripperError(f"serial link to the gripper lost: {self._link_error}")
        with self._write_lock:
            self._link.write(frame)

    def _read_loop(self) -> None:
        assert self._link is not None
        while not self._closing.is_set():
            try:
                data = self._link.read(max(1, self._link.in_waiting))
            except (serial.SerialException, OSError) as exc:
                self._link_error = str(exc)
                return
            for command_id, payload in self._parser.feed(data):
                try:
                    reply = split_response(payload)
                except GripperError:
                    continue  # a frame without a status code cannot be an answer
                with self._table_lock:
                    self._replies[command_id].put(reply)
