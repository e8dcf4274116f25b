"""Publish/subscribe and services over ZeroMQ, with discovery through the registry.

- Topics: a publisher binds an XPUB socket (so it sees subscriptions arrive) and advertises
  it; subscribers connect to every live publisher of the topic. Latched topics resend their
  last message when a subscriber joins (slow joiners get it); receivers drop the repeat by
  sequence number. Gaps in sequence numbers are counted as drops.
- Services: ROUTER servers, DEALER clients; a call has a time-out and retries, repeated
  requests are answered from a reply cache (a retry never runs a handler twice), and a bad
  request gets a ``ServiceError`` reply while the server keeps serving. A handler may return
  a ``concurrent.futures.Future`` (a motion running in the background): the reply goes out
  when it completes, and the server keeps serving meanwhile.
- Anything malformed, oversized or of the wrong type is dropped, counted and logged, the
  logging at most once a second per socket (a flood of garbage must not become a flood of
  log lines). Every socket that receives refuses oversized messages before allocating them,
  a publisher's too (it receives only subscriptions). Executors take at most
  ``SLICE_MESSAGES`` from one socket before serving the others, so a flood on one socket
  delays the rest by one slice, not by the whole flood.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import logging
import os
import time
import weakref
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, TypeVar

import msgpack
import zmq
import zmq.auth
from zmq.utils.monitor import recv_monitor_message

from msgs.base import Header, Message
from msgs.codec import DEFAULT_MAX_MESSAGE_BYTES, MAX_HEADER_BYTES, Envelope, MessageError, decode, encode
from msgs.system import ErrorCode, ServiceError
from nodes.registry import Endpoint, Registry
from nodes.security import CurveConfig, secure_client, secure_server, stop_authenticator

log = logging.getLogger("dtx.bus")
M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

DISCOVERY_PERIOD_S = 0.2
# zmq.POLLIN as a plain int: getsockopt(EVENTS) is an int, and int & IntFlag goes through the
# enum machinery (~1 us) on every message.
POLLIN = int(zmq.POLLIN)
# Every Bus not yet closed: a context left to the garbage collector can block it forever in
# zmq_term, so whoever owns a process's lifetime (a test run) closes what is left here.
OPEN_BUSES: "weakref.WeakSet[Bus]" = weakref.WeakSet()
FORGET_AFTER_S = 10.0
SLICE_MESSAGES = 100
# What a publisher's XPUB socket receives: subscriptions, a flag byte and a topic name.
MAX_SUBSCRIPTION_BYTES = 64 * 1024
DROP_LOG_PERIOD_S = 1.0
# How often a waiting client looks whether its server still lives (docs/wire-protocol.md §4).
LIVENESS_PERIOD_S = 0.25


class DropLog:
    """Warnings about dropped messages on one socket, at most one per ``DROP_LOG_PERIOD_S``,
    each saying how many were not reported since: the counters count every drop."""

    def __init__(self) -> None:
        self._next = 0.0
        self._unreported = 0

    def warning(self, text: str, *args: Any) -> None:
        now = time.monotonic()
        if now < self._next:
            self._unreported += 1
            return
        more = f" ({self._unreported} more dropped since the last report)" if self._unreported else ""
        log.warning(text + "%s", *args, more)
        self._next, self._unreported = now + DROP_LOG_PERIOD_S, 0


class ServiceCallError(RuntimeError):
    """The service answered with an error, or did not answer in time."""

    def __init__(self, service: str, code: str, text: str) -> None:
        super().__init__(f"service {service}: {code}: {text}")
        self.service, self.code, self.text = service, code, text


@dataclasses.dataclass
class TransportConfig:
    """Where this process's sockets listen. ``ipc`` (default) stays on this machine;
    ``tcp`` binds ``bind_host`` (127.0.0.1 unless a launch file says otherwise), with CURVE
    when ``curve`` is given."""

    transport: str = "ipc"
    bind_host: str = "127.0.0.1"
    curve: CurveConfig | None = None
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    high_water_mark: int = 1000
    # Crossing machines: fixed addresses to bind for some topics/services (name -> address,
    # e.g. "tcp://0.0.0.0:7000"), and remote ones to connect to (name -> PeerConfig).
    endpoints: dict[str, str] = dataclasses.field(default_factory=dict)
    peers: dict[str, "PeerConfig"] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class PeerConfig:
    """A topic or service on another machine: its address and its CURVE public key file."""

    address: str
    server_key_file: str = ""


@dataclasses.dataclass
class Counters:
    received: int = 0
    dropped: int = 0
    duplicates: int = 0
    malformed: int = 0
    wrong_type: int = 0
    connection_resets: int = 0
    handler_errors: int = 0
    bytes: int = 0


class Bus:
    """One process's view of the bus: a ZeroMQ context, the registry and its settings."""

    def __init__(
        self,
        node_name: str,
        registry: Registry | None = None,
        transport: TransportConfig | None = None,
        remaps: dict[str, str] | None = None,
    ) -> None:
        self.node_name = node_name
        self.registry = registry or Registry()
        self.transport = transport or TransportConfig()
        self.remaps = dict(remaps or {})
        self.context = zmq.Context()
        self._owner_count = 0
        self.closed = False
        OPEN_BUSES.add(self)

    def resolve(self, name: str) -> str:
        return self.remaps.get(name, name)

    def new_owner_id(self) -> str:
        self._owner_count += 1
        return f"{self.node_name}.{os.getpid()}.{self._owner_count}"

    def bind(self, sock: zmq.Socket, owner: str, name: str) -> tuple[str, str]:
        """Bind per the transport config; returns (address, CURVE public key or "")."""
        server_key = ""
        fixed = self.transport.endpoints.get(name)
        if fixed is not None:
            if fixed.startswith("tcp://") and self.transport.curve is not None:
                server_key = secure_server(self.context, sock, self.transport.curve)
            address = fixed
        elif self.transport.transport == "ipc":
            address = self.registry.socket_address(owner)
        elif self.transport.transport == "tcp":
            if self.transport.curve is not None:
                server_key = secure_server(self.context, sock, self.transport.curve)
            address = f"tcp://{self.transport.bind_host}:*"
        else:
            raise ValueError(f"transport {self.transport.transport!r} unknown (allowed: ipc, tcp)")
        sock.bind(address)
        return sock.getsockopt_string(zmq.LAST_ENDPOINT), server_key

    def secure_connection(self, sock: zmq.Socket, endpoint: Endpoint) -> None:
        if endpoint.curve_server_key:
            if self.transport.curve is None:
                raise ValueError(f"{endpoint.name} at {endpoint.address} needs CURVE keys; none configured")
            secure_client(sock, self.transport.curve, endpoint.curve_server_key)

    def publisher(self, topic: str, msg_type: type[M], latched: bool = False) -> "Publisher[M]":
        return Publisher(self, self.resolve(topic), msg_type, latched)

    def peer_endpoints(self, kind: str, name: str, schema: str) -> list[Endpoint]:
        """The launch file's remote endpoint for ``name``, if it names one."""
        peer = self.transport.peers.get(name)
        if peer is None:
            return []
        server_key = ""
        if peer.server_key_file:
            server_key = zmq.auth.load_certificate(peer.server_key_file)[0].decode()
        return [Endpoint(kind, name, peer.address, "remote", os.getpid(), schema, curve_server_key=server_key)]

    def subscriber(self, topic: str, msg_type: type[M] | None) -> "Subscriber[M]":
        topic = self.resolve(topic)
        schema = msg_type.SCHEMA if msg_type is not None else ""
        return Subscriber(self, topic, msg_type, self.peer_endpoints("topic", topic, schema))

    def service(
        self, name: str, request_type: type[M], reply_type: type[R], handler: Callable[[M], R]
    ) -> "ServiceServer[M, R]":
        return ServiceServer(self, self.resolve(name), request_type, reply_type, handler)

    def client(
        self, name: str, request_type: type[M], reply_type: type[R], stop: Callable[[], bool] | None = None
    ) -> "ServiceClient[M, R]":
        name = self.resolve(name)
        return ServiceClient(
            self, name, request_type, reply_type, self.peer_endpoints("service", name, request_type.SCHEMA), stop
        )

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        OPEN_BUSES.discard(self)
        stop_authenticator(self.context)
        self.context.destroy(linger=200)


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
        self.service_subscriptions()
        self.sock.send_multipart(frames, copy=False)
        if self.latched:
            self._last_frames = frames

    def service_subscriptions(self) -> None:
        """Count joins and leaves (at most a slice of them per call); a join on a latched
        topic gets the last message again."""
        for _ in range(SLICE_MESSAGES):
            if not self.sock.getsockopt(zmq.EVENTS) & POLLIN:  # cheaper than a failing recv
                return
            event = self.sock.recv()
            if event[:1] == b"\x01":
                self.subscriptions += 1
                if self._last_frames is not None:
                    self.sock.send_multipart(self._last_frames, copy=False)
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
            self.sock.poll(min(remaining, 0.05) * 1000, zmq.POLLIN)

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
        # ZeroMQ drops a connection that carries an oversized message (refused before it is
        # allocated) and does not come back by itself; the monitor tells us so we reconnect.
        self._monitor = self.sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        self.discover()

    def _reconnect_dropped(self) -> None:
        while self._monitor.poll(0):
            event = recv_monitor_message(self._monitor)
            address = event["endpoint"].decode()
            still_advertised = any(
                e.address == address for e in self._static + self.bus.registry.lookup("topic", self.topic)
            )
            if address in self._connected and still_advertised:  # not a publisher that ended
                self.counters.connection_resets += 1
                log.warning(
                    "%s: connection to %s dropped (oversized or malformed data); reconnecting", self.topic, address
                )
                self.sock.disconnect(address)
                self.sock.connect(address)

    def discover(self, force: bool = False) -> None:
        """Connect to new publishers of the topic, forget dead ones (cheap; called often)."""
        now = time.monotonic()
        if not force and now < self._next_discovery:
            return
        self._next_discovery = now + DISCOVERY_PERIOD_S
        self._reconnect_dropped()
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
            if self.sock.getsockopt(zmq.EVENTS) & POLLIN:
                envelope = self.handle(self.sock.recv_multipart(copy=False))
                if envelope is not None:
                    return envelope
                continue
            wait = DISCOVERY_PERIOD_S if deadline is None else min(DISCOVERY_PERIOD_S, deadline - time.monotonic())
            if wait > 0 and self.sock.poll(wait * 1000, zmq.POLLIN):
                envelope = self.handle(self.sock.recv_multipart(copy=False))
                if envelope is not None:
                    return envelope
                continue
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def receive_ready(self, limit: int = SLICE_MESSAGES) -> list[Envelope]:
        """The valid messages among the next ``limit`` waiting, without blocking (for
        executors: what is left waits for the next slice, after the other sockets)."""
        envelopes = []
        for _ in range(limit):
            try:
                frames = self.sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            envelope = self.handle(frames)
            if envelope is not None:
                envelopes.append(envelope)
        return envelopes

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


