"""A fake Universal Robots controller, CB3 or e-Series, that the real ``ur_rtde`` client can
drive: the strict counterpart of ``drivers.arm.ur`` in its tests and benchmarks. It runs the
software version it is given (:mod:`sim.ur_controller.versions`: what the dashboard knows, the
RTDE rate, local and remote control).

It speaks the controller's own protocols on one loopback address:

- RTDE on port 30004 (protocol version 2): protocol version and controller version
  requests, output and input recipe setup, start and pause, data packages packed per the
  RTDE guide's type table, and text messages (:mod:`sim.ur_controller.rtde`);
- the dashboard server on port 29999 (the commands ``ur_rtde`` and operators send;
  :mod:`sim.ur_controller.dashboard`);
- the script server on port 30003, which receives the control script ``ur_rtde`` uploads
  (:mod:`sim.ur_controller.script`).

Around them, :mod:`sim.ur_controller.controller` is the controller itself: a kinematic UR5e (UR5 on CB3)
(:mod:`sim.ur_controller.motion`), safety, the speed slider, the RTDE watchdog, and an
emulation of what ur_rtde 1.6.5's control script does with the RTDE registers; its module
docstring says how strict it is and which documents that follows.
:mod:`sim.ur_controller.server` runs all of it in its own (spawned) process, and tests drive
it through :class:`FakeURController`; every fake gets its own 127.x.y.z address because the
client's ports are fixed.
"""

from __future__ import annotations

from sim.ur_controller.controller import (
    CMD_MOVEJ,
    CMD_MOVEL,
    CMD_NONE,
    CMD_SET_WATCHDOG,
    CMD_STOP_SCRIPT,
    CMD_STOPJ,
    CMD_STOPL,
    HOME_Q,
)
from sim.ur_controller.dashboard import DASHBOARD_PORT
from sim.ur_controller.rtde import RTDE_PORT
from sim.ur_controller.script import SCRIPT_PORT
from sim.ur_controller.server import FakeURController
from sim.ur_controller.versions import DEFAULT_VERSION, SoftwareVersion

__all__ = [
    "CMD_MOVEJ",
    "CMD_MOVEL",
    "CMD_NONE",
    "CMD_SET_WATCHDOG",
    "CMD_STOPJ",
    "CMD_STOPL",
    "CMD_STOP_SCRIPT",
    "DASHBOARD_PORT",
    "DEFAULT_VERSION",
    "HOME_Q",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "FakeURController",
    "SoftwareVersion",
]
