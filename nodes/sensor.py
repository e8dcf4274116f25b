"""What the depth camera and GelSight nodes share: a backend that ``read()``s frames at the
sensor's own rate, published on ``/<node name>/<stream>``, with device errors counted and
a lost device handed to the launcher (which respawns the node and so reconnects it)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

from bus.node import Node, split_params
from bus.pubsub import Publisher
from drivers import Device


class SensorNode(Node):
    STREAM: ClassVar[str]
    MESSAGE: ClassVar[type]
    DEVICE_ERROR: ClassVar[type[Exception]]
    END_OF_STREAM: ClassVar[tuple[type[Exception], ...]] = ()  # a recording that ends stops the node
    make_backend: ClassVar[Callable[..., Device]]

    @dataclasses.dataclass
    class Params:
        reconnect_after_errors: int = 3

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        own, backend_params = split_params(self.Params, params or {})
        super().__init__(name, own, **kwargs)
        self.sensor = type(self).make_backend(backend_params)
        self.sensor.connect()
        self.frames: Publisher[Any] = self.create_publisher(f"/{name}/{self.STREAM}", self.MESSAGE)
        self.create_timer(self.frame_period_s(), self.publish_frame)
        self.errors = 0

    def frame_period_s(self) -> float:
        """How often ``publish_frame`` runs: at once again, as read() blocks until the next frame."""
        return 1e-3

    def publish_frame(self) -> None:
        try:
            frame = self.sensor.read()
        except self.END_OF_STREAM:
            self.log.info("the recording ended; stopping")
            self.request_shutdown()
            return
        except self.DEVICE_ERROR as exc:
            self.errors += 1
            self.status = "error"
            self.log.error("%s frame failed (%d in a row): %s", self.STREAM, self.errors, exc)
            if self.errors >= self.params.reconnect_after_errors:
                raise
            return
        self.errors = 0
        self.status = "ok"
        self.frames.publish(frame)

    def close(self) -> None:
        self.sensor.disconnect()
        super().close()
