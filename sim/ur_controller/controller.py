"""The fake UR controller's core: the arm, safety, the RTDE registers, and ur_rtde's control
script, advanced tick by tick; the interfaces (:mod:`sim.ur_controller.rtde`,
:mod:`sim.ur_controller.dashboard`, :mod:`sim.ur_controller.script`) read and drive it.

It does not interpret URScript. It recognises ``ur_rtde``'s control script and emulates
what that script does with the RTDE registers (ur_rtde 1.6.5, script of 14.02.2024):
``output_int_register_0`` says 1 (ready) or 2 (done with the command), the command number
arrives in ``input_int_register_0`` and its arguments in ``input_double_register_*`` and
``input_int_register_1``, and ``output_int_register_2`` reports asynchronous progress.
The robot is a kinematic UR5e, or UR5 on CB3 (:mod:`sim.ur_controller.motion`): moveJ interpolates the
joints, moveL the TCP (position linearly, orientation by slerp) with the joints following by
inverse kinematics, both with a trapezoidal speed profile.

It is as strict as the controller running what ur_rtde 1.6.5 uploads:

- a stop during a move is executed as ``stopj`` with the given deceleration in rad/s², for
  stopL too: the 1.6.5 control script (rtde_control.script, exec_stopl_stopj() and
  stop_thread(); ``global stop_type = 0 # 0 = stopj, 1 = stopl``) ends a running move with
  stopj, so the joints decelerate and the TCP leaves the line;
- a protective stop ends the running program (UR e-Series: the program stops and the
  operator must unlock the stop and start it again), so ur_rtde's script must be uploaded
  again (RTDEControlInterface::reuploadScript) after the unlock;
- the pendant's speed slider (:meth:`sim.ur_controller.FakeURController.set_speed_slider`)
  scales motion time; the RTDE outputs ``target_speed_fraction`` and ``speed_scaling`` report
  it (RTDE guide);
- the RTDE watchdog (command 35, set_watchdog: ``rtde_set_watchdog`` on the command
  register, ur_rtde's setWatchdog/kickWatchdog): when no input package reaches the watched
  register within 1/min_frequency, the program stops and so does the arm;
- it runs one software version (:mod:`sim.ur_controller.versions`): CB3 (3.x) or e-Series
  (5.x), which sets what the dashboard knows, the RTDE rate and whether there is a local and a
  remote control mode; an e-Series controller in local control does not run programs sent over
  the network (:meth:`sim.ur_controller.FakeURController.set_remote_control`);
- the script's command register has one cell (``input_int_register_0``), written by every
  input package that carries it, commands and ur_rtde's watchdog kicks (NO_CMD) alike, and
  read once a cycle (rtde_control.script, ``rtde_cmd()``); "done" stands until the register
  goes back to NO_CMD.

And it fails to answer the ways that register lets a real one (:data:`FAULTS`, injected per
command by :meth:`sim.ur_controller.FakeURController.inject_fault`): a command erased before
the script's cycle reads it, as a second writer's NO_CMD erases it (``lose_command``); a
"done" replaced by "ready" before any state package shows it, as a NO_CMD landing right after
the script's read makes it (``brief_done``; ur_rtde then waits its 300 s); the link dropped as
the command arrives (``cut_on_command``); and the dashboard's ``stop`` refused as a controller
refuses it ("Failed to execute: stop", ``refuse_dashboard_stop``).
"""

from __future__ import annotations

import collections
import re
import socket
import threading
import time
from typing import Any, Protocol, Sequence

import numpy as np

from sim.ur_controller.motion import KinematicArm, Motion
from sim.ur_controller.versions import SoftwareVersion

# A UR "home" (UR5e or UR5): upper arm up, forearm forward, tool pointing down.
HOME_Q = (0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)

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
FAULTS = ("lose_command", "brief_done", "cut_on_command", "refuse_dashboard_stop")


class StreamingSession(Protocol):
    """What the controller needs of an RTDE session (:class:`sim.ur_controller.rtde.RTDESession`):
    whether it streams, its data package at a tick, and a runtime error as a text message."""

    streaming: bool

    def send_state_if_due(self, tick: int) -> None: ...

    def send_exception(self, message: str, source: str) -> None: ...


class _ControlScript:
    """What ur_rtde's uploaded control script does with the RTDE registers, tick by tick."""

    def __init__(self, register_offset: int) -> None:
        self.offset = register_offset
        self.executing_command = False
        self.blocking_motion: Motion | None = None  # a synchronous move or stop in progress
        self.async_write_count = 0
        self.async_operation_id = 0
        self.brief_done = False  # the next "done" is cleared before a state package shows it


