"""The UR backend driving the real ur_rtde client against a fake UR controller.

Most tests run the fake's default software (PolyScope 5.11); the last ones run it as each kind
of controller a lab may own: CB3 (3.15), e-Series before remote control could be queried (5.4)
and after (5.20). Each test runs its own fake controller process on its own 127.x.y.z address
(the client's ports are fixed), and every test has a time-out so a hung client fails instead
of blocking.
"""

from __future__ import annotations

import random
import socket
import threading
import time
from typing import Callable, Iterator

import dashboard_client
import numpy as np
import pytest
import rtde_receive

from drivers.arm import make_backend
from drivers.arm.base import (
    ArmConnectionError,
    ArmError,
    ArmErrorCode,
    ConnectionLostError,
    EmergencyStopError,
    MotionAbortedError,
    MotionLimitError,
    ProtectiveStopError,
    WorkspaceError,
)
from drivers.arm.ur import URArm
from drivers.cli import check_device, format_report
from dtx.launch import NodeSpec
from sim.ur_controller import CMD_MOVEL, CMD_SET_WATCHDOG, CMD_STOPJ, CMD_STOPL, HOME_Q, FakeURController
from workcell.ur_kinematics import tcp_pose

pytestmark = pytest.mark.timeout(90)

WORKSPACE = {"x_min_m": -0.8, "x_max_m": 0.8, "y_min_m": -0.8, "y_max_m": 0.8, "z_min_m": 0.1, "z_max_m": 0.8}


def start_fake_controller(software_version: str | None = None) -> FakeURController:
    """Start a fake on a free random loopback address (another run may hold one)."""
    for _ in range(10):
        host = f"127.{random.randint(32, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
        controller = FakeURController(host, software_version=software_version)
        try:
            controller.start()
        except OSError:
            continue
        return controller
    raise RuntimeError("no free loopback address for the fake UR controller")


@pytest.fixture
def fake() -> Iterator[FakeURController]:
    controller = start_fake_controller()
    try:
        yield controller
    finally:
        controller.close()


@pytest.fixture
def arm(fake: FakeURController) -> Iterator[URArm]:
    # The simulated controller shares two busy cores with the test run and can pause for a
    # moment; only a longer silence than a real cell would tolerate counts as a lost link here.
    # Likewise the watchdog: no kick goes out while a command is handed over, and a loaded
    # machine can stall that hand-over for most of a second; 1 Hz tolerates it, 5 Hz might not.
    backend = make_backend(arm_params(fake))
    backend.connect()
    try:
        yield backend
    finally:
        backend.disconnect()


def arm_params(fake: FakeURController, **extra: object) -> dict:
    return {
        "backend": "ur_rtde",
        "robot_ip": fake.host,
        "model": fake.version.arm_model,  # UR5e, or UR5 on CB3
        "workspace": WORKSPACE,
        "stale_state_s": 3.0,
        "watchdog_hz": 1.0,
        "command_deadline_s": 5.0,
        **extra,
    }


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting until {what}")
        time.sleep(0.005)


