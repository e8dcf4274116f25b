"""Small nodes that launch tests start as real processes."""
from __future__ import annotations

import dataclasses
import os
import sys

import msgs
from nodes.node import Node, run_node


class CounterNode(Node):
    """Publishes an increasing count on /count; can finish or fail after some counts."""

    @dataclasses.dataclass
    class Params:
        period_s: float = 0.05
        finish_after: int = 0
        fail_after: int = 0

    def __init__(self, name: str, params: dict | None = None, **kwargs: object) -> None:
        super().__init__(name, params, **kwargs)
        self.count = 0
        self.publisher = self.create_publisher("/count", msgs.Log)
        self.create_service("/echo", msgs.GripperCommand, msgs.GripperState,
                            lambda request: msgs.GripperState(width_m=request.width_m, state="echo"))
        self.create_timer(self.params.period_s, self.tick)
        print(f"counter ready pid {os.getpid()}", flush=True)

    def tick(self) -> None:
        self.count += 1
        self.publisher.publish(msgs.Log(node=self.name, text=str(self.count)))
        if self.params.fail_after and self.count >= self.params.fail_after:
            sys.exit(3)
        if self.params.finish_after and self.count >= self.params.finish_after:
            self.request_shutdown()


if __name__ == "__main__":
    run_node(CounterNode)
