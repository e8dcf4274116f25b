"""The WSG binary command protocol (Weiss Robotics WSG-50), written by hand from its manual.

A frame is ``AA AA AA | command id | payload length (uint16 LE) | payload | CRC16 (LE)``.
The CRC is the one of Weiss' own driver: the CCITT table of polynomial 0x1021, start value
0xFFFF, but updated least-significant byte first; it runs over preamble, header and payload,
so a whole frame, CRC included, checks to 0. Every response payload starts with a uint16
status code; motion commands first answer E_CMD_PENDING, then the final status when the
fingers stop. Values travel as float32 LE in millimetres, mm/s and newtons.
"""

from __future__ import annotations

import enum
import struct
from typing import Callable

from drivers import DeviceError, DeviceTimeoutError

PREAMBLE = b"\xaa\xaa\xaa"
HEADER_BYTES = len(PREAMBLE) + 3
# Larger than any payload this driver sends or expects. A length field above it can only be
# a misaligned or corrupted header, so the parser resynchronises at once instead of waiting
# for hundreds of bytes that will never come.
MAX_PAYLOAD_BYTES = 64


class GripperError(DeviceError):
    """Any failure of the gripper or of the serial line; the message says what to do."""


class GripperTimeoutError(GripperError, DeviceTimeoutError):
    """The gripper did not answer a command, or finish a motion, within its deadline."""


class Command(enum.IntEnum):
    DISCONNECT = 0x07
    HOMING = 0x20
    PREPOSITION = 0x21
    STOP = 0x22
    FAST_STOP = 0x23
    ACK_FAST_STOP = 0x24
    GRASP = 0x25
    RELEASE = 0x26
    SET_ACCELERATION = 0x30
    GET_ACCELERATION = 0x31
    SET_FORCE_LIMIT = 0x32
    GET_FORCE_LIMIT = 0x33
    TARE_FORCE = 0x38
    GET_SYSTEM_STATE = 0x40
    GET_GRASPING_STATE = 0x41
    GET_WIDTH = 0x43
    GET_SPEED = 0x44
    GET_FORCE = 0x45


class Status(enum.IntEnum):
    E_SUCCESS = 0
    E_NOT_AVAILABLE = 1
    E_NO_SENSOR = 2
    E_NOT_INITIALIZED = 3
    E_ALREADY_RUNNING = 4
    E_FEATURE_NOT_SUPPORTED = 5
    E_INCONSISTENT_DATA = 6
    E_TIMEOUT = 7
    E_READ_ERROR = 8
    E_WRITE_ERROR = 9
    E_INSUFFICIENT_RESOURCES = 10
    E_CHECKSUM_ERROR = 11
    E_NO_PARAM_EXPECTED = 12
    E_NOT_ENOUGH_PARAMS = 13
    E_CMD_UNKNOWN = 14
    E_CMD_FORMAT_ERROR = 15
    E_ACCESS_DENIED = 16
    E_ALREADY_OPEN = 17
    E_CMD_FAILED = 18
    E_CMD_ABORTED = 19
    E_INVALID_HANDLE = 20
    E_NOT_FOUND = 21
    E_NOT_OPEN = 22
    E_IO_ERROR = 23
    E_INVALID_PARAMETER = 24
    E_INDEX_OUT_OF_BOUNDS = 25
    E_CMD_PENDING = 26
    E_OVERRUN = 27
    E_RANGE_ERROR = 28
    E_AXIS_BLOCKED = 29
    E_FILE_EXISTS = 30


class GraspingState(enum.IntEnum):
    IDLE = 0
    GRASPING = 1
    NO_PART_FOUND = 2
    PART_LOST = 3
    HOLDING = 4
    RELEASING = 5
    POSITIONING = 6
    ERROR = 7


class SystemFlag(enum.IntFlag):
    """Bits of the system state word (0x40), as the Weiss command set numbers them
    (wsg50-ros-pkg: wsg_50_driver/include/wsg_50/common.h lists the same bits)."""

    REFERENCED = 1 << 0
    MOVING = 1 << 1
    BLOCKED_MINUS = 1 << 2
    BLOCKED_PLUS = 1 << 3
    AXIS_STOPPED = 1 << 6
    TARGET_POS_REACHED = 1 << 7
    FAST_STOP = 1 << 12
    TEMP_FAULT = 1 << 14
    POWER_FAULT = 1 << 15
    CURR_FAULT = 1 << 16
    FINGER_FAULT = 1 << 17
    CMD_FAILURE = 1 << 18