def move_in_thread(move: Callable[[], None]) -> tuple[threading.Thread, list[BaseException]]:
    """Run a blocking move in a thread; the list receives the error it raises, if any."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            move()
        except BaseException as error:  # noqa: BLE001 - handed to the test thread to assert on
            errors.append(error)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, errors


def wait_until_moving(fake: FakeURController) -> None:
    """Wait until the fake arm moves and the client has finished handing over the command:
    a cut inside that handshake would leave ur_rtde waiting out its 300 s time-out."""

    def moving_and_handed_over() -> bool:
        snapshot = fake.snapshot()
        return snapshot["moving"] and snapshot["command_register"] == 0

    wait_until(moving_and_handed_over, "the fake arm moves and the client cleared the command")


def sent_after_connect(fake: FakeURController) -> list[int]:
    """Commands received beyond the watchdog set up by connect()."""
    return [cmd for _, cmd in fake.snapshot()["commands_received"] if cmd != CMD_SET_WATCHDOG]


def commands(fake: FakeURController, number: int) -> list[int]:
    return [cmd for _, cmd in fake.snapshot()["commands_received"] if cmd == number]


def test_connect_reads_the_controller_state(fake: FakeURController, arm: URArm) -> None:
    state = arm.read()
    snapshot = fake.snapshot()
    assert snapshot["program_running"], "connect() should have started the control script"
    np.testing.assert_allclose(state.joint_positions, HOME_Q, atol=1e-12)
    np.testing.assert_allclose(state.tcp_pose, snapshot["tcp_pose"], atol=1e-12)
    np.testing.assert_allclose(state.tcp_pose, tcp_pose(np.array(HOME_Q)), atol=1e-9)
    assert state.safety_status == "normal"
    assert not state.moving


def test_move_linear_reaches_the_target(fake: FakeURController, arm: URArm) -> None:
    target = arm.read().tcp_pose + np.array([0.05, -0.03, -0.1, 0.0, 0.0, 0.0])
    arm.move_linear(target, speed_m_s=0.25, accel_m_s2=1.2)
    snapshot = fake.snapshot()
    np.testing.assert_allclose(snapshot["tcp_pose"], target, atol=1e-6)
    np.testing.assert_allclose(arm.read().tcp_pose, target, atol=1e-6)
    np.testing.assert_allclose(tcp_pose(np.array(snapshot["q"])), target, atol=1e-6)
    assert commands(fake, CMD_MOVEL) == [CMD_MOVEL]


def test_move_joints_reaches_the_target(fake: FakeURController, arm: URArm) -> None:
    target = np.array(HOME_Q) + np.array([0.3, -0.1, 0.2, 0.0, 0.1, -0.2])
    arm.move_joints(target, speed_rad_s=1.0, accel_rad_s2=1.4)
    snapshot = fake.snapshot()
    np.testing.assert_allclose(snapshot["q"], target, atol=1e-9)
    np.testing.assert_allclose(snapshot["tcp_pose"], tcp_pose(target), atol=1e-9)
    np.testing.assert_allclose(arm.read().joint_positions, target, atol=1e-9)


def test_a_target_outside_the_workspace_is_refused_before_sending(fake: FakeURController, arm: URArm) -> None:
    below_the_table = arm.read().tcp_pose.copy()
    below_the_table[2] = 0.05
    with pytest.raises(WorkspaceError, match=r"z = 0\.0500 m is below z_min_m = 0\.1 m"):
        arm.move_linear(below_the_table, speed_m_s=0.1, accel_m_s2=1.0)
    folded_into_the_table = np.array(HOME_Q) + np.array([0.0, 1.2, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(WorkspaceError, match="z_min_m"):
        arm.move_joints(folded_into_the_table, speed_rad_s=0.5, accel_rad_s2=1.0)
    assert sent_after_connect(fake) == []


def test_a_speed_over_the_limit_is_refused_before_sending(fake: FakeURController, arm: URArm) -> None:
    target = arm.read().tcp_pose + np.array([0.0, 0.0, -0.05, 0.0, 0.0, 0.0])
    with pytest.raises(MotionLimitError, match="TCP speed 0.5 m/s exceeds the limit of 0.25 m/s"):
        arm.move_linear(target, speed_m_s=0.5, accel_m_s2=1.0)
    with pytest.raises(MotionLimitError, match="joint acceleration"):
        arm.move_joints(np.array(HOME_Q), speed_rad_s=0.5, accel_rad_s2=10.0)
    assert sent_after_connect(fake) == []


def test_a_move_is_refused_while_the_controller_is_in_protective_stop(fake: FakeURController, arm: URArm) -> None:
    fake.set_safety("protective_stop")
    wait_until(lambda: arm.read().safety_status == "protective_stop", "the stop is reported")
    target = arm.read().tcp_pose + np.array([0.0, 0.0, -0.05, 0.0, 0.0, 0.0])
    with pytest.raises(ProtectiveStopError, match="protective stop"):
        arm.move_linear(target, speed_m_s=0.1, accel_m_s2=1.0)
    assert commands(fake, CMD_MOVEL) == []


def test_a_protective_stop_during_a_move_raises(fake: FakeURController, arm: URArm) -> None:
    target = arm.read().tcp_pose + np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))
    wait_until_moving(fake)
    fake.set_safety("protective_stop")
    thread.join()
    assert len(errors) == 1 and isinstance(errors[0], ProtectiveStopError)
    assert arm.read().safety_status == "protective_stop"


def test_connect_to_a_controller_in_protective_stop_says_so(fake: FakeURController) -> None:
    fake.set_safety("protective_stop")
    backend = make_backend({"backend": "ur_rtde", "robot_ip": fake.host})
    with pytest.raises(ProtectiveStopError, match="unlock it on the pendant"):
        backend.connect()
    assert not fake.snapshot()["program_running"]


def test_a_connection_cut_mid_motion_raises_connection_lost(fake: FakeURController, arm: URArm) -> None:
    target = arm.read().tcp_pose + np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))
    wait_until_moving(fake)
    fake.cut_connections()
    thread.join(timeout=30.0)
    assert not thread.is_alive(), "the move hung after the connection was cut"
    assert len(errors) == 1 and isinstance(errors[0], ConnectionLostError)
    assert arm.read().safety_status == "disconnected"
    with pytest.raises(ConnectionLostError):
        arm.stop()


def test_stop_interrupts_a_move_with_the_stopj_the_script_runs(fake: FakeURController, arm: URArm) -> None:
    """U3: ur_rtde 1.6.5's script ends a moveL with stopj; the driver sends stopJ with a joint
    deceleration, so the deceleration configured is the one applied."""
    start = arm.read().tcp_pose
    target = start + np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))
    wait_until_moving(fake)
    arm.stop()
    thread.join()
    assert len(errors) == 1 and isinstance(errors[0], MotionAbortedError)
    snapshot = fake.snapshot()
    assert commands(fake, CMD_STOPJ) == [CMD_STOPJ] and commands(fake, CMD_STOPL) == []
    assert f"stopj {arm.config.stop_decel_rad_s2}" in snapshot["events"]
    assert not snapshot["moving"]
    assert 0.0 < snapshot["tcp_pose"][1] - start[1] < 0.3
    assert not arm.read().moving


def test_an_unreachable_controller_is_a_connection_error() -> None:
    backend = make_backend({"backend": "ur_rtde", "robot_ip": "127.0.0.254"})
    with pytest.raises(ArmConnectionError, match="127.0.0.254"):
        backend.connect()


def test_the_fake_packs_every_variable_of_the_clients_default_recipe(fake: FakeURController) -> None:
    # With no variable list, RTDEReceiveInterface subscribes to everything it knows for the
    # controller version; one wrongly sized type would shift every value after it.
    receive = rtde_receive.RTDEReceiveInterface(fake.host, 500.0)
    try:
        wait_until(lambda: receive.getTimestamp() > 0.0, "states arrive")
        np.testing.assert_allclose(receive.getActualQ(), HOME_Q, atol=1e-12)
        np.testing.assert_allclose(receive.getActualTCPPose(), tcp_pose(np.array(HOME_Q)), atol=1e-9)
        assert receive.getRobotMode() == 7  # RUNNING
        assert receive.getSafetyMode() == 1  # NORMAL
        assert receive.getSafetyStatusBits() == 1  # normal mode bit
        assert receive.getSpeedScaling() == 1.0
        assert receive.getRuntimeState() == 1  # STOPPED: no program uploaded yet
    finally:
        receive.disconnect()


def test_read_reports_an_emergency_stop(fake: FakeURController, arm: URArm) -> None:
    fake.set_safety("emergency_stop")
    wait_until(lambda: arm.read().safety_status == "emergency_stop", "the stop is reported")
    with pytest.raises(EmergencyStopError, match="emergency stop"):
        arm.move_joints(np.array(HOME_Q), speed_rad_s=0.5, accel_rad_s2=1.0)


def test_connect_to_a_powered_off_arm_says_how_to_fix_it(fake: FakeURController) -> None:
    dashboard = dashboard_client.DashboardClient(fake.host)
    dashboard.connect()
    try:
        dashboard.powerOff()
        backend = make_backend({"backend": "ur_rtde", "robot_ip": fake.host})
        with pytest.raises(ArmConnectionError, match="POWER_OFF; fix: power it on and release the brakes"):
            backend.connect()
        dashboard.powerOn()
        dashboard.brakeRelease()
        assert dashboard.robotmode() == "Robotmode: RUNNING"
        backend.connect()
        backend.disconnect()
    finally:
        dashboard.disconnect()


def test_the_move_deadline_follows_the_speed_slider(fake: FakeURController) -> None:
    """U1: at 20 % a 0.3 rad joint move (0.93 s at full speed, 4.6 s here) is no time-out."""
    backend = make_backend(arm_params(fake, move_timeout_margin_s=2.0))
    backend.connect()
    try:
        fake.set_speed_slider(0.2)
        target = np.array(HOME_Q) + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
        backend.move_joints(target, speed_rad_s=1.0, accel_rad_s2=1.4)
        np.testing.assert_allclose(fake.snapshot()["q"], target, atol=1e-9)
    finally:
        backend.disconnect()


def test_a_move_after_an_unlocked_protective_stop_uploads_the_script_again(fake: FakeURController, arm: URArm) -> None:
    """U2: the protective stop ended the control script; after the unlock the next move
    re-uploads it instead of being refused."""
    fake.set_safety("protective_stop")
    wait_until(lambda: arm.read().safety_status == "protective_stop", "the stop is reported")
    assert not fake.snapshot()["program_running"]
    dashboard = dashboard_client.DashboardClient(fake.host)
    dashboard.connect()
    try:
        dashboard.unlockProtectiveStop()
    finally:
        dashboard.disconnect()
    wait_until(lambda: arm.read().safety_status == "normal", "the unlock is reported")
    target = arm.read().tcp_pose + np.array([0.0, 0.0, -0.05, 0.0, 0.0, 0.0])
    arm.move_linear(target, speed_m_s=0.25, accel_m_s2=1.2)
    np.testing.assert_allclose(fake.snapshot()["tcp_pose"], target, atol=1e-6)
    assert fake.snapshot()["events"].count("control script started") == 2


def start_a_move_of(
    arm: URArm, fake: FakeURController, distance_m: float = 0.3
) -> tuple[threading.Thread, list[BaseException], np.ndarray]:
    target = arm.read().tcp_pose + np.array([0.0, distance_m, 0.0, 0.0, 0.0, 0.0])
    thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))
    wait_until_moving(fake)
    return thread, errors, target


def assert_stopped_short(
    fake: FakeURController, thread: threading.Thread, errors: list[BaseException], target: np.ndarray
) -> None:
    thread.join(timeout=30.0)
    assert not thread.is_alive(), "the move still waits after the stop returned"
    assert len(errors) == 1 and isinstance(errors[0], MotionAbortedError), errors
    snapshot = fake.snapshot()
    assert not snapshot["moving"]
    assert abs(snapshot["tcp_pose"][1] - target[1]) > 0.01, "the move reached its target: the stop was lost"


@pytest.fixture
def quick_arm(fake: FakeURController) -> Iterator[URArm]:
    """An arm whose stop times out well before the script's watchdog would end its wait (the
    test sets ``command_deadline_s`` once its move runs, so a loaded machine starts it)."""
    backend = make_backend(arm_params(fake, watchdog_hz=0.5))
    backend.connect()
    try:
        yield backend
    finally:
        backend.disconnect()


def test_an_erased_stop_is_carried_out_by_the_watchdog_it_leaves_unkicked(fake: FakeURController, arm: URArm) -> None:
    """The erased stop of issue 55, which let the move go on to its target: the pending stopJ
    holds the command register, so no kick reaches the watchdog, which ends the program."""
    thread, errors, target = start_a_move_of(arm, fake)
    fake.inject_fault("lose_command", CMD_STOPJ)
    arm.stop()
    assert_stopped_short(fake, thread, errors, target)
    assert arm.read().error_code == ArmErrorCode.STOP_BY_PROGRAM_END
    assert "watchdog: no input in time, program stopped" in fake.snapshot()["events"]


@pytest.mark.parametrize(
    ("faults", "code", "event"),
    [
        # A stop erased before the script's cycle read it.
        ([("lose_command", CMD_STOPJ)], ArmErrorCode.STOP_ESCALATED_DASHBOARD, "dashboard: stop"),
        # A "done" the client misses: ur_rtde would wait 300 s; the stop's deadline ends that wait.
        ([("brief_done", CMD_STOPJ)], ArmErrorCode.STOP_ESCALATED_DASHBOARD, "dashboard: stop"),
        # The stop erased and the dashboard's refused: silence until the watchdog ends the program.
        (
            [("lose_command", CMD_STOPJ), ("refuse_dashboard_stop", 0)],
            ArmErrorCode.STOP_ESCALATED_WATCHDOG,
            "watchdog: no input in time, program stopped",
        ),
    ],
)
def test_a_stop_the_controller_does_not_answer_escalates_until_the_arm_rests(
    fake: FakeURController, quick_arm: URArm, faults: list[tuple[str, int]], code: str, event: str
) -> None:
    arm = quick_arm
    thread, errors, target = start_a_move_of(arm, fake)
    for fault, command in faults:
        fake.inject_fault(fault, command)
    arm.config.command_deadline_s = 0.2
    arm.stop()
    arm.config.command_deadline_s = 5.0
    assert_stopped_short(fake, thread, errors, target)
    assert arm.read().error_code == code
    events = fake.snapshot()["events"]
    assert event in events and all(f"fault: {fault} {command}" in events for fault, command in faults)
    # The program ended; the next move uploads it again and clears the code.
    arm.move_linear(arm.read().tcp_pose + np.array([0.0, 0.0, -0.02, 0.0, 0.0, 0.0]), 0.25, 1.2)
    assert arm.read().error_code == ArmErrorCode.NONE and fake.snapshot()["program_running"]


def test_a_link_dropped_during_a_stop_is_reported_as_unverified(fake: FakeURController, arm: URArm) -> None:
    thread, errors, target = start_a_move_of(arm, fake)
    fake.inject_fault("cut_on_command", CMD_STOPJ)
    with pytest.raises(ConnectionLostError, match="cannot see the UR arm stop") as raised:
        arm.stop()
    assert raised.value.code == ArmErrorCode.STOP_UNVERIFIED
    assert arm.read().error_code == ArmErrorCode.STOP_UNVERIFIED
    wait_until(lambda: not fake.snapshot()["moving"], "the arm stops")
    thread.join(timeout=30.0)
    assert not thread.is_alive() and errors


def test_watchdog_kicks_never_erase_a_command(fake: FakeURController) -> None:
    """Kicks every 25 ms beside moves and stops: each command reaches the script, and every
    stop stops its move short. A loaded machine may stall a hand-over past the 100 ms watchdog,
    which then ends the program (its job): such a trial's move ends before it can be stopped
    and is not counted, and the stop's code is not asserted."""
    arm = make_backend(arm_params(fake, watchdog_hz=10.0))
    arm.connect()
    stopped = 0
    try:
        for trial in range(8):
            target = arm.read().tcp_pose + np.array([0.0, 0.2 if trial % 2 == 0 else -0.2, 0.0, 0.0, 0.0, 0.0])
            thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))
            wait_until(
                lambda: not thread.is_alive()
                or (fake.snapshot()["moving"] and fake.snapshot()["command_register"] == 0),
                "the move runs or ends",
            )
            if not thread.is_alive():
                continue
            arm.stop()
            assert_stopped_short(fake, thread, errors, target)
            stopped += 1
    finally:
        arm.disconnect()
    assert stopped >= 1
    assert not [event for event in fake.snapshot()["events"] if "erased" in event]


