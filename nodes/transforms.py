"""Transform tree publisher: the cell's frames on ``/tf`` as ``dtx.system.FrameTransform``
(recorded in bags and served live as ``foxglove.FrameTransform`` on ``/tf/foxglove``), so the
3D panel of Foxglove places the cameras, the tool and the gels, and a bag shows the cell move.

- ``world → camera_*``: each depth camera's calibration, as its frames carry it
  (``DepthImage.camera_to_world`` on ``/<camera>/depth``);
- ``world → tcp``: the arm's state (``/arm/state``, UR pose: position m, rotation vector rad);
- ``tcp → gel_left``, ``tcp → gel_right``: the gripper's width (``/gripper/state``) and the
  gripper geometry of ``scene`` (workcell.kinematics, the collector's own gel poses);
- ``world → object`` comes from the patch extractor itself, latched on ``/perception/object_pose``
  when it registers an object.

Each frame is published ``rate_hz`` times a second once its source has been heard, with the
stamp of the newest source message, so a slow topic never holds back a fast one.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

import msgs
from bus.node import Node, run_node
from workcell.kinematics import gel_poses_world, pose_to_matrix


def frame_transform(parent: str, child: str, child_to_parent: np.ndarray, stamp_ns: int) -> msgs.FrameTransform:
    """The pose of ``child`` in ``parent`` from a 4 x 4 rigid transform."""
    return msgs.FrameTransform(
        header=msgs.Header(stamp_ns=stamp_ns, frame_id=parent),
        child_frame_id=child,
        translation=np.array(child_to_parent[:3, 3], np.float64),
        rotation=Rotation.from_matrix(child_to_parent[:3, :3]).as_quat(),
    )


class TransformPublisher(Node):
    @dataclasses.dataclass
    class Params:
        cameras: list = dataclasses.field(default_factory=lambda: ["camera_left", "camera_right"])
        scene: str = "scenes/ycb_three.yaml"
        rate_hz: float = 20.0

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        from workcell.scene import load_scene  # noqa: PLC0415 - the gripper geometry, as the collector's

        self.geometry = load_scene(self.params.scene).gripper_geometry()
        self.tf = self.create_publisher("/tf", msgs.FrameTransform)
        # (parent, child) -> (child to parent, stamp) of the newest source message
        self.frames: dict[tuple[str, str], tuple[np.ndarray, int]] = {}
        for camera in self.params.cameras:
            self.create_subscription(
                f"/{camera}/depth",
                msgs.DepthImage,
                functools.partial(self._on_depth_image, camera),
            )
        self.create_subscription(
            "/arm/state", msgs.ArmState, lambda m: self._set("world", "tcp", pose_to_matrix(m.tcp_pose), m)
        )
        self.create_subscription("/gripper/state", msgs.GripperState, self._on_gripper)
        self.create_timer(1.0 / self.params.rate_hz, self.publish_tree)

    def _on_depth_image(self, camera: str, image: msgs.DepthImage) -> None:
        self._set("world", camera, image.camera_to_world, image)

    def _set(self, parent: str, child: str, child_to_parent: np.ndarray, source: msgs.Message) -> None:
        self.frames[(parent, child)] = (np.asarray(child_to_parent, np.float64), source.header.stamp_ns)

    def _on_gripper(self, state: msgs.GripperState) -> None:
        width = min(max(state.width_m, 0.0), self.geometry.max_width_m)  # a reading past the limits still draws
        for finger, gel_to_tcp in gel_poses_world(np.zeros(6), width, self.geometry).items():
            self._set("tcp", f"gel_{finger}", gel_to_tcp, state)

    def publish_tree(self) -> None:
        for (parent, child), (child_to_parent, stamp_ns) in self.frames.items():
            self.tf.publish(frame_transform(parent, child, child_to_parent, stamp_ns))


if __name__ == "__main__":
    run_node(TransformPublisher)
