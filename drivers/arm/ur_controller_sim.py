"""A fake Universal Robots e-Series controller that the real ``ur_rtde`` client can drive.

It speaks the controller's own protocols on one loopback address:

- RTDE on port 30004 (protocol version 2): protocol version and controller version
  requests, output and input recipe setup, start and pause, data packages packed per the
  RTDE guide's type table, and text messages;
- the dashboard server on port 29999 (the commands ``ur_rtde`` and operators send);
- the script server on port 30003, which receives the control script ``ur_rtde`` uploads.

It does not interpret URScript. It recognises ``ur_rtde``'s control script and emulates
what that script does with the RTDE registers (ur_rtde 1.6.5, script of 14.02.2024):
``output_int_register_0`` says 1 (ready) or 2 (done with the command), the command number
arrives in ``input_int_register_0`` and its arguments in ``input_double_register_*`` and
``input_int_register_1``, and ``output_int_register_2`` reports asynchronous progress.
The robot is a kinematic UR5e: moveJ interpolates the joints, moveL the TCP (position
linearly, orientation by slerp) with the joints following by inverse kinematics, both with
a trapezoidal speed profile.

It is as strict as the controller running what ur_rtde 1.6.5 uploads:

- a stop during a move is executed as ``stopj`` with the given deceleration in rad/s², for
  stopL too: the 1.6.5 control script (rtde_control.script, exec_stopl_stopj() and
  stop_thread(); ``global stop_type = 0 # 0 = stopj, 1 = stopl``) ends a running move with
  stopj, so the joints decelerate and the TCP leaves the line;
- a protective stop ends the running program (UR e-Series: the program stops and the
  operator must unlock the stop and start it again), so ur_rtde's script must be uploaded
  again (RTDEControlInterface::reuploadScript) after the unlock;
- the pendant's speed slider (:meth:`FakeURController.set_speed_slider`) scales motion time;
  the RTDE outputs ``target_speed_fraction`` and ``speed_scaling`` report it (RTDE guide);
- the RTDE watchdog (command 35, set_watchdog: ``rtde_set_watchdog`` on the command
  register, ur_rtde's setWatchdog/kickWatchdog): when no input package reaches the watched
  register within 1/min_frequency, the program stops and so does the arm;
- the dashboard reports local or remote control (:meth:`FakeURController.set_remote_control`).

The client's compiled code holds the GIL, so the fake runs in its own (spawned) process;
tests drive it through :class:`FakeURController`. Every fake gets its own 127.x.y.z
address because the client's ports are fixed.
"""

from __future__ import annotations

import collections
import dataclasses
import multiprocessing
import multiprocessing.connection
import re
import socket
import struct
import threading
import time
from typing import Any, Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from workcell.ur_kinematics import joint_frames, pose_to_matrix

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

# A UR5e "home": upper arm up, forearm forward, tool pointing down.
HOME_Q = (0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)

CONTROLLER_VERSION = (5, 11, 1, 108318)
POLYSCOPE_VERSION_LINE = "URSoftware 5.11.1.108318 (Mar 22 2021)"

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

# Codes the client reads (RTDE guide / ur_rtde enums).
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_MODES = {"normal": 1, "protective_stop": 3, "emergency_stop": 7}
SAFETY_STATUS_BITS = {"normal": 1 << 0, "protective_stop": 1 << 2, "emergency_stop": 1 << 6 | 1 << 7}
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
ROBOT_STATUS_POWER_ON, ROBOT_STATUS_PROGRAM_RUNNING = 1 << 0, 1 << 1

# ur_rtde control script handshake (output_int_register_0) and command numbers.
SCRIPT_READY, SCRIPT_DONE_WITH_COMMAND = 1, 2
CMD_NONE, CMD_MOVEJ, CMD_MOVEL, CMD_STOPL, CMD_STOPJ, CMD_SET_WATCHDOG, CMD_STOP_SCRIPT = 0, 1, 3, 33, 34, 35, 255
ASYNC_RUNNING_BIT = 1 << 15
PROGRAM_STOP_DECEL = 10.0  # m/s² or rad/s² when a program ends mid-move


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


