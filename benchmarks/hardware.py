"""Hardware driver figures, measured against the protocol-level fakes (no device needed).

Gripper: round trip of one WSG command (SET_FORCE_LIMIT: request frame out, status frame
back) through a pty to the firmware simulator. The firmware runs in its own process, as a
real gripper would, so it does not share the client's interpreter lock.
The arm's figures (RTDE state rate, stop latency) belong beside it in the returned list.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from drivers.gripper.firmware import GripperFirmware
from drivers.gripper.wsg50 import WSG50Config, WSG50Gripper


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gripper-commands", type=int, default=1000,
                        help="serial round trips to time")


def _serve_firmware(port_out: Connection, stop: Any) -> None:
    """Child process: run the firmware until told to stop; send back its port first."""
    with GripperFirmware() as firmware:
        port_out.send(firmware.port)
        stop.wait()


def gripper_round_trip(commands: int) -> dict[str, Any]:
    """p50/p99 (ms) of one request/response through the pty."""
    port_in, port_out = mp.Pipe(duplex=False)
    stop = mp.Event()
    firmware = mp.Process(target=_serve_firmware, args=(port_out, stop), daemon=True)
    firmware.start()
    try:
        gripper = WSG50Gripper(WSG50Config(port=port_in.recv()))
        gripper.connect()
        try:
            durations_ms = []
            for index in range(commands):
                start = time.perf_counter()
                gripper.set_force_limit(10.0 + index % 50)
                durations_ms.append((time.perf_counter() - start) * 1e3)
        finally:
            gripper.disconnect()
    finally:
        stop.set()
        firmware.join()
    return {"figure": "gripper serial round trip (pty)", "unit": "ms", "samples": commands,
            "p50": float(np.percentile(durations_ms, 50)),
            "p99": float(np.percentile(durations_ms, 99))}


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    return [gripper_round_trip(args.gripper_commands)]