def test_a_controller_that_accepts_and_never_answers_fails_connect_within_its_deadline() -> None:
    host = f"127.{random.randint(32, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
    silent = socket.create_server((host, 29999))
    try:
        arm = make_backend({"backend": "ur_rtde", "robot_ip": host, "dashboard_deadline_s": 0.5})
        with pytest.raises(ArmConnectionError, match="no answer within 0.5 s"):
            arm.connect()
    finally:
        silent.close()


def test_the_watchdog_stops_the_arm_when_the_link_is_cut(fake: FakeURController, arm: URArm) -> None:
    """U4: with the cable pulled the arm must not finish its last move unattended."""
    start = arm.read().tcp_pose
    target = start + np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    thread, errors = move_in_thread(lambda: arm.move_linear(target, 0.1, 1.0))  # 3.1 s
    wait_until_moving(fake)
    fake.cut_connections()
    wait_until(lambda: not fake.snapshot()["moving"], "the arm stops")
    snapshot = fake.snapshot()
    assert "watchdog: no input in time, program stopped" in snapshot["events"]
    assert snapshot["tcp_pose"][1] - start[1] < 0.25
    thread.join(timeout=30.0)
    assert errors and isinstance(errors[0], ArmError)


@pytest.mark.parametrize(
    "fault, reason, fix",
    [
        ("power_off", "is in robot mode POWER_OFF", "power it on and release the brakes"),
        ("local", "is in local control", "switch the pendant to remote control"),
        ("protective_stop", "the UR controller is in a protective stop", "inspect the cause, then unlock it"),
    ],
)
def test_hw_check_refuses_an_arm_that_cannot_move(fake: FakeURController, fault: str, reason: str, fix: str) -> None:
    if fault == "power_off":
        dashboard = dashboard_client.DashboardClient(fake.host)
        dashboard.connect()
        dashboard.powerOff()
        dashboard.disconnect()
    elif fault == "local":
        fake.set_remote_control(False)
    else:
        fake.set_safety("protective_stop")
    check = check_device(NodeSpec(name="arm", module="nodes.arm", params=arm_params(fake)))
    assert not check.ok
    assert check.error.endswith(reason) and check.fix.startswith(fix)
    assert not fake.snapshot()["program_running"]


