"""GelSight node: publishes ``/<node name>/image`` (msgs.TactileImage, with the no-contact
background captured at start) from its backend (a V4L2 camera or video file, or the
simulated world's renderer).

Params: the backend's (``backend:`` and its config fields, see ``drivers.gelsight``). A
simulated sensor has no physics of its own: it follows ``/arm/state`` and
``/gripper/state`` to know what its finger touches.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import drivers.gelsight
import msgs
from nodes.node import Node, run_node, split_params


class GelSightNode(Node):
    @dataclasses.dataclass
    class Params:
        reconnect_after_errors: int = 3

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        own, backend_params = split_params(self.Params, params or {})
        super().__init__(name, own, **kwargs)
        self.sensor = drivers.gelsight.make_backend(backend_params)
        self.sensor.connect()
        self.image = self.create_publisher(f"/{name}/image", msgs.TactileImage)
        if hasattr(self.sensor, "observe_robot"):
            self.arm: msgs.ArmState | None = None
            self.create_subscription("/arm/state", msgs.ArmState, self.on_arm)
            self.create_subscription("/gripper/state", msgs.GripperState, self.on_gripper)
        self.create_timer(1e-3, self.publish_frame)  # read() blocks until the next frame
        self.errors = 0

    def on_arm(self, state: msgs.ArmState) -> None:
        self.arm = state

    def on_gripper(self, state: msgs.GripperState) -> None:
        if self.arm is not None:
            self.sensor.observe_robot(self.arm.tcp_pose, state.width_m, state.force_n)

    def publish_frame(self) -> None:
        try:
            frame = self.sensor.read()
        except drivers.gelsight.EndOfStreamError:
            self.log.info("video ended; stopping")
            self.request_shutdown()
            return
        except drivers.gelsight.GelSightError as exc:
            self.errors += 1
            self.status = "error"
            self.log.error("tactile frame failed (%d in a row): %s", self.errors, exc)
            if self.errors >= self.params.reconnect_after_errors:
                raise  # the launcher respawns the node, which reconnects the camera
            return
        self.errors = 0
        self.status = "ok"
        self.image.publish(frame)

    def close(self) -> None:
        self.sensor.disconnect()
        super().close()


if __name__ == "__main__":
    run_node(GelSightNode)
