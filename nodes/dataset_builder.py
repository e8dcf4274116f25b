"""Dataset builder node: writes the samples announced on ``/collector/sample`` into a
dataset — how ``launch/replay.yaml`` rebuilds a session's dataset from its bag, with no
device. Ends (with success) once it has written every sample ``/bag/done`` says was played,
or with status 2 when ``/bag/done`` says the bag could not be played.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import msgs
from bus.node import EXIT_DO_NOT_RESPAWN, Node, run_node
from dataset.announced import dataset_info, write_samples
from dataset.writer import DatasetWriter


class DatasetBuilderNode(Node):
    @dataclasses.dataclass
    class Params:
        out: str = "out/replayed"
        topic: str = "/collector/sample"

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.writer: DatasetWriter | None = None
        self.expected: int | None = None
        self.create_subscription(self.params.topic, msgs.DatasetSample, self.on_sample)
        self.create_subscription("/bag/done", msgs.Log, self.on_done)

    def on_sample(self, sample: msgs.DatasetSample) -> None:
        if self.writer is None:
            self.writer = DatasetWriter(self.params.out, dataset_info(sample))
        if sample.sample_id not in self.writer:
            write_samples(self.writer, [sample])
        self.finish_if_complete()

    def on_done(self, message: msgs.Log) -> None:
        if message.level == "error":
            written = 0 if self.writer is None else len(self.writer)
            self.log.error(
                "the bag could not be played to its end (%s); dataset %s keeps the %d samples written",
                message.text,
                self.params.out,
                written,
            )
            raise SystemExit(EXIT_DO_NOT_RESPAWN)
        self.expected = int(json.loads(message.text).get(self.params.topic, 0))
        self.finish_if_complete()

    def finish_if_complete(self) -> None:
        written = 0 if self.writer is None else len(self.writer)
        if self.expected is not None and written >= self.expected:
            self.log.info("dataset %s rebuilt: %d samples", self.params.out, written)
            self.request_shutdown()


if __name__ == "__main__":
    run_node(DatasetBuilderNode)