# ---- every controller a lab may own ------------------------------------------------------
VERSIONS = ["3.15", "5.4", "5.20"]


@pytest.fixture(params=VERSIONS)
def versioned_fake(request: pytest.FixtureRequest) -> Iterator[FakeURController]:
    controller = start_fake_controller(request.param)
    try:
        yield controller
    finally:
        controller.close()


def hw_check(fake: FakeURController, **extra: object):
    return check_device(NodeSpec(name="arm", module="nodes.arm", params=arm_params(fake, **extra)))


def dashboard_commands(fake: FakeURController) -> list[str]:
    return [event.removeprefix("dashboard: ") for event in fake.snapshot()["events"] if event.startswith("dashboard: ")]


def test_every_version_connects_checks_and_moves_at_the_speed_sliders_pace(versioned_fake: FakeURController) -> None:
    """1 rad at 1 rad/s (1.7 s at full speed) with the slider at 30 %: 5.7 s, no time-out."""
    fake, version = versioned_fake, versioned_fake.version
    check = hw_check(fake)
    assert check.ok, check.error
    series = "CB3" if version.major == 3 else "e-Series"
    assert check.identity.startswith(f"UR controller PolyScope {version.major}.{version.minor}.0.0, {series}")
    assert format_report([check]).splitlines()[1].split() == ["found:", *check.identity.split()]
    backend = make_backend(arm_params(fake))
    backend.connect()
    try:
        fake.set_speed_slider(0.3)
        target = np.array(HOME_Q) + np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        backend.move_joints(target, speed_rad_s=1.0, accel_rad_s2=1.4)
        np.testing.assert_allclose(fake.snapshot()["q"], target, atol=1e-9)
    finally:
        backend.disconnect()
    # Only a controller that can answer is asked whether it is in remote control.
    assert ("is in remote control" in dashboard_commands(fake)) == (version.numbers >= (5, 6))


