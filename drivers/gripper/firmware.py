"""A WSG-50 firmware simulator on a pseudo-terminal, speaking the real command protocol.

The client opens ``firmware.port`` like the gripper's serial device. Fingers move at the
commanded speed in real time; a grasp stops where ``contact_width_m()`` says an object is
(None: nothing between the fingers) and then holds at the force limit. Motion commands
answer E_CMD_PENDING at once and the final status when the fingers stop, as the device
does (wsg50-ros-pkg: wsg_50_driver/src/functions.cpp, homing()/move()/grasp() wait for the
second answer). A second motion command while one runs gets E_ALREADY_RUNNING.

It is as strict as the public model of the device; :class:`Strictness` selects each
behaviour (all strict by default, the tests' setting), so a test can show what a lenient
simulator hid. Where the public sources leave a byte-level detail open, the simulator keeps
what it did before and its docstring says so.
"""

from __future__ import annotations

import dataclasses
import os
import select
import struct
import threading
import time
import tty
from typing import Callable

from drivers.gripper.protocol import (
    ACK_PAYLOAD,
    Command,
    FrameParser,
    GraspingState,
    Status,
    SystemFlag,
    encode_response,
)

# Longest the loop sleeps with nothing to do; bounds how late close() is noticed.
_IDLE_WAIT_S = 0.05
# Slowest finger speed the device runs; a lower commanded speed is raised to it.
_MIN_SPEED_M_S = 0.005


@dataclasses.dataclass(frozen=True)
class Strictness:
    """Which behaviours of the public device model the simulator shows (True: as the device).

    - ``idle_while_homing``: the grasping-state model has no homing state, so a gripper reports
      IDLE while it references (Weiss command set as wsg50-ros-pkg implements it: the state
      names in functions.cpp getGraspingState() are IDLE, GRIPPING, NO PART FOUND, PART LOST,
      HOLDING, RELEASING, POSITIONING, ERROR). Lenient: POSITIONING.
    - ``clamping_travel_m``: a grasp looks for the part only within this travel around the
      nominal width it is given (the web interface's clamping travel; wsg50-ros-pkg:
      functions.cpp grasp(objWidth, speed) sends the part's width). None: contact anywhere
      on the way counts. The 10 mm default is this simulator's choice, not a documented
      factory value.
    - ``stop_releases``: STOP ends in IDLE and drops the grasping force, also while HOLDING
      (wsg50-ros-pkg: functions.cpp stop(); the command set's state model). Lenient: a held
      part stays HOLDING with its force.
    - ``clamp_out_of_range``: widths beyond the stroke and speeds beyond the limits are
      clamped by the device and the command runs. Lenient: E_RANGE_ERROR.
    - ``answer_bad_checksum``: a frame with a wrong CRC is answered E_CHECKSUM_ERROR
      (wsg50-ros-pkg: common/functions.cpp msg_receive() checks the CRC; the status list has
      E_CHECKSUM_ERROR). Lenient: dropped unanswered.
    - ``referenced``: the gripper starts referenced. False: it starts as after power-up
      without automatic homing, and motion commands other than homing get E_ACCESS_DENIED.
    """

    idle_while_homing: bool = True
    clamping_travel_m: float | None = 0.010
    stop_releases: bool = True
    clamp_out_of_range: bool = True
    answer_bad_checksum: bool = True
    referenced: bool = True


LENIENT = Strictness(
    idle_while_homing=False,
    clamping_travel_m=None,
    stop_releases=False,
    clamp_out_of_range=False,
    answer_bad_checksum=False,
)


@dataclasses.dataclass
class _Motion:
    command: Command
    start_width_m: float
    end_width_m: float
    speed_m_s: float
    start_time_s: float
    final_status: Status
    final_state: GraspingState
    time_scale: float = 1.0

    def duration_s(self) -> float:
        return self.time_scale * abs(self.end_width_m - self.start_width_m) / self.speed_m_s

    def width_at(self, now_s: float) -> float:
        fraction = min(1.0, (now_s - self.start_time_s) / max(self.duration_s(), 1e-9))
        return self.start_width_m + fraction * (self.end_width_m - self.start_width_m)


