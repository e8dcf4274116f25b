"""Hardware driver figures, measured against the protocol-level fakes (no device needed).

Gripper, against the strict firmware simulator (firmware.Strictness defaults) in its own
process, as a real gripper would be, so it does not share the client's interpreter lock:

- round trip of one WSG command (SET_FORCE_LIMIT: request frame out, status frame back);
- stop preemption through the node: a client asks ``/gripper/command`` to stop while the
  node runs a slow grasp; the time until the stop's reply (fingers stopped), p50/p99;
- homing, move and grasp completion: wall time from the command to the driver's return,
  less the fingers' travel time, and how many ended as they should (homing at 110 mm though
  the grasping state reads IDLE throughout, the move at its width, the grasp holding).

The arm's figures (RTDE state rate, stop latency) belong beside these in the returned list.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from bus.services import ServiceCallError
from drivers.gripper.firmware import GripperFirmware
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper

OBJECT_WIDTH_M = 0.04  # the part between the fingers in the completion figures
HOMING_SPEED_M_S = 0.1  # the firmware simulator's referencing speed
FAST_M_S = 0.4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gripper-commands", type=int, default=1000, help="serial round trips to time")
    parser.add_argument("--stop-samples", type=int, default=50, help="grasps stopped through the node")
    parser.add_argument("--completion-samples", type=int, default=10, help="homing, move and grasp cycles to time")


def _part_between_fingers() -> float:
    return OBJECT_WIDTH_M


def _serve_firmware(port_out: Connection, stop: Any) -> None:
    """Child process: run the firmware until told to stop; send back its port first."""
    with GripperFirmware(_part_between_fingers, homing_speed_m_s=HOMING_SPEED_M_S) as firmware:
        port_out.send(firmware.port)
        stop.wait()


class _FirmwareProcess:
    """The firmware simulator in a child process, for the duration of a ``with`` block."""

    def __enter__(self) -> str:
        port_in, port_out = mp.Pipe(duplex=False)
        self._stop = mp.Event()
        self._process = mp.Process(target=_serve_firmware, args=(port_out, self._stop), daemon=True)
        self._process.start()
        return port_in.recv()

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._process.join()


def _percentiles(figure: str, samples_ms: list[float], **extra: Any) -> dict[str, Any]:
    return {
        "figure": figure,
        "unit": "ms",
        "samples": len(samples_ms),
        "p50": float(np.percentile(samples_ms, 50)),
        "p99": float(np.percentile(samples_ms, 99)),
        **extra,
    }


def gripper_round_trip(commands: int) -> dict[str, Any]:
    """p50/p99 (ms) of one request/response through the pty."""
    with _FirmwareProcess() as port:
        gripper = WSG50Gripper(WSG50Config(port=port))
        gripper.connect()
        try:
            durations_ms = []
            for index in range(commands):
                start = time.perf_counter()
                gripper.set_force_limit(10.0 + index % 50)
                durations_ms.append((time.perf_counter() - start) * 1e3)
        finally:
            gripper.disconnect()
    return _percentiles("gripper serial round trip (pty)", durations_ms)


def stop_preemption(samples: int) -> dict[str, Any]:
    """p50/p99 (ms) from a stop request to its reply through the gripper node, while the node
    runs a 9 s grasp that finds nothing; ``preempted`` counts stops that left the fingers
    short of the grasp's end."""
    import threading

    from nodes.gripper import GripperNode

    registry = Registry(Path(tempfile.mkdtemp(prefix="dtxb")))
    with _FirmwareProcess() as port:
        node = GripperNode("gripper", {"backend": "wsg50", "port": port, "state_rate_hz": 20.0}, registry=registry)
        done = threading.Event()
        spinner = threading.Thread(target=node.spin, kwargs={"until": done.is_set})
        spinner.start()
        operator = Bus("operator", registry)
        try:
            command = operator.client("/gripper/command", msgs.GripperCommand, msgs.GripperState)
            command.call(msgs.GripperCommand(action="stop"), timeout_s=10.0)  # untimed: connects the client
            durations_ms, preempted = [], 0
            for _ in range(samples):
                grasping = threading.Thread(target=_grasp_slowly, args=(registry,))
                grasping.start()
                time.sleep(0.2)  # well inside the 9 s grasp
                start = time.perf_counter()
                stopped = command.call(msgs.GripperCommand(action="stop"), timeout_s=10.0, retries=0)
                durations_ms.append((time.perf_counter() - start) * 1e3)
                preempted += stopped.width_m > 0.025
                grasping.join()
                command.call(msgs.GripperCommand(action="release", width_m=0.11, speed_m_s=FAST_M_S), timeout_s=10.0)
        finally:
            operator.close()
            done.set()
            spinner.join()
            node.close()
    return _percentiles("gripper stop preemption through the node (during a grasp)", durations_ms, preempted=preempted)


def _grasp_slowly(registry: Registry) -> None:
    bus = Bus("grasper", registry)
    try:
        bus.client("/gripper/command", msgs.GripperCommand, msgs.GripperState).call(
            msgs.GripperCommand(action="grasp", width_m=0.03, speed_m_s=0.01, force_n=10.0), timeout_s=15.0, retries=0
        )
    except ServiceCallError:
        pass  # the stop aborts it: that is the point
    finally:
        bus.close()


def completion(cycles: int) -> list[dict[str, Any]]:
    """Per command: wall time to the driver's return less the fingers' travel time (ms), and
    how many of ``cycles`` ended where and as they should."""
    overhead_ms: dict[str, list[float]] = {"homing": [], "move": [], "grasp": []}
    correct = dict.fromkeys(overhead_ms, 0)
    with _FirmwareProcess() as port:
        gripper = WSG50Gripper(WSG50Config(port=port))
        gripper.connect()
        try:
            for _ in range(cycles):
                start = time.perf_counter()
                state = gripper.move(0.06, FAST_M_S)
                overhead_ms["move"].append((time.perf_counter() - start - 0.05 / FAST_M_S) * 1e3)
                correct["move"] += abs(state.width_m - 0.06) < 1e-6
                start = time.perf_counter()
                state = gripper.home()
                overhead_ms["homing"].append((time.perf_counter() - start - 0.05 / HOMING_SPEED_M_S) * 1e3)
                correct["homing"] += abs(state.width_m - 0.110) < 1e-6
                start = time.perf_counter()
                state = gripper.grasp(OBJECT_WIDTH_M, FAST_M_S, 10.0)
                overhead_ms["grasp"].append((time.perf_counter() - start - 0.07 / FAST_M_S) * 1e3)
                correct["grasp"] += state.state == "holding"
                gripper.release(0.110, FAST_M_S)
        finally:
            gripper.disconnect()
    return [
        _percentiles(
            f"gripper {name} completion beyond finger travel (strict firmware)", values, completed=correct[name]
        )
        for name, values in overhead_ms.items()
    ]


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    return [
        gripper_round_trip(args.gripper_commands),
        stop_preemption(args.stop_samples),
        *completion(args.completion_samples),
    ]
