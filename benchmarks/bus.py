"""Bus latency and throughput: dtx messages next to raw pyzmq zero-copy multipart (the limit).

Each row: a publisher here, a subscriber in another process, one transport, one payload.
One-way latency uses CLOCK_MONOTONIC stamps (shared by processes on one machine) on messages
paced so that no queue builds up; throughput sends back to back and counts what arrives.

``--work``: instead, the Python work per message on each side, warm, in this process (a
PUSH/PULL pair over ipc; the best of 10 x ``--repeats`` batches of 200, so that another process's time
slices do not count): dtx's encode and send, and receive and decode (the validation included),
beside raw pyzmq's send and receive of the same payload. This is the part of the latency and
throughput gap that is ours; the rest is the operating system's and ZeroMQ's. ``idle_send_us``
and ``idle_receive_us``: the same work, each call 2 ms after the one before (the median of
100), as the latency rows' paced messages find it. On this shared virtual machine the processor's
caches and predictors no longer hold the interpreter's working set after such a gap, even with
the thread spinning instead of sleeping, and every Python or NumPy call costs several times its
warm price: the latency gap follows how much each side touches per message, not its warm work.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import tempfile
import time
from collections.abc import Callable
from multiprocessing.context import SpawnContext
from pathlib import Path
from typing import Any

import numpy as np
import zmq

import msgs
from bus.context import TransportConfig, recv_frames, send_frames
from bus.pubsub import Bus, Subscriber
from bus.registry import Registry
from msgs.base import Header, Message
from msgs.codec import decode, encode

PAYLOADS = {  # bytes -> the message a real node sends at that size
    1024: "1 KiB",
    512 * 424 * 2: "434 KiB depth frame",
    640 * 480 * 3: "900 KiB RGB frame",
    200_000 * 3 * 4: "2.4 MiB 200k-point cloud",
}
TOPIC = "/bench"


def make_message(payload_bytes: int) -> Message:
    """A real message type of (about) the payload size."""
    if payload_bytes == 512 * 424 * 2:
        return msgs.DepthImage(depth=np.ones((424, 512), np.uint16))
    if payload_bytes == 640 * 480 * 3:
        return msgs.TactileImage(image=np.ones((480, 640, 3), np.uint8))
    return msgs.PointCloud(points=np.ones((payload_bytes // 12, 3), np.float32))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--latency-messages", type=int, default=300)
    parser.add_argument("--throughput-mb", type=float, default=400.0, help="MB sent per throughput run")
    parser.add_argument("--transports", nargs="+", default=["ipc", "tcp"], choices=["ipc", "tcp"])
    parser.add_argument("--repeats", type=int, default=3, help="runs per row; figures are their medians")
    parser.add_argument("--work", action="store_true", help="the Python work per message only (see above)")


def _receiver(impl: str, transport: str, address: str, bus_dir: str, expected: int, out: Any) -> None:
    """Child process: receive ``expected`` messages, report latencies (us) and the span."""
    latencies: list[float] = []
    first, last, received, nbytes = 0.0, 0.0, 0, 0
    if impl == "dtx":
        bus = Bus("bench_sub", Registry(Path(bus_dir)), TransportConfig(transport=transport, high_water_mark=100_000))
        subscriber: Subscriber[Message] = bus.subscriber(TOPIC, None)  # any schema: the receiver reads headers only
        out.put("ready")
        while received < expected:
            envelope = subscriber.receive(timeout_s=5.0)
            if envelope is None:
                break
            now = time.monotonic_ns()
            latencies.append((now - envelope.message.header.stamp_ns) / 1e3)
            nbytes += envelope.size_bytes
            first = first or now
            last = now
            received += 1
        bus.close()
    else:
        context = zmq.Context()
        sock = context.socket(zmq.SUB)
        sock.setsockopt(zmq.RCVHWM, 100_000)
        sock.setsockopt(zmq.SUBSCRIBE, b"")
        sock.connect(address)
        out.put("ready")
        while received < expected and sock.poll(5000):
            frames = sock.recv_multipart(copy=False)
            now = time.monotonic_ns()
            latencies.append((now - int.from_bytes(frames[1].bytes, "little")) / 1e3)
            nbytes += sum(len(f.buffer) for f in frames)
            first = first or now
            last = now
            received += 1
        context.destroy(linger=0)
    out.put({"latencies_us": latencies, "span_s": (last - first) / 1e9, "received": received, "bytes": nbytes})


def _send_dtx(
    context_mp: SpawnContext, message: Message, transport: str, bus_dir: str, count: int, pause_s: float
) -> dict:
    """One phase through dtx: publish ``count`` stamped messages to a receiver process, ``pause_s``
    apart; the receiver's report."""
    out = context_mp.Queue()
    bus = Bus("bench_pub", Registry(Path(bus_dir)), TransportConfig(transport=transport, high_water_mark=100_000))
    publisher = bus.publisher(TOPIC, type(message))
    child = context_mp.Process(target=_receiver, args=("dtx", transport, "", bus_dir, count, out))
    child.start()
    out.get(timeout=60)
    publisher.wait_for_subscribers(1, 30)
    time.sleep(0.2)
    for _ in range(count):
        message.header = Header(stamp_ns=time.monotonic_ns())
        publisher.publish(message)
        if pause_s:
            time.sleep(pause_s)
    result = out.get(timeout=120)
    publisher.close()
    bus.close()
    child.join(timeout=30)
    return result


