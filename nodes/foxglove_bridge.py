"""Foxglove bridge: shows a live session in Foxglove Studio through the foxglove-sdk
WebSocket server (connect Studio to ws://HOST:8765; docs/foxglove.md). Both subprotocols are accepted:
the SDK's ``foxglove.sdk.v1`` and, through :class:`SubprotocolAdapter`, ``foxglove.websocket.v1``.

Every topic whose messages have a Foxglove well-known form (depth and tactile images,
point clouds, transforms; see ``msgs.foxglove``) is served as the channel ``<topic>/foxglove``,
the name its bag channel has. A channel is advertised as soon as its topic is discovered, not
with its first message: a message on a channel nobody could yet subscribe to is lost, and a
subscription sent right after a late advertise can race it. A latched topic's last message is
sent again when a client subscribes, so a cloud published once still reaches a viewer that
connects later. At most ``max_rate_hz`` per topic is forwarded, so a browser never slows the
session. Off by default; the collection launch files switch it on with ``foxglove:=true``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
import socket
import threading
import time
from typing import Any

import foxglove

import msgs
from msgs.foxglove import FOXGLOVE_SUFFIX, foxglove_schema, foxglove_view
from nodes.node import Node, run_node


class _Resender(foxglove.ServerListener):
    """Sends a latched channel's last message again when a client subscribes to it (the SDK
    has no per-client send, so its other subscribers see it twice; latched topics are rare)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.last: dict[str, tuple[foxglove.Channel, bytes, int]] = {}  # channel topic -> last message

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self.lock:
            latest = self.last.get(channel.topic)
        if latest is not None:
            latest[0].log(latest[1], log_time=latest[2])


SDK_SUBPROTOCOL = b"foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = b"foxglove.websocket.v1"
_MAX_HANDSHAKE_BYTES = 16 * 1024
# A viewer sends only control messages (the bridge offers no client publishing): a longer
# client frame ends its connection rather than being buffered.
_MAX_CLIENT_FRAME_BYTES = 1024 * 1024


class SubprotocolAdapter:
    """The public port: relays every connection to the SDK's server, and lets a client that
    offers only ``foxglove.websocket.v1`` (Foxglove Studio 1.x, Lichtblick before late 2025,
    @foxglove/ws-protocol's default) in. foxglove-sdk 0.30 speaks the same messages under the
    name ``foxglove.sdk.v1`` but answers the old name with HTTP 400, so the adapter renames the
    subprotocol in the opening handshake, both ways, and relays the bytes after it untouched —
    except that a client's ``subscribe`` is held ``SUBSCRIBE_DELAY_S``: the SDK queues a
    channel's advertisement to the client before it adds the channel to that client's map
    (rust/foxglove/src/websocket/connected_client.rs, ``advertise_channels``), so a client that
    subscribes the moment it is advertised can be told "Unknown channel ID" (1 in 100 such
    subscriptions on a loaded machine, tests/test_third_party_clients.py)."""

    SUBSCRIBE_DELAY_S = 0.05

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.listener = socket.create_server((host, port))
        self.port = self.listener.getsockname()[1]
        self._closed = False
        threading.Thread(target=self._accept, daemon=True, name="foxglove-adapter").start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return  # closed
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        with client, socket.create_connection(self.upstream) as server:
            request, rest = _read_handshake(client)
            offered = re.search(rb"(?im)^sec-websocket-protocol:(.*)$", request)
            legacy = (
                offered is not None
                and SDK_SUBPROTOCOL not in offered.group(1)
                and LEGACY_SUBPROTOCOL in offered.group(1)
            )
            if legacy:
                request = request.replace(LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL)
            server.sendall(request)
            response, from_server = _read_handshake(server)
            client.sendall(
                (response.replace(SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL) if legacy else response) + from_server
            )
            threading.Thread(target=_pipe, args=(server, client), daemon=True).start()
            self._relay_client_frames(client, server, rest)

    def _relay_client_frames(self, client: socket.socket, server: socket.socket, pending: bytes) -> None:
        """Client to server, frame by frame (RFC 6455 section 5.2), a subscribe held back."""
        buffer = bytearray(pending)
        try:
            while True:
                frame = _split_frame(buffer)
                while frame is None:
                    chunk = client.recv(65536)
                    if not chunk:
                        return
                    buffer += chunk
                    frame = _split_frame(buffer)
                if _is_subscribe(frame):
                    time.sleep(self.SUBSCRIBE_DELAY_S)
                server.sendall(frame)
        except OSError:
            pass
        finally:
            _shutdown(client, server)

    def close(self) -> None:
        self._closed = True
        self.listener.close()


