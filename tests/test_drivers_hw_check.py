"""``dtx hw check``: every configured device is connected and reported, OK or why not."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
from pathlib import Path

import pytest
import yaml

from drivers.cli import HARDWARE_NODES, add_commands, check_devices, format_report
from dtx.launch import NodeSpec, load_launch

LAB_LAUNCH = Path(__file__).resolve().parent.parent / "launch" / "collect_lab.yaml"
node_modules_present = all(
    importlib.util.find_spec(f"nodes.{kind}") is not None for kind in ("depth_camera", "gelsight", "arm", "gripper")
)
needs_node_modules = pytest.mark.skipif(
    not node_modules_present, reason="the hardware node modules (nodes.*) are not written yet"
)


@pytest.fixture
def mixed_nodes(tmp_path):
    return [
        NodeSpec(name="gripper_sim", module="nodes.gripper", params={"backend": "simulated"}),
        NodeSpec(
            name="gripper", module="nodes.gripper", params={"backend": "wsg50", "port": str(tmp_path / "ttyUSB7")}
        ),
        NodeSpec(
            name="gelsight_left",
            module="nodes.gelsight",
            params={"backend": "v4l2", "sysfs_root": str(tmp_path / "video4linux")},
        ),
        NodeSpec(
            name="kinect_left",
            module="nodes.depth_camera",
            params={
                "backend": "openni2",
                "library_dir": str(tmp_path),
                "calibration_file": str(LAB_LAUNCH.parent / "calibration" / "camera_left.yaml"),
            },
        ),
        NodeSpec(name="kinect_right", module="nodes.depth_camera", params={"backend": "kinect_v1"}),
        NodeSpec(name="collector", module="nodes.collector", params={}),
    ]


def test_each_device_reports_its_own_reason(mixed_nodes):
    checks = {check.node: check for check in check_devices(mixed_nodes)}
    assert "collector" not in checks  # not hardware
    assert checks["gripper_sim"].ok
    assert "GripperError: cannot open the gripper's serial port" in checks["gripper"].error
    assert "GelSightError: no V4L2 cameras at all" in checks["gelsight_left"].error
    assert "DepthCameraError: OpenNI2 library not found" in checks["kinect_left"].error
    assert "ValueError: depth_camera: unknown backend 'kinect_v1'" in checks["kinect_right"].error


def test_report_lists_every_device_and_the_count(mixed_nodes):
    report = format_report(check_devices(mixed_nodes)).splitlines()
    assert report[0].split() == ["gripper_sim", "simulated", "OK"]
    assert report[1].split()[:3] == ["gripper", "wsg50", "FAILED"]
    assert report[-1] == "1 of 5 devices OK"


def substitute(value, args):
    """$(var NAME) replaced in every string, which stays a string."""
    if isinstance(value, dict):
        return {key: substitute(item, args) for key, item in value.items()}
    if isinstance(value, str):
        return re.sub(r"\$\(var (\w+)\)", lambda match: args[match.group(1)], value)
    return value


def test_lab_launch_parameters_build_every_backend():
    """Each node's params fit its real backend's config exactly (nothing is connected)."""
    nodes = [node for node in load_launch(LAB_LAUNCH, {"robot_ip": "127.0.0.1"}).nodes if node.module in HARDWARE_NODES]
    assert {node.module for node in nodes} == set(HARDWARE_NODES)
    for node in nodes:
        assert node.params["backend"] in {"openni2", "v4l2", "ur_rtde", "wsg50"}  # real backends only
        importlib.import_module(HARDWARE_NODES[node.module]).make_backend(node.params)


def test_serial_read_as_a_number_is_refused():
    from drivers.depth_camera import make_backend

    with pytest.raises(ValueError, match=r"serial must be text, got 525951783 .*quote it"):
        make_backend({"backend": "openni2", "serial": yaml.safe_load("003726261447")})


def run_hw_check(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="dtx")
    add_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["hw", "check", *argv])
    return args.func(args)


def test_launch_file_without_hardware_nodes(tmp_path, capsys):
    launch = tmp_path / "empty.yaml"
    launch.write_text("launch:\n  - arg: {name: robot_ip, default: 192.168.1.10}\n")
    assert run_hw_check(str(launch)) == 2
    assert "starts no hardware node" in capsys.readouterr().err


def test_unreadable_launch_file(tmp_path, capsys):
    assert run_hw_check(str(tmp_path / "none.yaml")) == 2
    assert "cannot be read" in capsys.readouterr().err


@needs_node_modules
def test_hw_check_on_the_lab_launch_file_here(capsys):
    # nothing is connected on this machine
    assert run_hw_check(str(LAB_LAUNCH), "robot_ip:=127.0.0.1", "gripper_port:=/dev/dtx-no-such-port") == 1
    out = capsys.readouterr().out
    assert "no OpenNI2 depth camera with serial '011987650947'" in out
    # Quoted in the launch file, so it must stay text (unquoted it would read as octal).
    assert "no OpenNI2 depth camera with serial '003726261447'" in out
    assert "cannot reach the UR dashboard server at 127.0.0.1" in out
    assert "cannot open the gripper's serial port /dev/dtx-no-such-port" in out
    assert out.count("GelSightError") == 2
    assert out.strip().endswith("0 of 6 devices OK")
    assert sum(node.module in HARDWARE_NODES for node in load_launch(LAB_LAUNCH, {"robot_ip": "127.0.0.1"}).nodes) == 6


def gripper_launch(tmp_path: Path, port: str) -> Path:
    launch = tmp_path / "gripper.yaml"
    launch.write_text(
        "launch:\n  - node:\n      name: gripper\n      module: nodes.gripper\n"
        f"      params: {{backend: wsg50, port: {port}}}\n"
    )
    return launch


@pytest.mark.parametrize(
    "fault, reason, fix",
    [
        ("fast_stop", "the gripper is in FAST STOP", "fix: clear its cause, then `dtx hw acknowledge"),
        ("unreferenced", "the gripper is not referenced", "fix: home it"),
    ],
)
def test_a_gripper_that_cannot_move_fails_the_check_until_acknowledged(tmp_path, capsys, fault, reason, fix):
    from drivers.gripper.firmware import GripperFirmware, Strictness

    with GripperFirmware(strictness=Strictness(referenced=fault != "unreferenced"), homing_speed_m_s=0.4) as firmware:
        if fault == "fast_stop":
            firmware.trip_fast_stop()
        launch = gripper_launch(tmp_path, firmware.port)
        assert run_hw_check(str(launch)) == 1
        lines = capsys.readouterr().out.splitlines()
        assert lines[0].split()[:3] == ["gripper", "wsg50", "FAILED"] and lines[0].endswith(reason)
        assert lines[1].strip().startswith(fix)
        parser = argparse.ArgumentParser(prog="dtx")
        add_commands(parser.add_subparsers(dest="command", required=True))
        args = parser.parse_args(["hw", "acknowledge", str(launch)])
        assert args.func(args) == 0
        assert run_hw_check(str(launch)) == 0