# Faults that keep the gripper from moving until an operator has dealt with the cause.
FAULT_FLAGS = SystemFlag.TEMP_FAULT | SystemFlag.POWER_FAULT | SystemFlag.CURR_FAULT | SystemFlag.FINGER_FAULT
# The fast stop is acknowledged with the three bytes "ack" (wsg50-ros-pkg: functions.cpp, ack_fault()).
ACK_PAYLOAD = b"ack"


def status_name(code: int) -> str:
    """``E_...`` name of a status code, or the number if the manual does not list it."""
    try:
        return Status(code).name
    except ValueError:
        return f"status {code}"


def _ccitt_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        value = byte << 8
        for _ in range(8):
            value = ((value << 1) ^ 0x1021) if value & 0x8000 else value << 1
        table.append(value & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _ccitt_table()


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """The WSG checksum of ``data`` (continue a running checksum by passing ``crc``)."""
    for byte in data:
        crc = _CRC_TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


def encode_frame(command_id: int, payload: bytes = b"") -> bytes:
    """One complete frame carrying ``payload`` for ``command_id``."""
    if len(payload) > 0xFFFF:
        raise ValueError(f"payload of {len(payload)} bytes does not fit a WSG frame")
    body = PREAMBLE + struct.pack("<BH", command_id, len(payload)) + payload
    return body + struct.pack("<H", crc16(body))


def encode_response(command_id: int, status: int, data: bytes = b"") -> bytes:
    """A device answer: the status code first, then the command's data."""
    return encode_frame(command_id, struct.pack("<H", status) + data)


def split_response(payload: bytes) -> tuple[int, bytes]:
    """(status code, data after it) of a response payload."""
    if len(payload) < 2:
        raise GripperError(f"response of {len(payload)} bytes carries no status code")
    return struct.unpack_from("<H", payload)[0], payload[2:]


class FrameParser:
    """Cuts a byte stream into frames, skipping garbage and frames with a wrong CRC.

    ``feed`` keeps incomplete data for the next call. After a bad frame it searches again
    from the byte after that frame's first byte, so a real frame hidden behind garbage
    that looked like a header is still found. ``discarded_bytes`` counts what was skipped.
    ``on_bad_checksum`` (the device side) hears the command id of every complete frame
    whose CRC is wrong, so it can answer E_CHECKSUM_ERROR as the gripper does.
    """

    def __init__(self, on_bad_checksum: Callable[[int], None] | None = None) -> None:
        self._buffer = bytearray()
        self.discarded_bytes = 0
        self._on_bad_checksum = on_bad_checksum

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """Append ``data``; return every complete, valid (command id, payload) found."""
        self._buffer += data
        frames: list[tuple[int, bytes]] = []
        while True:
            start = self._buffer.find(PREAMBLE)
            if start < 0:
                # Keep a trailing AA or AA AA: it may be the start of the next preamble.
                trailing = len(self._buffer) - len(self._buffer.rstrip(b"\xaa"))
                keep = min(trailing, len(PREAMBLE) - 1)
                self._discard(len(self._buffer) - keep)
                return frames
            self._discard(start)
            if len(self._buffer) < HEADER_BYTES:
                return frames
            command_id, length = struct.unpack_from("<BH", self._buffer, len(PREAMBLE))
            if length > MAX_PAYLOAD_BYTES:
                self._discard(1)
                continue
            total = HEADER_BYTES + length + 2
            if len(self._buffer) < total:
                return frames
            if crc16(bytes(self._buffer[:total])) != 0:
                if self._on_bad_checksum is not None:
                    self._on_bad_checksum(command_id)
                self._discard(1)
                continue
            frames.append((command_id, bytes(self._buffer[HEADER_BYTES : HEADER_BYTES + length])))
            del self._buffer[:total]

    def _discard(self, count: int) -> None:
        self.discarded_bytes += count
        del self._buffer[:count]