def _read_handshake(sock: socket.socket) -> tuple[bytes, bytes]:
    """The HTTP head (up to its blank line) and whatever came after it."""
    data = b""
    while b"\r\n\r\n" not in data and len(data) < _MAX_HANDSHAKE_BYTES:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    return head + b"\r\n\r\n", rest


def _split_frame(buffer: bytearray) -> bytes | None:
    """Takes the first whole WebSocket frame off ``buffer`` (None: not all of it is there);
    OSError for a frame longer than a viewer sends."""
    if len(buffer) < 2:
        return None
    length, start = buffer[1] & 0x7F, 2
    if length >= 126:
        start = 4 if length == 126 else 10
        if len(buffer) < start:
            return None
        length = int.from_bytes(buffer[2:start], "big")
    if length > _MAX_CLIENT_FRAME_BYTES:
        raise OSError(f"a client frame of {length} bytes (at most {_MAX_CLIENT_FRAME_BYTES})")
    end = start + (4 if buffer[1] & 0x80 else 0) + length
    if len(buffer) < end:
        return None
    frame = bytes(buffer[:end])
    del buffer[:end]
    return frame


def _is_subscribe(frame: bytes) -> bool:
    """Whether a client frame is a text frame holding the JSON op ``subscribe``."""
    if frame[0] & 0x0F != 1 or not frame[1] & 0x80:  # text, masked (every client frame is)
        return False
    length, start = frame[1] & 0x7F, 2
    if length >= 126:
        start = 4 if length == 126 else 10
    mask, payload = frame[start : start + 4], frame[start + 4 :]
    try:
        message = json.loads(bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))
    except ValueError:
        return False
    return isinstance(message, dict) and message.get("op") == "subscribe"


def _pipe(source: socket.socket, sink: socket.socket) -> None:
    try:
        while chunk := source.recv(65536):
            sink.sendall(chunk)
    except OSError:
        pass
    finally:
        _shutdown(source, sink)


def _shutdown(*sockets: socket.socket) -> None:
    for sock in sockets:
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class FoxgloveBridge(Node):
    @dataclasses.dataclass
    class Params:
        host: str = "127.0.0.1"
        port: int = 8765
        max_rate_hz: float = 10.0

    def __init__(self, name: str, params: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(name, params, **kwargs)
        self.resender = _Resender()
        self.server = foxglove.start_server(name="dtx", host="127.0.0.1", port=0, server_listener=self.resender)
        self.adapter = SubprotocolAdapter(self.params.host, self.params.port, self.server.port)
        self.port = self.adapter.port
        self.channels: dict[str, foxglove.Channel] = {}  # dtx topic -> its Foxglove channel
        self.latched: set[str] = set()
        self.last_sent: dict[str, float] = {}
        self.create_timer(1.0, self.discover_topics)
        self.discover_topics()
        self.log.info("Foxglove Studio: connect to ws://%s:%d", self.params.host, self.port)

    def discover_topics(self) -> None:
        for topic, endpoints in self.bus.registry.names("topic").items():
            schema = foxglove_schema(endpoints[0].schema)
            if topic in self.channels or schema is None:
                continue
            self.channels[topic] = foxglove.Channel(topic + FOXGLOVE_SUFFIX, schema=schema, message_encoding="protobuf")
            if any(e.latched for e in endpoints):
                self.latched.add(topic)
            self.last_sent[topic] = -float("inf")
            self.create_subscription(
                topic,
                msgs.MESSAGE_TYPES[endpoints[0].schema],
                functools.partial(self.forward, topic),
            )

    def forward(self, topic: str, message: msgs.Message) -> None:
        now = time.monotonic()
        if now - self.last_sent[topic] < 1.0 / self.params.max_rate_hz:
            return
        self.last_sent[topic] = now
        view = foxglove_view(message)
        if view is None:
            return
        data, log_time = view.encode(), message.header.stamp_ns or time.time_ns()
        channel = self.channels[topic]
        if topic in self.latched:
            with self.resender.lock:
                # Channel.topic is a method here (the listener's ChannelView has it as a field).
                self.resender.last[channel.topic()] = (channel, data, log_time)
        channel.log(data, log_time=log_time)

    def close(self) -> None:
        self.adapter.close()
        self.server.stop()
        super().close()


if __name__ == "__main__":
    run_node(FoxgloveBridge)
