"""Depth camera node: publishes ``/<node name>/depth`` (msgs.DepthImage) from its backend
(OpenNI2 / libfreenect2 on a Kinect v2, or the simulated world's ray caster).

Params: ``reconnect_after_errors`` and the backend's (``backend:`` and its config fields,
see ``drivers.depth_camera``). The backend's ``read()`` paces the stream.
"""

from __future__ import annotations

import drivers.depth_camera
import msgs
from bus.node import run_node
from nodes.sensor import SensorNode


class DepthCameraNode(SensorNode):
    STREAM = "depth"
    MESSAGE = msgs.DepthImage
    DEVICE_ERROR = drivers.depth_camera.DepthCameraError
    make_backend = staticmethod(drivers.depth_camera.make_backend)


if __name__ == "__main__":
    run_node(DepthCameraNode)