def _skew(vector: np.ndarray) -> np.ndarray:
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula; plain numpy because scipy's per-call cost does not fit a tick."""
    k = _skew(axis)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix, robust at half turns (a tool pointing
    straight down is one)."""
    angle = float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-6:
        return _small_rotation_vector(rotation)
    sine_axis = _small_rotation_vector(rotation)
    if angle > np.pi - 1e-6:
        # Near a half turn R + I = 2 k k^T: take its largest column, signed like sin(angle) k.
        symmetric = rotation + np.eye(3)
        column = symmetric[:, int(np.argmax(np.linalg.norm(symmetric, axis=0)))]
        axis = column / np.linalg.norm(column)
        return angle * (-axis if float(axis @ sine_axis) < 0.0 else axis)
    return angle * sine_axis / np.sin(angle)


def _pose(transform: np.ndarray) -> np.ndarray:
    """[x, y, z, rx, ry, rz] (m, rad) of a 4x4 transform."""
    return np.concatenate([transform[:3, 3], _rotation_vector(transform[:3, :3])])


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs more than the whole IK step)."""
    return (a[:, [1, 2, 0]] * b[:, [2, 0, 1]]) - (a[:, [2, 0, 1]] * b[:, [1, 2, 0]])


def _small_rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix close to identity (error terms, per-tick turns)."""
    return 0.5 * np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )


@dataclasses.dataclass
class _Motion:
    """One move along a path parametrised by s in [0, length]: joint angle of the leading
    joint (moveJ, rad) or TCP travel (moveL, m; rad for a pure rotation)."""

    kind: str  # "joint" | "linear"
    start: np.ndarray  # joints (rad), or the TCP as a 4x4 transform
    target: np.ndarray
    length: float
    speed: float
    accel: float
    asynchronous: bool
    turn_axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    turn_angle: float = 0.0  # the moveL orientation change, as one rotation about turn_axis
    s: float = 0.0
    v: float = 0.0
    stop_decel: float | None = None  # set by stopL/stopJ

    @staticmethod
    def joint(q_start: np.ndarray, q_target: np.ndarray, speed: float, accel: float, asynchronous: bool) -> "_Motion":
        length = float(np.max(np.abs(q_target - q_start)))
        return _Motion("joint", q_start, q_target, length, speed, accel, asynchronous)

    @staticmethod
    def linear(
        tcp_start: np.ndarray, pose_target: np.ndarray, speed: float, accel: float, asynchronous: bool
    ) -> "_Motion":
        target = pose_to_matrix(pose_target)
        turn = Rotation.from_matrix(tcp_start[:3, :3].T @ target[:3, :3]).as_rotvec()
        turn_angle = float(np.linalg.norm(turn))
        travel = float(np.linalg.norm(target[:3, 3] - tcp_start[:3, 3]))
        length = travel if travel > 1e-9 else turn_angle
        motion = _Motion("linear", tcp_start, target, length, speed, accel, asynchronous)
        if turn_angle > 1e-12:
            motion.turn_axis, motion.turn_angle = turn / turn_angle, turn_angle
        return motion

    @property
    def finished(self) -> bool:
        return self.s >= self.length or (self.stop_decel is not None and self.v <= 0.0)

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds: accelerate, cruise, brake to arrive, or stop."""
        remaining = self.length - self.s
        if self.stop_decel is not None:
            self.v = max(0.0, self.v - self.stop_decel * dt)
        else:
            self.v = min(
                self.speed,
                self.v + self.accel * dt,
                float(np.sqrt(2.0 * self.accel * max(remaining, 0.0))) + self.accel * dt,
            )
        self.s = min(self.length, self.s + self.v * dt)

    def setpoint(self) -> np.ndarray:
        """Joint angles (joint move) or the TCP transform (linear move) at the current s:
        position on the straight line, orientation turned by the same fraction."""
        fraction = 1.0 if self.length <= 0.0 else self.s / self.length
        if self.kind == "joint":
            return self.start + fraction * (self.target - self.start)
        transform = np.eye(4)
        transform[:3, 3] = self.start[:3, 3] + fraction * (self.target[:3, 3] - self.start[:3, 3])
        transform[:3, :3] = self.start[:3, :3] @ _axis_angle_matrix(self.turn_axis, fraction * self.turn_angle)
        return transform


