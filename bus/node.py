"""The node base: a process with a name, parameters, publishers, subscribers, services,
timers, a heartbeat, and a clean shutdown on SIGINT/SIGTERM.

A node runs a single-threaded executor (like ROS 2's): callbacks of subscriptions, services
and timers run one at a time in ``spin``, so node code needs no locks. A node module ends with
``if __name__ == "__main__": run_node(MyNode)``; ``dtx launch`` starts it as
``python -m MODULE --name NAME --params JSON --remap FROM:=TO``.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, ClassVar, TypeVar

import zmq

from bus.context import Counters, PeerConfig, TransportConfig
from bus.pubsub import Bus, Publisher, Subscriber
from bus.registry import Registry
from bus.security import CurveConfig
from bus.services import ServiceClient, ServiceServer
from bus.start import STOP_SIGNALS, stop_quietly
from msgs.base import Message
from msgs.codec import Envelope
from msgs.config import ConfigError, config_from_dict
from msgs.system import Heartbeat, Log

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)
P = TypeVar("P")

HEARTBEAT_PERIOD_S = 1.0

# The exit-status contract with the launcher: 0 is a clean stop; a node exiting with
# EXIT_DO_NOT_RESPAWN (bad parameters, an unwritable output) would only fail again, so the
# launcher does not respawn it; any other status is a crash, respawned when the launch file asks.
EXIT_DO_NOT_RESPAWN = 2


class ParameterError(ValueError):
    """A node parameter is unknown, missing or of the wrong type."""


def parse_params(params_type: type[P], values: dict[str, Any], node: str = "") -> P:
    """Build the node's parameter dataclass (msgs.config), refusing unknown keys and wrong types."""
    try:
        return config_from_dict(params_type, values)
    except ConfigError as exc:
        raise ParameterError(f"node {node}: {exc}") from None


