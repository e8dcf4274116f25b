"""The live Foxglove bridge: topics appear as Foxglove channels on a real WebSocket server."""

from __future__ import annotations

import base64
import os
import socket
import time

import numpy as np
import pytest

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from nodes.foxglove_bridge import FoxgloveBridge, FrameThrottle


def test_image_topic_is_served_to_foxglove_studio(registry: Registry) -> None:
    bridge = FoxgloveBridge("foxglove", {"port": 0, "max_rate_hz": 100.0}, registry=registry)
    camera = Bus("camera", registry)
    publisher = camera.publisher("/gelsight_left/image", msgs.TactileImage)
    try:
        deadline = time.monotonic() + 10
        while "/gelsight_left/image" not in bridge.channels and time.monotonic() < deadline:
            publisher.publish(msgs.TactileImage(image=np.zeros((12, 16, 3), np.uint8), sensor="left"))
            bridge.spin_once(0.05)
        assert "/gelsight_left/image" in bridge.channels
        assert "thinned:/gelsight_left/image" in bridge.counters()  # the heartbeat reports each topic
        with socket.create_connection(("127.0.0.1", bridge.port), timeout=5) as client:
            key = base64.b64encode(os.urandom(16)).decode()
            client.sendall(
                (
                    f"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                    "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
                ).encode()
            )
            answer = client.recv(4096)
            while b'"op":"advertise"' not in answer and b"/gelsight_left/image" not in answer:
                chunk = client.recv(65536)
                assert chunk, "server closed the connection"
                answer += chunk
        assert b"101 Switching Protocols" in answer and b"/gelsight_left/image" in answer
    finally:
        camera.close()
        bridge.close()


def transform(parent: str, child: str) -> msgs.FrameTransform:
    return msgs.FrameTransform(header=msgs.Header(frame_id=parent), child_frame_id=child)


TREE = [
    ("world", "camera_left"),
    ("world", "camera_right"),
    ("world", "tcp"),
    ("tcp", "gel_left"),
    ("tcp", "gel_right"),
]


def test_messages_of_one_topic_in_other_frames_do_not_thin_each_other() -> None:
    """The two fingers' samples come back to back on one topic, and so does the whole tree on
    /tf: at 10 Hz per topic and frame, every one of them goes."""
    throttle = FrameThrottle(max_rate_hz=10.0)
    throttle.limit("/collector/sample", msgs.DatasetSample.SCHEMA)
    throttle.limit("/tf", msgs.FrameTransform.SCHEMA)
    fingers = [msgs.DatasetSample(finger=finger) for finger in ("left", "right")]
    assert [throttle.offer("/collector/sample", sample, now=5.0) for sample in fingers] == [True, True]
    assert all(throttle.offer("/tf", transform(*pair), now=5.0) for pair in TREE)
    assert throttle.thinned == {"/collector/sample": 0, "/tf": 0}


def test_the_newest_message_that_came_too_soon_is_sent_when_its_interval_ends() -> None:
    """Three widths of one finger within 0.1 s: the first goes, the second is replaced by the
    third (counted thinned), and the third, the gripper's last state, goes once 0.1 s is over."""
    throttle = FrameThrottle(max_rate_hz=10.0)
    throttle.limit("/tf", msgs.FrameTransform.SCHEMA)
    widths = [transform("tcp", "gel_left") for _ in range(3)]
    assert [throttle.offer("/tf", width, now) for width, now in zip(widths, (0.0, 0.03, 0.06), strict=True)] == [
        True,
        False,
        False,
    ]
    assert throttle.release_due(now=0.09) == []
    assert throttle.release_due(now=0.1) == [("/tf", widths[2])]
    assert throttle.release_due(now=0.5) == [] and throttle.thinned == {"/tf": 1}


def test_every_transform_goes_at_least_once_a_second_however_low_the_rate() -> None:
    """max_rate_hz 0.2 thins images to one in 5 s, but each transform of a 20 Hz tree still goes
    at least once a second (the bridge releases what it holds every half shortest interval)."""
    throttle = FrameThrottle(max_rate_hz=0.2)
    throttle.limit("/tf", msgs.FrameTransform.SCHEMA)
    throttle.limit("/camera_left/depth", msgs.DepthImage.SCHEMA)
    sent: dict[tuple[str, str], list[float]] = {pair: [] for pair in TREE}
    images = 0
    for tick in range(200):  # 10 s at 20 Hz, the transform node's rate
        now = tick * 0.05
        for pair in TREE:
            if throttle.offer("/tf", transform(*pair), now):
                sent[pair].append(now)
        images += throttle.offer("/camera_left/depth", msgs.DepthImage(header=msgs.Header(frame_id="camera_left")), now)
        if tick % 10 == 0:  # every 0.5 s
            for _, message in throttle.release_due(now):
                if isinstance(message, msgs.FrameTransform):
                    sent[(message.header.frame_id, message.child_frame_id)].append(now)
    assert images == 2
    for pair, times in sent.items():
        assert times[0] == 0.0 and max(b - a for a, b in zip(times, times[1:])) <= 1.0, pair
    # Each message was sent, thinned, or is the one still held for its transform.
    assert throttle.thinned["/tf"] == 5 * 200 - sum(len(times) for times in sent.values()) - sum(
        key[0] == "/tf" for key in throttle.held
    )


def test_a_rate_that_is_not_positive_is_refused() -> None:
    with pytest.raises(ValueError, match="max_rate_hz must be positive, got 0"):
        FrameThrottle(max_rate_hz=0.0)
