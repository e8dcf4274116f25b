"""The fake UR controller's RTDE interface: RTDE on port 30004 (protocol version 2).

One :class:`RTDESession` per client connection handles protocol version and controller
version requests, output and input recipe setup, start and pause, data packages packed per
the RTDE guide's type table, and text messages. A data package goes out every
round(state rate / recipe frequency) controller ticks; input packages write the registers
the controller core (:mod:`sim.ur_controller.controller`) reads, and one that writes the
control script's command register kicks the RTDE watchdog (ur_rtde's kickWatchdog). The
controller version it reports and the fastest recipe it accepts (125 Hz CB3, 500 Hz
e-Series) are those of the controller's software version (:mod:`sim.ur_controller.versions`).
A variable the controller does not model reads as zero of its RTDE type.
"""

from __future__ import annotations

import re
import socket
import struct
import threading
import time
from typing import Any, Sequence

from sim.ur_controller.controller import Controller

RTDE_PORT = 30004

# RTDE package types (RTDE guide).
RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
RTDE_GET_URCONTROL_VERSION = ord("v")
RTDE_TEXT_MESSAGE = ord("M")
RTDE_DATA_PACKAGE = ord("U")
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
RTDE_CONTROL_PACKAGE_START = ord("S")
RTDE_CONTROL_PACKAGE_PAUSE = ord("P")
RTDE_HEADER = struct.Struct(">HB")
TEXT_MESSAGE_EXCEPTION = 0

# Wire format of each RTDE data type (big-endian, RTDE guide).
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

# Types of the RTDE variables with fixed names (RTDE guide, PolyScope 5.11).
VARIABLE_TYPES = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "actual_current_as_torque": "VECTOR6D",
    # Inputs a client may write.
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
REGISTER_NAME = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)$")
REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}


def variable_type(name: str) -> str | None:
    """RTDE type of a variable name, or None if the controller does not know it."""
    match = REGISTER_NAME.match(name)
    if match:
        kind, number = match.group(2), int(match.group(3))
        valid = 64 <= number <= 127 if kind == "bit" else 0 <= number <= 47
        return REGISTER_TYPES[kind] if valid else None
    return VARIABLE_TYPES.get(name)


def zero_value(rtde_type: str) -> Any:
    fmt = TYPE_FORMATS[rtde_type]
    if fmt[0].isdigit():
        return [0] * int(fmt[0])
    return False if fmt == "?" else 0


def recipe_struct(types: Sequence[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))