def _send_raw(
    context_mp: SpawnContext, payload_bytes: int, transport: str, bus_dir: str, count: int, pause_s: float
) -> dict:
    """The same phase through raw pyzmq: topic, stamp and payload frames, sent zero-copy."""
    out = context_mp.Queue()
    context = zmq.Context()
    sock = context.socket(zmq.XPUB)
    sock.setsockopt(zmq.SNDHWM, 100_000)
    address = f"ipc://{bus_dir}/raw.sock" if transport == "ipc" else "tcp://127.0.0.1:*"
    sock.bind(address)
    address = sock.getsockopt_string(zmq.LAST_ENDPOINT)
    child = context_mp.Process(target=_receiver, args=("raw_pyzmq", transport, address, bus_dir, count, out))
    child.start()
    out.get(timeout=60)
    sock.recv()  # the subscription arrives: the subscriber is connected
    time.sleep(0.2)
    payload = np.ones(payload_bytes, np.uint8).data  # a memoryview of the array
    for _ in range(count):
        sock.send_multipart([TOPIC.encode(), time.monotonic_ns().to_bytes(8, "little"), payload], copy=False)
        if pause_s:
            time.sleep(pause_s)
    result = out.get(timeout=120)
    context.destroy(linger=1000)
    child.join(timeout=30)
    return result


def _run_row(impl: str, transport: str, payload_bytes: int, args: argparse.Namespace, bus_dir: str) -> dict:
    message = make_message(payload_bytes)
    n_latency = args.latency_messages
    n_throughput = max(20, int(args.throughput_mb * 1e6 / payload_bytes))
    n_throughput = min(n_throughput, 20_000)
    context_mp = mp.get_context("spawn")
    results: list[dict] = []
    for phase, count, pause_s in (
        ("latency", n_latency, 0.002 + payload_bytes / 2e9),
        ("throughput", n_throughput, 0.0),
    ):
        if impl == "dtx":
            results.append(_send_dtx(context_mp, message, transport, bus_dir, count, pause_s))
        else:
            results.append(_send_raw(context_mp, payload_bytes, transport, bus_dir, count, pause_s))
    latency, throughput = results
    lat = np.array(latency["latencies_us"])
    spanned = throughput["span_s"] > 0
    mb_per_s = throughput["bytes"] / throughput["span_s"] / 1e6 if spanned else float("nan")
    return {
        "impl": impl,
        "transport": transport,
        "payload_bytes": payload_bytes,
        "p50_us": round(float(np.percentile(lat, 50)), 1),
        "p99_us": round(float(np.percentile(lat, 99)), 1),
        "mb_per_s": round(mb_per_s, 1),
        **({} if spanned else {"mb_per_s_undefined": "fewer than two throughput messages arrived: no time span"}),
        "throughput_received": throughput["received"],
        "throughput_sent": n_throughput,
    }