def test_every_version_refuses_an_arm_that_is_powered_off_or_in_a_protective_stop(
    versioned_fake: FakeURController,
) -> None:
    fake = versioned_fake
    dashboard = dashboard_client.DashboardClient(fake.host)
    dashboard.connect()
    try:
        dashboard.powerOff()
        check = hw_check(fake)
        assert not check.ok and check.error.endswith("is in robot mode POWER_OFF")
        dashboard.powerOn()
        dashboard.brakeRelease()
        fake.set_safety("protective_stop")
        check = hw_check(fake)
        assert not check.ok and check.error.endswith("the UR controller is in a protective stop")
        dashboard.unlockProtectiveStop()
    finally:
        dashboard.disconnect()
    assert hw_check(fake).ok
    assert not fake.snapshot()["program_running"]


def test_local_control_is_refused_where_the_controller_has_that_mode(versioned_fake: FakeURController) -> None:
    fake, version = versioned_fake, versioned_fake.version
    if version.major == 3:
        with pytest.raises(ValueError, match="CB3 controller has no local or remote control mode"):
            fake.set_remote_control(False)
        return
    fake.set_remote_control(False)
    check = hw_check(fake)
    assert not check.ok
    if version.numbers >= (5, 6):
        # Asked and answered: refused before anything is uploaded.
        assert check.error.endswith(f"(PolyScope {version.major}.{version.minor}.0.0) is in local control")
        assert check.fix.startswith("switch the pendant to remote control")
    else:
        # It cannot say, and does not run the uploaded script: the failed start names the cause.
        assert "cannot start ur_rtde's control script" in check.error
        assert check.fix.startswith(
            f"check that the pendant is in remote control (PolyScope {version.major}.{version.minor}.0.0 cannot report it)"
        )
        assert "program refused: the controller is in local control" in fake.snapshot()["events"]
    assert not fake.snapshot()["program_running"]


