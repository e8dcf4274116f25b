"""Services over ZeroMQ: ROUTER servers, DEALER clients, found through the registry.

A call has a time-out and retries, repeated requests are answered from a reply cache (a retry
never runs a handler twice), and a bad request gets a ``ServiceError`` reply while the server
keeps serving. A handler may return a ``concurrent.futures.Future`` (a motion running in the
background): the reply goes out when it completes, and the server keeps serving meanwhile.
"""

from __future__ import annotations

import collections
import hashlib
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Generic, TypeVar

import msgpack
import zmq

from bus.context import SLICE_MESSAGES, BusContext, Counters, DropLog, recv_frames, send_frames
from bus.registry import Endpoint
from msgs.base import Header, Message
from msgs.codec import MAX_HEADER_BYTES, Envelope, MessageError, decode, encode
from msgs.system import ErrorCode, ServiceError

log = logging.getLogger("dtx.bus")
M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

# How often a waiting client looks whether its server still lives (docs/wire-protocol.md §4).
LIVENESS_PERIOD_S = 0.25


class ServiceCallError(RuntimeError):
    """The service answered with an error, or did not answer in time."""

    def __init__(self, service: str, code: str, text: str) -> None:
        super().__init__(f"service {service}: {code}: {text}")
        self.service, self.code, self.text = service, code, text


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
        self,
        bus: BusContext,
        name: str,
        request_type: type[M],
        reply_type: type[R],
        handler: Callable[[M], R | Future[R]],
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
                frames = recv_frames(self.sock, zmq.NOBLOCK)
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
            self._refuse_malformed(identity, frames, exc)
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
            self._refuse_reused_sequence(identity, envelope)
            return
        if key in self._replies:
            self.counters.duplicates += 1
            send_frames(self.sock, [identity, *self._replies[key][0]])
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

    def _refuse_malformed(self, identity: bytes, frames: list[Any], exc: MessageError) -> None:
        """Answer a request that does not decode with a bad-request error (counted, logged)."""
        self.counters.malformed += 1
        self._drop_log.warning("%s: malformed request (%s)", self.name, exc)
        # The reply carries the request's (p, q) whenever they can be read, so a client
        # waiting for that q gets its answer instead of a time-out.
        client, seq = request_id(frames[1:])
        self._send(identity, ServiceError(code=ErrorCode.BAD_REQUEST, text=str(exc)), client, seq)

    def _refuse_reused_sequence(self, identity: bytes, envelope: Envelope) -> None:
        """Answer a request whose (publisher, seq) an earlier, different request already used."""
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

    def _send(self, identity: bytes, reply: Message, client: str, seq: int) -> list[Any]:
        frames = encode(
            self.name, reply, client, Header(stamp_ns=time.time_ns(), seq=seq, frame_id=reply.header.frame_id)
        )
        send_frames(self.sock, [identity, *frames])
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
        bus: BusContext,
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
                send_frames(self.sock, frames, zmq.NOBLOCK)
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
            if not self.sock.poll(min(remaining, LIVENESS_PERIOD_S) * 1000, zmq.POLLIN):  # type: ignore[arg-type]  # pyzmq polls float ms; its stub says int
                self._check_cancelled()
                dead = self._forget_dead_servers()
                if dead:
                    return dead
                continue
            try:
                envelope = decode(recv_frames(self.sock), self.bus.transport.max_message_bytes)
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
