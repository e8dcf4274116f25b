"""``dtx bench fuzz``: malformed messages at every endpoint of a live collection session.

Runs ``launch/collect_sim.yaml`` (recording, so the recorder listens to every topic) as an
operator would; once grasps are being written, sends ``--messages`` mutated messages to each
service (a DEALER on its socket, as a client) and to each topic's subscribers (a publisher of
that topic that the subscribers find on the bus and connect to): damaged copies of a valid
message of that endpoint's schema, fields replaced with values of the wrong type or range,
arrays re-announced as zero-size with huge dimensions, bytes flipped, frames dropped. Only
mutants that the codec refuses are sent: a forged message that still decodes would be a real
request (a move of the arm) or a real sample, not a fault.

Figures: per endpoint the messages sent and, for services, the error replies (a server
answers every request it can address, docs/wire-protocol.md); the nodes whose process changed
while the fuzzing ran (a crash, then a respawn: the target is none) and the launcher's respawns;
and how the session ended, its services having served the collector throughout (exit code,
pairs, ``dtx dataset check``). Issue 16's target: 0 crashes from 10,000 mutated messages per
endpoint.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zmq

from benchmarks.collect import launch_collection
from bus.pubsub import Bus
from bus.registry import Endpoint, Registry
from dataset.check import check_dataset
from msgs import MESSAGE_TYPES
from msgs.codec import MessageError, decode, encode


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--messages", type=int, default=10_000, help="mutated messages per endpoint")
    parser.add_argument("--grasps", type=int, default=600, help="session size (long enough to fuzz every endpoint)")
    parser.add_argument("--seed", type=int, default=0)


def mutants(good: list[bytes], count: int, seed: int) -> list[list[bytes]]:
    """``count`` damaged copies of the frames ``good``: fields replaced, arrays re-announced
    with zero-size huge shapes, bytes flipped, frames dropped (what a buggy or hostile peer
    sends); the first is the message that once killed every node."""
    rng = np.random.default_rng(seed)
    header = msgpack.unpackb(good[1])
    odd_values: list[Any] = [None, -1, 2**63 - 1, 2**64 - 1, 1.5, "x", [], {}, True, b"\xff"]
    found = [[good[0], msgpack.packb({**header, "s": "dtx.system.Empty", "a": [["<f4", [2**63 - 1, 0]]]}), b""]]
    while len(found) < count:
        kind = rng.integers(4)
        forged = dict(header)
        if kind == 0:
            forged[str(rng.choice(sorted(header)))] = odd_values[rng.integers(len(odd_values))]
            found.append([good[0], msgpack.packb(forged), *good[2:]])
        elif kind == 1:
            forged["a"] = [[str(rng.choice(["<f4", "<u8", "|u1"])), [2 ** int(rng.integers(20, 64)) - 1, 0]]]
            found.append([good[0], msgpack.packb(forged), b""])
        elif kind == 2:
            damaged = bytearray(good[1])
            damaged[rng.integers(len(damaged))] ^= int(rng.integers(1, 256))
            found.append([good[0], bytes(damaged), *good[2:]])
        else:
            found.append(good[: rng.integers(1, len(good))])
    return found


def refused_mutants(name: str, schema: str, count: int, seed: int) -> list[list[bytes]]:
    """``count`` mutants of a default message of ``schema`` on ``name`` that the codec refuses."""
    good = [bytes(memoryview(f)) for f in encode(name, MESSAGE_TYPES[schema](), "fuzzer")]
    chosen: list[list[bytes]] = []
    batch = 0
    while len(chosen) < count:
        for frames in mutants(good, count, seed + batch):
            try:
                decode(frames)
            except MessageError:
                chosen.append(frames)
        batch += 1
    return chosen[:count]


def _fuzz_service(context: zmq.Context, address: str, frames_list: list[list[bytes]]) -> int:
    """Send every mutant on one DEALER; the error replies counted (read as they come)."""
    sock = context.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(address)
    replies = 0
    for frames in frames_list:
        sock.send_multipart(frames)
        while sock.poll(0):
            sock.recv_multipart()
            replies += 1
    while sock.poll(2000):  # the replies to the last ones
        sock.recv_multipart()
        replies += 1
    sock.close()
    return replies


def _fuzz_topic(bus: Bus, topic: str, schema: str, frames_list: list[list[bytes]]) -> int:
    """Publish every mutant on ``topic`` once its subscribers have connected (in slices, so
    that none is lost to a subscriber's queue); how many subscribers there were."""
    publisher = bus.publisher(topic, MESSAGE_TYPES[schema])
    if publisher.wait_for_subscribers(1, timeout_s=5.0):
        publisher.wait_for_subscribers(99, timeout_s=0.5)  # the topic's other subscribers find it too
    for start in range(0, len(frames_list), 500):
        for frames in frames_list[start : start + 500]:
            publisher.sock.send_multipart(frames)
        time.sleep(0.05)
    publisher.service_subscriptions()
    subscribers = publisher.subscriptions
    publisher.close()
    return subscribers


def _live(registry: Registry) -> dict[str, int]:
    return {s["node"]: int(s["pid"]) for s in registry.node_statuses() if s["alive"]}


def run(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="dtxf") as bus_dir, tempfile.TemporaryDirectory() as work:
        out = Path(work) / "session"
        launcher = launch_collection(out, args.grasps, args.seed, True, bus_dir)
        registry = Registry(Path(bus_dir))
        _wait_until_writing(launcher, out / "manifest.jsonl")
        before = _live(registry)
        services = {name: endpoints[0] for name, endpoints in registry.names("service").items()}
        topics = {name: endpoints[0] for name, endpoints in registry.names("topic").items()}
        context = zmq.Context()
        bus = Bus("fuzzer", registry)
        started = time.monotonic()
        try:
            rows = _fuzz_services(context, services, args.messages, args.seed)
            rows += _fuzz_topics(bus, topics, args.messages, args.seed)
            fuzz_s = time.monotonic() - started
            after = _live(registry)
            session_running = launcher.poll() is None
        finally:
            bus.close()
            context.destroy(linger=0)
        output, _ = launcher.communicate(timeout=1800)
        report = check_dataset(out)
    if not session_running:
        raise RuntimeError(f"the session ended before the fuzzing did ({fuzz_s:.0f} s): give more --grasps")
    return {
        "messages_per_endpoint": args.messages,
        "services": len(services),
        "topics": len(topics),
        "fuzz_s": round(fuzz_s, 1),
        # A node that died of a message is respawned by the launcher under a new pid.
        "nodes_crashed": sorted(node for node, pid in before.items() if after.get(node) != pid),
        "nodes_checked": len(before),
        "respawns": output.count("respawning"),
        "session_exit_code": launcher.returncode,
        "pairs": report.samples,
        "pairs_expected": 2 * args.grasps,
        "dataset_check_ok": report.ok,
        "endpoints": rows,
    }


def _wait_until_writing(launcher: subprocess.Popen[str], manifest: Path) -> None:
    """Until the session has written two grasps (four pairs), at most 300 s; RuntimeError with
    the session's output if it ends or times out first."""
    deadline = time.monotonic() + 300
    while not (manifest.exists() and len(manifest.read_text().splitlines()) >= 4):
        if launcher.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the session did not start writing: {launcher.communicate()[0][-2000:]}")
        time.sleep(0.2)


def _fuzz_services(context: zmq.Context, services: dict[str, Endpoint], messages: int, seed: int) -> list[dict]:
    """``messages`` refused mutants to each service (by name); a row per service with the error
    replies."""
    rows = []
    for i, (name, endpoint) in enumerate(sorted(services.items())):
        frames_list = refused_mutants(name, endpoint.schema, messages, seed + i)
        rows.append(
            {
                "endpoint": name,
                "kind": "service",
                "node": endpoint.node,
                "sent": len(frames_list),
                "error_replies": _fuzz_service(context, endpoint.address, frames_list),
            }
        )
        print(
            f"fuzz {name}: {rows[-1]['sent']} sent, {rows[-1]['error_replies']} error replies",
            file=sys.stderr,
            flush=True,
        )
    return rows


def _fuzz_topics(bus: Bus, topics: dict[str, Endpoint], messages: int, seed: int) -> list[dict]:
    """``messages`` refused mutants published on each topic (by name); a row per topic with its
    subscribers."""
    rows = []
    for i, (name, endpoint) in enumerate(sorted(topics.items())):
        frames_list = refused_mutants(name, endpoint.schema, messages, seed + 1000 + i)
        rows.append(
            {
                "endpoint": name,
                "kind": "topic",
                "sent": len(frames_list),
                "subscribers": _fuzz_topic(bus, name, endpoint.schema, frames_list),
            }
        )
        print(
            f"fuzz {name}: {rows[-1]['sent']} sent to {rows[-1]['subscribers']} subscriber(s)",
            file=sys.stderr,
            flush=True,
        )
    return rows
