"""The GelSight node on a recorded tactile video: frames published, a clean stop at its end."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import msgs
from bus.pubsub import Bus
from bus.registry import Registry
from nodes.gelsight import GelSightNode

FRAMES = Path(__file__).resolve().parent.parent / "assets" / "gelsight" / "ball_presses.npz"


def test_gelsight_node_plays_a_video_and_stops_at_its_end(registry: Registry, tmp_path: Path) -> None:
    data = np.load(FRAMES)
    frames = [data["background"]] * 8 + list(data["frames"][:6])
    video = tmp_path / "presses.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 120))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    node = GelSightNode(
        "gelsight_left",
        {"backend": "v4l2", "video_file": str(video), "warmup_frames": 0, "background_frames": 2},
        registry=registry,
    )
    listener = Bus("listener", registry)
    images = listener.subscriber("/gelsight_left/image", msgs.TactileImage)
    received = []
    node.spin(until=lambda: len(received) > 100)  # ends by itself when the video does
    while (envelope := images.receive(0.5)) is not None:
        received.append(envelope.message)
    node.close()
    listener.close()
    assert node.shutting_down
    assert 0 < len(received) <= len(frames)
    assert all(m.sensor == "left" and m.image.shape[2] == 3 for m in received)
