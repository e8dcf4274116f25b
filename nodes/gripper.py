"""Gripper node: publishes ``/gripper/state`` (msgs.GripperState) and serves
``/gripper/command`` (msgs.GripperCommand: home, move, grasp, release, stop, acknowledge ->
the state).

Params: ``state_rate_hz``, ``scene`` (simulated backend only: where the fingers meet the
object comes from this scene and ``/arm/state``) and the backend's (``backend:`` wsg50 or
simulated, see ``drivers.gripper``). Motions run in the background so the state keeps
flowing; the serial line is polled only between commands. ``stop`` is sent at once, beside
the running motion (the driver is safe for that), never queued behind it: a stop that waits
for the grasp it should stop is no stop. ``acknowledge`` clears a FAST STOP once its cause is
dealt with.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import Future
from typing import Any

import drivers.gripper
import msgs
from bus.node import Node, run_node, split_params


class GripperNode(Node):
    @dataclasses.dataclass
    class Params:
        state_rate_hz: float = 20.0
        scene: str = "scenes/ycb_three.yaml"

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        own, backend_params = split_params(self.Params, params or {})
        super().__init__(name, own, **kwargs)
        self.tcp_pose: Any = None
        self.arm_stamp_ns = 0
        self.simulated = backend_params.get("backend") == "simulated"
        self.force_n = 0.0
        extras = {}
        if self.simulated:
            from sim.world import shared_world  # noqa: PLC0415 - only the simulation needs it

            shared_world(self.params.scene)  # loaded now, not while the firmware must answer
            extras["contact_width_m"] = self.contact_width_m
            self.create_subscription("/arm/state", msgs.ArmState, self.on_arm)
        self.gripper = drivers.gripper.make_backend(backend_params, **extras)
        self.gripper.connect()
        self.line = threading.Lock()  # one command at a time on the serial line
        self.last_state = msgs.GripperState()
        self.state = self.create_publisher("/gripper/state", msgs.GripperState)
        self.create_service("/gripper/command", msgs.GripperCommand, msgs.GripperState, self.on_command)
        self.create_timer(1.0 / self.params.state_rate_hz, self.publish_state)

    def on_arm(self, state: msgs.ArmState) -> None:
        self.tcp_pose = state.tcp_pose
        self.arm_stamp_ns = state.header.stamp_ns

    def wait_for_arm_state_after(self, stamp_ns: int, timeout_s: float = 2.0) -> None:
        """Simulation only: a real gripper feels the object; the simulated one must know where
        the arm is, so a command waits for an arm state newer than itself."""
        deadline = time.monotonic() + timeout_s
        while self.arm_stamp_ns < stamp_ns and time.monotonic() < deadline:
            time.sleep(0.002)

    def contact_width_m(self) -> float | None:
        """Where the closing fingers meet the object (simulated world), None if nothing."""
        from sim.world import shared_world  # noqa: PLC0415 - only the simulation needs it

        if self.tcp_pose is None:
            return None
        return shared_world(self.params.scene).contact_width_m(self.tcp_pose, self.force_n)

    def publish_state(self) -> None:
        if self.line.acquire(blocking=False):
            try:
                self.last_state = self.gripper.read()
            finally:
                self.line.release()
        self.state.publish(self.last_state)

    def on_command(self, command: msgs.GripperCommand) -> msgs.GripperState | Future[msgs.GripperState]:
        actions = {
            "home": lambda: self.gripper.home(),
            "move": lambda: self.gripper.move(command.width_m, command.speed_m_s),
            "grasp": lambda: self.gripper.grasp(command.width_m, command.speed_m_s, command.force_n),
            "release": lambda: self.gripper.release(command.width_m, command.speed_m_s),
            "acknowledge": lambda: self.gripper.acknowledge(),
        }
        if command.action == "stop":
            self.last_state = self.gripper.stop()
            return self.last_state
        if command.action not in actions:
            raise ValueError(f"action {command.action!r} unknown; allowed: {sorted([*actions, 'stop'])}")
        if command.action == "grasp":
            self.force_n = command.force_n
        # Fingers that only open meet nothing: the simulated world need not know where the arm is.
        opens = command.action == "release" or (command.action == "move" and command.width_m >= self.last_state.width_m)
        return self.background.submit(self._run, actions[command.action], command.header.stamp_ns, not opens)

    def _run(self, action: Any, requested_ns: int, may_touch: bool) -> msgs.GripperState:
        if self.simulated and may_touch:
            self.wait_for_arm_state_after(requested_ns)
        with self.line:
            action()
            self.last_state = self.gripper.read()
        return self.last_state

    def close(self) -> None:
        self.gripper.disconnect()
        super().close()


if __name__ == "__main__":
    run_node(GripperNode)