class _KinematicArm:
    """Joint state of a UR5e and its TCP; linear moves drive the joints by damped least
    squares inverse kinematics."""

    def __init__(self, q: Sequence[float]) -> None:
        self.q = np.asarray(q, dtype=np.float64)
        self.qd = np.zeros(6)
        self.tcp_transform = joint_frames(self.q)[-1]
        self.tcp = _pose(self.tcp_transform)
        self.tcp_speed = np.zeros(6)

    def update_tcp(self, previous_q: np.ndarray, dt: float) -> None:
        """Recompute the TCP and the joint and TCP velocities after the joints moved."""
        previous = self.tcp_transform
        self.tcp_transform = joint_frames(self.q)[-1]
        self.tcp = _pose(self.tcp_transform)
        self.qd = (self.q - previous_q) / dt
        self.tcp_speed = np.concatenate(
            [
                (self.tcp_transform[:3, 3] - previous[:3, 3]) / dt,
                _small_rotation_vector(self.tcp_transform[:3, :3] @ previous[:3, :3].T) / dt,
            ]
        )

    def track(self, target: np.ndarray, iterations: int) -> float:
        """Move the joints toward a TCP transform by damped least squares steps; return the
        position error (m) before the last step, which is what a failure shows in."""
        position_error = 0.0
        for _ in range(iterations):
            frames = joint_frames(self.q)
            tcp = frames[-1]
            error = np.concatenate(
                [
                    target[:3, 3] - tcp[:3, 3],
                    _small_rotation_vector(target[:3, :3] @ tcp[:3, :3].T),
                ]
            )
            position_error = float(np.linalg.norm(error[:3]))
            if np.linalg.norm(error) < 1e-13:
                break
            axes = np.array([frame[:3, 2] for frame in frames[:6]])
            lever = tcp[:3, 3] - np.array([frame[:3, 3] for frame in frames[:6]])
            jacobian = np.vstack([_cross_rows(axes, lever).T, axes.T])
            damping = 1e-9 * np.eye(6)
            self.q = self.q + jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping, error)
        return position_error


class _ControlScript:
    """What ur_rtde's uploaded control script does with the RTDE registers, tick by tick."""

    def __init__(self, register_offset: int) -> None:
        self.offset = register_offset
        self.executing_command = False
        self.blocking_motion: _Motion | None = None  # a synchronous move or stop in progress
        self.async_write_count = 0
        self.async_operation_id = 0


