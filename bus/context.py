"""What every socket of one process's bus is made with, and what every socket owner keeps.

A :class:`BusContext` holds the ZeroMQ context, the registry and the transport settings (ipc or
tcp, CURVE, fixed endpoints, peers on other machines), and binds and connects sockets by them.
:class:`bus.pubsub.Bus` adds the factories of publishers, subscribers, services and clients on
top of it; those (bus.pubsub, bus.services) are built on this part alone, so neither has to
import the other. Socket owners share :class:`Counters`, :class:`DropLog` (dropped-message
warnings at most once a second per socket) and ``SLICE_MESSAGES``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
import weakref
from typing import Any

import zmq
import zmq.auth

from bus.registry import Endpoint, Registry
from bus.security import CurveConfig, secure_client, secure_server, stop_authenticator
from msgs.codec import DEFAULT_MAX_MESSAGE_BYTES

log = logging.getLogger("dtx.bus")

# Every Bus not yet closed: a context left to the garbage collector can block it forever in
# zmq_term, so whoever owns a process's lifetime (a test run) closes what is left here.
OPEN_BUSES: "weakref.WeakSet[BusContext]" = weakref.WeakSet()
SLICE_MESSAGES = 100
DROP_LOG_PERIOD_S = 1.0
# Frames from this size up are sent without copying; smaller ones are copied, which costs less
# than handing ZeroMQ a reference it must release later (pyzmq's own threshold).
ZERO_COPY_BYTES = zmq.COPY_THRESHOLD
SNDMORE = int(zmq.SNDMORE)  # a plain int: flag arithmetic on the enum goes through the enum machinery


def send_frames(sock: zmq.Socket, frames: list[Any], flags: int = 0) -> None:
    """Send ``frames`` (buffers whose ``len`` is their byte count) as one multipart message.

    Written out instead of pyzmq's ``send_multipart``, which checks every frame's type in Python
    first: per 4-frame sensor message that loop measured 59k instructions against 18k here
    (callgrind), and the bus runs it on every message."""
    last = len(frames) - 1
    for i, frame in enumerate(frames):
        sock.send(frame, flags | SNDMORE if i < last else flags, copy=len(frame) < ZERO_COPY_BYTES)


def recv_frames(sock: zmq.Socket, flags: int = 0) -> list[zmq.Frame]:
    """The next multipart message as frames (views of ZeroMQ's memory, no copy); raises
    zmq.Again under NOBLOCK when none is waiting. Each frame says whether more follow, so no
    socket option is read per frame as pyzmq's ``recv_multipart`` does (62k -> 26k
    instructions per 4-frame message, callgrind)."""
    frame = sock.recv(flags, copy=False)
    frames = [frame]
    while frame.more:
        frame = sock.recv(copy=False)  # the rest of a message arrives with its first frame
        frames.append(frame)
    return frames


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
    connection_resets: int = 0  # links ZeroMQ closed over oversized or malformed data
    publishers_gone: int = 0  # links whose publisher went away unannounced (killed, or the link lost)
    handler_errors: int = 0
    bytes: int = 0


class BusContext:
    """The part of a Bus that its sockets use: the ZeroMQ context, the registry and the
    transport settings, by which it binds and connects them."""

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

    def peer_endpoints(self, kind: str, name: str, schema: str) -> list[Endpoint]:
        """The launch file's remote endpoint for ``name``, if it names one."""
        peer = self.transport.peers.get(name)
        if peer is None:
            return []
        server_key = ""
        if peer.server_key_file:
            server_key = zmq.auth.load_certificate(peer.server_key_file)[0].decode()
        return [Endpoint(kind, name, peer.address, "remote", os.getpid(), schema, curve_server_key=server_key)]

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        OPEN_BUSES.discard(self)
        stop_authenticator(self.context)
        self.context.destroy(linger=200)