def split_params(params_type: type, values: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the node's own parameters, the rest) — hardware nodes hand the rest to their backend."""
    own = {f.name for f in dataclasses.fields(params_type)}
    return ({k: v for k, v in values.items() if k in own}, {k: v for k, v in values.items() if k not in own})


@dataclasses.dataclass
class NoParams:
    pass


class _BusLogHandler(logging.Handler):
    def __init__(self, node: "Node") -> None:
        super().__init__(logging.INFO)
        self.node = node

    def emit(self, record: logging.LogRecord) -> None:
        publisher = self.node._log_publisher
        if publisher is not None and not self.node._closing:
            publisher.publish(Log(level=record.levelname.lower(), node=self.node.name, text=record.getMessage()))


class Node:
    """Subclass it, set ``Params`` to a dataclass of parameters, wire things in ``__init__``."""

    Params: ClassVar[type] = NoParams

    def __init__(
        self,
        name: str,
        params: dict[str, Any] | None = None,
        *,
        registry: Registry | None = None,
        transport: TransportConfig | None = None,
        remaps: dict[str, str] | None = None,
    ) -> None:
        self.name = name
        self.params: Any = parse_params(self.Params, params or {}, name)
        registry = registry or Registry()
        holder = registry.live_node_pid(name)
        if holder is not None and holder != os.getpid():
            # Two graphs in one domain would answer each other's requests and mix their data.
            raise ValueError(
                f"a node named {name!r} already runs (pid {holder}) on bus {registry.root}; stop that "
                "graph, or give this one a bus of its own with DTX_DOMAIN=NAME"
            )
        self.bus = Bus(name, registry, transport, remaps)
        self.log = logging.getLogger(f"dtx.{name}")
        self._publishers: list[Publisher[Any]] = []
        self._subscriptions: list[tuple[Subscriber[Any], Callable[[Any], None]]] = []
        self._counted: list[Subscriber[Any]] = []  # whose counters the heartbeat reports
        self._services: list[ServiceServer[Any, Any]] = []
        self._clients: list[ServiceClient[Any, Any]] = []
        self._timers: list[tuple[float, int, float, Callable[[], None]]] = []
        # Long device commands (a motion, a grasp) run here so the executor keeps publishing;
        # a pipe wakes the executor when one completes (a pipe, as any thread may write it).
        self.background = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_read, False)
        self._timer_count = 0
        self._shutdown = False
        self._closing = False
        self.status = "ok"
        self._log_publisher: Publisher[Log] | None = None
        self._log_publisher = self.create_publisher("/log", Log)
        self._bus_log_handler = _BusLogHandler(self)
        self.log.addHandler(self._bus_log_handler)
        self._heartbeat = self.create_publisher("/heartbeat", Heartbeat)
        self.create_timer(HEARTBEAT_PERIOD_S, self._beat)

    # -- wiring -------------------------------------------------------------------------
    def create_publisher(self, topic: str, msg_type: type[M], latched: bool = False) -> Publisher[M]:
        publisher = self.bus.publisher(topic, msg_type, latched)
        self._publishers.append(publisher)
        return publisher

    def create_subscription(self, topic: str, msg_type: type[M], callback: Callable[[M], None]) -> Subscriber[M]:
        subscriber = self.bus.subscriber(topic, msg_type)
        self._subscriptions.append((subscriber, lambda envelope: callback(envelope.message)))
        self.count_subscriber(subscriber)
        return subscriber

    def create_service(
        self, name: str, request_type: type[M], reply_type: type[R], handler: Callable[[M], R | Future[R]]
    ) -> ServiceServer[M, R]:
        """``handler`` may return a Future (work in ``self.background``): the executor is
        woken the moment it completes, and its reply goes out then."""

        def wake_when_done(request: M) -> R | Future[R]:
            result = handler(request)
            if isinstance(result, Future):
                result.add_done_callback(lambda _: os.write(self._wake_write, b"x"))
            return result

        server = self.bus.service(name, request_type, reply_type, wake_when_done)
        self._services.append(server)
        return server

    def create_client(self, name: str, request_type: type[M], reply_type: type[R]) -> ServiceClient[M, R]:
        """A client whose calls end (``cancelled``) once the node is asked to stop: a call
        whose server stops with the graph would otherwise outlast the launcher's grace time."""
        client = self.bus.client(name, request_type, reply_type, stop=lambda: self._shutdown)
        self._clients.append(client)
        return client

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> None:
        if not period_s > 0:
            raise ValueError(f"timer period must be positive, got {period_s}")
        self._timer_count += 1
        heapq.heappush(self._timers, (time.monotonic() + period_s, self._timer_count, period_s, callback))

    # -- executor -----------------------------------------------------------------------
    def spin_once(self, timeout_s: float = 0.1) -> None:
        """Wait up to ``timeout_s`` for work, then run every callback that is due."""
        poller = zmq.Poller()
        for subscriber, _ in self._subscriptions:
            subscriber.discover()
            poller.register(subscriber.sock, zmq.POLLIN)
        for server in self._services:
            poller.register(server.sock, zmq.POLLIN)
        for publisher in self._publishers:
            poller.register(publisher.sock, zmq.POLLIN)
        poller.register(self._wake_read, zmq.POLLIN)
        next_timer = self._timers[0][0] if self._timers else time.monotonic() + timeout_s
        wait_s = max(0.0, min(timeout_s, next_timer - time.monotonic()))
        ready = dict(poller.poll(wait_s * 1000))  # type: ignore[arg-type]  # pyzmq takes float ms; its stub says int
        if self._wake_read in ready:
            os.read(self._wake_read, 4096)
        for publisher in self._publishers:
            if publisher.sock in ready:
                publisher.service_subscriptions()
        for server in self._services:
            if server.sock in ready or server.pending:
                server.serve_ready()
        for subscriber, callback in self._subscriptions:
            if subscriber.sock in ready:
                for envelope in subscriber.receive_ready():
                    self._deliver(subscriber, callback, envelope)
        now = time.monotonic()
        while self._timers and self._timers[0][0] <= now:
            due, count, period_s, on_timer = heapq.heappop(self._timers)
            # Re-arm from the due time so a periodic timer keeps its rate, unless it fell behind.
            heapq.heappush(self._timers, (max(due + period_s, now), count, period_s, on_timer))
            on_timer()

    def _deliver(self, subscriber: Subscriber, callback: Callable[[Envelope], None], envelope: Envelope) -> None:
        # A message that passed decoding can still break a callback (a value its code did not
        # expect); that costs the message, counted and logged, never the node. A failing disk or
        # device (OSError) is the node's own state, not the message's, and still ends it.
        try:
            callback(envelope)
        except OSError:
            raise
        except Exception:
            subscriber.counters.handler_errors += 1
            self.log.exception(
                "%s: a callback failed on a %s; message dropped", subscriber.topic, envelope.message.SCHEMA
            )

    def spin(self, until: Callable[[], bool] | None = None) -> None:
        while not self._shutdown and not (until is not None and until()):
            self.spin_once()

    def spin_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Run callbacks until ``done()`` holds or ``timeout_s`` has passed; whether it holds."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                return False
            self.spin_once(0.01)
        return True

    def keep_alive(self) -> bool:
        """For nodes whose work is one long loop (recording, playing a bag): run what is due
        (heartbeat, services) without waiting, and say whether to stop."""
        self.spin_once(0.0)
        return self._shutdown

    def request_shutdown(self) -> None:
        self._shutdown = True

    @property
    def shutting_down(self) -> bool:
        return self._shutdown

    def count_subscriber(self, subscriber: Subscriber[Any]) -> None:
        """Add the counters of a subscriber the node reads itself (not through
        ``create_subscription``; a recorder's) to those its heartbeat reports."""
        self._counted.append(subscriber)

    def counters(self) -> dict[str, int]:
        total = Counters()
        for subscriber in self._counted:
            for key, value in dataclasses.asdict(subscriber.counters).items():
                setattr(total, key, getattr(total, key) + value)
        return dataclasses.asdict(total)

    def _beat(self) -> None:
        info = Heartbeat(
            node=self.name,
            pid=os.getpid(),
            status=self.status,
            publishers=[p.topic for p in self._publishers],
            subscribers=[s.topic for s, _ in self._subscriptions],
            services=[s.name for s in self._services],
            counters=self.counters(),
        )
        self._heartbeat.publish(info)
        status = dataclasses.asdict(info)
        status.pop("header")
        status["stamp"] = time.time()
        self.bus.registry.write_node_status(self.name, status)

    def close(self) -> None:
        self.background.shutdown(wait=True, cancel_futures=True)
        self._closing = True
        self.log.removeHandler(self._bus_log_handler)
        self.status = "stopped"
        self._beat()
        for publisher in self._publishers:
            publisher.close()
        for server in self._services:
            server.close()
        for subscriber, _ in self._subscriptions:
            subscriber.close()
        for client in self._clients:
            client.close()
        self.bus.close()
        os.close(self._wake_read)
        os.close(self._wake_write)


