"""Small nodes that launch tests start as real processes."""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from concurrent.futures import Future

import msgs
from bus.node import Node, run_node
from bus.services import ServiceCallError


class CounterNode(Node):
    """Publishes an increasing count on /count; can finish or fail after some counts. /echo
    answers at once; /hold answers after ``hold_s`` of background work (a motion, a
    registration), which ends early when the node is asked to stop."""

    @dataclasses.dataclass
    class Params:
        period_s: float = 0.05
        finish_after: int = 0
        fail_after: int = 0
        hold_s: float = 0.0
        text_bytes: int = 0  # padding of each /count message, for a recorder to fill a disk
        call_hold: bool = False  # each tick calls /target/hold and waits (as the collector calls)
        start_s: float = 0.0  # how long making the node takes (a device connecting, a model loading)

    def __init__(self, name: str, params: dict | None = None, **kwargs: object) -> None:
        super().__init__(name, params, **kwargs)
        if self.params.start_s:
            print("starting", flush=True)
            time.sleep(self.params.start_s)
        self.count = 0
        self.publisher = self.create_publisher("/count", msgs.Log)
        self.create_service(
            "/echo",
            msgs.GripperCommand,
            msgs.GripperState,
            lambda request: msgs.GripperState(width_m=request.width_m, state="echo"),
        )
        self.create_service("/hold", msgs.GripperCommand, msgs.GripperState, self.hold)
        self.hold_client = self.create_client("/target/hold", msgs.GripperCommand, msgs.GripperState)
        self.create_timer(self.params.period_s, self.tick)
        print(f"counter ready pid {os.getpid()}", flush=True)

    def hold(self, request: msgs.GripperCommand) -> Future[msgs.GripperState]:
        def work() -> msgs.GripperState:
            deadline = time.monotonic() + self.params.hold_s
            while time.monotonic() < deadline and not self.shutting_down:
                time.sleep(0.01)
            return msgs.GripperState(width_m=request.width_m, state=f"held by {os.getpid()}")

        return self.background.submit(work)

    def tick(self) -> None:
        self.count += 1
        text = str(self.count)
        if self.params.text_bytes:
            text += " " + os.urandom(self.params.text_bytes // 2).hex()  # random: compression cannot shrink it
        self.publisher.publish(msgs.Log(node=self.name, text=text))
        if self.params.fail_after and self.count >= self.params.fail_after:
            sys.exit(3)
        if self.params.finish_after and self.count >= self.params.finish_after:
            self.request_shutdown()
        if self.params.call_hold:
            try:
                self.hold_client.call(msgs.GripperCommand(width_m=0.01), timeout_s=60.0)
            except ServiceCallError as error:
                print(f"call ended: {error.code}", flush=True)


if __name__ == "__main__":
    run_node(CounterNode)
