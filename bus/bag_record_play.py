"""Record the bus into an MCAP bag (bus.bag), and replay a bag onto the bus.

Recording goes in rounds, fair to every topic: a round takes everything waiting on each topic's
socket (at most ``round_limit`` messages, by default the bus's high-water mark, what a socket
holds), then writes all of it, the topics merged oldest header stamp first, before the next round
takes more. However busy a topic, none of its messages waits past the round after the one it
arrived in, so no topic falls behind another by more than a round (a fixed share per socket and
turn, 100 messages, let the busiest topic, ``/tf``, fall seconds behind whenever rounds were
slow). :class:`RecordStats` says per topic how far behind the recorder is. Playing keeps the
recorded timing scaled by a rate and can publish the bag's time on ``/clock``.
"""

from __future__ import annotations

import dataclasses
import heapq
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zmq

import msgs
from bus.bag import BagWriter, bag_channels, iter_envelopes
from bus.bag_format import MESSAGE_ENCODING, BagError
from bus.pubsub import Bus, Publisher, Subscriber
from msgs.codec import Envelope

# The longest the recorder writes without serving its node (heartbeat, services, a stop).
SERVE_PERIOD_S = 0.05
SCAN_PERIOD_S = 0.5  # how often new topics and publishers are looked for
IDLE_WAIT_MS = 50  # with nothing waiting, how long to wait for a message before serving again

Taken = tuple[list[zmq.Frame], Envelope]  # a received message: its frames (written as they are) and itself


@dataclasses.dataclass
class TopicProgress:
    """How far behind the recorder is on one topic."""

    written: int = 0
    backlog: int = 0  # received and not yet written
    peak_backlog: int = 0  # the largest backlog since the last report
    peak_lag_ns: int = 0  # the largest lag of a message written since the last report


class RecordStats:
    """What ``record`` says while it runs, per topic: messages written, the backlog (received and
    not yet written) and the lag (write time minus the message's header stamp). Messages ZeroMQ
    still holds for the recorder cannot be counted (it does not tell a queue's length); the next
    round takes them, up to its limit."""

    def __init__(self) -> None:
        self.topics: dict[str, TopicProgress] = {}

    def received(self, topic: str, count: int) -> None:
        progress = self.topics.setdefault(topic, TopicProgress())
        progress.backlog += count
        progress.peak_backlog = max(progress.peak_backlog, progress.backlog)

    def wrote(self, topic: str, lag_ns: int) -> None:
        progress = self.topics[topic]
        progress.written += 1
        progress.backlog -= 1
        progress.peak_lag_ns = max(progress.peak_lag_ns, lag_ns)

    def report(self) -> dict[str, int]:
        """``backlog:<topic>`` and ``lag_ms:<topic>``: the largest since the previous report (a
        node's heartbeat counters, once a beat); the next report's start from now."""
        counters = {}
        for topic, progress in self.topics.items():
            counters[f"backlog:{topic}"] = progress.peak_backlog
            counters[f"lag_ms:{topic}"] = progress.peak_lag_ns // 1_000_000
            progress.peak_backlog, progress.peak_lag_ns = progress.backlog, 0
        return counters


def record(
    path: str | Path,
    bus: Bus,
    stop: Callable[[], bool],
    topics: list[str] | None = None,
    compression: str = "lz4",
    foxglove: bool = True,
    on_subscriber: Callable[[Subscriber[Any]], None] | None = None,
    stats: RecordStats | None = None,
    round_limit: int | None = None,
    on_round: Callable[[dict[str, int]], None] | None = None,
) -> dict[str, int]:
    """Record ``topics`` (all topics, also ones that appear later, when None) until ``stop()``,
    which is called between rounds and at least every ``SERVE_PERIOD_S`` while one is written.
    Returns messages written per topic; the bag is closed properly when this returns. When the
    disk refuses the data, BagWriteError: recording stops, the bag keeps what it had.
    ``on_subscriber`` is told of each subscriber made (a node counts its drops), ``stats`` kept
    up to date (a node's heartbeat reports it), ``on_round`` told what each round wrote per topic."""
    writer = BagWriter(path, compression, foxglove)
    stats = stats if stats is not None else RecordStats()
    limit = round_limit or bus.transport.high_water_mark
    subscribers: list[Subscriber[Any]] = []
    poller = zmq.Poller()
    next_scan = 0.0
    stopping = False

    def serve() -> bool:
        nonlocal next_scan, stopping
        if time.monotonic() >= next_scan:
            next_scan = time.monotonic() + SCAN_PERIOD_S
            for subscriber in _subscribe_new(bus, topics, subscribers, on_subscriber):
                poller.register(subscriber.sock, zmq.POLLIN)
        stopping = stop() or stopping
        return stopping

    try:
        while not serve():
            batch = _take(subscribers, limit, stats)
            if batch:
                _write_round(batch, writer, stats, serve, on_round)
            else:
                poller.poll(IDLE_WAIT_MS)
                writer.flush_if_due()
        if batch := _take(subscribers, limit, stats):  # what arrived before the stop is kept
            _write_round(batch, writer, stats, serve, on_round)
    finally:
        for subscriber in subscribers:
            subscriber.close()
        writer.close()  # after a BagWriteError, a no-op: the file is already closed as it stood
    return dict(writer.counts)


def _subscribe_new(
    bus: Bus,
    topics: list[str] | None,
    subscribers: list[Subscriber[Any]],
    on_subscriber: Callable[[Subscriber[Any]], None] | None,
) -> list[Subscriber[Any]]:
    """Subscribe to the topics not yet recorded (added to ``subscribers``, and returned), and let
    every subscriber look for new publishers."""
    known = {subscriber.topic for subscriber in subscribers}
    made: list[Subscriber[Any]] = [
        bus.subscriber(t, None) for t in topics or bus.registry.names("topic") if t not in known
    ]
    for subscriber in made:
        subscribers.append(subscriber)
        if on_subscriber is not None:
            on_subscriber(subscriber)
    for subscriber in subscribers:
        subscriber.discover()
    return made


def _take(subscribers: list[Subscriber[Any]], limit: int, stats: RecordStats) -> list[list[Taken]]:
    """What waits on each subscriber, ``limit`` messages at most from each: a list per topic,
    in the order received."""
    batch = []
    for subscriber in subscribers:
        taken: list[Taken] = subscriber.receive_ready_frames(limit)
        if taken:
            stats.received(subscriber.topic, len(taken))
            batch.append(taken)
    return batch


def _write_round(
    batch: list[list[Taken]],
    writer: BagWriter,
    stats: RecordStats,
    serve: Callable[[], bool],
    on_round: Callable[[dict[str, int]], None] | None,
) -> None:
    """Write a round's messages, the topics merged oldest header stamp first (each keeps its own
    order, so a topic whose stamps are not in order, as /tf's, still comes out as received);
    ``serve`` is called at least every ``SERVE_PERIOD_S``."""
    written: dict[str, int] = {}
    next_serve = time.monotonic() + SERVE_PERIOD_S
    for frames, envelope in heapq.merge(*batch, key=lambda taken: taken[1].message.header.stamp_ns):
        log_time_ns = time.time_ns()
        writer.write(envelope, frames, log_time_ns)
        stats.wrote(envelope.topic, log_time_ns - envelope.message.header.stamp_ns)
        written[envelope.topic] = written.get(envelope.topic, 0) + 1
        if time.monotonic() >= next_serve:
            serve()
            next_serve = time.monotonic() + SERVE_PERIOD_S
    if on_round is not None:
        on_round(written)


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