class _Controller:
    """The fake controller: arm, safety, registers, the running control script, and the
    sessions that talk to it. One lock guards all of it."""

    def __init__(self, host: str, state_rate_hz: float, initial_q: Sequence[float]) -> None:
        self.host = host
        self.dt = 1.0 / state_rate_hz
        self.state_rate_hz = state_rate_hz
        self.lock = threading.RLock()
        self.arm = _KinematicArm(initial_q)
        self.motion: _Motion | None = None
        self.script: _ControlScript | None = None
        self.safety = "normal"
        self.robot_mode = ROBOT_MODE_RUNNING
        self.registers: dict[str, Any] = {}
        self.ticks = 0
        self.commands_received: collections.deque[tuple[int, int]] = collections.deque(maxlen=10000)
        self.events: collections.deque[str] = collections.deque(maxlen=1000)
        self.rtde_sessions: list[_RTDESession] = []
        self.sockets: list[socket.socket] = []  # every accepted connection, for cut()
        self.listeners: list[socket.socket] = []
        self.running = True
        self.speed_fraction = 1.0  # the pendant's speed slider
        self.remote_control = True
        self.watchdog_period_s: float | None = None  # set by the script's set_watchdog
        self.watchdog_kicked = time.monotonic()
        self.outputs = self._modelled_outputs()

    # ---- values the RTDE outputs report -------------------------------------------
    def _modelled_outputs(self) -> dict[str, Any]:
        """This tick's values of the outputs the fake models; the others read as zero."""
        q, qd = self.arm.q.tolist(), self.arm.qd.tolist()
        tcp, tcp_speed = self.arm.tcp.tolist(), self.arm.tcp_speed.tolist()
        program_running = self.script is not None and self.safety == "normal"
        return {
            "timestamp": self.ticks * self.dt,
            "actual_q": q,
            "target_q": q,
            "actual_qd": qd,
            "target_qd": qd,
            "actual_TCP_pose": tcp,
            "target_TCP_pose": tcp,
            "actual_TCP_speed": tcp_speed,
            "target_TCP_speed": tcp_speed,
            "robot_mode": self.robot_mode,
            "safety_mode": SAFETY_MODES[self.safety],
            "safety_status": SAFETY_MODES[self.safety],
            "safety_status_bits": SAFETY_STATUS_BITS[self.safety],
            "robot_status_bits": ROBOT_STATUS_POWER_ON | (ROBOT_STATUS_PROGRAM_RUNNING if program_running else 0),
            "runtime_state": self.runtime_state(),
            "speed_scaling": self.speed_fraction,
            "target_speed_fraction": self.speed_fraction,
        }

    def output_value(self, name: str) -> Any:
        if name in self.registers:
            return self.registers[name]
        if name in self.outputs:
            return self.outputs[name]
        return zero_value(variable_type(name) or "DOUBLE")

    def runtime_state(self) -> int:
        if self.script is None:
            return RUNTIME_STOPPED
        return RUNTIME_PLAYING if self.safety == "normal" else RUNTIME_PAUSED

    # ---- the control loop -----------------------------------------------------------
    def tick(self) -> None:
        with self.lock:
            self.ticks += 1
            if self.safety == "normal":
                self._check_watchdog()
                self._run_script()
                self._move()
            else:
                self.arm.qd[:] = 0.0
                self.arm.tcp_speed[:] = 0.0
            self.outputs = self._modelled_outputs()
            sessions = [s for s in self.rtde_sessions if s.streaming]
        for session in sessions:
            session.send_state_if_due(self.ticks)

    def _move(self) -> None:
        arm, motion = self.arm, self.motion
        if motion is None:
            arm.qd[:] = 0.0
            arm.tcp_speed[:] = 0.0
            return
        previous_q = arm.q.copy()
        motion.step(self.dt * self.speed_fraction)
        if motion.kind == "joint":
            arm.q = motion.setpoint()
        else:
            # One step per tick keeps up with the setpoint; at the end, converge fully so
            # the arm stops exactly on the target. Falling a few ticks behind means the
            # pose has no IK solution.
            iterations = 50 if motion.finished else 1
            if arm.track(motion.setpoint(), iterations) > 1e-3 + 3.0 * motion.speed * self.dt:
                self._halt_program("movel: inverse kinematics found no solution")
        arm.update_tcp(previous_q, self.dt)
        if motion.finished:
            self.motion = None
            self._motion_ended(motion)

    def _motion_ended(self, motion: _Motion) -> None:
        script = self.script
        if script is None:
            return
        if script.blocking_motion is motion:
            script.blocking_motion = None
            self._write_int(0, SCRIPT_DONE_WITH_COMMAND)
        if motion.asynchronous:
            self._write_async_progress(-1)

    def _run_script(self) -> None:
        script = self.script
        if script is None or script.blocking_motion is not None:
            return
        command = int(self.registers.get(f"input_int_register_{script.offset}", CMD_NONE))
        if command == CMD_NONE:
            script.executing_command = False
            self._write_int(0, SCRIPT_READY)
        elif not script.executing_command:
            script.executing_command = True
            self._process_command(command)

    def _process_command(self, command: int) -> None:
        script = self.script
        assert script is not None
        doubles = [float(self.registers.get(f"input_double_register_{script.offset + i}", 0.0)) for i in range(8)]
        asynchronous = int(self.registers.get(f"input_int_register_{script.offset + 1}", 0)) == 1
        if command in (CMD_MOVEJ, CMD_MOVEL):
            self._stop_async_motion()
            target, speed, accel = np.array(doubles[:6]), doubles[6], doubles[7]
            if command == CMD_MOVEJ:
                motion = _Motion.joint(self.arm.q.copy(), target, speed, accel, asynchronous)
            else:
                motion = _Motion.linear(self.arm.tcp_transform, target, speed, accel, asynchronous)
            self.motion = motion
            self.events.append(f"{'movej' if command == CMD_MOVEJ else 'movel'} {target.tolist()}")
            if asynchronous:
                self._write_async_progress(0)
            else:
                script.blocking_motion = motion
                return
        elif command in (CMD_STOPL, CMD_STOPJ):
            # Both end a running move with stopj (see the module docstring).
            self.events.append(f"stopj {doubles[0]}")
            if self.motion is not None:
                self._stop_in_joint_space(doubles[0])
                if not asynchronous:
                    script.blocking_motion = self.motion
                    return
        elif command == CMD_SET_WATCHDOG:
            self.events.append(f"set_watchdog {doubles[0]}")
            self.watchdog_period_s = 1.0 / doubles[0]
            self.watchdog_kicked = time.monotonic()
        elif command == CMD_STOP_SCRIPT:
            self.events.append("stop script")
            self._end_program()
            return
        else:
            self._halt_program(f"command {command} is not emulated by the fake controller")
            return
        self._write_int(0, SCRIPT_DONE_WITH_COMMAND)

    def _stop_in_joint_space(self, decel_rad_s2: float) -> None:
        """stopj: every joint keeps its direction and slows at ``decel_rad_s2`` (the fastest
        one; the others in proportion), wherever that takes the TCP."""
        motion, qd = self.motion, self.arm.qd
        assert motion is not None
        lead = float(np.max(np.abs(qd)))
        if lead <= 0.0:
            motion.stop_decel = decel_rad_s2
            return
        q = self.arm.q.copy()
        stop = _Motion.joint(q, q + qd / lead, lead, decel_rad_s2, motion.asynchronous)
        stop.v, stop.stop_decel = lead, decel_rad_s2
        self.motion = stop
        if self.script is not None and self.script.blocking_motion is motion:
            self.script.blocking_motion = stop

    def _check_watchdog(self) -> None:
        """The watchdog's action: stop the program (and with it the arm) when the watched
        register has not been written for a period."""
        if self.script is None or self.watchdog_period_s is None:
            return
        if time.monotonic() - self.watchdog_kicked > self.watchdog_period_s:
            self.events.append("watchdog: no input in time, program stopped")
            self._end_program()

    def _stop_async_motion(self) -> None:
        if self.motion is not None and self.motion.asynchronous:
            self.motion = None
            self._write_async_progress(-1)

    def _write_int(self, register: int, value: int) -> None:
        assert self.script is not None
        self.registers[f"output_int_register_{self.script.offset + register}"] = value

    def _write_async_progress(self, progress: int) -> None:
        """Encode progress as the script's write_async_progress_register does: change count
        in bits 16-22, operation id in bits 24-30, bit 15 while running, progress below."""
        script = self.script
        assert script is not None
        script.async_write_count = (script.async_write_count + 1) % 128
        if progress == 0:
            script.async_operation_id = (script.async_operation_id + 1) % 128
        value = script.async_write_count * 65536 + script.async_operation_id * 16777216
        if progress >= 0:
            value += min(progress, 32767) + ASYNC_RUNNING_BIT
        self._write_int(2, value)

    def start_program(self, script_text: str) -> None:
        with self.lock:
            # ur_rtde injects the offset after the comment that marks its place.
            match = re.search(r"global reg_offset_int = (?:#[^\n]*\n)?\s*(\d+)", script_text)
            if "def rtde_control():" not in script_text or match is None:
                self.events.append("received a program that is not ur_rtde's control script")
                return
            self.motion = None
            self.script = _ControlScript(int(match.group(1)))
            self._write_async_progress(-1)
            self._write_int(0, SCRIPT_READY)
            self.events.append("control script started")

    def _end_program(self) -> None:
        self.script = None
        self.watchdog_period_s = None
        if self.motion is not None:
            self.motion.stop_decel = self.motion.stop_decel or PROGRAM_STOP_DECEL

    def _halt_program(self, reason: str) -> None:
        """A runtime error in the script: the program stops and the motion halts."""
        self.events.append(f"program halted: {reason}")
        self.script = None
        self.motion = None
        for session in self.rtde_sessions:
            session.send_text_message(reason, "fake_controller", TEXT_MESSAGE_EXCEPTION)

    # ---- operator and test actions ----------------------------------------------------
    def set_safety(self, safety: str) -> None:
        with self.lock:
            if safety not in SAFETY_MODES:
                raise ValueError(f"unknown safety state {safety!r}")
            self.safety = safety
            if safety != "normal":
                if self.script is not None:
                    self._stop_async_motion()
                    self.events.append(f"{safety}: program stopped")
                    self._end_program()
                self.motion = None

    def set_speed_slider(self, fraction: float) -> None:
        with self.lock:
            self.speed_fraction = float(fraction)

    def cut(self) -> None:
        """Drop every connection and stop accepting new ones, like a pulled network cable."""
        with self.lock:
            connections = self.listeners + self.sockets
            self.listeners, self.sockets = [], []
            for session in self.rtde_sessions:
                session.streaming = False
            self.events.append("connections cut")
        for sock in connections:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            offset = self.script.offset if self.script is not None else 0
            return {
                "command_register": self.registers.get(f"input_int_register_{offset}", CMD_NONE),
                "q": self.arm.q.tolist(),
                "qd": self.arm.qd.tolist(),
                "tcp_pose": self.arm.tcp.tolist(),
                "moving": self.motion is not None,
                "safety": self.safety,
                "program_running": self.script is not None,
                "commands_received": list(self.commands_received),
                "events": list(self.events),
                "controller_time_s": self.ticks * self.dt,
            }

    def note_command(self, name: str, value: Any, received_ns: int) -> None:
        """Log when a new command number reaches the script's command register."""
        offset = self.script.offset if self.script is not None else 0
        register = f"input_int_register_{offset}"
        if name == register and value != CMD_NONE and self.registers.get(register) != value:
            self.commands_received.append((received_ns, int(value)))


