"""The fake UR controller's dashboard server on port 29999: the commands ``ur_rtde`` and
operators send, one command per line and one answer per line. Power, brake release,
stopping the program and unlocking a protective stop act on the controller core
(:mod:`sim.ur_controller.controller`).

Which commands it knows depends on the controller's software version
(:mod:`sim.ur_controller.versions`, which cites the command table it follows): a command the
version does not have, like any unknown one, is answered ``could not understand: '<command>'``.
So a CB3 or an e-Series controller before 5.6.0 cannot say whether it is in remote control,
which ur_rtde's own ``DashboardClient::isInRemoteControl`` acknowledges (dashboard_client.cpp:
it sends the query only for PolyScope 5.6 and later and otherwise warns and returns false).
"""

from __future__ import annotations

import socket

from sim.ur_controller.controller import (
    ROBOT_MODE_IDLE,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_RUNNING,
    Controller,
)
from sim.ur_controller.versions import DASHBOARD_COMMANDS_SINCE

DASHBOARD_PORT = 29999

# Answers that do not depend on the controller's state.
_FIXED_ANSWERS = {
    "get serial number": "20235500001",
    "get robot model": "UR5",
    "play": "Failed to execute: play",
    "close safety popup": "closing safety popup",
    "close popup": "closing popup",
    "quit": "Disconnected",
}
_ROBOT_MODE_NAMES = {ROBOT_MODE_POWER_OFF: "POWER_OFF", ROBOT_MODE_IDLE: "IDLE", ROBOT_MODE_RUNNING: "RUNNING"}
_SAFETY_NAMES = {
    "normal": "NORMAL",
    "protective_stop": "PROTECTIVE_STOP",
    "emergency_stop": "ROBOT_EMERGENCY_STOP",
}


def serve_dashboard(controller: Controller, sock: socket.socket) -> None:
    """The dashboard server: one command per line, one answer per line."""
    reader = sock.makefile("r", encoding="utf-8", newline="\n")
    try:
        sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        for line in reader:
            command = line.strip()
            answer = _dashboard_answer(controller, command)
            sock.sendall((answer + "\n").encode())
            if command == "quit":
                break
    except OSError:
        pass
    finally:
        sock.close()


def _dashboard_answer(controller: Controller, command: str) -> str:
    with controller.lock:
        controller.events.append(f"dashboard: {command}")
        name = "popup" if command.startswith("popup ") else command
        if name in DASHBOARD_COMMANDS_SINCE and not controller.version.has_dashboard_command(name):
            return f"could not understand: '{command}'"
        if command == "PolyscopeVersion":
            return controller.version.polyscope_version_line
        if command in _FIXED_ANSWERS:
            return _FIXED_ANSWERS[command]
        answer = _status_answer(controller, command)
        if answer is None:
            answer = _action_answer(controller, command)
        if answer is not None:
            return answer
        if command.startswith("popup "):
            return "showing popup"
        return f"could not understand: '{command}'"


def _status_answer(controller: Controller, command: str) -> str | None:
    """The answer to a query of the controller's state, or None if ``command`` is none."""
    running = controller.script is not None
    if command == "is in remote control":
        return "true" if controller.remote_control else "false"
    if command == "robotmode":
        return f"Robotmode: {_ROBOT_MODE_NAMES[controller.robot_mode]}"
    if command == "safetymode":
        return f"Safetymode: {_SAFETY_NAMES[controller.safety]}"
    if command == "safetystatus":
        return f"Safetystatus: {_SAFETY_NAMES[controller.safety]}"
    if command == "running":
        return f"Program running: {'true' if running else 'false'}"
    if command == "programState":
        return "PLAYING rtde_control" if running else "STOPPED <unnamed>"
    return None


def _action_answer(controller: Controller, command: str) -> str | None:
    """Carry out a command that changes the controller's state and answer it, or None if
    ``command`` is none."""
    if command == "stop":
        if controller.script is None or controller.take_fault("refuse_dashboard_stop", 0):
            return "Failed to execute: stop"
        controller.end_program()
        return "Stopped"
    if command == "power on":
        controller.robot_mode = ROBOT_MODE_IDLE
        return "Powering on"
    if command == "power off":
        controller.robot_mode = ROBOT_MODE_POWER_OFF
        controller.end_program()
        return "Powering off"
    if command == "brake release":
        controller.robot_mode = ROBOT_MODE_RUNNING
        return "Brake releasing"
    if command == "unlock protective stop":
        if controller.safety != "protective_stop":
            return "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
        controller.safety = "normal"
        return "Protective stop releasing"
    return None