def request_id(frames: list[Any]) -> tuple[str, int]:
    """The ``p`` and ``q`` of a request that does not decode, read as leniently as possible:
    ``("", 0)`` where the header is not a msgpack map or ``p``/``q`` are not a string and a
    non-negative integer (q 0 is never a request's own number; docs/wire-protocol.md)."""
    try:
        view = memoryview(getattr(frames[1], "buffer", frames[1]))
        header = msgpack.unpackb(view, raw=False) if view.nbytes <= MAX_HEADER_BYTES else None
    except Exception:  # noqa: BLE001 - msgpack raises several unrelated types on garbage; a missing frame too
        return "", 0
    if not isinstance(header, dict):
        return "", 0
    client, seq = header.get("p"), header.get("q")
    client = client if isinstance(client, str) else ""
    seq = seq if isinstance(seq, int) and not isinstance(seq, bool) and 0 <= seq < 2**63 else 0
    return client, seq


class ServiceServer(Generic[M, R]):
    # Replies kept for retried requests: the newest, within both bounds (an inference reply
    # can be many MB, so the count alone would not bound the memory).
    REPLY_CACHE = 256
    REPLY_CACHE_BYTES = 64 * 1024 * 1024

    def __init__(
        self, bus: Bus, name: str, request_type: type[M], reply_type: type[R], handler: Callable[[M], R]
    ) -> None:
        self.bus, self.name = bus, name
        self.request_type, self.reply_type, self.handler = request_type, reply_type, handler
        self.id = bus.new_owner_id()
        self.sock = bus.context.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.MAXMSGSIZE, bus.transport.max_message_bytes)
        self.sock.setsockopt(zmq.LINGER, 500)
        self.address, server_key = bus.bind(self.sock, self.id, name)
        self.counters = Counters()
        self._drop_log = DropLog()
        # (client identity, publisher, seq) -> (reply frames, their size, the request's digest)
        self._replies: collections.OrderedDict[tuple[bytes, str, int], tuple[list[Any], int, bytes]] = (
            collections.OrderedDict()
        )
        self._reply_bytes = 0
        self._pending: list[tuple[tuple[bytes, str, int], Future[Any], bytes]] = []
        self._entry = bus.registry.advertise(
            Endpoint(
                "service",
                name,
                self.address,
                bus.node_name,
                os.getpid(),
                request_type.SCHEMA,
                reply_schema=reply_type.SCHEMA,
                curve_server_key=server_key,
            )
        )

    def serve_ready(self, limit: int = SLICE_MESSAGES) -> int:
        """Answer every finished background request and up to ``limit`` waiting ones (the
        rest wait for the next slice, after the other sockets); returns how many."""
        answered = self._finish_pending()
        for _ in range(limit):
            try:
                frames = self.sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            self._answer(frames)
            answered += 1
        return answered

    @property
    def pending(self) -> int:
        """Requests whose handler runs in the background (a motion, a grasp)."""
        return len(self._pending)

    def _finish_pending(self) -> int:
        finished = [entry for entry in self._pending if entry[1].done()]
        for entry in finished:
            self._pending.remove(entry)
            key, future, digest = entry
            error = future.exception()
            reply = self._checked_reply(future.result() if error is None else None, error)
            self._remember(key, self._send(key[0], reply, key[1], key[2]), digest)
        return len(finished)

    def _checked_reply(self, reply: Any, error: BaseException | None) -> Message:
        if error is None and not isinstance(reply, (self.reply_type, ServiceError)):
            error = TypeError(f"handler returned {type(reply).__name__}, not {self.reply_type.__name__}")
        if error is not None:
            log.error("%s: handler failed: %s: %s", self.name, type(error).__name__, error)
            return ServiceError(
                code=getattr(error, "code", ErrorCode.HANDLER_ERROR), text=f"{type(error).__name__}: {error}"
            )
        return reply

    def _remember(self, key: tuple[bytes, str, int], frames: list[Any], digest: bytes) -> None:
        size = sum(memoryview(getattr(f, "buffer", f)).nbytes for f in frames)
        self._replies[key] = (frames, size, digest)
        self._reply_bytes += size
        while len(self._replies) > self.REPLY_CACHE or (
            self._reply_bytes > self.REPLY_CACHE_BYTES and len(self._replies) > 1
        ):
            _, (_, dropped, _) = self._replies.popitem(last=False)
            self._reply_bytes -= dropped

    def _answer(self, frames: list[Any]) -> None:
        identity = frames[0].bytes
        try:
            envelope = decode(frames[1:], self.bus.transport.max_message_bytes)
        except MessageError as exc:
            self.counters.malformed += 1
            self._drop_log.warning("%s: malformed request (%s)", self.name, exc)
            # The reply carries the request's (p, q) whenever they can be read, so a client
            # waiting for that q gets its answer instead of a time-out.
            client, seq = request_id(frames[1:])
            self._send(identity, ServiceError(code=ErrorCode.BAD_REQUEST, text=str(exc)), client, seq)
            return
        key = (identity, envelope.publisher, envelope.message.header.seq)
        # A retry resends the very frames; the same (publisher, seq) with other content is not
        # one, and must not get the earlier request's reply.
        hasher = hashlib.sha256()  # twice blake2b's speed on CPUs with SHA instructions (a 134 MB cloud: 75 ms)
        for frame in frames[1:]:
            hasher.update(memoryview(getattr(frame, "buffer", frame)))
        digest = hasher.digest()
        if key in self._replies:
            earlier: bytes | None = self._replies[key][2]
        else:
            earlier = next((d for pending_key, _, d in self._pending if pending_key == key), None)
        if earlier is not None and earlier != digest:
            self.counters.malformed += 1
            self._send(
                identity,
                ServiceError(
                    code=ErrorCode.BAD_REQUEST,
                    text=(
                        f"request {envelope.message.header.seq} of {envelope.publisher} was already used for another "
                        "request: a retry must resend the same request, a new request needs a new sequence number"
                    ),
                ),
                envelope.publisher,
                envelope.message.header.seq,
            )
            return
        if key in self._replies:
            self.counters.duplicates += 1
            self.sock.send_multipart([identity, *self._replies[key][0]], copy=False)
            return
        if earlier is not None:
            self.counters.duplicates += 1  # a retry of a request still running: answered when done
            return
        request = envelope.message
        if not isinstance(request, self.request_type):
            self.counters.wrong_type += 1
            reply: Message = ServiceError(
                code=ErrorCode.WRONG_TYPE, text=f"{self.name} takes {self.request_type.SCHEMA}, got {request.SCHEMA}"
            )
        else:
            self.counters.received += 1
            try:
                result = self.handler(request)
            except Exception as exc:  # noqa: BLE001 - a handler's failure is the caller's error reply, not our death
                reply = self._checked_reply(None, exc)
            else:
                if isinstance(result, Future):
                    self._pending.append((key, result, digest))
                    return
                reply = self._checked_reply(result, None)
        self._remember(key, self._send(identity, reply, envelope.publisher, envelope.message.header.seq), digest)

    def _send(self, identity: bytes, reply: Message, client: str, seq: int) -> list[Any]:
        frames = encode(
            self.name, reply, client, Header(stamp_ns=time.time_ns(), seq=seq, frame_id=reply.header.frame_id)
        )
        self.sock.send_multipart([identity, *frames], copy=False)
        return frames

    def close(self) -> None:
        self._entry.unlink(missing_ok=True)
        self.sock.close()