class _RTDESession:
    """One RTDE client connection: control packages in, data packages out."""

    def __init__(self, controller: _Controller, sock: socket.socket) -> None:
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
            self._send(package_type, struct.pack(">IIII", *CONTROLLER_VERSION))
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
                controller.note_command(name, value, received_ns)
                controller.registers[name] = value
                if controller.script is not None and name == f"input_int_register_{controller.script.offset}":
                    controller.watchdog_kicked = time.monotonic()

    def send_state_if_due(self, tick: int) -> None:
        if self.output_struct is None or tick % self.ticks_per_package:
            return
        with self.controller.lock:
            values = [self.controller.output_value(name) for name in self.output_names]
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


def _serve_dashboard(controller: _Controller, sock: socket.socket) -> None:
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


def _dashboard_answer(controller: _Controller, command: str) -> str:
    with controller.lock:
        controller.events.append(f"dashboard: {command}")
        running = controller.script is not None
        modes = {ROBOT_MODE_POWER_OFF: "POWER_OFF", ROBOT_MODE_IDLE: "IDLE", ROBOT_MODE_RUNNING: "RUNNING"}
        safety_names = {
            "normal": "NORMAL",
            "protective_stop": "PROTECTIVE_STOP",
            "emergency_stop": "ROBOT_EMERGENCY_STOP",
        }
        if command == "PolyscopeVersion":
            return POLYSCOPE_VERSION_LINE
        if command == "get serial number":
            return "20235500001"
        if command == "get robot model":
            return "UR5"
        if command == "is in remote control":
            return "true" if controller.remote_control else "false"
        if command == "robotmode":
            return f"Robotmode: {modes[controller.robot_mode]}"
        if command == "safetymode":
            return f"Safetymode: {safety_names[controller.safety]}"
        if command == "safetystatus":
            return f"Safetystatus: {safety_names[controller.safety]}"
        if command == "running":
            return f"Program running: {'true' if running else 'false'}"
        if command == "programState":
            return "PLAYING rtde_control" if running else "STOPPED <unnamed>"
        if command == "stop":
            if not running:
                return "Failed to execute: stop"
            controller._end_program()
            return "Stopped"
        if command == "play":
            return "Failed to execute: play"
        if command == "power on":
            controller.robot_mode = ROBOT_MODE_IDLE
            return "Powering on"
        if command == "power off":
            controller.robot_mode = ROBOT_MODE_POWER_OFF
            controller._end_program()
            return "Powering off"
        if command == "brake release":
            controller.robot_mode = ROBOT_MODE_RUNNING
            return "Brake releasing"
        if command == "unlock protective stop":
            if controller.safety != "protective_stop":
                return "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
            controller.safety = "normal"
            return "Protective stop releasing"
        if command == "close safety popup":
            return "closing safety popup"
        if command == "close popup":
            return "closing popup"
        if command.startswith("popup "):
            return "showing popup"
        if command == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"