class GripperFirmware:
    """Simulated WSG-50 behind a pty; use as a context manager or call start()/close()."""

    def __init__(
        self,
        contact_width_m: Callable[[], float | None] = lambda: None,
        *,
        max_width_m: float = 0.110,
        max_speed_m_s: float = 0.42,
        max_force_n: float = 80.0,
        initial_width_m: float = 0.110,
        time_scale: float = 1.0,
        homing_speed_m_s: float = 0.1,
        strictness: Strictness = Strictness(),
    ) -> None:
        """Limits as the WSG 50-110 data sheet: stroke 110 mm, 420 mm/s, 80 N. ``time_scale``
        stretches finger motions in wall time (0: instantaneous, for fast simulated sessions).
        ``homing_speed_m_s``: referencing runs slower than a move (the value is this
        simulator's choice)."""
        if not 0.0 <= time_scale <= 100.0:
            raise ValueError(f"time_scale {time_scale} outside [0, 100]")
        self.time_scale = time_scale
        self.strictness = strictness
        self._contact_width_m = contact_width_m
        self.max_width_m = max_width_m
        self.max_speed_m_s = max_speed_m_s
        self.max_force_n = max_force_n
        self.homing_speed_m_s = homing_speed_m_s
        self._width_m = initial_width_m
        self._force_limit_n = max_force_n
        self._acceleration_mm_s2 = 1000.0
        self._holding_force_n = 0.0
        self._state = GraspingState.IDLE
        self._flags = SystemFlag.REFERENCED if strictness.referenced else SystemFlag(0)
        self._motion: _Motion | None = None
        self._parser = FrameParser(self._bad_checksum if strictness.answer_bad_checksum else None)
        self._lock = threading.Lock()  # fast_stop() comes from another thread than the loop
        self._master, self._slave = os.openpty()
        # Raw mode: no echo and no newline translation, or the protocol's bytes get mangled.
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="wsg50-firmware", daemon=True)

    def start(self) -> "GripperFirmware":
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the firmware thread and release the pty (again: nothing happens)."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join()
        os.close(self._master)
        os.close(self._slave)

    def __enter__(self) -> "GripperFirmware":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def moving(self) -> bool:
        """Whether the fingers are in motion now (what SF_MOVING reports)."""
        return self._motion is not None

    def trip_fast_stop(self) -> None:
        """An error condition (or the FAST STOP command) stops the fingers at once and locks
        the gripper: every motion gets E_ACCESS_DENIED until 0x24 acknowledges it (Weiss
        command set: SF_FAST_STOP; wsg50-ros-pkg: functions.cpp ack_fault()). The grasping
        state reads ERROR meanwhile (this simulator's choice: the sources do not say)."""
        with self._lock:
            self._trip_fast_stop()

    # -- the loop -------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stopping.is_set():
            wait = _IDLE_WAIT_S
            if self._motion is not None:
                remaining = self._motion.start_time_s + self._motion.duration_s() - time.monotonic()
                wait = max(0.0, min(wait, remaining))
            readable, _, _ = select.select([self._master], [], [], wait)
            with self._lock:
                if readable:
                    for command_id, payload in self._parser.feed(os.read(self._master, 4096)):
                        self._handle(command_id, payload)
                self._finish_motion_if_done()

    def _send(self, command_id: int, status: Status, data: bytes = b"") -> None:
        os.write(self._master, encode_response(command_id, status, data))

    def _bad_checksum(self, command_id: int) -> None:
        self._send(command_id, Status.E_CHECKSUM_ERROR)

    def _now_width_m(self) -> float:
        if self._motion is None:
            return self._width_m
        return self._motion.width_at(time.monotonic())

    def _finish_motion_if_done(self) -> None:
        motion = self._motion
        if motion is None or time.monotonic() < motion.start_time_s + motion.duration_s():
            return
        if motion.command == Command.HOMING:
            self._flags |= SystemFlag.REFERENCED
        self._end_motion(motion.end_width_m, motion.final_status, motion.final_state)

    def _end_motion(self, width_m: float, status: Status, state: GraspingState) -> None:
        assert self._motion is not None
        command = self._motion.command
        self._motion = None
        self._width_m = width_m
        self._state = state
        self._holding_force_n = self._force_limit_n if state == GraspingState.HOLDING else 0.0
        self._send(command, status)

    # -- commands -------------------------------------------------------------------------
    def _handle(self, command_id: int, payload: bytes) -> None:
        handlers = {
            Command.HOMING: self._homing,
            Command.PREPOSITION: self._preposition,
            Command.GRASP: self._grasp,
            Command.RELEASE: self._release,
            Command.STOP: self._stop,
            Command.SET_FORCE_LIMIT: self._set_force_limit,
            Command.FAST_STOP: self._fast_stop,
            Command.ACK_FAST_STOP: self._acknowledge,
            Command.SET_ACCELERATION: self._set_acceleration,
            Command.DISCONNECT: self._disconnect,
            Command.TARE_FORCE: self._tare_force,
        }
        getters = {
            Command.GET_WIDTH: lambda: self._now_width_m() * 1e3,
            Command.GET_SPEED: lambda: 0.0 if self._motion is None else self._motion.speed_m_s * 1e3,
            Command.GET_FORCE: lambda: self._holding_force_n,
            Command.GET_FORCE_LIMIT: lambda: self._force_limit_n,
            Command.GET_ACCELERATION: lambda: self._acceleration_mm_s2,
        }
        if command_id in getters:
            self._send(command_id, Status.E_SUCCESS, struct.pack("<f", getters[Command(command_id)]()))
        elif command_id == Command.GET_GRASPING_STATE:
            self._send(command_id, Status.E_SUCCESS, bytes([self._state]))
        elif command_id == Command.GET_SYSTEM_STATE:
            flags = self._flags | (SystemFlag.MOVING if self._motion is not None else SystemFlag(0))
            self._send(command_id, Status.E_SUCCESS, struct.pack("<I", int(flags)))
        elif command_id in handlers:
            handlers[Command(command_id)](payload)
        else:
            self._send(command_id, Status.E_CMD_UNKNOWN)

    def _start_motion(
        self,
        command: Command,
        target_m: float,
        speed_m_s: float,
        moving_state: GraspingState,
        final_status: Status,
        final_state: GraspingState,
    ) -> None:
        self._motion = _Motion(
            command, self._width_m, target_m, speed_m_s, time.monotonic(), final_status, final_state, self.time_scale
        )
        self._state = moving_state
        self._holding_force_n = 0.0
        self._flags &= ~SystemFlag.AXIS_STOPPED
        self._send(command, Status.E_CMD_PENDING)

    def _refuse_motion(self, command: Command, payload: bytes, expected_bytes: int) -> bool:
        """Answer and return True when the motion command cannot start: in FAST STOP, or not
        referenced (homing excepted), E_ACCESS_DENIED (Weiss command set; the public homing
        handler checks SF_FAST_STOP first, then SF_MOVING, then the format)."""
        if self._flags & SystemFlag.FAST_STOP or (
            command != Command.HOMING and not self._flags & SystemFlag.REFERENCED
        ):
            self._send(command, Status.E_ACCESS_DENIED)
        elif self._motion is not None:
            self._send(command, Status.E_ALREADY_RUNNING)
        elif len(payload) != expected_bytes:
            self._send(command, Status.E_CMD_FORMAT_ERROR)
        else:
            return False
        return True

    def _limited(self, command: Command, width_m: float, speed_m_s: float) -> tuple[float, float] | None:
        """(width, speed) the device runs, or None after answering E_RANGE_ERROR (lenient)."""
        if 0.0 <= width_m <= self.max_width_m and _MIN_SPEED_M_S <= speed_m_s <= self.max_speed_m_s:
            return width_m, speed_m_s
        if not self.strictness.clamp_out_of_range:
            self._send(command, Status.E_RANGE_ERROR)
            return None
        return (min(max(width_m, 0.0), self.max_width_m), min(max(speed_m_s, _MIN_SPEED_M_S), self.max_speed_m_s))

    def _contact_between(self, from_m: float, to_m: float) -> float | None:
        """Where closing from ``from_m`` towards ``to_m`` touches the object, if it does."""
        contact = self._contact_width_m()
        if contact is not None and to_m <= contact <= from_m:
            return contact
        return None

    def _homing(self, payload: bytes) -> None:
        """Reference the fingers: direction 2 against the closed end, 0 (default) and 1 open.
        The grasping state stays IDLE while homing (``idle_while_homing``); only the system
        state's SF_MOVING and the final answer tell that it runs."""
        if self._refuse_motion(Command.HOMING, payload, 1):
            return
        target = 0.0 if payload[0] == 2 else self.max_width_m
        moving = GraspingState.IDLE if self.strictness.idle_while_homing else GraspingState.POSITIONING
        self._start_motion(Command.HOMING, target, self.homing_speed_m_s, moving, Status.E_SUCCESS, GraspingState.IDLE)

    def _preposition(self, payload: bytes) -> None:
        """Move without force control; flag 0x01 makes the width relative. An object in the way
        stops the fingers with E_AXIS_BLOCKED (what the existing simulator did; stop-on-block
        is flag 0x02 in wsg50-ros-pkg: functions.cpp move())."""
        if self._refuse_motion(Command.PREPOSITION, payload, 9):
            return
        flags, width_mm, speed_mm_s = struct.unpack("<Bff", payload)
        target = width_mm * 1e-3 + (self._width_m if flags & 0x01 else 0.0)
        limited = self._limited(Command.PREPOSITION, target, speed_mm_s * 1e-3)
        if limited is None:
            return
        target, speed = limited
        contact = self._contact_between(self._width_m, target)
        if contact is None:
            self._start_motion(
                Command.PREPOSITION, target, speed, GraspingState.POSITIONING, Status.E_SUCCESS, GraspingState.IDLE
            )
        else:
            self._start_motion(
                Command.PREPOSITION,
                contact,
                speed,
                GraspingState.POSITIONING,
                Status.E_AXIS_BLOCKED,
                GraspingState.IDLE,
            )

    def _grasp(self, payload: bytes) -> None:
        """Close on a part of nominal width ``width`` (wsg50-ros-pkg: functions.cpp
        grasp(objWidth, speed)). With a clamping travel the device looks for the part only in
        [width - travel, width + travel]: the fingers close to width - travel and a part met
        there is held; nothing met ends NO PART FOUND; a part met before the window (wider
        than width + travel) stops the fingers and also ends NO PART FOUND with E_CMD_FAILED
        (the sources do not say which status; this is the simulator's choice)."""
        if self._refuse_motion(Command.GRASP, payload, 8):
            return
        width_mm, speed_mm_s = struct.unpack("<ff", payload)
        limited = self._limited(Command.GRASP, width_mm * 1e-3, speed_mm_s * 1e-3)
        if limited is None:
            return
        nominal, speed = limited
        travel = self.strictness.clamping_travel_m
        target = nominal if travel is None else max(0.0, nominal - travel)
        if target >= self._width_m:
            self._send(Command.GRASP, Status.E_RANGE_ERROR)  # a grasp must close
            return
        contact = self._contact_between(self._width_m, target)
        if contact is None:
            self._start_motion(
                Command.GRASP, target, speed, GraspingState.GRASPING, Status.E_CMD_FAILED, GraspingState.NO_PART_FOUND
            )
        elif travel is not None and contact > nominal + travel:
            self._start_motion(
                Command.GRASP, contact, speed, GraspingState.GRASPING, Status.E_CMD_FAILED, GraspingState.NO_PART_FOUND
            )
        else:
            self._start_motion(
                Command.GRASP, contact, speed, GraspingState.GRASPING, Status.E_SUCCESS, GraspingState.HOLDING
            )

    def _release(self, payload: bytes) -> None:
        """Open to ``width``, which must be wider than now (E_RANGE_ERROR otherwise, as the
        existing simulator did)."""
        if self._refuse_motion(Command.RELEASE, payload, 8):
            return
        width_mm, speed_mm_s = struct.unpack("<ff", payload)
        limited = self._limited(Command.RELEASE, width_mm * 1e-3, speed_mm_s * 1e-3)
        if limited is None:
            return
        target, speed = limited
        if target < self._width_m:
            self._send(Command.RELEASE, Status.E_RANGE_ERROR)
            return
        self._start_motion(
            Command.RELEASE, target, speed, GraspingState.RELEASING, Status.E_SUCCESS, GraspingState.IDLE
        )

    def _stop(self, payload: bytes) -> None:
        """Stop the fingers: a running command ends E_CMD_ABORTED, then STOP answers E_SUCCESS;
        SF_AXIS_STOPPED is set until the next motion. Strict: the grasping state becomes IDLE
        and the force drops, also when a part was held (``stop_releases``)."""
        if payload:
            self._send(Command.STOP, Status.E_NO_PARAM_EXPECTED)
            return
        if self._motion is not None:
            self._end_motion(self._now_width_m(), Status.E_CMD_ABORTED, GraspingState.IDLE)
        elif self.strictness.stop_releases and self._state == GraspingState.HOLDING:
            self._state = GraspingState.IDLE
            self._holding_force_n = 0.0
        self._flags |= SystemFlag.AXIS_STOPPED
        self._send(Command.STOP, Status.E_SUCCESS)

    def _fast_stop(self, payload: bytes) -> None:
        """0x23 FAST STOP: see :meth:`trip_fast_stop`."""
        self._trip_fast_stop()
        self._send(Command.FAST_STOP, Status.E_SUCCESS)

    def _trip_fast_stop(self) -> None:
        if self._motion is not None:
            self._end_motion(self._now_width_m(), Status.E_CMD_ABORTED, GraspingState.ERROR)
        self._state = GraspingState.ERROR
        self._holding_force_n = 0.0
        self._flags |= SystemFlag.FAST_STOP

    def _acknowledge(self, payload: bytes) -> None:
        """0x24 acknowledges a fast stop; its payload is "ack" (wsg50-ros-pkg: functions.cpp
        ack_fault()), anything else E_CMD_FORMAT_ERROR (simulator's choice)."""
        if payload != ACK_PAYLOAD:
            self._send(Command.ACK_FAST_STOP, Status.E_CMD_FORMAT_ERROR)
            return
        if self._flags & SystemFlag.FAST_STOP:
            self._flags &= ~SystemFlag.FAST_STOP
            self._state = GraspingState.IDLE
        self._send(Command.ACK_FAST_STOP, Status.E_SUCCESS)

    def _set_force_limit(self, payload: bytes) -> None:
        if len(payload) != 4:
            self._send(Command.SET_FORCE_LIMIT, Status.E_CMD_FORMAT_ERROR)
            return
        (force_n,) = struct.unpack("<f", payload)
        if not 0.0 < force_n <= self.max_force_n:
            if not self.strictness.clamp_out_of_range:
                self._send(Command.SET_FORCE_LIMIT, Status.E_RANGE_ERROR)
                return
            force_n = min(max(force_n, 0.0), self.max_force_n)
        self._force_limit_n = force_n
        self._send(Command.SET_FORCE_LIMIT, Status.E_SUCCESS)

    def _set_acceleration(self, payload: bytes) -> None:
        """0x30: finger acceleration (mm/s², float); kept and read back by 0x31, motion
        timing does not use it (simulator's simplification)."""
        if len(payload) != 4:
            self._send(Command.SET_ACCELERATION, Status.E_CMD_FORMAT_ERROR)
            return
        self._acceleration_mm_s2 = struct.unpack("<f", payload)[0]
        self._send(Command.SET_ACCELERATION, Status.E_SUCCESS)

    def _tare_force(self, payload: bytes) -> None:
        """0x38: zero the force sensor; nothing to do without one, answered E_SUCCESS."""
        self._send(Command.TARE_FORCE, Status.E_SUCCESS)

    def _disconnect(self, payload: bytes) -> None:
        """0x07: the client announces it disconnects; answered E_SUCCESS (wsg50-ros-pkg:
        common/cmd.c cmd_disconnect() sends it before closing)."""
        self._send(Command.DISCONNECT, Status.E_SUCCESS)
