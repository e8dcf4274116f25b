"""Foxglove bridge: shows a live session in Foxglove Studio through the foxglove-sdk
WebSocket server (connect Studio to ws://HOST:PORT).

Every topic whose messages have a Foxglove well-known form (depth and tactile images,
point clouds, transforms; see ``msgs.foxglove``) is forwarded as it appears on the bus,
at most ``max_rate_hz`` per topic so a browser never slows the session. Off by default;
the collection launch files switch it on with ``foxglove:=true``.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import foxglove

import msgs
from msgs.foxglove import foxglove_view
from nodes.node import Node, run_node

VIEWABLE = {msgs.DepthImage.SCHEMA, msgs.TactileImage.SCHEMA, msgs.PointCloud.SCHEMA, msgs.FrameTransform.SCHEMA}


class FoxgloveBridge(Node):
    @dataclasses.dataclass
    class Params:
        host: str = "127.0.0.1"
        port: int = 8765
        max_rate_hz: float = 10.0

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.server = foxglove.start_server(name="dtx", host=self.params.host, port=self.params.port)
        self.channels: dict[str, foxglove.Channel] = {}
        self.last_sent: dict[str, float] = {}
        self.create_timer(1.0, self.discover_topics)
        self.log.info("Foxglove Studio: connect to ws://%s:%d", self.params.host, self.server.port)

    def discover_topics(self) -> None:
        for topic, endpoints in self.bus.registry.names("topic").items():
            schema = endpoints[0].schema
            if topic not in self.last_sent and schema in VIEWABLE:
                self.last_sent[topic] = 0.0
                self.create_subscription(topic, msgs.MESSAGE_TYPES[schema],
                                         lambda message, topic=topic: self.forward(topic, message))

    def forward(self, topic: str, message: msgs.Message) -> None:
        now = time.monotonic()
        if now - self.last_sent[topic] < 1.0 / self.params.max_rate_hz:
            return
        self.last_sent[topic] = now
        view = foxglove_view(message)
        if view is None:
            return
        if topic not in self.channels:
            schema = view.get_schema()
            self.channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="protobuf")
        self.channels[topic].log(view.encode(), log_time=message.header.stamp_ns or time.time_ns())

    def close(self) -> None:
        self.server.stop()
        super().close()


if __name__ == "__main__":
    run_node(FoxgloveBridge)
