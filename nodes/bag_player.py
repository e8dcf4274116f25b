"""Bag player node: ``dtx bag play`` as a node a launch file starts. When the bag is done it
announces on the latched ``/bag/done`` how many messages it published per topic, so the
nodes that rebuild something from the bag know when they have everything. A bag that
cannot be played (damaged, refused by the reader's limits) is announced there too, at level
``error`` with the reason, so they end instead of waiting."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import msgs
from bus.bag_format import BagError
from bus.bag_record_play import play
from bus.node import Node, run_node


class BagPlayerNode(Node):
    @dataclasses.dataclass
    class Params:
        bag: str = ""
        rate: float = 0.0  # 0: as fast as possible
        topics: list = dataclasses.field(default_factory=list)  # empty: every dtx topic of the bag
        wait_for_subscribers_s: float = 10.0
        clock: bool = False

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        if not self.params.bag:
            raise ValueError("bag:=FILE is required")
        self.done = self.create_publisher("/bag/done", msgs.Log, latched=True)

    def spin(self, until: Any = None) -> None:
        try:
            counts = play(
                self.params.bag,
                self.bus,
                rate=self.params.rate or None,
                clock=self.params.clock,
                topics=self.params.topics or None,
                wait_for_subscribers_s=self.params.wait_for_subscribers_s,
                stop=self.keep_alive,
            )
        except BagError as error:
            # The listeners must not wait for an end that will not come: /bag/done says it failed.
            self.status = "error"
            self.done.publish(msgs.Log(level="error", node=self.name, text=str(error)))
            self.log.error("cannot play %s: %s", self.params.bag, error)
        else:
            self.done.publish(msgs.Log(node=self.name, text=json.dumps(counts)))
            self.log.info("played %s: %s", self.params.bag, counts)
        super().spin()  # stay up so late joiners get /bag/done, until the launch ends


if __name__ == "__main__":
    run_node(BagPlayerNode)