def _serve_script(controller: _Controller, sock: socket.socket) -> None:
    """The script server: a program starts when its top-level ``def ...():`` block ends."""
    program = ""
    try:
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                break
            program += chunk.decode(errors="replace")
            while True:
                match = re.search(r"^def \w+\(\):\n.*?^end\s*$", program, re.S | re.M)
                if match is None:
                    break
                controller.start_program(match.group(0))
                program = program[match.end() :]
    except OSError:
        pass
    finally:
        sock.close()


def _accept_loop(controller: _Controller, listener: socket.socket, serve: Callable[[socket.socket], None]) -> None:
    while controller.running:
        try:
            sock, _ = listener.accept()
        except socket.timeout:
            continue
        except OSError:
            return  # the listener was closed by cut() or shutdown
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with controller.lock:
            controller.sockets.append(sock)
        threading.Thread(target=serve, args=(sock,), daemon=True).start()


def _serve_rtde(controller: _Controller, sock: socket.socket) -> None:
    session = _RTDESession(controller, sock)
    with controller.lock:
        controller.rtde_sessions.append(session)
    session.serve()


def _listen(host: str, port: int) -> socket.socket:
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind((host, port))
    listener.listen(8)
    listener.settimeout(0.2)
    return listener


def _controller_process(
    pipe: multiprocessing.connection.Connection, host: str, state_rate_hz: float, initial_q: Sequence[float]
) -> None:
    """Entry point of the fake's process: serve the ports, tick, and obey the test's pipe."""
    controller = _Controller(host, state_rate_hz, initial_q)
    try:
        servers = {RTDE_PORT: _serve_rtde, DASHBOARD_PORT: _serve_dashboard, SCRIPT_PORT: _serve_script}
        for port, serve in servers.items():
            listener = _listen(host, port)
            controller.listeners.append(listener)
            threading.Thread(
                target=_accept_loop, daemon=True, args=(controller, listener, lambda s, f=serve: f(controller, s))
            ).start()
    except OSError as error:
        pipe.send(("error", f"cannot listen on {host}: {error}"))
        return
    threading.Thread(target=_tick_loop, args=(controller,), daemon=True).start()
    pipe.send(("ready", None))
    while controller.running:
        request, argument = pipe.recv()
        if request == "snapshot":
            pipe.send(("ok", controller.snapshot()))
        elif request == "safety":
            controller.set_safety(argument)
            pipe.send(("ok", None))
        elif request == "speed_slider":
            controller.set_speed_slider(argument)
            pipe.send(("ok", None))
        elif request == "remote_control":
            with controller.lock:
                controller.remote_control = bool(argument)
            pipe.send(("ok", None))
        elif request == "cut":
            controller.cut()
            pipe.send(("ok", None))
        elif request == "shutdown":
            controller.running = False
            controller.cut()
            pipe.send(("ok", None))