def test_dashboard_answers_follow_the_software_version(versioned_fake: FakeURController) -> None:
    fake, version = versioned_fake, versioned_fake.version
    dashboard = dashboard_client.DashboardClient(fake.host)
    dashboard.connect()
    try:
        assert dashboard.polyscopeVersion() == f"{version.major}.{version.minor}.0.0"
        # ur_rtde refuses to ask an older controller; it would not have understood.
        assert dashboard.isInRemoteControl() == (version.numbers >= (5, 6))
        assert dashboard.safetystatus() == (
            "Safetystatus: NORMAL" if version.numbers >= (5, 4) else "could not understand: 'safetystatus'"
        )
    finally:
        dashboard.disconnect()


def test_a_cb3_streams_at_125_hz_and_a_faster_rate_or_an_e_series_arm_is_refused() -> None:
    fake = start_fake_controller("3.15")
    try:
        check = hw_check(fake, model="ur5e")
        assert not check.ok
        assert check.error.endswith("model 'ur5e' is not among the arms CB3 controllers drive (PolyScope 3.15.0.0)")
        assert check.fix == "set the arm's model to the CB3 arm (ur3, ur5, ur10), e.g. ur5"
        check = hw_check(fake, rtde_frequency_hz=500.0)
        assert not check.ok
        assert check.error.endswith(
            "rtde_frequency_hz 500 is faster than the 125 Hz a CB3 controller streams (PolyScope 3.15.0.0)"
        )
        assert check.fix == "set rtde_frequency_hz to 125 or less, or leave it out"
        receive = rtde_receive.RTDEReceiveInterface(fake.host, 125.0, ["timestamp"])
        try:
            wait_until(lambda: receive.getTimestamp() > 0.0, "states arrive")
            ticks = receive.getTimestamp() * 125  # the controller's clock runs in 8 ms steps
            assert ticks == pytest.approx(round(ticks), abs=1e-6)
        finally:
            receive.disconnect()
    finally:
        fake.close()
