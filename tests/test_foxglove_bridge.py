"""The live Foxglove bridge: topics appear as Foxglove channels on a real WebSocket server."""

from __future__ import annotations

import base64
import os
import socket
import time

import numpy as np

import msgs
from nodes.bus import Bus
from nodes.foxglove_bridge import FoxgloveBridge
from nodes.registry import Registry


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