def _tick_loop(controller: _Controller) -> None:
    """Tick at the state rate on a fixed schedule; after a stall, resume without bursts."""
    next_tick = time.monotonic()
    while controller.running:
        controller.tick()
        next_tick += controller.dt
        delay = next_tick - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_tick = time.monotonic()


class FakeURController:
    """Handle on a fake UR controller running in its own process on ``host`` (127.x.y.z).

    Use as a context manager; ``start()`` raises OSError if the address is taken.
    """

    def __init__(self, host: str, state_rate_hz: float = 500.0, initial_q: Sequence[float] = HOME_Q) -> None:
        self.host = host
        self.state_rate_hz = state_rate_hz
        self.initial_q = tuple(float(v) for v in initial_q)
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe: multiprocessing.connection.Connection | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        context = multiprocessing.get_context("spawn")
        self._pipe, child_pipe = context.Pipe()
        self._process = context.Process(
            target=_controller_process,
            daemon=True,
            name=f"fake-ur-{self.host}",
            args=(child_pipe, self.host, self.state_rate_hz, self.initial_q),
        )
        self._process.start()
        child_pipe.close()
        if not self._pipe.poll(timeout_s):
            self.close()
            raise TimeoutError(f"fake UR controller on {self.host} did not start in {timeout_s} s")
        status, message = self._pipe.recv()
        if status != "ready":
            self.close()
            raise OSError(message)

    def snapshot(self) -> dict[str, Any]:
        """Joints (rad), TCP pose, safety, program state, the command register (0 once
        the client has finished a command), received commands (``time.monotonic_ns()`` at
        receipt, command number) and an event log."""
        return self._request("snapshot")

    def set_safety(self, safety: str) -> None:
        """Enter "protective_stop" or "emergency_stop" (motion halts), or back to "normal"."""
        self._request("safety", safety)

    def set_speed_slider(self, fraction: float) -> None:
        """The pendant's speed slider, 0-1: motions run at this fraction of their speed."""
        self._request("speed_slider", fraction)

    def set_remote_control(self, remote: bool) -> None:
        """Remote control (True) or local control (False) on the pendant."""
        self._request("remote_control", remote)

    def cut_connections(self) -> None:
        """Drop all client connections and refuse new ones."""
        self._request("cut")

    def close(self) -> None:
        if self._process is None:
            return
        if self._process.is_alive() and self._pipe is not None:
            try:
                self._request("shutdown")
            except (OSError, EOFError):
                pass
        self._process.join(timeout=5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        if self._pipe is not None:
            self._pipe.close()
        self._process = None

    def _request(self, request: str, argument: Any = None) -> Any:
        assert self._pipe is not None, "start() the fake controller first"
        self._pipe.send((request, argument))
        if not self._pipe.poll(10.0):
            raise TimeoutError(f"fake UR controller on {self.host} did not answer {request!r}")
        status, value = self._pipe.recv()
        return value

    def __enter__(self) -> "FakeURController":
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
