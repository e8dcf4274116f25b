"""Arm node: publishes ``/arm/state`` (msgs.ArmState) at the state rate and serves
``/arm/move`` (msgs.ArmMoveRequest -> the state on arrival) and ``/arm/stop``.

Poses on the bus are in ``world``. A real UR reports and takes poses in its ``base`` frame;
``base_pose_world`` (x, y, z, rx, ry, rz: where the robot stands on the table) converts both
ways. Params: ``state_rate_hz``, ``base_pose_world`` and the backend's (``backend:``
ur_rtde or simulated and its config fields, see ``drivers.arm``). Targets outside the workspace or limits are refused by
the backend before anything moves; a protective stop or a lost link makes the node report
the error and stop (the session then stops safely). ``/arm/stop`` answers once the arm is
at rest; ``/arm/state``'s ``error_code`` says what a stop took (drivers.arm.base.ArmErrorCode).
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future
from typing import Any

import numpy as np

import drivers.arm
import drivers.arm.base
import msgs
from bus.node import Node, run_node, split_params
from workcell.kinematics import matrix_to_pose, pose_to_matrix


class ArmNode(Node):
    @dataclasses.dataclass
    class Params:
        state_rate_hz: float = 125.0
        base_pose_world: list = dataclasses.field(default_factory=lambda: [0.0] * 6)

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        own, backend_params = split_params(self.Params, params or {})
        super().__init__(name, own, **kwargs)
        self.base_to_world = pose_to_matrix(np.asarray(self.params.base_pose_world, dtype=np.float64))
        self.arm = drivers.arm.make_backend(backend_params)
        self.arm.connect()
        self.state = self.create_publisher("/arm/state", msgs.ArmState)
        self.create_service("/arm/move", msgs.ArmMoveRequest, msgs.ArmState, self.on_move)
        self.create_service("/arm/stop", msgs.Empty, msgs.ArmState, self.on_stop)
        self.create_timer(1.0 / self.params.state_rate_hz, self.publish_state)

    def read_world(self) -> msgs.ArmState:
        state = self.arm.read()
        if state.header.frame_id == "base":
            state.tcp_pose = matrix_to_pose(self.base_to_world @ pose_to_matrix(state.tcp_pose))
            state.header.frame_id = "world"
        return state

    def publish_state(self) -> None:
        state = self.read_world()
        self.status = state.safety_status if state.safety_status != "normal" else state.error_code or "ok"
        self.state.publish(state)

    def on_move(self, request: msgs.ArmMoveRequest) -> Future[msgs.ArmState]:
        if request.mode not in ("moveL", "moveJ"):
            raise ValueError(f"mode {request.mode!r} unknown; allowed: moveL, moveJ")
        move = self.arm.move_linear if request.mode == "moveL" else self.arm.move_joints
        return self.background.submit(self._move_and_read, move, request)

    def _move_and_read(self, move: Any, request: msgs.ArmMoveRequest) -> msgs.ArmState:
        target = np.asarray(request.target, dtype=np.float64)
        if request.mode == "moveL" and self.arm.read().header.frame_id == "base":
            target = matrix_to_pose(np.linalg.inv(self.base_to_world) @ pose_to_matrix(target))
        move(target, request.speed, request.acceleration)
        return self.read_world()

    def on_stop(self, _request: msgs.Empty) -> msgs.ArmState:
        self.arm.stop()
        return self.read_world()

    def close(self) -> None:
        try:
            self.arm.stop()
        except drivers.arm.base.ArmError as error:
            self.log.error("stopping the arm on close: %s (code %s)", error, error.code)
        finally:
            self.arm.disconnect()
            super().close()


if __name__ == "__main__":
    run_node(ArmNode)
