"""Record the bus into an MCAP bag (nodes.bag), and replay a bag onto the bus.

Recording takes a slice from each ready topic in turn, so one busy topic does not starve the
others; playing keeps the recorded timing scaled by a rate and can publish the bag's time on
``/clock``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zmq

import msgs
from nodes.bag import BagWriter, bag_channels, iter_envelopes
from nodes.bag_format import MESSAGE_ENCODING, BagError
from nodes.bus import Bus, Publisher, Subscriber
from nodes.bus_context import SLICE_MESSAGES, recv_frames


def record(
    path: str | Path,
    bus: Bus,
    stop: Callable[[], bool],
    topics: list[str] | None = None,
    compression: str = "lz4",
    foxglove: bool = True,
    on_message: Callable[[str], None] | None = None,
    on_subscriber: Callable[[Subscriber[Any]], None] | None = None,
) -> dict[str, int]:
    """Record ``topics`` (all topics, also ones that appear later, when None) until ``stop()``.
    Returns messages written per topic; the bag is closed properly when this returns. When the
    disk refuses the data, BagWriteError: recording stops, the bag keeps what it had.
    ``on_subscriber`` is told of each subscriber made (a node counts its drops)."""
    writer = BagWriter(path, compression, foxglove)
    subscribers: dict[zmq.Socket, Subscriber[Any]] = {}
    poller = zmq.Poller()
    next_scan = 0.0
    try:
        while not stop():
            if time.monotonic() >= next_scan:
                next_scan = time.monotonic() + 0.5
                for topic in topics or list(bus.registry.names("topic")):
                    if topic not in {s.topic for s in subscribers.values()}:
                        subscriber: Subscriber[Any] = bus.subscriber(topic, None)
                        subscribers[subscriber.sock] = subscriber
                        poller.register(subscriber.sock, zmq.POLLIN)
                        if on_subscriber is not None:
                            on_subscriber(subscriber)
                for subscriber in subscribers.values():
                    subscriber.discover()
            for sock, _ in poller.poll(50):  # a slice from each ready topic, then the others
                _drain(subscribers[sock], writer, on_message, SLICE_MESSAGES)
            writer.flush_if_due()
        for subscriber in subscribers.values():  # what arrived before the stop is kept
            _drain(subscriber, writer, on_message, None)
    finally:
        for subscriber in subscribers.values():
            subscriber.close()
        writer.close()  # after a BagWriteError, a no-op: the file is already closed as it stood
    return dict(writer.counts)


def _drain(
    subscriber: Subscriber[Any], writer: BagWriter, on_message: Callable[[str], None] | None, limit: int | None
) -> None:
    """Write what is waiting on one subscriber: ``limit`` messages at most (None: all)."""
    count = 0
    while limit is None or count < limit:
        count += 1
        try:
            frames = recv_frames(subscriber.sock, zmq.NOBLOCK)
        except zmq.Again:
            return
        envelope = subscriber.handle(frames)
        if envelope is not None:
            writer.write(envelope, frames)
            if on_message is not None:
                on_message(envelope.topic)


def play(
    path: str | Path,
    bus: Bus,
    rate: float | None = 1.0,
    clock: bool = False,
    topics: list[str] | None = None,
    wait_for_subscribers_s: float = 0.0,
    stop: Callable[[], bool] = lambda: False,
) -> dict[str, int]:
    """Publish a bag's dtx messages with their recorded timing scaled by ``rate`` (None: as
    fast as possible). With ``clock``, ``/clock`` carries the bag's time, like ROS's /clock.
    Returns messages published per topic."""
    if rate is not None and not rate > 0:
        raise BagError(f"rate must be positive (or None for as fast as possible), got {rate}")
    publishers: dict[str, Publisher[Any]] = {}
    for topic, (schema, encoding) in bag_channels(path).items():
        if encoding == MESSAGE_ENCODING and (topics is None or topic in topics):
            if schema not in msgs.MESSAGE_TYPES:
                raise BagError(f"{path}: topic {topic} holds {schema!r}, unknown to this build")
            publishers[topic] = bus.publisher(topic, msgs.MESSAGE_TYPES[schema])
    clock_publisher = bus.publisher("/clock", msgs.Clock) if clock else None
    deadline = time.monotonic() + wait_for_subscribers_s
    # Slow joiners: let subscribers connect first, /clock's too (a clock that starts late
    # would leave a listener without the bag's time for the messages it already got).
    for publisher in [*publishers.values(), *([clock_publisher] if clock_publisher else [])]:
        publisher.wait_for_subscribers(1, max(0.0, deadline - time.monotonic()))
    counts: dict[str, int] = {}
    start_wall = time.monotonic()
    start_bag: int | None = None
    try:
        for log_time_ns, envelope in iter_envelopes(path):
            if stop():
                break
            if envelope.topic not in publishers:
                continue
            if start_bag is None:
                start_bag = log_time_ns
            if rate is not None:
                due = start_wall + (log_time_ns - start_bag) / 1e9 / rate
                while (delay := due - time.monotonic()) > 0:
                    time.sleep(min(delay, 0.05))
                    if stop():
                        return counts
            if clock_publisher is not None:
                clock_publisher.publish(msgs.Clock(sim_time_ns=log_time_ns))
            publishers[envelope.topic].publish(envelope.message)
            counts[envelope.topic] = counts.get(envelope.topic, 0) + 1
    finally:
        for publisher in publishers.values():
            publisher.close()
        if clock_publisher is not None:
            clock_publisher.close()
    return counts