def _batch_us(step: Callable[[], object], calls: int = 200) -> float:
    """Microseconds per call of ``step`` over ``calls`` calls in a row."""
    started = time.perf_counter_ns()
    for _ in range(calls):
        step()
    return (time.perf_counter_ns() - started) / calls / 1e3


def _after_idle_us(step: Callable[[], object], calls: int = 100, idle_s: float = 0.002) -> float:
    """Median microseconds of ``step``, each call ``idle_s`` after the one before."""
    times = []
    for _ in range(calls):
        time.sleep(idle_s)
        started = time.perf_counter_ns()
        step()
        times.append(time.perf_counter_ns() - started)
    return float(np.median(times)) / 1e3


def _work_rows(payload_bytes: int, batches: int, bus_dir: str) -> list[dict]:
    """Send and receive work per message, dtx and raw, warm and after an idle gap (see the
    module docstring)."""
    context = zmq.Context()
    push, pull = context.socket(zmq.PUSH), context.socket(zmq.PULL)
    push.setsockopt(zmq.SNDHWM, 0)  # no limit: a batch is queued whole
    pull.setsockopt(zmq.RCVHWM, 0)
    push.bind(f"ipc://{bus_dir}/work.sock")
    pull.connect(f"ipc://{bus_dir}/work.sock")
    message = make_message(payload_bytes)
    payload = np.ones(payload_bytes, np.uint8).data  # a memoryview of the array
    sends: dict[str, Callable[[], object]] = {  # the reference first, as in the other rows
        "raw_pyzmq": lambda: push.send_multipart(
            [TOPIC.encode(), time.monotonic_ns().to_bytes(8, "little"), payload], copy=False
        ),
        "dtx": lambda: send_frames(push, encode(TOPIC, message, "bench", Header(stamp_ns=time.monotonic_ns(), seq=1))),
    }
    receives: dict[str, Callable[[], object]] = {
        "raw_pyzmq": lambda: int.from_bytes(pull.recv_multipart(copy=False)[1].bytes, "little"),
        "dtx": lambda: decode(recv_frames(pull)).message.header.stamp_ns,
    }
    measured = {impl: {"send_us": math.inf, "receive_us": math.inf} for impl in sends}
    # Rounds take turns, the first of them a warm-up: whichever goes first at a size pays the
    # allocator's first page faults for its buffers.
    for round_index in range(batches + 1):
        for impl, figures in measured.items():
            send_us = _batch_us(sends[impl])
            receive_us = _batch_us(receives[impl])  # reads what the sends queued, one per call
            if round_index:
                figures["send_us"] = min(figures["send_us"], send_us)
                figures["receive_us"] = min(figures["receive_us"], receive_us)
    for impl, figures in measured.items():
        figures["idle_send_us"] = _after_idle_us(sends[impl])
        figures["idle_receive_us"] = _after_idle_us(receives[impl])  # the messages just sent
    rows = [
        {"impl": impl, "payload_bytes": payload_bytes, **{key: round(us, 2) for key, us in figures.items()}}
        for impl, figures in measured.items()
    ]
    context.destroy(linger=0)
    return rows


def run(args: argparse.Namespace) -> list[dict]:
    """Each (transport, payload) pair is measured ``--repeats`` times, raw and dtx taking turns,
    and each figure is the median over the repeats: on a shared machine one run's scheduling
    noise can exceed the difference being measured."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="dtxb") as bus_dir:
        if args.work:
            return [row for payload_bytes in PAYLOADS for row in _work_rows(payload_bytes, args.repeats * 10, bus_dir)]
        for transport in args.transports:
            for payload_bytes in PAYLOADS:
                trials: dict[str, list[dict]] = {"raw_pyzmq": [], "dtx": []}
                for _ in range(args.repeats):
                    for impl in trials:
                        trials[impl].append(_run_row(impl, transport, payload_bytes, args, bus_dir))
                for impl, runs in trials.items():
                    row = dict(runs[0])
                    for key in ("p50_us", "p99_us", "mb_per_s"):
                        row[key] = round(float(np.median([r[key] for r in runs])), 1)
                    row["repeats"] = len(runs)
                    rows.append(row)
    return rows
