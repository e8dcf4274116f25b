"""Recording under full sensor load, then replay speed.

A publisher process emits what a collection session does — two 512x424 depth streams and two
640x480 RGB tactile streams at 30 Hz, arm and gripper state at 125 Hz, six transforms on
``/tf`` at 20 Hz — while the real ``dtx bag record`` runs as its own process. Per topic:
published, recorded, dropped, and how far behind the recorder was, read from the bag
(``bus.bag.recording_lag``: lag p50/p99/max and the largest backlog); then how much further
``/tf`` fell behind than the worst other topic (issue 55's target: at most 1 s under load) and
the spread from the least to the most behind topic. Then the bag is replayed with
``dtx bag play --fast`` and its rate given in MB/s.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

import msgs
from bus.bag import bag_info
from bus.pubsub import Bus
from bus.registry import Registry

STREAMS = {  # topic -> (rate Hz, message factory)
    "/camera/left/depth": 30.0,
    "/camera/right/depth": 30.0,
    "/gelsight/left/image": 30.0,
    "/gelsight/right/image": 30.0,
    "/arm/state": 125.0,
    "/gripper/state": 125.0,
    "/tf": 120.0,  # the transform node's six frames at 20 Hz
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of full load")
    parser.add_argument("--compression", choices=["none", "lz4", "zstd"], default="lz4")
    parser.add_argument("--out-dir", default="", help="where the bag goes (default: a temporary folder)")


def _sensor_messages(rng: np.random.Generator) -> dict[str, Any]:
    """Sensor-like content (smooth fields plus noise), so compression sees realistic data."""
    rows, cols = np.mgrid[0:424, 0:512]
    depth = (800 + 0.5 * rows + rng.normal(0, 2, (424, 512))).astype(np.uint16)
    y, x = np.mgrid[0:480, 0:640]
    shade = (120 + 40 * np.sin(x / 50.0) * np.cos(y / 60.0))[..., None] + rng.normal(0, 3, (480, 640, 3))
    image = np.clip(shade, 0, 255).astype(np.uint8)
    return {
        "/camera/left/depth": msgs.DepthImage(header=msgs.Header(frame_id="camera_left"), depth=depth),
        "/camera/right/depth": msgs.DepthImage(header=msgs.Header(frame_id="camera_right"), depth=depth.copy()),
        "/gelsight/left/image": msgs.TactileImage(header=msgs.Header(frame_id="gel_left"), image=image, sensor="left"),
        "/gelsight/right/image": msgs.TactileImage(
            header=msgs.Header(frame_id="gel_right"), image=image.copy(), sensor="right"
        ),
        "/arm/state": msgs.ArmState(tcp_pose=np.zeros(6), joint_positions=np.zeros(6), joint_velocities=np.zeros(6)),
        "/gripper/state": msgs.GripperState(width_m=0.08),
        "/tf": msgs.FrameTransform(header=msgs.Header(frame_id="world"), child_frame_id="tcp", translation=np.zeros(3)),
    }


def _publish_load(bus_dir: str, duration_s: float, out: Any) -> None:
    bus = Bus("sensor_load", Registry(Path(bus_dir)))
    messages = _sensor_messages(np.random.default_rng(0))
    publishers = {topic: bus.publisher(topic, type(messages[topic])) for topic in STREAMS}
    for publisher in publishers.values():
        publisher.wait_for_subscribers(1, 30.0)
    time.sleep(0.5)
    start = time.monotonic()
    due = {topic: start for topic in STREAMS}
    published = dict.fromkeys(STREAMS, 0)
    while (now := time.monotonic()) - start < duration_s:
        for topic, rate in STREAMS.items():
            while due[topic] <= now:
                publishers[topic].publish(messages[topic])
                published[topic] += 1
                due[topic] += 1.0 / rate
        time.sleep(max(0.0, min(due.values()) - time.monotonic()))
    for publisher in publishers.values():
        publisher.close()
    bus.close()
    out.put(published)


def run(args: argparse.Namespace) -> dict:
    with tempfile.TemporaryDirectory(prefix="dtxr") as bus_dir, tempfile.TemporaryDirectory(prefix="dtxbag") as tmp:
        bag = Path(args.out_dir or tmp) / "load.mcap"
        env = {**os.environ, "DTX_BUS_DIR": bus_dir}
        recorder = subprocess.Popen(
            [sys.executable, "-m", "dtx.cli", "bag", "record", "-o", str(bag), "--compression", args.compression],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )
        out = mp.get_context("spawn").Queue()
        load = mp.get_context("spawn").Process(target=_publish_load, args=(bus_dir, args.duration, out))
        load.start()
        published = out.get(timeout=args.duration + 120)
        load.join()
        time.sleep(1.0)
        recorder.send_signal(signal.SIGINT)
        # A recorder that fell behind (a loaded machine) writes its whole backlog before it ends:
        # minutes after a minute of load on two busy cores.
        recorder_output, _ = recorder.communicate(timeout=120 + 10 * args.duration)
        recorded = json.loads(recorder_output.strip().splitlines()[-1])["recorded"]
        info = bag_info(bag)
        size_mb = bag.stat().st_size / 1e6
        started = time.monotonic()
        player = subprocess.run(
            [sys.executable, "-m", "dtx.cli", "bag", "play", str(bag), "--fast", "--wait", "0"],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        play_s = time.monotonic() - started
        dtx_bytes = sum(t["bytes"] for name, t in info.topics.items() if not name.endswith("/foxglove"))
        reported_s = json.loads(player.stdout.strip().splitlines()[-1])["seconds"]
    per_topic = [
        {
            "topic": t,
            "published": published[t],
            "recorded": recorded.get(t, 0),
            "dropped": published[t] - recorded.get(t, 0),
            **_lag_columns(info.topics.get(t)),
        }
        for t in STREAMS
    ]
    return {
        "duration_s": args.duration,
        "compression": args.compression,
        "topics": per_topic,
        "dropped_total": sum(row["dropped"] for row in per_topic),
        **_tf_behind_others(per_topic),
        "bag_mb": round(size_mb, 1),
        "bag_truncated": info.truncated,
        "play_fast_mb_per_s": round(dtx_bytes / 1e6 / reported_s, 1),
        "play_fast_wall_s_including_start": round(play_s, 2),
    }


def _lag_columns(entry: dict[str, Any] | None) -> dict[str, Any]:
    """A topic's lag figures from ``bag_info`` as flat columns (null, with the reason, if none)."""
    if entry is None or entry["lag_ms"] is None:
        reason = "the topic has no stamped message in the bag"
        return {
            **{f"lag_{k}_ms": None for k in ("p50", "p99", "max")},
            **{f"lag_{k}_ms_undefined": reason for k in ("p50", "p99", "max")},
            "backlog_max": None,
            "backlog_max_undefined": reason,
        }
    return {**{f"lag_{k}_ms": v for k, v in entry["lag_ms"].items()}, "backlog_max": entry["backlog_max"]}


def _tf_behind_others(per_topic: list[dict[str, Any]]) -> dict[str, Any]:
    """Fairness in two figures per statistic (p99, max of the lag): how much further /tf went
    than the worst other topic (negative: less far), and the spread from the least to the most
    behind of all topics."""
    figures: dict[str, Any] = {}
    if any(row["lag_max_ms"] is None for row in per_topic):
        reason = "a topic has no lag to compare (it recorded nothing)"
        for stat in ("p99", "max"):
            for key in (f"tf_lag_{stat}_over_others_ms", f"lag_{stat}_spread_ms"):
                figures[key], figures[f"{key}_undefined"] = None, reason
        return figures
    for stat in ("p99", "max"):
        lags = {row["topic"]: row[f"lag_{stat}_ms"] for row in per_topic}
        tf = lags.pop("/tf")
        figures[f"tf_lag_{stat}_over_others_ms"] = round(tf - max(lags.values()), 3)
        figures[f"lag_{stat}_spread_ms"] = round(max(tf, *lags.values()) - min(tf, *lags.values()), 3)
    return figures
