"""The transform tree: every frame the cell uses reaches /tf, each from its source."""

from __future__ import annotations

import contextlib
import time

import numpy as np
from scipy.spatial.transform import Rotation

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from nodes.transforms import TransformPublisher
from workcell.kinematics import gel_poses_world, pose_to_matrix


def test_cameras_tool_and_gels_are_published_from_their_sources(registry: Registry) -> None:
    node = TransformPublisher("transforms", {"rate_hz": 50.0}, registry=registry)
    camera_to_world = np.eye(4)
    camera_to_world[:3, 3] = [0.5, -0.4, 0.9]
    tcp_pose = np.array([0.3, 0.1, 0.4, np.pi, 0.0, 0.0])
    with contextlib.closing(Bus("cell", registry)) as bus:
        camera = bus.publisher("/camera_left/depth", msgs.DepthImage)
        arm = bus.publisher("/arm/state", msgs.ArmState)
        gripper = bus.publisher("/gripper/state", msgs.GripperState)
        tf = bus.subscriber("/tf", msgs.FrameTransform)
        seen: dict[tuple[str, str], msgs.FrameTransform] = {}
        deadline = time.monotonic() + 60
        try:
            while len(seen) < 4 and time.monotonic() < deadline:
                camera.publish(msgs.DepthImage(camera_to_world=camera_to_world))
                arm.publish(msgs.ArmState(tcp_pose=tcp_pose))
                gripper.publish(msgs.GripperState(width_m=0.04))
                node.spin_once(0.05)
                while (envelope := tf.receive(timeout_s=0.0)) is not None:
                    message = envelope.message
                    seen[(message.header.frame_id, message.child_frame_id)] = message
        finally:
            node.close()
    assert set(seen) == {("world", "camera_left"), ("world", "tcp"), ("tcp", "gel_left"), ("tcp", "gel_right")}

    def matrix(t: msgs.FrameTransform) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = Rotation.from_quat(t.rotation).as_matrix(), t.translation
        return out

    np.testing.assert_allclose(matrix(seen[("world", "camera_left")]), camera_to_world, atol=1e-12)
    tcp_to_world = matrix(seen[("world", "tcp")])
    np.testing.assert_allclose(tcp_to_world, pose_to_matrix(tcp_pose), atol=1e-12)
    expected = gel_poses_world(tcp_pose, 0.04, node.geometry)
    for finger in ("left", "right"):
        np.testing.assert_allclose(tcp_to_world @ matrix(seen[("tcp", f"gel_{finger}")]), expected[finger], atol=1e-9)
