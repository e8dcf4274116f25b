"""``dtx hw check LAUNCHFILE [name:=value ...]``: connect to every device a launch file
configures, print OK or the reason it failed, exit 0 only if all are OK.

Each hardware node's ``params`` are its backend's (``backend:`` plus the config fields), so
the check builds exactly the backend the node would run, connects and disconnects it.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from typing import Any, Iterable, Protocol

# Node module -> the driver package whose make_backend(params) builds its device.
HARDWARE_NODES = {
    "nodes.depth_camera": "drivers.depth_camera",
    "nodes.gelsight": "drivers.gelsight",
    "nodes.arm": "drivers.arm",
    "nodes.gripper": "drivers.gripper",
}


class NodeLike(Protocol):
    name: str
    module: str
    params: dict[str, Any]


@dataclasses.dataclass
class DeviceCheck:
    node: str
    module: str
    backend: str
    error: str = ""  # empty when the device connected

    @property
    def ok(self) -> bool:
        return not self.error


def check_device(node: NodeLike) -> DeviceCheck:
    """Build the node's backend, connect, disconnect; record why any step failed."""
    result = DeviceCheck(node.name, node.module, str(node.params.get("backend", "?")))
    try:
        backend = importlib.import_module(HARDWARE_NODES[node.module]).make_backend(dict(node.params))
        backend.connect()
    # A pre-flight must report every failure whatever raised it: the drivers' own errors,
    # a bad parameter (ValueError), or a library that is not installed (ImportError).
    except Exception as exc:  # noqa: BLE001
        result.error = f"{type(exc).__name__}: {exc}"
        return result
    try:
        backend.disconnect()
    except Exception as exc:  # noqa: BLE001
        result.error = f"connected, but disconnecting failed: {type(exc).__name__}: {exc}"
    return result


def check_devices(nodes: Iterable[NodeLike]) -> list[DeviceCheck]:
    """One check per hardware node, in launch-file order; other nodes are skipped."""
    return [check_device(node) for node in nodes if node.module in HARDWARE_NODES]


def format_report(checks: list[DeviceCheck]) -> str:
    width = max(len(check.node) for check in checks)
    lines = []
    for check in checks:
        verdict = "OK" if check.ok else f"FAILED  {check.error}"
        lines.append(f"{check.node:<{width}}  {check.backend:<10} {verdict}")
    failed = sum(not check.ok for check in checks)
    lines.append(f"{len(checks) - failed} of {len(checks)} devices OK")
    return "\n".join(lines)


def cmd_hw_check(args: argparse.Namespace) -> int:
    from dtx.launch import LaunchError, load_launch, parse_launch_args

    try:
        description = load_launch(args.file, parse_launch_args(args.args))
    except LaunchError as exc:
        print(f"dtx hw check: {exc}", file=sys.stderr)
        return 2
    checks = check_devices(description.nodes)
    if not checks:
        print(f"dtx hw check: {args.file} starts no hardware node ({', '.join(HARDWARE_NODES)})",
              file=sys.stderr)
        return 2
    print(format_report(checks))
    return 0 if all(check.ok for check in checks) else 1


def add_commands(subparsers: Any) -> None:
    """Add the ``hw`` group to the ``dtx`` command line."""
    hw = subparsers.add_parser("hw", help="lab hardware").add_subparsers(dest="verb", required=True)
    check = hw.add_parser("check", help="connect to every device of a launch file and report")
    check.add_argument("file", help="launch file, e.g. launch/collect_lab.yaml")
    check.add_argument("args", nargs="*", help="launch arguments name:=value")
    check.set_defaults(func=cmd_hw_check)
