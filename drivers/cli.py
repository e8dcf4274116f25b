"""``dtx hw check LAUNCHFILE [name:=value ...]``: connect to every device a launch file
configures, print OK or the reason it failed (and on the next lines what the device said it
is, e.g. a UR controller's PolyScope version, and the fix, where an operator can act), exit 0
only if all are OK.

Each hardware node's ``params`` are its backend's (``backend:`` plus the config fields), so
the check builds exactly the backend the node would run, connects, runs its ``preflight()``
where it has one (a gripper that answers but cannot move: FAST STOP, fault, not referenced),
and disconnects. ``dtx hw acknowledge LAUNCHFILE`` is the operator's explicit step that
clears what the check refuses on a gripper: it acknowledges a FAST STOP and homes an
unreferenced gripper (the fingers move).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from typing import Any, Callable, Iterable, Protocol

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
    fix: str = ""  # what an operator does about the error, when the driver knows
    identity: str = ""  # what the device reported about itself once connected (Device.identify)

    @property
    def ok(self) -> bool:
        return not self.error


def check_device(node: NodeLike) -> DeviceCheck:
    """Build the node's backend, connect, run its preflight, disconnect; record why any step
    failed."""
    return _with_device(node, lambda backend: getattr(backend, "preflight", lambda: None)())


def acknowledge_device(node: NodeLike) -> DeviceCheck:
    """Clear a gripper's FAST STOP and home it if it is not referenced, then preflight it."""

    def clear(gripper: Any) -> None:
        gripper.acknowledge()
        if not gripper.referenced():
            gripper.home()
        gripper.preflight()

    return _with_device(node, clear)


def _with_device(node: NodeLike, action: Callable[[Any], None]) -> DeviceCheck:
    result = DeviceCheck(node.name, node.module, str(node.params.get("backend", "?")))
    try:
        backend = importlib.import_module(HARDWARE_NODES[node.module]).make_backend(dict(node.params))
        backend.connect()
        result.identity = backend.identify()
    # A pre-flight must report every failure whatever raised it: the drivers' own errors,
    # a bad parameter (ValueError), or a library that is not installed (ImportError).
    except Exception as exc:  # noqa: BLE001 - see above
        _record(result, exc)
        return result
    try:
        action(backend)
    except Exception as exc:  # noqa: BLE001 - reported like a failed connect
        _record(result, exc)
    try:
        backend.disconnect()
    except Exception as exc:  # noqa: BLE001 - any failure to let go is reported
        result.error = result.error or f"connected, but disconnecting failed: {type(exc).__name__}: {exc}"
    return result


def _record(result: DeviceCheck, exc: Exception) -> None:
    """The reason on one line and the fix on another: a DeviceError carries them apart."""
    result.error = f"{type(exc).__name__}: {getattr(exc, 'reason', exc)}"
    result.fix = getattr(exc, "fix", "")


def check_devices(nodes: Iterable[NodeLike]) -> list[DeviceCheck]:
    """One check per hardware node, in launch-file order; other nodes are skipped."""
    return [check_device(node) for node in nodes if node.module in HARDWARE_NODES]


def format_report(checks: list[DeviceCheck]) -> str:
    width = max(len(check.node) for check in checks)
    lines = []
    for check in checks:
        verdict = "OK" if check.ok else f"FAILED  {check.error}"
        lines.append(f"{check.node:<{width}}  {check.backend:<10} {verdict}")
        if check.identity:
            lines.append(f"{'':<{width}}  {'':<10} found: {check.identity}")
        if check.fix:
            lines.append(f"{'':<{width}}  {'':<10} fix: {check.fix}")
    failed = sum(not check.ok for check in checks)
    lines.append(f"{len(checks) - failed} of {len(checks)} devices OK")
    return "\n".join(lines)


def cmd_hw_check(args: argparse.Namespace) -> int:
    return _run_on_launch(args, "check", check_devices)


def cmd_hw_acknowledge(args: argparse.Namespace) -> int:
    return _run_on_launch(
        args,
        "acknowledge",
        lambda nodes: [acknowledge_device(node) for node in nodes if node.module == "nodes.gripper"],
    )


def _run_on_launch(args: argparse.Namespace, verb: str, run: Callable[[list[Any]], list[DeviceCheck]]) -> int:
    from dtx.launch import LaunchError, load_launch, parse_launch_args

    try:
        description = load_launch(args.file, parse_launch_args(args.args))
    except LaunchError as exc:
        print(f"dtx hw {verb}: {exc}", file=sys.stderr)
        return 2
    checks = run(description.nodes)
    if not checks:
        print(f"dtx hw {verb}: {args.file} starts no hardware node ({', '.join(HARDWARE_NODES)})", file=sys.stderr)
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
    acknowledge = hw.add_parser(
        "acknowledge", help="clear a gripper's FAST STOP and home it if unreferenced (the fingers move)"
    )
    acknowledge.add_argument("file", help="launch file, e.g. launch/collect_lab.yaml")
    acknowledge.add_argument("args", nargs="*", help="launch arguments name:=value")
    acknowledge.set_defaults(func=cmd_hw_acknowledge)