class ServiceClient(Generic[M, R]):
    """Calls one service. While it waits for a reply it looks at its servers' discovery entries
    every ``LIVENESS_PERIOD_S``: a server whose process ended (or whose entry the launcher
    removed) cannot answer, so the attempt ends at once instead of at its time-out, and the next
    attempt resends to a live server (a respawn); with no attempt left the call fails with
    ``server_died``. ``stop`` (a node's shutdown flag) cancels a call: ``cancelled``."""

    def __init__(
        self,
        bus: Bus,
        name: str,
        request_type: type[M],
        reply_type: type[R],
        static_endpoints: list[Endpoint] | None = None,
        stop: Callable[[], bool] | None = None,
    ) -> None:
        self.bus, self.name = bus, name
        self.request_type, self.reply_type = request_type, reply_type
        self.id = bus.new_owner_id()
        self.sock = bus.context.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.IMMEDIATE, 1)  # never queue a request for a server not there
        self.sock.setsockopt(zmq.MAXMSGSIZE, bus.transport.max_message_bytes)
        self._static = list(static_endpoints or [])
        self._connected: dict[str, Endpoint] = {}
        self._stop = stop or (lambda: False)
        self.seq = 0

    def _discover(self) -> int:
        for endpoint in self._static + self.bus.registry.lookup("service", self.name):
            if endpoint.address not in self._connected:
                self.bus.secure_connection(self.sock, endpoint)
                self.sock.connect(endpoint.address)
                self._connected[endpoint.address] = endpoint
        return len(self._connected)

    def _forget_dead_servers(self) -> list[Endpoint]:
        """Disconnect the servers whose entry is gone (process ended, or removed by the
        launcher); the ones forgotten. Launch-file peers on other machines are never judged."""
        live = {e.address for e in self._static + self.bus.registry.lookup("service", self.name)}
        dead = [endpoint for address, endpoint in self._connected.items() if address not in live]
        for endpoint in dead:
            del self._connected[endpoint.address]
            try:
                self.sock.disconnect(endpoint.address)
            except zmq.ZMQError:
                pass  # already gone on ZeroMQ's side
        return dead

    def _check_cancelled(self) -> None:
        if self._stop():
            raise ServiceCallError(self.name, ErrorCode.CANCELLED, "the calling node is shutting down")

    def _send_when_connected(self, frames: list[Any], deadline: float) -> bool:
        """Send once a server is connected (a DEALER would block forever with none), looking
        for new servers meanwhile, e.g. the respawn of one that died."""
        while True:
            self._discover()
            try:
                self.sock.send_multipart(frames, zmq.NOBLOCK, copy=False)
                return True
            except zmq.Again:
                self._check_cancelled()
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.02)

    def server_count(self) -> int:
        """How many servers of the name this client knows now (found on the bus or given)."""
        return self._discover()

    def wait_for_service(self, timeout_s: float = 5.0) -> bool:
        """Whether a server appears within ``timeout_s``; False at once when ``stop`` is set."""
        deadline = time.monotonic() + timeout_s
        while self._discover() == 0:
            if time.monotonic() > deadline or self._stop():
                return False
            time.sleep(0.05)
        return True

    def call(self, request: M, timeout_s: float = 5.0, retries: int = 2) -> R:
        """Send ``request``; wait ``timeout_s`` per attempt, ``1 + retries`` attempts. An
        attempt whose server dies ends at once (see the class)."""
        if not isinstance(request, self.request_type):
            raise TypeError(f"{self.name} takes {self.request_type.__name__}, not {type(request).__name__}")
        if not self.wait_for_service(timeout_s):
            self._check_cancelled()
            raise ServiceCallError(self.name, ErrorCode.UNAVAILABLE, "no server found on the bus")
        self.seq += 1
        frames = encode(
            self.name, request, self.id, Header(stamp_ns=time.time_ns(), seq=self.seq, frame_id=request.header.frame_id)
        )
        size = sum(memoryview(getattr(f, "buffer", f)).nbytes for f in frames)
        if size > self.bus.transport.max_message_bytes:
            # A server drops an oversized request unread, so no reply could ever say why.
            raise ServiceCallError(
                self.name,
                ErrorCode.REQUEST_TOO_LARGE,
                f"request of {size} bytes exceeds the limit of {self.bus.transport.max_message_bytes}",
            )
        failure = (ErrorCode.TIMEOUT, f"no reply in {1 + retries} attempts of {timeout_s} s")
        for _attempt in range(1 + retries):
            deadline = time.monotonic() + timeout_s
            if not self._send_when_connected(frames, deadline):
                failure = (ErrorCode.UNAVAILABLE, f"no server came back in {timeout_s} s")
                continue  # every known server is gone; the next attempt looks again
            reply = self._await_reply(deadline)
            if isinstance(reply, list):  # the servers it may have gone to died: resend
                failure = (
                    "server_died",
                    f"server pid {', '.join(str(e.pid) for e in reply)} ended while the "
                    f"request was in flight ({1 + retries} attempt(s))",
                )
                continue
            if reply is not None:
                return reply
            failure = (ErrorCode.TIMEOUT, f"no reply in {1 + retries} attempts of {timeout_s} s")
        raise ServiceCallError(self.name, *failure)

    def _await_reply(self, deadline: float) -> R | list[Endpoint] | None:
        """The reply to request ``self.seq``; the servers that died meanwhile; None at the
        deadline. A ServiceError reply is raised."""
        while (remaining := deadline - time.monotonic()) > 0:
            if not self.sock.poll(min(remaining, LIVENESS_PERIOD_S) * 1000, zmq.POLLIN):
                self._check_cancelled()
                dead = self._forget_dead_servers()
                if dead:
                    return dead
                continue
            try:
                envelope = decode(self.sock.recv_multipart(copy=False), self.bus.transport.max_message_bytes)
            except MessageError as exc:
                log.warning("%s: malformed reply dropped (%s)", self.name, exc)
                continue
            if envelope.message.header.seq != self.seq:
                continue  # the late answer to an earlier attempt of an earlier call
            reply = envelope.message
            if isinstance(reply, ServiceError):
                raise ServiceCallError(self.name, reply.code, reply.text)
            if not isinstance(reply, self.reply_type):
                raise ServiceCallError(self.name, "wrong_type", f"reply is {reply.SCHEMA}")
            return reply
        return None

    def close(self) -> None:
        self.sock.close()
