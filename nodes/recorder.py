"""Recorder node: what ``dtx bag record`` does, as a node a launch file starts, so every
session leaves an MCAP bag of every topic beside its dataset."""
from __future__ import annotations

import dataclasses
from typing import Any

from dtx.bag import record
from nodes.node import Node, run_node


class RecorderNode(Node):
    @dataclasses.dataclass
    class Params:
        bag: str = "out/session.mcap"
        compression: str = "lz4"
        foxglove: bool = True
        topics: list = dataclasses.field(default_factory=list)  # empty: every topic

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.bus.transport.high_water_mark = 100_000  # a recorder queues rather than drops

    def spin(self, until: Any = None) -> None:
        counts = record(self.params.bag, self.bus, lambda: self.shutting_down, topics=self.params.topics or None,
                        compression=self.params.compression, foxglove=self.params.foxglove)
        self.log.info("bag %s closed: %d messages on %d topics", self.params.bag, sum(counts.values()), len(counts))


if __name__ == "__main__":
    run_node(RecorderNode)
