"""The recorder is fair to every topic and says how far behind it is (issue 55).

One topic floods (300 messages for each one of another), as ``/tf`` outnumbers the rest of a
session. The recorder and the publishers share one thread and talk over ``inproc://``, where a
message sent is at once in the receiver's queue, so what each round takes is known exactly and
every check is about counts and order, never about time."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import msgs
from bus.bag import bag_info, iter_envelopes
from bus.bag_record_play import RecordStats, record
from bus.context import PeerConfig, TransportConfig
from bus.pubsub import Bus, Publisher
from bus.registry import Registry
from dtx.cli import main
from nodes.recorder import RecorderNode

# Per tick: how many messages each topic gets (the flood's published first, the trickle's last).
TICK = {"/tf": 300, "/arm/state": 10, "/gripper/state": 1}
TICKS = 20


@pytest.fixture
def inproc_bus(registry: Registry) -> Iterator[Bus]:
    """One bus whose topics are bound and reached in-process (the same ZeroMQ context)."""
    endpoints = {topic: f"inproc://{topic}" for topic in TICK}
    transport = TransportConfig(endpoints=endpoints, peers={t: PeerConfig(a) for t, a in endpoints.items()})
    with contextlib.closing(Bus("fairness", registry, transport)) as bus:
        yield bus


def record_ticks(bus: Bus, path: Path, round_limit: int | None) -> tuple[list[dict[str, int]], RecordStats]:
    """Record while each tick is published once the last is written; the rounds' counts, the stats."""
    publishers: dict[str, Publisher[msgs.Log]] = {topic: bus.publisher(topic, msgs.Log) for topic in TICK}
    rounds: list[dict[str, int]] = []
    stats = RecordStats()
    published = 0

    def stop() -> bool:
        nonlocal published
        written = sum(progress.written for progress in stats.topics.values())
        if written < published:
            return False  # called inside a round: its tick is not all written yet
        if published == 0:
            assert all(p.wait_for_subscribers(1, 30.0) for p in publishers.values()), "the recorder never joined"
        elif published == TICKS * sum(TICK.values()):
            return True
        for topic, count in TICK.items():
            for _ in range(count):
                publishers[topic].publish(msgs.Log(text=topic))
        published += sum(TICK.values())
        return False

    record(path, bus, stop, topics=list(TICK), stats=stats, round_limit=round_limit, on_round=rounds.append)
    for publisher in publishers.values():
        publisher.close()
    return rounds, stats


def test_every_round_writes_every_topic_in_full_in_publish_order(inproc_bus: Bus, tmp_path: Path) -> None:
    path = tmp_path / "fair.mcap"
    rounds, stats = record_ticks(inproc_bus, path, round_limit=None)
    # Each round took all each topic had, the flood's 300 too: no topic left for a later round.
    assert rounds == [TICK] * TICKS
    # Written in the order published across topics: none behind another, the flood included.
    stamps = [envelope.message.header.stamp_ns for _, envelope in iter_envelopes(path)]
    assert len(stamps) == TICKS * sum(TICK.values()) and stamps == sorted(stamps)
    counters = stats.report()
    assert {topic: counters[f"backlog:{topic}"] for topic in TICK} == TICK  # a round's take, at its largest
    assert all(counters[f"lag_ms:{topic}"] >= 0 for topic in TICK)
    assert all(progress.backlog == 0 for progress in stats.topics.values())
    assert stats.report()["backlog:/tf"] == 0  # the next report starts afresh
    # The bag says the same: when the first of a tick's 300 was written, 299 more were published.
    topics = bag_info(path).topics
    assert {topic: topics[topic]["backlog_max"] for topic in TICK} == {t: n - 1 for t, n in TICK.items()}
    lag = topics["/tf"]["lag_ms"]
    assert 0 <= lag["p50"] <= lag["p99"] <= lag["max"]


def test_a_round_bounds_each_topics_share_and_the_flood_starves_no_one(inproc_bus: Bus, tmp_path: Path) -> None:
    path = tmp_path / "bounded.mcap"
    rounds, stats = record_ticks(inproc_bus, path, round_limit=100)
    # The flood's 300 take three rounds; the other topics are written in the first of them.
    assert rounds == [TICK | {"/tf": 100}, {"/tf": 100}, {"/tf": 100}] * TICKS
    # The recorder counts what it took; what ZeroMQ still holds, only the bag's stamps show.
    assert stats.report()["backlog:/tf"] == 100
    assert bag_info(path).topics["/tf"]["backlog_max"] == 299


def test_bag_info_prints_each_topics_lag_and_backlog(
    inproc_bus: Bus, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "info.mcap"
    record_ticks(inproc_bus, path, round_limit=None)
    assert main(["bag", "info", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    tf = next(i for i, line in enumerate(lines) if line.strip().startswith("/tf "))
    assert "lag p50" in lines[tf + 1] and "backlog at most 299" in lines[tf + 1]


def test_the_recorders_heartbeat_says_how_far_behind_it_is_per_topic(registry: Registry, tmp_path: Path) -> None:
    node = RecorderNode("recorder", {"bag": str(tmp_path / "node.mcap"), "topics": ["/tf"]}, registry=registry)
    with contextlib.closing(Bus("talker", registry)) as bus:
        publisher = bus.publisher("/tf", msgs.FrameTransform)
        spinner = threading.Thread(target=node.spin)
        spinner.start()
        try:
            assert publisher.wait_for_subscribers(1, 30.0), "the recorder never joined"
            counters: dict[str, int] = {}
            deadline = time.monotonic() + 30
            while "lag_ms:/tf" not in counters and time.monotonic() < deadline:
                publisher.publish(msgs.FrameTransform(child_frame_id="tcp"))
                time.sleep(0.05)
                status = next((s for s in registry.node_statuses() if s["node"] == "recorder"), {})
                counters = status.get("counters", {})
        finally:
            node.request_shutdown()
            spinner.join()
            node.close()
    assert counters["backlog:/tf"] >= 1 and counters["lag_ms:/tf"] >= 0, counters
    assert counters["received"] >= 1 and "publishers_gone" in counters, counters
