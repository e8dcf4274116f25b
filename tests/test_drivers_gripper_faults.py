"""A bad serial line: a seeded relay between client and firmware flips, drops or adds bytes.

Under each fault every command must either complete with the right result or raise a
GripperError that says what happened; none may hang or return wrong data.
"""

from __future__ import annotations

import os
import random
import select
import threading
import tty

import pytest

from drivers.gripper import GripperError
from drivers.gripper.firmware import GripperFirmware
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper

FAST = 0.4  # m/s
OBJECT_WIDTH_M = 0.045


class CorruptingRelay:
    """client <-> (pty) <-> relay <-> (pty) <-> firmware, mangling bytes both ways."""

    def __init__(self, firmware_port: str, seed: int, flip: float = 0.0, drop: float = 0.0, extra: float = 0.0) -> None:
        self._rng = random.Random(seed)
        self._flip, self._drop, self._extra = flip, drop, extra
        self._firmware_side = os.open(firmware_port, os.O_RDWR | os.O_NOCTTY)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.mangled_bytes = 0
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _mangle(self, data: bytes) -> bytes:
        out = bytearray()
        for byte in data:
            roll = self._rng.random()
            if roll < self._drop:
                self.mangled_bytes += 1
                continue
            if roll < self._drop + self._flip:
                self.mangled_bytes += 1
                byte ^= 1 << self._rng.randrange(8)
            out.append(byte)
            if self._rng.random() < self._extra:
                self.mangled_bytes += 1
                out.append(self._rng.randrange(256))
        return bytes(out)

    def _pump(self) -> None:
        peer = {self._master: self._firmware_side, self._firmware_side: self._master}
        while not self._stopping.is_set():
            readable, _, _ = select.select(list(peer), [], [], 0.05)
            for source in readable:
                os.write(peer[source], self._mangle(os.read(source, 4096)))

    def close(self) -> None:
        self._stopping.set()
        self._thread.join()
        for fd in (self._firmware_side, self._master, self._slave):
            os.close(fd)


def run_session(fault: dict[str, float], seed: int, cycles: int) -> tuple[int, list[str], int, int]:
    """Grasp-release cycles over a faulty line:
    (commands completed, errors, bytes mangled by the relay, bytes the client skipped)."""
    completed, errors = 0, []
    with GripperFirmware(lambda: OBJECT_WIDTH_M) as firmware:
        relay = CorruptingRelay(firmware.port, seed, **fault)
        client = WSG50Gripper(WSG50Config(port=relay.port, response_timeout_s=0.1, retries=4))
        try:
            client.connect()
        except GripperError as exc:
            errors.append(str(exc))
            cycles = 0
        try:
            for _ in range(cycles):
                motion_failed = False
                for command in (
                    lambda: client.grasp(OBJECT_WIDTH_M, FAST, 20.0),
                    lambda: client.release(0.1, FAST),
                    lambda: client.move(0.08, FAST),
                    client.read,
                ):
                    try:
                        state = command()
                    except GripperError as exc:
                        errors.append(str(exc))
                        motion_failed = True
                        continue
                    completed += 1
                    # A move whose reply was lost may still be under way when the state is read.
                    settled = {"idle", "holding"} | ({"moving"} if command is client.read and motion_failed else set())
                    assert state.state in settled
                    motion_failed = False
                    if state.state == "holding":
                        assert state.width_m == pytest.approx(OBJECT_WIDTH_M, abs=1e-6)
                        assert state.force_n == pytest.approx(20.0)
        finally:
            client.disconnect()
            relay.close()
    return completed, errors, relay.mangled_bytes, client.discarded_bytes


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault", [{"flip": 0.01}, {"drop": 0.01}, {"extra": 0.01}], ids=["1%-flipped", "1%-dropped", "1%-extra"]
)
def test_every_command_completes_or_fails_clearly(fault):
    completed, errors, mangled, skipped = run_session(fault, seed=7, cycles=8)
    assert mangled > 0, "the relay must actually have corrupted the line"
    assert skipped > 0, "the client must have resynchronised past bad bytes"
    assert completed >= 28  # of 32: retries recover nearly everything
    for message in errors:
        assert any(
            reason in message for reason in ("no answer to", "another motion is running", "did not finish", "failed:")
        ), message


def test_heavy_corruption_fails_clearly_instead_of_hanging():
    _, errors, _, _ = run_session({"flip": 0.2}, seed=3, cycles=2)
    assert errors
    assert all(
        "no answer to" in message or "failed" in message or "blocked" in message or "motion is running" in message
        for message in errors
    )