def _parse_remap(text: str) -> tuple[str, str]:
    if ":=" not in text:
        raise argparse.ArgumentTypeError(f"remap {text!r} must look like FROM:=TO")
    source, target = text.split(":=", 1)
    return source, target


def run_node(node_class: type[Node], argv: list[str] | None = None) -> None:
    """Entry point of a node process: parse the launcher's arguments, spin until a signal."""
    parser = argparse.ArgumentParser(prog=node_class.__module__)
    parser.add_argument("--name", default=node_class.__module__.rsplit(".", 1)[-1])
    parser.add_argument("--params", default="{}", help="parameters as a JSON object")
    parser.add_argument("--remap", action="append", type=_parse_remap, default=[])
    parser.add_argument("--transport", choices=["ipc", "tcp"], default="ipc")
    parser.add_argument("--bind-host", default="127.0.0.1")
    parser.add_argument("--curve-secret-key", default="")
    parser.add_argument("--curve-authorized-keys", default="")
    parser.add_argument("--endpoints", default="{}", help="JSON: name -> address to bind")
    parser.add_argument("--peers", default="{}", help="JSON: name -> {address, server_key_file}")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(message)s")
    curve = CurveConfig(args.curve_secret_key, args.curve_authorized_keys) if args.curve_secret_key else None
    # A stop while the node is being made (a device connecting, a model loading) ends it at once,
    # quietly: the launcher's start-up handler (bus.start), in place as well for a node started by hand.
    for signum in STOP_SIGNALS:
        signal.signal(signum, stop_quietly)
    try:
        peers = {name: PeerConfig(**peer) for name, peer in json.loads(args.peers).items()}
        transport = TransportConfig(
            args.transport, args.bind_host, curve, endpoints=json.loads(args.endpoints), peers=peers
        )
        node = node_class(args.name, json.loads(args.params), transport=transport, remaps=dict(args.remap))
    except (ParameterError, ValueError, TypeError) as exc:
        print(f"{args.name}: cannot start: {exc}", file=sys.stderr)
        raise SystemExit(EXIT_DO_NOT_RESPAWN) from exc
    try:
        for signum in STOP_SIGNALS:
            signal.signal(signum, lambda *_: node.request_shutdown())
        node.spin()
    finally:
        node.close()
