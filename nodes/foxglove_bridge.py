"""Foxglove bridge: shows a live session in Foxglove Studio through the foxglove-sdk
WebSocket server (connect Studio to ws://HOST:8765; docs/foxglove.md). Both subprotocols are accepted:
the SDK's ``foxglove.sdk.v1`` and, through :class:`SubprotocolAdapter`, ``foxglove.websocket.v1``.

Every topic whose messages have a Foxglove well-known form (depth and tactile images,
point clouds, transforms; see ``msgs.foxglove``) is served as the channel ``<topic>/foxglove``,
the name its bag channel has. A channel is advertised as soon as its topic is discovered, not
with its first message: a message on a channel nobody could yet subscribe to is lost, and a
subscription sent right after a late advertise can race it. A latched topic's last message of
each frame is sent again when a client subscribes, so a cloud published once still reaches a
viewer that connects later (as Foxglove's ROS bridge keeps a transient-local topic's latest
messages for new subscribers: foxglove/ros-foxglove-bridge issue #31).

At most ``max_rate_hz`` of each topic *and frame* is forwarded (:class:`FrameThrottle`), so a
browser never slows the session, yet messages that share a topic but not a frame — the two
fingers' samples, each transform of ``/tf`` — never thin each other out; a transform goes at
least once a second whatever ``max_rate_hz``. The heartbeat's counters say how many messages
were thinned, per topic (``thinned:<topic>``). Off by default; the collection launch files
switch it on with ``foxglove:=true``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import socket
import threading
import time
from typing import Any

import foxglove

import msgs
from bus.node import Node, run_node
from msgs.foxglove import FOXGLOVE_SUFFIX, foxglove_frames, foxglove_schema, foxglove_view

# What the rate limit tells apart: (dtx topic, frame id, child frame id).
ThrottleKey = tuple[str, str, str]

# Foxglove's 3D panel places a frame by its newest transform: each one is refreshed at least
# this often, however low max_rate_hz is set.
TRANSFORM_MAX_INTERVAL_S = 1.0


class FrameThrottle:
    """At most one message per interval of each (topic, frame id, child frame id), the newest
    held back rather than lost.

    Foxglove's ROS bridge throttles per topic *and* ``header.frame_id``
    (foxglove/ros-foxglove-bridge, ``topic_throttle_rates``, src/message_throttler.cpp, pull
    request #374), so streams that share a topic in other frames keep their own rate; a
    ``FrameTransform`` names a parent and a child, so each transform is a stream of its own.
    Where that bridge drops what comes too soon, this one holds the newest such message and
    sends it once its interval ends (:meth:`release_due`), replacing an older one it held: the
    foxglove-sdk server's own per-client queue, when full, likewise drops the oldest and keeps
    the newest (docs.rs foxglove, ``WebSocketServer::message_backlog_size``). So the last
    message of every frame — a sample, the gripper's final width — always reaches the viewer,
    and ``thinned`` counts, per topic, the messages a newer one of their frame replaced."""

    def __init__(self, max_rate_hz: float) -> None:
        if not max_rate_hz > 0:
            raise ValueError(f"max_rate_hz must be positive, got {max_rate_hz}")
        self.max_rate_hz = max_rate_hz
        self.interval_s: dict[str, float] = {}  # topic -> its interval
        self.next_send: dict[ThrottleKey, float] = {}  # monotonic time the key may send again
        self.held: dict[ThrottleKey, msgs.Message] = {}
        self.thinned: dict[str, int] = {}

    def limit(self, topic: str, schema: str) -> None:
        """Limits ``topic``, whose messages are of ``schema``."""
        interval_s = 1.0 / self.max_rate_hz
        if schema == msgs.FrameTransform.SCHEMA:
            interval_s = min(interval_s, TRANSFORM_MAX_INTERVAL_S)
        self.interval_s[topic] = interval_s
        self.thinned[topic] = 0

    def offer(self, topic: str, message: msgs.Message, now: float) -> bool:
        """Whether to send ``message`` now; if not, it is held for :meth:`release_due`."""
        key = (topic, *foxglove_frames(message))
        if key in self.held:
            # Whether it goes now or waits, the newer message supersedes the one held.
            del self.held[key]
            self.thinned[topic] += 1
        if now >= self.next_send.get(key, -math.inf):
            self.next_send[key] = now + self.interval_s[topic]
            return True
        self.held[key] = message
        return False

    def release_due(self, now: float) -> list[tuple[str, msgs.Message]]:
        """The held (topic, message) pairs whose interval has ended, taken from the hold."""
        due = [key for key in self.held if now >= self.next_send[key]]
        for key in due:
            self.next_send[key] = now + self.interval_s[key[0]]
        return [(key[0], self.held.pop(key)) for key in due]


class _Resender(foxglove.ServerListener):
    """Sends a latched channel's last message of each frame again when a client subscribes to
    it (the SDK has no per-client send, so its other subscribers see it twice; latched topics
    are rare)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        # channel topic -> (frame id, child frame id) -> (channel, last message, log time)
        self.last: dict[str, dict[tuple[str, str], tuple[foxglove.Channel, bytes, int]]] = {}

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self.lock:
            latest = list(self.last.get(channel.topic, {}).values())
        for sender, data, log_time in latest:
            sender.log(data, log_time=log_time)


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
        self.throttle = FrameThrottle(self.params.max_rate_hz)
        self.resender = _Resender()
        self.server = foxglove.start_server(name="dtx", host="127.0.0.1", port=0, server_listener=self.resender)
        self.adapter = SubprotocolAdapter(self.params.host, self.params.port, self.server.port)
        self.port = self.adapter.port
        self.channels: dict[str, foxglove.Channel] = {}  # dtx topic -> its Foxglove channel
        self.latched: set[str] = set()
        self.create_timer(1.0, self.discover_topics)
        # A held message goes out within half the shortest interval of its due time.
        self.create_timer(0.5 * min(1.0 / self.params.max_rate_hz, TRANSFORM_MAX_INTERVAL_S), self.release_held)
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
            self.throttle.limit(topic, endpoints[0].schema)
            self.create_subscription(
                topic,
                msgs.MESSAGE_TYPES[endpoints[0].schema],
                functools.partial(self.forward, topic),
            )

    def forward(self, topic: str, message: msgs.Message) -> None:
        if self.throttle.offer(topic, message, time.monotonic()):
            self.send(topic, message)

    def release_held(self) -> None:
        for topic, message in self.throttle.release_due(time.monotonic()):
            self.send(topic, message)

    def send(self, topic: str, message: msgs.Message) -> None:
        view = foxglove_view(message)
        if view is None:
            return
        data, log_time = view.encode(), message.header.stamp_ns or time.time_ns()
        channel = self.channels[topic]
        if topic in self.latched:
            with self.resender.lock:
                # Channel.topic is a method here (the listener's ChannelView has it as a field).
                self.resender.last.setdefault(channel.topic(), {})[foxglove_frames(message)] = (channel, data, log_time)
        channel.log(data, log_time=log_time)

    def counters(self) -> dict[str, int]:
        thinned = {f"thinned:{topic}": count for topic, count in self.throttle.thinned.items()}
        return {**super().counters(), **thinned}

    def close(self) -> None:
        for topic, message in self.throttle.release_due(math.inf):  # each frame's last message goes too
            self.send(topic, message)
        self.adapter.close()
        self.server.stop()
        super().close()


if __name__ == "__main__":
    run_node(FoxgloveBridge)
