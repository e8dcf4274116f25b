"""A WSG-50 firmware simulator on a pseudo-terminal, speaking the real command protocol.

The client opens ``firmware.port`` like the gripper's serial device. Fingers move at the
commanded speed in real time; a grasp stops where ``contact_width_m()`` says an object is
(None: nothing between the fingers) and then holds at the force limit. Motion commands
answer E_CMD_PENDING at once and the final status when the fingers stop, as the device
does. Frames with a wrong CRC are dropped unanswered: the client's retry covers them.
A second motion command while one runs gets E_ALREADY_RUNNING.
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

from drivers.gripper.protocol import (Command, FrameParser, GraspingState, Status,
                                      encode_response)

# Longest the loop sleeps with nothing to do; bounds how late close() is noticed.
_IDLE_WAIT_S = 0.05


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

    def __init__(self, contact_width_m: Callable[[], float | None] = lambda: None, *,
                 max_width_m: float = 0.110, max_speed_m_s: float = 0.42,
                 max_force_n: float = 80.0, initial_width_m: float = 0.110, time_scale: float = 1.0) -> None:
        """Limits as the WSG 50-110 data sheet: stroke 110 mm, 420 mm/s, 80 N. ``time_scale``
        stretches finger motions in wall time (0: instantaneous, for fast simulated sessions)."""
        if not 0.0 <= time_scale <= 100.0:
            raise ValueError(f"time_scale {time_scale} outside [0, 100]")
        self.time_scale = time_scale
        self._contact_width_m = contact_width_m
        self.max_width_m = max_width_m
        self.max_speed_m_s = max_speed_m_s
        self.max_force_n = max_force_n
        self._width_m = initial_width_m
        self._force_limit_n = max_force_n
        self._holding_force_n = 0.0
        self._state = GraspingState.IDLE
        self._motion: _Motion | None = None
        self._parser = FrameParser()
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

    # -- the loop -------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stopping.is_set():
            wait = _IDLE_WAIT_S
            if self._motion is not None:
                remaining = self._motion.start_time_s + self._motion.duration_s() - time.monotonic()
                wait = max(0.0, min(wait, remaining))
            readable, _, _ = select.select([self._master], [], [], wait)
            if readable:
                for command_id, payload in self._parser.feed(os.read(self._master, 4096)):
                    self._handle(command_id, payload)
            self._finish_motion_if_done()

    def _send(self, command_id: int, status: Status, data: bytes = b"") -> None:
        os.write(self._master, encode_response(command_id, status, data))

    def _now_width_m(self) -> float:
        if self._motion is None:
            return self._width_m
        return self._motion.width_at(time.monotonic())

    def _finish_motion_if_done(self) -> None:
        motion = self._motion
        if motion is None or time.monotonic() < motion.start_time_s + motion.duration_s():
            return
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
            Command.HOMING: self._homing, Command.PREPOSITION: self._preposition,
            Command.GRASP: self._grasp, Command.RELEASE: self._release,
            Command.STOP: self._stop, Command.SET_FORCE_LIMIT: self._set_force_limit,
        }
        if command_id in (Command.GET_WIDTH, Command.GET_SPEED, Command.GET_FORCE):
            self._send(command_id, Status.E_SUCCESS, struct.pack("<f", self._measured(command_id)))
        elif command_id == Command.GET_GRASPING_STATE:
            self._send(command_id, Status.E_SUCCESS, bytes([self._state]))
        elif command_id in handlers:
            handlers[Command(command_id)](payload)
        else:
            self._send(command_id, Status.E_CMD_UNKNOWN)

    def _measured(self, command_id: int) -> float:
        if command_id == Command.GET_WIDTH:
            return self._now_width_m() * 1e3
        if command_id == Command.GET_SPEED:
            return 0.0 if self._motion is None else self._motion.speed_m_s * 1e3
        return self._holding_force_n

    def _start_motion(self, command: Command, target_m: float, speed_m_s: float,
                      moving_state: GraspingState, final_status: Status,
                      final_state: GraspingState) -> None:
        self._motion = _Motion(command, self._width_m, target_m, speed_m_s, time.monotonic(),
                               final_status, final_state, self.time_scale)
        self._state = moving_state
        self._holding_force_n = 0.0
        self._send(command, Status.E_CMD_PENDING)

    def _refuse_motion(self, command: Command, payload: bytes, expected_bytes: int) -> bool:
        """Answer and return True when the motion command cannot start."""
        if len(payload) != expected_bytes:
            self._send(command, Status.E_CMD_FORMAT_ERROR)
        elif self._motion is not None:
            self._send(command, Status.E_ALREADY_RUNNING)
        else:
            return False
        return True

    def _in_range(self, width_m: float, speed_m_s: float) -> bool:
        return 0.0 <= width_m <= self.max_width_m and 0.0 < speed_m_s <= self.max_speed_m_s

    def _contact_between(self, from_m: float, to_m: float) -> float | None:
        """Where closing from ``from_m`` towards ``to_m`` touches the object, if it does."""
        contact = self._contact_width_m()
        if contact is not None and to_m <= contact <= from_m:
            return contact
        return None

    def _homing(self, payload: bytes) -> None:
        if self._refuse_motion(Command.HOMING, payload, 1):
            return
        # Direction 2 references against the closed end; 0 (default) and 1 open.
        target = 0.0 if payload[0] == 2 else self.max_width_m
        self._start_motion(Command.HOMING, target, self.max_speed_m_s, GraspingState.POSITIONING,
                           Status.E_SUCCESS, GraspingState.IDLE)

    def _preposition(self, payload: bytes) -> None:
        if self._refuse_motion(Command.PREPOSITION, payload, 9):
            return
        flags, width_mm, speed_mm_s = struct.unpack("<Bff", payload)
        target = width_mm * 1e-3 + (self._width_m if flags & 0x01 else 0.0)
        speed = speed_mm_s * 1e-3
        if not self._in_range(target, speed):
            self._send(Command.PREPOSITION, Status.E_RANGE_ERROR)
            return
        contact = self._contact_between(self._width_m, target)
        if contact is None:
            self._start_motion(Command.PREPOSITION, target, speed, GraspingState.POSITIONING,
                               Status.E_SUCCESS, GraspingState.IDLE)
        else:
            self._start_motion(Command.PREPOSITION, contact, speed, GraspingState.POSITIONING,
                               Status.E_AXIS_BLOCKED, GraspingState.IDLE)

    def _grasp(self, payload: bytes) -> None:
        if self._refuse_motion(Command.GRASP, payload, 8):
            return
        width_mm, speed_mm_s = struct.unpack("<ff", payload)
        target, speed = width_mm * 1e-3, speed_mm_s * 1e-3
        if not self._in_range(target, speed) or target >= self._width_m:
            self._send(Command.GRASP, Status.E_RANGE_ERROR)
            return
        contact = self._contact_between(self._width_m, target)
        if contact is None:
            self._start_motion(Command.GRASP, target, speed, GraspingState.GRASPING,
                               Status.E_CMD_FAILED, GraspingState.NO_PART_FOUND)
        else:
            self._start_motion(Command.GRASP, contact, speed, GraspingState.GRASPING,
                               Status.E_SUCCESS, GraspingState.HOLDING)

    def _release(self, payload: bytes) -> None:
        if self._refuse_motion(Command.RELEASE, payload, 8):
            return
        width_mm, speed_mm_s = struct.unpack("<ff", payload)
        target, speed = width_mm * 1e-3, speed_mm_s * 1e-3
        if not self._in_range(target, speed) or target < self._width_m:
            self._send(Command.RELEASE, Status.E_RANGE_ERROR)
            return
        self._start_motion(Command.RELEASE, target, speed, GraspingState.RELEASING,
                           Status.E_SUCCESS, GraspingState.IDLE)

    def _stop(self, payload: bytes) -> None:
        if payload:
            self._send(Command.STOP, Status.E_NO_PARAM_EXPECTED)
            return
        if self._motion is not None:
            self._end_motion(self._now_width_m(), Status.E_CMD_ABORTED, GraspingState.IDLE)
        self._send(Command.STOP, Status.E_SUCCESS)

    def _set_force_limit(self, payload: bytes) -> None:
        if len(payload) != 4:
            self._send(Command.SET_FORCE_LIMIT, Status.E_CMD_FORMAT_ERROR)
            return
        (force_n,) = struct.unpack("<f", payload)
        if not 0.0 < force_n <= self.max_force_n:
            self._send(Command.SET_FORCE_LIMIT, Status.E_RANGE_ERROR)
            return
        self._force_limit_n = force_n
        self._send(Command.SET_FORCE_LIMIT, Status.E_SUCCESS)
