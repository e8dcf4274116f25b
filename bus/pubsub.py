"""Publish/subscribe over ZeroMQ, with discovery through the registry; the Bus that makes
publishers, subscribers, services (bus.services) and clients.

- Topics: a publisher binds an XPUB socket (so it sees subscriptions arrive) and advertises
  it; subscribers connect to every live publisher of the topic. Latched topics resend their
  last message when a subscriber joins (slow joiners get it); receivers drop the repeat by
  sequence number. Gaps in sequence numbers are counted as drops.
- Anything malformed, oversized or of the wrong type is dropped, counted and logged, the
  logging at most once a second per socket (a flood of garbage must not become a flood of
  log lines). Every socket that receives refuses oversized messages before allocating them,
  a publisher's too (it receives only subscriptions). Executors take at most
  ``SLICE_MESSAGES`` from one socket before serving the others, so a flood on one socket
  delays the rest by one slice, not by the whole flood.
- A dropped link is told apart by what ZeroMQ does next: one whose publisher went away without
  leaving (killed with -9, or the link broke) counts as ``publishers_gone``; one ZeroMQ closed
  over an oversized or malformed message counts as ``connection_resets`` and is reconnected.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, TypeVar

import zmq
from zmq.utils.monitor import recv_monitor_message

from bus.context import SLICE_MESSAGES, BusContext, Counters, DropLog, recv_frames, send_frames
from bus.registry import Endpoint
from bus.services import ServiceClient, ServiceServer
from msgs.base import Header, Message
from msgs.codec import Envelope, MessageError, decode, encode

log = logging.getLogger("dtx.bus")
M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

DISCOVERY_PERIOD_S = 0.2
# zmq.POLLIN as a plain int: getsockopt(EVENTS) is an int, and int & IntFlag goes through the
# enum machinery (~1 us) on every message.
POLLIN = int(zmq.POLLIN)
FORGET_AFTER_S = 10.0
# A publisher reads its subscription events at most this often while publishing (reading
# them costs a socket-option call, ~2 us warm and ~25 us on a paced sensor's cold path);
# an executor reads them as soon as they arrive.
SUBSCRIPTIONS_PERIOD_S = 0.05
# What a publisher's XPUB socket receives: subscriptions, a flag byte and a topic name.
MAX_SUBSCRIPTION_BYTES = 64 * 1024
# How long a dropped link waits for ZeroMQ's own reconnect before the drop is taken for refused
# data; libzmq reports the retry in the same call as the drop, so any wait will do, and links are
# looked at once a discovery period (DISCOVERY_PERIOD_S) anyway.
LINK_VERDICT_S = 0.05


class Bus(BusContext):
    """One process's view of the bus: a ZeroMQ context, the registry and its settings (its
    :class:`BusContext`), and the publishers, subscribers, services and clients it makes."""

    def publisher(self, topic: str, msg_type: type[M], latched: bool = False) -> "Publisher[M]":
        return Publisher(self, self.resolve(topic), msg_type, latched)

    def subscriber(self, topic: str, msg_type: type[M] | None) -> "Subscriber[M]":
        topic = self.resolve(topic)
        schema = msg_type.SCHEMA if msg_type is not None else ""
        return Subscriber(self, topic, msg_type, self.peer_endpoints("topic", topic, schema))

    def service(
        self, name: str, request_type: type[M], reply_type: type[R], handler: Callable[[M], R | Future[R]]
    ) -> "ServiceServer[M, R]":
        return ServiceServer(self, self.resolve(name), request_type, reply_type, handler)

    def client(
        self, name: str, request_type: type[M], reply_type: type[R], stop: Callable[[], bool] | None = None
    ) -> "ServiceClient[M, R]":
        name = self.resolve(name)
        return ServiceClient(
            self, name, request_type, reply_type, self.peer_endpoints("service", name, request_type.SCHEMA), stop
        )


class Publisher(Generic[M]):
    def __init__(self, bus: Bus, topic: str, msg_type: type[M], latched: bool) -> None:
        self.bus, self.topic, self.msg_type, self.latched = bus, topic, msg_type, latched
        self.id = bus.new_owner_id()
        self.sock = bus.context.socket(zmq.XPUB)
        self.sock.setsockopt(zmq.XPUB_VERBOSE, 1)  # every join is seen, so latched resend works
        self.sock.setsockopt(zmq.SNDHWM, bus.transport.high_water_mark)
        self.sock.setsockopt(zmq.MAXMSGSIZE, MAX_SUBSCRIPTION_BYTES)  # refused before allocation
        self.sock.setsockopt(zmq.LINGER, 500)
        self.address, server_key = bus.bind(self.sock, self.id, topic)
        self.seq = 0
        self.subscriptions = 0
        self._next_service = 0.0
        self._last_frames: list[Any] | None = None
        self._entry = bus.registry.advertise(
            Endpoint(
                "topic",
                topic,
                self.address,
                bus.node_name,
                os.getpid(),
                msg_type.SCHEMA,
                latched=latched,
                curve_server_key=server_key,
            )
        )

    def publish(self, message: M) -> None:
        if not isinstance(message, self.msg_type):
            raise TypeError(f"{self.topic} carries {self.msg_type.__name__}, not {type(message).__name__}")
        self.seq += 1
        header = message.header
        frames = encode(
            self.topic,
            message,
            self.id,
            Header(stamp_ns=header.stamp_ns or time.time_ns(), seq=self.seq, frame_id=header.frame_id),
        )
        now = time.monotonic()
        if now >= self._next_service:
            self._next_service = now + SUBSCRIPTIONS_PERIOD_S
            self.service_subscriptions()
        send_frames(self.sock, frames)
        if self.latched:
            self._last_frames = frames

    def service_subscriptions(self) -> None:
        """Count joins and leaves (at most a slice of them per call); a join on a latched
        topic gets the last message again."""
        for _ in range(SLICE_MESSAGES):
            if not self.sock.getsockopt(zmq.EVENTS) & POLLIN:  # type: ignore[operator]  # an int; cheaper than a failing recv
                return
            event = self.sock.recv()
            if event[:1] == b"\x01":
                self.subscriptions += 1
                if self._last_frames is not None:
                    send_frames(self.sock, self._last_frames)
            elif event[:1] == b"\x00":
                self.subscriptions = max(0, self.subscriptions - 1)

    def wait_for_subscribers(self, count: int = 1, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while True:
            self.service_subscriptions()
            if self.subscriptions >= count:
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self.sock.poll(min(remaining, 0.05) * 1000, zmq.POLLIN)  # type: ignore[arg-type]  # pyzmq polls float ms; its stub says int

    def close(self) -> None:
        self._entry.unlink(missing_ok=True)
        self.sock.close()


class Subscriber(Generic[M]):
    """Receives one topic from every publisher of it. ``msg_type`` None accepts any schema
    (recorders, ``dtx topic echo``)."""

    def __init__(
        self, bus: Bus, topic: str, msg_type: type[M] | None, static_endpoints: list[Endpoint] | None = None
    ) -> None:
        self.bus, self.topic, self.msg_type = bus, topic, msg_type
        self.sock = bus.context.socket(zmq.SUB)
        self.sock.setsockopt(zmq.RCVHWM, bus.transport.high_water_mark)
        self.sock.setsockopt(zmq.MAXMSGSIZE, bus.transport.max_message_bytes)  # refused before allocation
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SUBSCRIBE, topic.encode())
        self.counters = Counters()
        self._drop_log = DropLog()
        self._static = list(static_endpoints or [])
        self._connected: dict[str, Endpoint] = {}
        self._missing_since: dict[str, float] = {}
        self._last_seq: dict[str, int] = {}
        self._next_discovery = 0.0
        # ZeroMQ reports every dropped link alike (EVENT_DISCONNECTED); what it does next says
        # why. After a connection error (the publisher was killed, or the link broke) it
        # reconnects by itself and says so at once (EVENT_CONNECT_RETRIED); after a protocol
        # error (a message over MAXMSGSIZE, refused before it is allocated, or broken framing)
        # it gives the link up for good, so we reconnect (libzmq session_base_t::engine_error).
        self._monitor = self.sock.get_monitor_socket(zmq.EVENT_DISCONNECTED | zmq.EVENT_CONNECT_RETRIED)
        # Dropped links whose cause is not known yet: address -> (when seen, whether the drop is news)
        self._dropped: dict[str, tuple[float, bool]] = {}
        self.discover()

    def _sort_dropped_links(self) -> None:
        """Count and log each dropped link by its cause, and reconnect a link ZeroMQ gave up."""
        now = time.monotonic()
        while self._monitor.poll(0):
            event = recv_monitor_message(self._monitor)
            address = event["endpoint"].decode()
            if event["event"] == zmq.EVENT_DISCONNECTED:
                self._dropped[address] = (now, self._unannounced(address))
            elif address in self._dropped:  # ZeroMQ retries by itself: the peer left, the data was fine
                _, news = self._dropped.pop(address)
                if news:
                    self.counters.publishers_gone += 1
                    log.warning(
                        "%s: the publisher at %s went away without leaving the registry (killed, or the "
                        "link broke); ZeroMQ reconnects if it comes back",
                        self.topic,
                        address,
                    )
        for address, (seen, news) in list(self._dropped.items()):
            if now - seen < LINK_VERDICT_S:
                continue
            del self._dropped[address]
            if news and address in self._connected:  # no retry came: ZeroMQ refused the data
                self.counters.connection_resets += 1
                log.warning(
                    "%s: connection to %s dropped (oversized or malformed data); reconnecting", self.topic, address
                )
                self.sock.disconnect(address)
                self.sock.connect(address)

    def _unannounced(self, address: str) -> bool:
        """Whether a link to ``address`` ending is news: one of ours whose publisher is still
        advertised. A publisher that closes removes its entry first, so its leaving is not."""
        return address in self._connected and any(
            e.address == address for e in self._static + self.bus.registry.lookup("topic", self.topic)
        )

    def discover(self, force: bool = False) -> None:
        """Connect to new publishers of the topic, forget dead ones (cheap; called often)."""
        now = time.monotonic()
        if not force and now < self._next_discovery:
            return
        self._next_discovery = now + DISCOVERY_PERIOD_S
        self._sort_dropped_links()
        endpoints = self._static + self.bus.registry.lookup("topic", self.topic)
        live = {e.address: e for e in endpoints}
        for address, endpoint in live.items():
            if address not in self._connected:
                if self.msg_type is not None and endpoint.schema != self.msg_type.SCHEMA:
                    log.warning(
                        "%s: publisher %s sends %s, expected %s; not connecting",
                        self.topic,
                        endpoint.node,
                        endpoint.schema,
                        self.msg_type.SCHEMA,
                    )
                    continue
                self.bus.secure_connection(self.sock, endpoint)
                self.sock.connect(address)
                self._connected[address] = endpoint
        for address in list(self._connected):
            if address in live:
                self._missing_since.pop(address, None)
            elif now - self._missing_since.setdefault(address, now) > FORGET_AFTER_S:
                # Disconnecting discards what is still queued from that publisher, so a
                # publisher that just finished (a bag player, a node that ended) gets time.
                self.sock.disconnect(address)
                del self._connected[address]
                del self._missing_since[address]

    @property
    def publisher_count(self) -> int:
        return len(self._connected)

    def receive(self, timeout_s: float | None = None) -> Envelope | None:
        """The next valid message, or None after ``timeout_s`` (None: wait forever)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            self.discover()
            ready = self.sock.getsockopt(zmq.EVENTS) & POLLIN  # type: ignore[operator]  # EVENTS is an int
            if not ready:  # wait, at most until the next discovery or the deadline
                wait = DISCOVERY_PERIOD_S if deadline is None else min(DISCOVERY_PERIOD_S, deadline - time.monotonic())
                ready = wait > 0 and self.sock.poll(wait * 1000, zmq.POLLIN)  # type: ignore[arg-type]  # pyzmq polls float ms; its stub says int
            if ready:
                envelope = self.handle(recv_frames(self.sock))
                if envelope is not None:
                    return envelope
            elif deadline is not None and time.monotonic() >= deadline:
                return None

    def receive_ready(self, limit: int = SLICE_MESSAGES) -> list[Envelope]:
        """The valid messages among the next ``limit`` waiting, without blocking (for
        executors: what is left waits for the next slice, after the other sockets)."""
        return [envelope for _, envelope in self.receive_ready_frames(limit)]

    def receive_ready_frames(self, limit: int) -> list[tuple[list[zmq.Frame], Envelope]]:
        """As :meth:`receive_ready`, each message with the frames it came in (a recorder writes
        them as they are)."""
        received = []
        for _ in range(limit):
            try:
                frames = recv_frames(self.sock, zmq.NOBLOCK)
            except zmq.Again:
                break
            envelope = self.handle(frames)
            if envelope is not None:
                received.append((frames, envelope))
        return received

    def handle(self, frames: list[Any]) -> Envelope | None:
        try:
            envelope = decode(frames, self.bus.transport.max_message_bytes)
        except MessageError as exc:
            self.counters.malformed += 1
            self._drop_log.warning("%s: dropped a malformed message (%s)", self.topic, exc)
            return None
        if envelope.topic != self.topic:
            return None  # prefix match of the ZeroMQ filter, another topic
        if self.msg_type is not None and not isinstance(envelope.message, self.msg_type):
            self.counters.wrong_type += 1
            self._drop_log.warning(
                "%s: dropped a %s, expected %s", self.topic, envelope.message.SCHEMA, self.msg_type.SCHEMA
            )
            return None
        seq = envelope.message.header.seq
        last = self._last_seq.get(envelope.publisher)
        if last is not None and seq <= last:
            self.counters.duplicates += 1  # a latched resend this subscriber already has
            return None
        if last is not None and seq > last + 1:
            self.counters.dropped += seq - last - 1
        self._last_seq[envelope.publisher] = seq
        self.counters.received += 1
        self.counters.bytes += envelope.size_bytes
        return envelope

    def close(self) -> None:
        self.sock.disable_monitor()
        self._monitor.close()
        self.sock.close()
