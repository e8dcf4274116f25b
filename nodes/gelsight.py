"""GelSight node: publishes ``/<node name>/image`` (msgs.TactileImage, with the no-contact
background captured at start) from its backend (a V4L2 camera or video file, or the
simulated world's renderer).

Params: ``reconnect_after_errors`` and the backend's (``backend:`` and its config fields,
see ``drivers.gelsight``). A simulated sensor has no physics of its own: it follows
``/arm/state`` and ``/gripper/state`` to know what its finger touches. A video file that
ends stops the node.
"""

from __future__ import annotations

import typing
from typing import Any

import drivers.gelsight
import msgs
from bus.node import run_node
from nodes.sensor import SensorNode

if typing.TYPE_CHECKING:
    from drivers.gelsight.simulated import SimulatedGelSight


class GelSightNode(SensorNode):
    STREAM = "image"
    MESSAGE = msgs.TactileImage
    DEVICE_ERROR = drivers.gelsight.GelSightError
    END_OF_STREAM = (drivers.gelsight.EndOfStreamError,)
    make_backend = staticmethod(drivers.gelsight.make_backend)

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        params = dict(params or {})
        self.follows_robot = params.get("backend") == "simulated"
        if self.follows_robot:
            # A read() that sleeps until its frame time would keep a /gripper/state waiting
            # and render the frame from the grip before it: the node's timer paces instead.
            params["pace"] = False
        super().__init__(name, params, **kwargs)
        self.arm: msgs.ArmState | None = None
        if self.follows_robot:
            self.create_subscription("/arm/state", msgs.ArmState, self.on_arm)
            self.create_subscription("/gripper/state", msgs.GripperState, self.on_gripper)

    @property
    def simulated(self) -> SimulatedGelSight:
        """The backend, when it is the simulated GelSight (``follows_robot``)."""
        return typing.cast("SimulatedGelSight", self.sensor)

    def frame_period_s(self) -> float:
        if self.follows_robot:
            return 1.0 / self.simulated.config.rate_hz
        return super().frame_period_s()

    def on_arm(self, state: msgs.ArmState) -> None:
        self.arm = state

    def on_gripper(self, state: msgs.GripperState) -> None:
        if self.arm is not None:
            self.simulated.observe_robot(self.arm.tcp_pose, state.width_m, state.force_n, state.header.stamp_ns)


if __name__ == "__main__":
    run_node(GelSightNode)