class Controller:
    """The fake controller: arm, safety, registers, the running control script, and the
    sessions that talk to it. One lock guards all of it."""

    def __init__(self, host: str, state_rate_hz: float, initial_q: Sequence[float], version: SoftwareVersion) -> None:
        self.host = host
        self.version = version
        self.dt = 1.0 / state_rate_hz
        self.state_rate_hz = state_rate_hz
        self.lock = threading.RLock()
        self.arm = KinematicArm(initial_q, version.arm_model)
        self.motion: Motion | None = None
        self.script: _ControlScript | None = None
        self.safety = "normal"
        self.robot_mode = ROBOT_MODE_RUNNING
        self.registers: dict[str, Any] = {}
        self.ticks = 0
        self.commands_received: collections.deque[tuple[int, int]] = collections.deque(maxlen=10000)
        self.events: collections.deque[str] = collections.deque(maxlen=1000)
        self.rtde_sessions: list[StreamingSession] = []
        self.sockets: list[socket.socket] = []  # every accepted connection, for cut()
        self.listeners: list[socket.socket] = []
        self.running = True
        self.speed_fraction = 1.0  # the pendant's speed slider
        self.remote_control = True  # e-Series only: CB3 has no local or remote control
        self.watchdog_period_s: float | None = None  # set by the script's set_watchdog
        self.watchdog_kicked = time.monotonic()
        self.faults: dict[str, int] = {}  # fault -> the command number it strikes (0: dashboard)
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

    def _motion_ended(self, motion: Motion) -> None:
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
                motion = Motion.joint(self.arm.q.copy(), target, speed, accel, asynchronous)
            else:
                motion = Motion.linear(self.arm.tcp_transform, target, speed, accel, asynchronous)
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
            self.end_program()
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
        stop = Motion.joint(q, q + qd / lead, lead, decel_rad_s2, motion.asynchronous)
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
            self.end_program()

    def _stop_async_motion(self) -> None:
        if self.motion is not None and self.motion.asynchronous:
            self.motion = None
            self._write_async_progress(-1)

    def _write_int(self, register: int, value: int) -> None:
        script = self.script
        assert script is not None
        if register == 0 and value == SCRIPT_DONE_WITH_COMMAND and script.brief_done:
            # A NO_CMD lands on the command register right after the script read it: the next
            # cycle sees no command and says "ready" before the client saw "done".
            script.brief_done = False
            script.executing_command = False
            self.registers[f"input_int_register_{script.offset}"] = CMD_NONE
            value = SCRIPT_READY
        self.registers[f"output_int_register_{script.offset + register}"] = value

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
            if not self.remote_control:
                self.events.append("program refused: the controller is in local control")
                return
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

    def end_program(self) -> None:
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
            session.send_exception(reason, "fake_controller")

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
                    self.end_program()
                self.motion = None

    def set_remote_control(self, remote: bool) -> None:
        with self.lock:
            if not self.version.e_series:
                raise ValueError("a CB3 controller has no local or remote control mode")
            self.remote_control = remote

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

    def write_input(self, name: str, value: Any, received_ns: int) -> None:
        """One value of an RTDE input package: a new command number is logged (when it was
        received, ``time.monotonic_ns()``), any write of the command register kicks the
        watchdog, and a fault injected for the command strikes it. A command overwritten before
        the script's cycle read it is logged as erased: a real controller loses it silently."""
        offset = self.script.offset if self.script is not None else 0
        register = f"input_int_register_{offset}"
        previous = self.registers.get(register, CMD_NONE)
        new_command = name == register and value != CMD_NONE and previous != value
        if new_command:
            self.commands_received.append((received_ns, int(value)))
        script = self.script
        if (
            name == register
            and previous not in (CMD_NONE, value)
            and script is not None
            and not script.executing_command
        ):
            self.events.append(f"command {previous} erased before the script read it")
        self.registers[name] = value
        if self.script is not None and name == register:
            self.watchdog_kicked = time.monotonic()
        if new_command:
            self._strike(int(value), register)

    def inject_fault(self, fault: str, command: int) -> None:
        """Let ``fault`` (one of FAULTS) strike the next ``command`` (a command number; 0 for
        the dashboard's stop)."""
        with self.lock:
            if fault not in FAULTS:
                raise ValueError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
            self.faults[fault] = int(command)

    def take_fault(self, fault: str, command: int) -> bool:
        """Whether ``fault`` was injected for ``command``; it strikes once."""
        if self.faults.get(fault) != command:
            return False
        del self.faults[fault]
        self.events.append(f"fault: {fault} {command}")
        return True

    def _strike(self, command: int, register: str) -> None:
        if self.take_fault("lose_command", command):
            self.registers[register] = CMD_NONE
        if self.take_fault("brief_done", command) and self.script is not None:
            self.script.brief_done = True
        if self.take_fault("cut_on_command", command):
            self.cut()
