"""UR arm figures through the real ur_rtde client against the fake UR controller
(sim/ur_controller/): the RTDE state rate the client actually receives from a 500 Hz
controller; for stops during a moveL, the time from ``stop()`` on the backend to the
controller receiving the stopJ command (URArm.stop sends stopJ; see its docstring) and to
``stop()`` returning with the arm verified at rest, how many stops needed an escalation (the
arm's error code after the stop) and how many were lost (the move went on to its target).
Both clocks are the machine's monotonic clock. ``dtx bench arm_stress`` runs this many times,
beside CPU hogs, and counts hangs."""

from __future__ import annotations

import argparse
import collections
import random
import threading
import time
from typing import Any

import numpy as np
import rtde_receive

from drivers.arm.base import ArmError, MotionAbortedError
from drivers.arm.ur import STATE_VARIABLES, URArm, URArmConfig
from sim.ur_controller import CMD_STOPJ, FakeURController

POLL_PERIOD_S = 50e-6


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--state-rate-hz", type=float, default=500.0, help="state rate of the fake controller (Hz)")
    parser.add_argument("--rate-seconds", type=float, default=5.0, help="how long to count received states (s)")
    parser.add_argument("--stop-trials", type=int, default=20, help="stop requests to time")
    parser.add_argument("--each-stop", action="store_true", help="list every stop's time (ms) beside its percentiles")


def received_state_rate(host: str, frequency_hz: float, seconds: float) -> list[dict[str, Any]]:
    """Distinct RTDE states seen by a receive interface subscribed like the backend's."""
    receive = rtde_receive.RTDEReceiveInterface(host, frequency_hz, STATE_VARIABLES)
    try:
        timestamps = [receive.getTimestamp()]
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            timestamp = receive.getTimestamp()
            if timestamp != timestamps[-1]:
                timestamps.append(timestamp)
            time.sleep(POLL_PERIOD_S)
        elapsed = time.monotonic() - start
    finally:
        receive.disconnect()
    received = len(timestamps) - 1
    return [
        {"figure": "RTDE states received by ur_rtde", "unit": "Hz", "samples": received, "value": received / elapsed},
        {
            "figure": "fake controller clock advance",
            "unit": "Hz",
            "samples": received,
            "value": (timestamps[-1] - timestamps[0]) * frequency_hz / elapsed,
        },
    ]


def stop_trials(fake: FakeURController, trials: int, each_stop: bool = False) -> list[dict[str, Any]]:
    """Stops during a moveL: p50/p99 (ms) from URArm.stop() to the fake receiving stopJ and to
    stop() returning at rest, the stops that escalated (by error code) and the lost ones."""
    arm = URArm(URArmConfig(robot_ip=fake.host))
    arm.connect()
    received_ms, rest_ms, lost = [], [], 0
    escalations, unstarted = collections.Counter[str](), collections.Counter[str]()
    try:
        start = arm.read().tcp_pose
        for trial in range(trials):
            target = start + np.array([0.0, 0.2 if trial % 2 == 0 else -0.2, 0.0, 0.0, 0.0, 0.0])
            outcome: list[str] = []
            mover = threading.Thread(target=_move_until_stopped, args=(arm, target, outcome))
            mover.start()
            if not _wait_until_moving(fake, mover):
                unstarted[outcome[0]] += 1
                continue
            requested_ns = time.monotonic_ns()
            arm.stop()
            rest_ms.append((time.monotonic_ns() - requested_ns) / 1e6)
            mover.join()
            escalations[arm.read().error_code or "none"] += 1
            lost += outcome == ["arrived"]
            received = [t for t, cmd in fake.snapshot()["commands_received"] if cmd == CMD_STOPJ and t >= requested_ns]
            if received:
                received_ms.append((min(received) - requested_ns) / 1e6)
    finally:
        arm.disconnect()
    return [
        _percentiles("stop() to controller receiving stopJ", received_ms, each_stop),
        _percentiles("stop() to the arm verified at rest", rest_ms, each_stop),
        {"figure": "stops lost (the move reached its target)", "unit": "stops", "samples": trials, "value": lost},
        *(
            {"figure": f"stops ending with error code {code}", "unit": "stops", "samples": trials, "value": count}
            for code, count in sorted(escalations.items())
        ),
        *(
            {"figure": f"moves that ended before their stop ({code})", "unit": "moves", "samples": trials, "value": n}
            for code, n in sorted(unstarted.items())
        ),
    ]


def _percentiles(figure: str, values_ms: list[float], each: bool) -> dict[str, Any]:
    row = {
        "figure": figure,
        "unit": "ms",
        "samples": len(values_ms),
        "p50": float(np.percentile(values_ms, 50)) if values_ms else None,
        "p99": float(np.percentile(values_ms, 99)) if values_ms else None,
    }
    return {**row, "each": values_ms} if each else row


def _move_until_stopped(arm: URArm, target: np.ndarray, outcome: list[str]) -> None:
    try:
        arm.move_linear(target, speed_m_s=0.1, accel_m_s2=1.0)
        outcome.append("arrived")
    except MotionAbortedError:
        outcome.append("stopped")  # the stop this trial is timing
    except ArmError as error:
        outcome.append(error.code)


def _wait_until_moving(fake: FakeURController, mover: threading.Thread) -> bool:
    """Whether the fake arm moves with the move command cleared by the client before the move
    ends (a move that failed to start ends at once)."""
    while mover.is_alive():
        snapshot = fake.snapshot()
        if snapshot["moving"] and snapshot["command_register"] == 0:
            return True
        time.sleep(0.002)
    return False


def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    host = f"127.{random.randint(32, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
    with FakeURController(host, state_rate_hz=args.state_rate_hz) as fake:
        rows = received_state_rate(host, args.state_rate_hz, args.rate_seconds)
        rows.extend(stop_trials(fake, args.stop_trials, args.each_stop))
    return rows
