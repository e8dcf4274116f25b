"""Depth camera node: publishes ``/<node name>/depth`` (msgs.DepthImage) from its backend
(OpenNI2 / libfreenect2 on a Kinect v2, or the simulated world's ray caster).

Params: the backend's (``backend:`` and its config fields, see ``drivers.depth_camera``).
The backend's ``read()`` paces the stream at the camera's frame rate.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import drivers.depth_camera
import msgs
from nodes.node import Node, run_node, split_params


class DepthCameraNode(Node):
    @dataclasses.dataclass
    class Params:
        reconnect_after_errors: int = 3

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        own, backend_params = split_params(self.Params, params or {})
        super().__init__(name, own, **kwargs)
        self.camera = drivers.depth_camera.make_backend(backend_params)
        self.camera.connect()
        self.depth = self.create_publisher(f"/{name}/depth", msgs.DepthImage)
        self.create_timer(1e-3, self.publish_frame)  # read() blocks until the next frame
        self.errors = 0

    def publish_frame(self) -> None:
        try:
            frame = self.camera.read()
        except drivers.depth_camera.DepthCameraError as exc:
            self.errors += 1
            self.status = "error"
            self.log.error("depth frame failed (%d in a row): %s", self.errors, exc)
            if self.errors >= self.params.reconnect_after_errors:
                raise  # the launcher respawns the node, which reconnects the camera
            return
        self.errors = 0
        self.status = "ok"
        self.depth.publish(frame)

    def close(self) -> None:
        self.camera.disconnect()
        super().close()


if __name__ == "__main__":
    run_node(DepthCameraNode)
