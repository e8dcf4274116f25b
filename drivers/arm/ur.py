"""Universal Robots backend through ur_rtde (``RTDEControlInterface``, ``RTDEReceiveInterface``).

State comes from a receive interface at the RTDE rate; moves go through the control
interface, which uploads ur_rtde's control script and passes commands in RTDE registers.
Moves are sent *asynchronously* and awaited here, in Python: a blocking moveL holds the
script's command register for the whole motion, and no stop could be handed over meanwhile.

What the controller really does shapes the rest (ur_rtde 1.6.5 and its rtde_control.script):
the pendant's speed slider scales motion time, so a move's deadline stretches by the
``target_speed_fraction`` the controller reports; the script ends a running move with
``stopj`` whichever stop is asked for, so ``stop()`` sends stopJ with a joint deceleration
that means what it says; a protective stop ends the uploaded script, so a move after the
unlock uploads it again (``reuploadScript``); and the script's RTDE watchdog
(``setWatchdog``), kicked by a thread of this process, stops the robot when this process or
the link dies.

Every UR controller a lab may own works: connect() first asks the dashboard server the
controller's PolyScope version (:mod:`drivers.arm.ur_software`), streams RTDE at the fastest
rate that version serves unless told otherwise (125 Hz CB3, 500 Hz e-Series), and refuses
local control where the controller has that mode and can say so (e-Series from 5.6.0). A CB3
has no such mode; an e-Series before 5.6 cannot say, and in local control does not run the
uploaded script, so that failure's fix names remote control. ``identify()`` reports what was
found, for ``dtx hw check``.

Every call that waits on the controller has a deadline (URArmConfig's ``*_deadline_s``):
ur_rtde waits for its script's "done" up to 300 s (``UR_EXECUTION_TIMEOUT`` in
rtde_control_interface.h), so each call runs under :func:`drivers.call_with_deadline` (the
1.6.5 bindings release the GIL while they wait) and a late one raises ArmTimeoutError.

One writer of the script's command register at a time. ``input_int_register_0`` carries both
the commands and the watchdog's kicks (ur_rtde's kickWatchdog writes NO_CMD there, rtde.cpp),
and the script reads it once a cycle (rtde_control.script, ``rtde_cmd()``): a kick that lands
between a command and the script's read erases the command, and one that lands while the
script shows "done" turns it back to "ready" within a cycle, so a client that misses that
cycle waits 300 s. Every write therefore holds ``_register``, kicks included, and a command
waits for no motion (moves and stops are sent asynchronously and awaited here).

A stop is verified: ``stop()`` returns once the state says the arm is at rest, escalating as
UR's own tools do when it is not: the script's asynchronous stopJ, then the dashboard
server's ``stop`` (the program ends and the controller brakes the arm), then silence on the
link (the script's RTDE watchdog stops the program). ``read()`` reports what it took as
``ArmState.error_code`` (drivers.arm.base.ArmErrorCode).

The module is longer than 500 lines because one class keeps one controller's contract: connect, moves, the
verified stop and disconnect share its register lock, watchdog and state, and splitting them
would spread that shared state over modules.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Any, Callable, TypeVar

import dashboard_client
import numpy as np
import rtde_control
import rtde_receive
from scipy.spatial.transform import Rotation

from drivers import call_with_deadline, requires_connection
from drivers.arm.base import (
    Arm,
    ArmConnectionError,
    ArmError,
    ArmErrorCode,
    ArmTimeoutError,
    ConnectionLostError,
    EmergencyStopError,
    MotionAbortedError,
    MotionLimits,
    ProtectiveStopError,
    StopFailedError,
    WorkspaceBox,
    WorkspaceError,
    as_six_vector,
)
from drivers.arm.ur_software import ControllerSoftware
from msgs.base import Header
from msgs.robot import ArmState
from workcell.ur_kinematics import DH_PARAMETERS, tcp_pose

# What the receive interface subscribes to: only what read() needs, which keeps the RTDE
# stream small (the controller drops clients that do not drain it).
STATE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_qd",
    "actual_TCP_pose",
    "robot_mode",
    "safety_status_bits",
    "target_speed_fraction",
]
ROBOT_MODE_RUNNING = 7
ROBOT_MODE_NAMES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}
UR_JOINT_RANGE_RAD = 2.0 * np.pi
MOVING_SPEED_RAD_S = 1e-3
POLL_PERIOD_S = 0.002
SAFETY_REPORT_WAIT_S = 0.05
SCRIPT_START_TIMEOUT_S = 5.0  # a re-uploaded script reports running within this
REST_STATES = 3  # consecutive fresh states with every joint still: the arm is at rest

T = TypeVar("T")


@dataclasses.dataclass
class URArmConfig:
    """How to reach and drive a UR arm. Units: m, rad, s; speeds m/s or rad/s."""

    robot_ip: str = "192.168.1.10"
    # None: the fastest the controller streams, 125 Hz on CB3 and 500 Hz on e-Series.
    rtde_frequency_hz: float | None = None
    model: str = "ur5e"  # DH parameters used to check joint-move targets
    tcp_offset: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # as set on the pendant
    workspace: WorkspaceBox = dataclasses.field(default_factory=WorkspaceBox)
    limits: MotionLimits = dataclasses.field(default_factory=MotionLimits)
    stop_decel_rad_s2: float = 2.0  # stopj deceleration of the joints (every stop is a stopj)
    position_tolerance_m: float = 1e-3  # a linear move counts as arrived within this
    orientation_tolerance_rad: float = 5e-3
    joint_tolerance_rad: float = 2e-3  # a joint move counts as arrived within this
    stale_state_s: float = 0.5  # no new RTDE state for this long means the link is lost
    move_timeout_margin_s: float = 5.0  # added to the expected duration of a move
    # The robot stops when the script's watchdog hears nothing for 1/watchdog_hz s; this
    # process kicks it four times as often.
    watchdog_hz: float = 5.0
    # Deadlines of the calls that wait on the controller (s). A real controller hands a
    # command over in a few ms; connecting uploads and starts the control script.
    command_deadline_s: float = 1.0
    connect_deadline_s: float = 15.0
    dashboard_deadline_s: float = 3.0
    stop_margin_s: float = 0.5  # a stop escalates this long after its deceleration should have ended

    def __post_init__(self) -> None:
        if self.model not in DH_PARAMETERS:
            raise ValueError(f"unknown UR model {self.model!r}; known: {sorted(DH_PARAMETERS)}")
        self.tcp_offset = tuple(as_six_vector(self.tcp_offset, "tcp_offset"))
        if self.rtde_frequency_hz is not None and not 0 < self.rtde_frequency_hz < float("inf"):
            raise ValueError(
                f"rtde_frequency_hz must be a positive rate in Hz or left out, got {self.rtde_frequency_hz}"
            )
        for name in (
            "watchdog_hz",
            "command_deadline_s",
            "connect_deadline_s",
            "dashboard_deadline_s",
            "stop_margin_s",
        ):
            value = getattr(self, name)
            if not 0 < value < float("inf"):
                raise ValueError(f"{name} must be a positive number, got {value}")


class URArm(Arm):
    """A UR arm behind ur_rtde. Safe to call ``stop()`` and ``read()`` from another thread
    while a move is waiting."""

    def __init__(self, config: URArmConfig) -> None:
        self.config = config
        # ur_rtde's interfaces once connected (the binding has no type information).
        self._receive: Any = None  # rtde_receive.RTDEReceiveInterface
        self._control: Any = None  # rtde_control.RTDEControlInterface
        self._last_timestamp: float | None = None
        self._last_fresh = 0.0
        self._move_lock = threading.Lock()
        # Held by every write of the script's command register until ur_rtde's call returns,
        # even after its deadline: a late call may still clear the register.
        self._register = threading.Lock()
        self._error_code = ArmErrorCode.NONE
        self._kicking = threading.Event()  # set: the watchdog kicker should end
        self._kicker: threading.Thread | None = None
        self.software: ControllerSoftware | None = None  # known from connect() on

    def connect(self) -> None:
        """Ask the controller its software version, open the RTDE state stream at a rate it
        serves, check the arm can move, upload the control script and start its watchdog.

        Raises ArmConnectionError (unreachable, software not CB3 or e-Series, an arm model of
        the other series, rate too high, not powered, local control), ProtectiveStopError,
        EmergencyStopError; each with the operator's fix.
        """
        self.software = self._ask_software()
        self.software.check_arm_model(self.config.model)
        ip, frequency = self.config.robot_ip, self._rtde_frequency_hz()
        self._error_code = ArmErrorCode.NONE
        try:
            self._receive = self._connect_call(
                "open RTDE", lambda: rtde_receive.RTDEReceiveInterface(ip, frequency, STATE_VARIABLES)
            )
        except RuntimeError as error:
            raise ArmConnectionError(f"cannot open RTDE to the UR controller at {ip}: {error}") from error
        self._last_timestamp = None
        try:
            self._check_ready_to_move()
        except ArmError:
            self._receive.disconnect()
            self._receive = None
            raise
        try:
            self._control = self._connect_call(
                "start ur_rtde's control script",
                lambda: rtde_control.RTDEControlInterface(
                    ip, frequency, rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
                ),
            )
        except (RuntimeError, ArmTimeoutError) as error:
            self._receive.disconnect()
            self._receive = None
            raise ArmConnectionError(
                f"cannot start ur_rtde's control script on {ip} ({self.software.name}): {error}",
                self.software.script_fix,
            ) from error
        self._start_watchdog()

    def _connect_call(self, what: str, call: Callable[[], T]) -> T:
        """``call()`` within the connect deadline. A late one is abandoned: the interface it
        may still build is never used, and without our kicks its script's watchdog stays off
        (it is armed only by connect(), after this)."""
        return call_with_deadline(
            call, self.config.connect_deadline_s, f"UR at {self.config.robot_ip}: {what}", ArmTimeoutError
        )

    def _command(self, what: str, call: Callable[[], T], deadline_s: float | None = None) -> T:
        """``call()``, a ur_rtde call that writes the script's command register, once no
        other write is pending, within ``deadline_s`` (the command deadline by default)."""
        deadline_s = self.config.command_deadline_s if deadline_s is None else deadline_s
        if not self._register.acquire(timeout=deadline_s):
            raise ArmTimeoutError(
                f"{what}: the previous command to the UR controller is still pending after {deadline_s:g} s"
            )
        return call_with_deadline(call, deadline_s, what, ArmTimeoutError, on_return=self._register.release)

    def _dashboard(self, what: str, call: Callable[[Any], T]) -> T:
        """``call(client)`` on a dashboard connection of its own, connect to disconnect within
        the dashboard deadline (the server answers each query with one line)."""

        def session() -> T:
            dashboard = dashboard_client.DashboardClient(self.config.robot_ip)
            try:
                dashboard.connect()
                return call(dashboard)
            finally:
                dashboard.disconnect()

        return call_with_deadline(
            session,
            self.config.dashboard_deadline_s,
            f"UR dashboard at {self.config.robot_ip}: {what}",
            ArmTimeoutError,
        )

    def identify(self) -> str:
        return "" if self.software is None else f"UR controller {self.software.name}, {self.software.control_mode}"

    def _ask_software(self) -> ControllerSoftware:
        """The controller's software version from the dashboard server, and whether it is in
        remote control where it has that mode and can say (ArmConnectionError if it is not)."""
        ip = self.config.robot_ip

        def ask(dashboard: Any) -> tuple[ControllerSoftware, bool]:
            software = ControllerSoftware.parse(dashboard.polyscopeVersion())
            return software, dashboard.isInRemoteControl() if software.reports_remote_control else True

        try:
            software, remote = self._dashboard("software version", ask)
        except ArmTimeoutError as error:
            raise ArmConnectionError(error.reason, "check that the controller is on and reachable") from error
        except ArmError:
            raise  # the version's own error, which says what the controller answered
        except RuntimeError as error:
            raise ArmConnectionError(f"cannot reach the UR dashboard server at {ip}: {error}") from error
        if not remote:
            raise ArmConnectionError(
                f"UR at {ip} ({software.name}) is in local control",
                "switch the pendant to remote control (top right of PolyScope)",
            )
        return software

    def _rtde_frequency_hz(self) -> float:
        """The configured RTDE rate, or the fastest the controller streams when none is set."""
        assert self.software is not None
        fastest = self.software.max_rtde_frequency_hz
        if self.config.rtde_frequency_hz is None:
            return fastest
        if self.config.rtde_frequency_hz > fastest:
            raise ArmConnectionError(
                f"rtde_frequency_hz {self.config.rtde_frequency_hz:g} is faster than the {fastest:g} Hz "
                f"a {self.software.series} controller streams ({self.software.name})",
                f"set rtde_frequency_hz to {fastest:g} or less, or leave it out",
            )
        return self.config.rtde_frequency_hz

    def _check_ready_to_move(self) -> None:
        self._raise_if_unsafe(self.read(), "connect")
        robot_mode = self._receive.getRobotMode()
        if robot_mode != ROBOT_MODE_RUNNING:
            name = ROBOT_MODE_NAMES.get(robot_mode, str(robot_mode))
            raise ArmConnectionError(
                f"UR at {self.config.robot_ip} is in robot mode {name}",
                "power it on and release the brakes (pendant, or dashboard 'power on' then 'brake release')",
            )

    def _start_watchdog(self) -> None:
        """Arm the script's watchdog and kick it from a thread of this process: if the
        process or the link dies, the kicks stop and so does the robot."""
        control = self._control
        self._command("set the RTDE watchdog", lambda: control.setWatchdog(self.config.watchdog_hz))
        if self._kicker is not None and self._kicker.is_alive():
            return  # still kicking: a re-uploaded script only needed its watchdog set again
        self._kicking.clear()
        self._kicker = threading.Thread(target=self._kick_watchdog, name="ur-watchdog", daemon=True)
        self._kicker.start()

    def _kick_watchdog(self) -> None:
        period_s = 0.25 / self.config.watchdog_hz
        while not self._kicking.wait(period_s):
            control = self._control
            if control is None:
                return
            try:
                self._command("kick the RTDE watchdog", control.kickWatchdog)
            except ArmTimeoutError:
                continue  # a command holds the register; if it keeps it, the watchdog stops the arm
            except RuntimeError:
                return  # the link is gone: the robot stops by the watchdog, as it should

    def _reupload_script(self, description: str) -> None:
        """Upload ur_rtde's script again and wait until it runs (reuploadScript returns once
        it is sent, before the controller reports the program running)."""
        deadline = time.monotonic() + SCRIPT_START_TIMEOUT_S
        uploaded = self._command(
            "upload the control script", self._control.reuploadScript, deadline_s=SCRIPT_START_TIMEOUT_S
        )
        while uploaded and not self._control.isProgramRunning():
            if time.monotonic() > deadline:
                uploaded = False
            time.sleep(POLL_PERIOD_S)
        if not uploaded:
            assert self.software is not None
            raise ArmConnectionError(
                f"{description}: ur_rtde's control script did not start again", self.software.script_fix
            )
        self._start_watchdog()

    def _stop_watchdog(self) -> None:
        self._kicking.set()
        if self._kicker is not None:
            self._kicker.join()
            self._kicker = None

    @property
    def is_connected(self) -> bool:
        return self._receive is not None and self._control is not None

    def read(self) -> ArmState:
        """Latest state: TCP pose (m, rotation vector rad, base frame), joints (rad, rad/s).

        ``safety_status`` is "disconnected" when the stream closed or went stale, and before
        ``connect()``: the arm node publishes that state rather than failing, so read() is the
        one method of this backend that works unconnected.
        """
        receive = self._receive
        if receive is None:
            return ArmState(header=Header.now("base"), safety_status="disconnected", error_code=self._error_code)
        now = time.monotonic()
        timestamp = receive.getTimestamp()
        if timestamp != self._last_timestamp:
            self._last_timestamp, self._last_fresh = timestamp, now
        joint_velocities = np.array(receive.getActualQd())
        if not receive.isConnected() or now - self._last_fresh > self.config.stale_state_s:
            safety_status = "disconnected"
        elif receive.isEmergencyStopped():
            safety_status = "emergency_stop"
        elif receive.isProtectiveStopped():
            safety_status = "protective_stop"
        else:
            safety_status = "normal"
        return ArmState(
            header=Header.now("base"),
            tcp_pose=np.array(receive.getActualTCPPose()),
            joint_positions=np.array(receive.getActualQ()),
            joint_velocities=joint_velocities,
            moving=self._move_lock.locked() or bool(np.any(np.abs(joint_velocities) > MOVING_SPEED_RAD_S)),
            safety_status=safety_status,
            error_code=self._error_code,
        )

    @requires_connection
    def move_linear(self, tcp_pose: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        """Move the TCP in a straight line to ``tcp_pose`` [x, y, z, rx, ry, rz] (m, rad)
        at ``speed_m_s`` (m/s) and ``accel_m_s2`` (m/s²); block until it arrives.

        Checked before sending: workspace (WorkspaceError) and limits (MotionLimitError).
        """
        target = as_six_vector(tcp_pose, "tcp_pose")
        self.config.workspace.check(target)
        self.config.limits.check_linear(speed_m_s, accel_m_s2)
        start = self.read().tcp_pose
        travel = max(float(np.linalg.norm(target[:3] - start[:3])), _rotation_between(start, target))

        def arrived(state: ArmState) -> bool:
            return (
                float(np.linalg.norm(state.tcp_pose[:3] - target[:3])) <= self.config.position_tolerance_m
                and _rotation_between(state.tcp_pose, target) <= self.config.orientation_tolerance_rad
            )

        self._execute(
            f"moveL to {np.round(target, 4).tolist()}",
            send=lambda: self._control.moveL(target.tolist(), speed_m_s, accel_m_s2, True),
            arrived=arrived,
            expected_s=travel / speed_m_s + speed_m_s / accel_m_s2,
        )

    @requires_connection
    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Move the joints to ``q_rad`` (rad) at ``speed_rad_s`` (rad/s) and
        ``accel_rad_s2`` (rad/s²); block until it arrives.

        Checked before sending: the UR joint range and that the TCP at ``q_rad`` is inside
        the workspace (WorkspaceError), and limits (MotionLimitError).
        """
        target = as_six_vector(q_rad, "q_rad")
        for joint, angle in enumerate(target):
            if abs(angle) > UR_JOINT_RANGE_RAD:
                raise WorkspaceError(f"joint {joint} = {angle:.4f} rad is outside the UR range of ±2π rad")
        self.config.workspace.check(tcp_pose(target, self.config.model, np.array(self.config.tcp_offset)))
        self.config.limits.check_joint(speed_rad_s, accel_rad_s2)
        travel = float(np.max(np.abs(target - self.read().joint_positions)))

        def arrived(state: ArmState) -> bool:
            return float(np.max(np.abs(state.joint_positions - target))) <= self.config.joint_tolerance_rad

        self._execute(
            f"moveJ to {np.round(target, 4).tolist()}",
            send=lambda: self._control.moveJ(target.tolist(), speed_rad_s, accel_rad_s2, True),
            arrived=arrived,
            expected_s=travel / speed_rad_s + speed_rad_s / accel_rad_s2,
        )

    def stop(self) -> None:
        """Bring the arm to rest and return once its state says it is: every joint still for
        REST_STATES fresh states and no asynchronous operation of the script running. A move
        waiting in another thread then raises MotionAbortedError.

        Escalates while the arm is not at rest in its deceleration time plus ``stop_margin_s``
        (controller time): the script's asynchronous stopJ, then the dashboard's ``stop``, then
        silence on the link until the script's watchdog ends the program. ``read()`` then
        reports the step that worked as its error code. Raises StopFailedError if the arm still
        moves after all three (the fix: the emergency stop), ConnectionLostError (code
        STOP_UNVERIFIED) if the link is down and the stop cannot be seen.

        Sends stopJ: ur_rtde 1.6.5's script ends a running move with stopj whichever stop is
        asked for (rtde_control.script, exec_stopl_stopj() and stop_thread()), so a stopL
        would have its TCP deceleration applied to the joints."""
        state = self._state_for_stop()
        if state.safety_status != "normal":
            return  # a protective or emergency stop has already brought the arm to rest
        decel_s = float(np.max(np.abs(state.joint_velocities))) / self.config.stop_decel_rad_s2
        control = self._control
        try:
            self._command("stopJ", lambda: control.stopJ(self.config.stop_decel_rad_s2, True))
        except ArmTimeoutError:
            pass  # the script's state is unknown now: the dashboard's stop settles it
        else:
            if self._wait_for_rest(decel_s):
                # stopJ returns nothing: a script that ended while it waited (its watchdog,
                # unkicked while the command held the register, or the pendant) did not run it.
                program_running = control.isProgramRunning()
                self._error_code = ArmErrorCode.NONE if program_running else ArmErrorCode.STOP_BY_PROGRAM_END
                return
        try:
            self._dashboard("stop", lambda dashboard: dashboard.stop())
        except (ArmError, RuntimeError):
            pass  # refused or unanswered: the watchdog is the last resort
        else:
            if self._wait_for_rest(decel_s):
                self._error_code = ArmErrorCode.STOP_ESCALATED_DASHBOARD
                return
        self._stop_watchdog()  # the script hears nothing more: its watchdog ends the program
        if self._wait_for_rest(decel_s + 1.0 / self.config.watchdog_hz):
            self._error_code = ArmErrorCode.STOP_ESCALATED_WATCHDOG
            return
        self._error_code = ArmErrorCode.STOP_FAILED
        raise StopFailedError(
            f"the UR arm at {self.config.robot_ip} still moves after stopJ, the dashboard's stop and the watchdog",
            "press the emergency stop",
        )

    def _state_for_stop(self) -> ArmState:
        state = self.read()
        if state.safety_status == "disconnected":
            self._error_code = ArmErrorCode.STOP_UNVERIFIED
            raise ConnectionLostError(
                "cannot see the UR arm stop: no live connection to the controller",
                f"its watchdog stops the arm within {1.0 / self.config.watchdog_hz:g} s of silence; check it has",
                code=ArmErrorCode.STOP_UNVERIFIED,
            )
        return state

    def _wait_for_rest(self, decel_s: float) -> bool:
        """Whether the arm comes to rest within ``decel_s`` plus the stop margin, counted on
        the controller's clock (a stalled controller is no moving arm; a silent one raises
        ConnectionLostError through the staleness of its state)."""
        allowed_s = decel_s + self.config.stop_margin_s
        receive, control = self._receive, self._control
        start = last = receive.getTimestamp()
        still = 0
        while last - start <= allowed_s:
            state = self._state_for_stop()
            if state.safety_status != "normal":
                return True  # a safety stop holds the arm
            timestamp = receive.getTimestamp()
            if timestamp != last:
                last = timestamp
                joints_still = bool(np.all(np.abs(state.joint_velocities) <= MOVING_SPEED_RAD_S))
                operation_running = (
                    control.isProgramRunning() and control.getAsyncOperationProgressEx().isAsyncOperationRunning()
                )
                still = still + 1 if joints_still and not operation_running else 0
                if still >= REST_STATES:
                    return True
            time.sleep(POLL_PERIOD_S)
        return False

    def disconnect(self) -> None:
        """Stop ur_rtde's control script and close both RTDE connections, each within its
        deadline (a late one is abandoned: the script's watchdog is silent from here on)."""
        self._stop_watchdog()
        control, receive = self._control, self._receive
        self._control = self._receive = None
        if control is not None:
            if receive is not None and receive.isConnected() and control.isConnected():
                try:
                    self._command("stop the control script", control.stopScript)
                except ArmTimeoutError:
                    pass  # its watchdog ends the script within a period
            self._connect_call("close the control link", control.disconnect)
        if receive is not None:
            self._connect_call("close the state stream", receive.disconnect)

    def _execute(
        self, description: str, send: Callable[[], bool], arrived: Callable[[ArmState], bool], expected_s: float
    ) -> None:
        if not self._move_lock.acquire(blocking=False):
            raise ArmError(f"{description}: another move is in progress")
        try:
            self._raise_if_unsafe(self.read(), description)
            if not self._control.isProgramRunning():
                # A protective stop (or the pendant) ended the script; after the unlock it
                # has to be uploaded again, with its watchdog.
                self._reupload_script(description)
            # The script's operation id changes when the move starts, so a move counts
            # as finished only once it has started and then stopped running.
            operation_before = self._control.getAsyncOperationProgressEx().operationId()
            self._send_move(description, send)
            # The deadline runs in the controller's time: at the speed slider's fraction f a
            # move takes 1/f as long (at 0 the operator has paused it, and it waits).
            allowed_s = expected_s + self.config.move_timeout_margin_s
            # The controller's own clock (RTDE timestamp), not this computer's: a controller
            # that falls behind (a loaded simulator) does not run out of time it never had.
            elapsed_s, last = 0.0, self._receive.getTimestamp()
            while True:
                self._raise_if_unsafe(self.read(), description)
                if not self._control.isProgramRunning():
                    # A safety stop also stops the script; the receive stream may report it
                    # a few packages after the control stream, and it is the better error.
                    time.sleep(SAFETY_REPORT_WAIT_S)
                    self._raise_if_unsafe(self.read(), description)
                    raise MotionAbortedError(
                        f"{description}: ur_rtde's control script stopped running (program stopped on the pendant?)"
                    )
                status = self._control.getAsyncOperationProgressEx()
                if status.operationId() != operation_before and not status.isAsyncOperationRunning():
                    break
                now = self._receive.getTimestamp()
                elapsed_s += (now - last) * self._receive.getTargetSpeedFraction()
                last = now
                if elapsed_s > allowed_s:
                    self.stop()
                    raise MotionAbortedError(
                        f"{description}: not finished after {expected_s:.1f} s "
                        f"+ {self.config.move_timeout_margin_s} s at the speed "
                        "slider's pace; stopped"
                    )
                time.sleep(POLL_PERIOD_S)
            final = self.read()
            if not arrived(final):
                # A safety stop also ends a move short, and its report may come a few packages
                # after the move's end (as above): it is the better error.
                time.sleep(SAFETY_REPORT_WAIT_S)
                self._raise_if_unsafe(self.read(), description)
                raise MotionAbortedError(f"{description}: stopped short at TCP {np.round(final.tcp_pose, 4).tolist()}")
        finally:
            self._move_lock.release()

    def _send_move(self, description: str, send: Callable[[], bool]) -> None:
        """Hand the move to the script within the command deadline; a late hand-over may still
        start the move, so the arm is brought to rest before the ArmTimeoutError is raised."""
        try:
            accepted = self._command(description, send)
        except ArmTimeoutError:
            self._error_code = ArmErrorCode.COMMAND_TIMEOUT
            self.stop()
            raise
        if not accepted:
            self._raise_if_unsafe(self.read(), description)
            raise ArmError(f"{description}: the controller refused the command")
        self._error_code = ArmErrorCode.NONE

    @staticmethod
    def _raise_if_unsafe(state: ArmState, action: str) -> None:
        if state.safety_status == "disconnected":
            raise ConnectionLostError(f"{action}: lost the RTDE connection to the UR controller")
        if state.safety_status == "protective_stop":
            raise ProtectiveStopError(
                f"{action}: the UR controller is in a protective stop",
                "inspect the cause, then unlock it on the pendant",
            )
        if state.safety_status == "emergency_stop":
            raise EmergencyStopError(f"{action}: the UR emergency stop is active", "release it and restart the arm")


def _rotation_between(pose_a: np.ndarray, pose_b: np.ndarray) -> float:
    """Angle (rad) of the rotation taking the orientation of pose_a to that of pose_b."""
    return float((Rotation.from_rotvec(pose_b[3:6]) * Rotation.from_rotvec(pose_a[3:6]).inv()).magnitude())