class RTDESession:
    """One RTDE client connection: control packages in, data packages out."""

    def __init__(self, controller: Controller, sock: socket.socket) -> None:
        self.controller = controller
        self.sock = sock
        self.send_lock = threading.Lock()
        self.output_names: list[str] = []
        self.output_struct: struct.Struct | None = None
        self.output_recipe_id = 0
        self.ticks_per_package = 1
        self.input_recipes: dict[int, tuple[list[str], struct.Struct]] = {}
        self.streaming = False

    def serve(self) -> None:
        buffer = b""
        while True:
            try:
                chunk = self.sock.recv(65536)
            except OSError:
                break
            if not chunk:
                break
            buffer += chunk
            while len(buffer) >= RTDE_HEADER.size:
                size, package_type = RTDE_HEADER.unpack_from(buffer)
                if size < RTDE_HEADER.size or len(buffer) < size:
                    break
                payload, buffer = buffer[RTDE_HEADER.size : size], buffer[size:]
                self._handle(package_type, payload, time.monotonic_ns())
        self.streaming = False
        with self.controller.lock:
            if self in self.controller.rtde_sessions:
                self.controller.rtde_sessions.remove(self)

    def _handle(self, package_type: int, payload: bytes, received_ns: int) -> None:
        if package_type == RTDE_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self._send(package_type, struct.pack(">B", 1 if version in (1, 2) else 0))
        elif package_type == RTDE_GET_URCONTROL_VERSION:
            self._send(package_type, struct.pack(">IIII", *self.controller.version.numbers))
        elif package_type == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            self._setup_outputs(frequency, _names(payload[8:]))
        elif package_type == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(_names(payload))
        elif package_type == RTDE_CONTROL_PACKAGE_START:
            self.streaming = self.output_struct is not None
            self._send(package_type, struct.pack(">B", 1 if self.streaming else 0))
        elif package_type == RTDE_CONTROL_PACKAGE_PAUSE:
            self.streaming = False
            self._send(package_type, struct.pack(">B", 1))
        elif package_type == RTDE_DATA_PACKAGE:
            self._apply_inputs(payload, received_ns)

    def _setup_outputs(self, frequency: float, names: list[str]) -> None:
        types = [variable_type(name) or "NOT_FOUND" for name in names]
        valid = "NOT_FOUND" not in types and 0.0 < frequency <= self.controller.state_rate_hz
        if valid:
            self.output_names = names
            self.output_struct = recipe_struct(types)
            self.output_recipe_id = 1
            self.ticks_per_package = max(1, round(self.controller.state_rate_hz / frequency))
        recipe_id = self.output_recipe_id if valid else 0
        self._send(RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode())

    def _setup_inputs(self, names: list[str]) -> None:
        types = [variable_type(name) or "NOT_FOUND" for name in names]
        recipe_id = 0
        if "NOT_FOUND" not in types:
            recipe_id = len(self.input_recipes) + 1
            self.input_recipes[recipe_id] = (names, recipe_struct(types))
        self._send(RTDE_CONTROL_PACKAGE_SETUP_INPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode())

    def _apply_inputs(self, payload: bytes, received_ns: int) -> None:
        recipe = self.input_recipes.get(payload[0])
        if recipe is None:
            return
        names, layout = recipe
        flat = list(layout.unpack(payload[1 : 1 + layout.size]))
        controller = self.controller
        with controller.lock:
            for name in names:
                width = _width(variable_type(name) or "DOUBLE")
                value = flat[0] if width == 1 else flat[:width]
                del flat[:width]
                controller.write_input(name, value, received_ns)

    def send_state_if_due(self, tick: int) -> None:
        if self.output_struct is None or tick % self.ticks_per_package:
            return
        with self.controller.lock:
            values = [_output_value(self.controller, name) for name in self.output_names]
        flat: list[Any] = []
        for value in values:
            flat.extend(value if isinstance(value, list) else [value])
        package = struct.pack(">B", self.output_recipe_id) + self.output_struct.pack(*flat)
        self._send(RTDE_DATA_PACKAGE, package)

    def send_text_message(self, message: str, source: str, level: int) -> None:
        encoded_message, encoded_source = message.encode()[:255], source.encode()[:255]
        self._send(
            RTDE_TEXT_MESSAGE,
            struct.pack(">B", len(encoded_message))
            + encoded_message
            + struct.pack(">B", len(encoded_source))
            + encoded_source
            + struct.pack(">B", level),
        )

    def send_exception(self, message: str, source: str) -> None:
        """A runtime error of the running program, as the controller reports it."""
        self.send_text_message(message, source, TEXT_MESSAGE_EXCEPTION)

    def _send(self, package_type: int, payload: bytes) -> None:
        with self.send_lock:
            try:
                self.sock.sendall(RTDE_HEADER.pack(RTDE_HEADER.size + len(payload), package_type) + payload)
            except OSError:
                self.streaming = False


def _names(payload: bytes) -> list[str]:
    return [name for name in payload.decode().split(",") if name]


def _width(rtde_type: str) -> int:
    fmt = TYPE_FORMATS[rtde_type]
    return int(fmt[0]) if fmt[0].isdigit() else 1


def _output_value(controller: Controller, name: str) -> Any:
    """An output's value: a register, a value the controller models, or zero of its type."""
    if name in controller.registers:
        return controller.registers[name]
    if name in controller.outputs:
        return controller.outputs[name]
    return zero_value(variable_type(name) or "DOUBLE")


def serve_rtde(controller: Controller, sock: socket.socket) -> None:
    """Serve one RTDE client connection until it closes."""
    session = RTDESession(controller, sock)
    with controller.lock:
        controller.rtde_sessions.append(session)
    session.serve()
