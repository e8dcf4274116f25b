"""Recorder node: what ``dtx bag record`` does, as a node a launch file starts, so every
session leaves an MCAP bag of every topic beside its dataset. On a full disk it stops with
exit status 2 (the launcher does not respawn it) and the bag keeps what it had. Its heartbeat's
counters say per topic how far behind it is: ``backlog:<topic>`` (messages received and not yet
written) and ``lag_ms:<topic>`` (write time minus header stamp), each the largest since the
previous heartbeat."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from bus.bag import BagWriteError
from bus.bag_record_play import RecordStats, record
from bus.node import EXIT_DO_NOT_RESPAWN, Node, run_node


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
        self.progress = RecordStats()

    def spin(self, until: Any = None) -> None:
        bag = free_bag_path(Path(self.params.bag))
        try:
            counts = record(
                bag,
                self.bus,
                self.keep_alive,
                topics=self.params.topics or None,
                compression=self.params.compression,
                foxglove=self.params.foxglove,
                on_subscriber=self.count_subscriber,
                stats=self.progress,
            )
        except BagWriteError as error:
            # A full disk stays full: a respawn would only leave one more empty bag per second.
            self.log.error("%s; the recorder stops (errno %s)", error, error.errno)
            raise SystemExit(EXIT_DO_NOT_RESPAWN) from error
        self.log.info("bag %s closed: %d messages on %d topics", bag, sum(counts.values()), len(counts))

    def counters(self) -> dict[str, int]:
        return {**super().counters(), **self.progress.report()}


def free_bag_path(path: Path) -> Path:
    """``path``, or ``name.1.mcap``, ``name.2.mcap``... when it exists: a respawned recorder
    must not overwrite the bag its previous life wrote."""
    candidate, number = path, 0
    while candidate.exists():
        number += 1
        candidate = path.with_name(f"{path.stem}.{number}{path.suffix}")
    return candidate


if __name__ == "__main__":
    run_node(RecorderNode)
