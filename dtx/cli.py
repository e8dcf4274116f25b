"""``dtx``: the one command line of the system, in the spirit of ``ros2``."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import signal
import sys
import time
import typing
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dtx import calibrate, demo
from msgs import strict_json

# Packages that add their own command groups (each has cli.add_commands(subparsers)).
COMMAND_PACKAGES: list[str] = ["drivers", "sim", "perception", "models", "dataset", "report"]


def _summarise(value: Any, full: bool) -> Any:
    if isinstance(value, np.ndarray):
        if full or value.size <= 16:
            return value.tolist()
        finite = value[np.isfinite(value)] if value.dtype.kind == "f" else value
        summary = f"<{value.dtype} array {list(value.shape)}"
        if finite.size:
            summary += f" min {finite.min():.6g} max {finite.max():.6g}"
        return summary + ">"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _summarise(getattr(value, f.name), full) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_summarise(v, full) for v in value]
    if isinstance(value, dict):
        return {k: _summarise(v, full) for k, v in value.items()}
    return value


def message_to_yaml(message: Any, full: bool = False) -> str:
    return yaml.safe_dump(_summarise(message, full), sort_keys=False, width=120)


def _bus(name: str) -> Any:
    from bus.pubsub import Bus

    return Bus(name)


# -- launch / node -----------------------------------------------------------------------
def cmd_launch(args: argparse.Namespace) -> int:
    from dtx.launch import Launcher, LaunchError, load_launch, parse_launch_args

    try:
        description = load_launch(args.file, parse_launch_args(args.args))
    except LaunchError as exc:
        print(f"dtx launch: {exc}", file=sys.stderr)
        return 2
    return Launcher(description).run()


def cmd_node_list(args: argparse.Namespace) -> int:
    from bus.registry import Registry

    rows = [s for s in Registry().node_statuses() if s["alive"] or args.all]
    print(f"{'NAME':24} {'PID':>7} {'STATUS':10} {'AGE_S':>6}  TOPICS")
    for s in rows:
        status = s.get("status", "?") if s["alive"] else "dead"
        age = time.time() - float(s.get("stamp", 0))
        print(
            f"{s['node']:24} {s['pid']:>7} {status:10} {age:6.1f}  pub {len(s['publishers'])} "
            f"sub {len(s['subscribers'])} srv {len(s['services'])}"
        )
    return 0


# -- topics ------------------------------------------------------------------------------
def cmd_topic_list(args: argparse.Namespace) -> int:
    from bus.registry import Registry

    for topic, endpoints in Registry().names("topic").items():
        schemas = sorted({e.schema for e in endpoints})
        nodes = sorted({e.node for e in endpoints})
        print(f"{topic}  [{', '.join(schemas)}]  from {', '.join(nodes)}" if args.verbose else topic)
    return 0


def cmd_topic_echo(args: argparse.Namespace) -> int:
    bus = _bus("dtx_topic_echo")
    subscriber = bus.subscriber(args.topic, None)
    shown = 0
    try:
        while args.count == 0 or shown < args.count:
            envelope = subscriber.receive(timeout_s=args.timeout or None)
            if envelope is None:
                print(f"no message on {args.topic} within {args.timeout} s", file=sys.stderr)
                return 1
            print(message_to_yaml(envelope.message, args.full) + "---", flush=True)
            shown += 1
    except KeyboardInterrupt:
        pass
    finally:
        bus.close()
    return 0


def _measure(topic: str, duration_s: float) -> tuple[list[float], list[int], Any]:
    bus = _bus("dtx_topic_stats")
    subscriber = bus.subscriber(topic, None)
    stamps: list[float] = []
    sizes: list[int] = []
    deadline = time.monotonic() + duration_s
    try:
        while (remaining := deadline - time.monotonic()) > 0:
            envelope = subscriber.receive(timeout_s=remaining)
            if envelope is not None:
                stamps.append(time.monotonic())
                sizes.append(envelope.size_bytes)
    except KeyboardInterrupt:
        pass
    counters = subscriber.counters
    bus.close()
    return stamps, sizes, counters


def cmd_topic_hz(args: argparse.Namespace) -> int:
    stamps, _, counters = _measure(args.topic, args.duration)
    if len(stamps) < 2:
        print(f"{args.topic}: fewer than two messages in {args.duration} s")
        return 1
    gaps = np.diff(stamps)
    print(
        f"{args.topic}: average rate {1 / gaps.mean():.2f} Hz  min {gaps.min() * 1e3:.2f} ms  "
        f"max {gaps.max() * 1e3:.2f} ms  std {gaps.std() * 1e3:.2f} ms  window {len(stamps)}  "
        f"dropped {counters.dropped}"
    )
    return 0


def cmd_topic_bw(args: argparse.Namespace) -> int:
    stamps, sizes, _ = _measure(args.topic, args.duration)
    if len(stamps) < 2:
        print(f"{args.topic}: fewer than two messages in {args.duration} s")
        return 1
    span = stamps[-1] - stamps[0]
    print(
        f"{args.topic}: {sum(sizes[1:]) / span / 1e6:.3f} MB/s  mean {np.mean(sizes) / 1e3:.1f} kB  "
        f"min {min(sizes) / 1e3:.1f} kB  max {max(sizes) / 1e3:.1f} kB  n {len(sizes)}"
    )
    return 0


# -- services ----------------------------------------------------------------------------
def cmd_service_list(args: argparse.Namespace) -> int:
    from bus.registry import Registry

    for name, endpoints in Registry().names("service").items():
        e = endpoints[0]
        print(f"{name}  [{e.schema} -> {e.reply_schema}]  from {', '.join(sorted({x.node for x in endpoints}))}")
    return 0


def cmd_service_call(args: argparse.Namespace) -> int:
    from bus.registry import Registry
    from bus.services import ServiceCallError
    from msgs import MESSAGE_TYPES

    endpoints = Registry().lookup("service", args.name)
    if not endpoints:
        print(f"service {args.name} not found (see `dtx service list`)", file=sys.stderr)
        return 1
    request_type = MESSAGE_TYPES[endpoints[0].schema]
    reply_type = MESSAGE_TYPES[endpoints[0].reply_schema]
    fields = yaml.safe_load(args.request) or {}
    if not isinstance(fields, dict):
        print('request must be a YAML mapping of fields, e.g. "{action: home}"', file=sys.stderr)
        return 2
    try:
        request = request_type(**_fields_from_yaml(request_type, fields))
    except (TypeError, ValueError) as exc:
        print(f"bad request for {request_type.SCHEMA}: {exc}", file=sys.stderr)
        return 2
    bus = _bus("dtx_service_call")
    try:
        reply = bus.client(args.name, request_type, reply_type).call(request, timeout_s=args.timeout)
    except ServiceCallError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    finally:
        bus.close()
    print(message_to_yaml(reply, args.full), end="")
    return 0


def _fields_from_yaml(msg_type: type, fields: dict[str, Any]) -> dict[str, Any]:
    """YAML lists become arrays where the message declares an array field."""
    hints = typing.get_type_hints(msg_type)
    unknown = sorted(set(fields) - set(hints))
    if unknown:
        raise ValueError(f"unknown field(s) {unknown}; fields: {sorted(hints)}")
    return {k: np.asarray(v) if hints[k] is np.ndarray else v for k, v in fields.items()}


# -- bags --------------------------------------------------------------------------------
def cmd_bag_record(args: argparse.Namespace) -> int:
    from bus.bag_record_play import record

    stop_at = time.monotonic() + args.duration if args.duration else None
    stopping = {"now": False}
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stopping.update(now=True))
    bus = _bus("dtx_bag_record")
    bus.transport.high_water_mark = 100_000  # a recorder queues rather than drops
    counts = record(
        args.output,
        bus,
        lambda: stopping["now"] or (stop_at is not None and time.monotonic() > stop_at),
        topics=args.topics or None,
        compression=args.compression,
        foxglove=not args.no_foxglove,
    )
    bus.close()
    print(strict_json.dumps({"bag": args.output, "recorded": counts}))
    return 0


def cmd_bag_play(args: argparse.Namespace) -> int:
    from bus.bag_format import BagError
    from bus.bag_record_play import play

    bus = _bus("dtx_bag_play")
    stopping = {"now": False}
    signal.signal(signal.SIGINT, lambda *_: stopping.update(now=True))
    started = time.monotonic()
    try:
        counts = play(
            args.file,
            bus,
            rate=None if args.fast else args.rate,
            clock=args.clock,
            topics=args.topics or None,
            wait_for_subscribers_s=args.wait,
            stop=lambda: stopping["now"],
        )
    except BagError as exc:
        print(f"bag play stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        bus.close()
    elapsed = time.monotonic() - started
    print(strict_json.dumps({"published": counts, "seconds": round(elapsed, 3)}))
    return 0


def cmd_bag_info(args: argparse.Namespace) -> int:
    from bus.bag import bag_info
    from bus.bag_format import BagError

    try:
        info = bag_info(args.file)
    except BagError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    if args.json:
        print(strict_json.dumps({**dataclasses.asdict(info), "duration_s": info.duration_s}, indent=2))
        return 0
    print(f"path:        {info.path}")
    print(f"truncated:   {'yes (cut short; everything before the cut was read)' if info.truncated else 'no'}")
    print(f"compression: {info.compression}")
    print(f"duration:    {info.duration_s:.3f} s")
    print(f"messages:    {info.message_count}")
    for topic, entry in info.topics.items():
        print(f"  {topic:40} {entry['count']:8d} msgs  {entry['bytes'] / 1e6:9.2f} MB  {entry['schema']}")
        lag = entry["lag_ms"]
        if lag is not None:  # how far behind the recorder was (docs/bag-format.md)
            print(
                f"  {'':40} lag p50 {lag['p50']:.1f} ms, p99 {lag['p99']:.1f} ms, max {lag['max']:.1f} ms; "
                f"backlog at most {entry['backlog_max']}"
            )
    return 0


# -- benchmarks and keys -----------------------------------------------------------------
def _print_table(result: Any) -> None:
    rows = result if isinstance(result, list) else None
    if rows and all(isinstance(r, dict) for r in rows):
        keys = list(dict.fromkeys(k for r in rows for k in r))
        print("  ".join(f"{k:>14}" for k in keys))
        for row in rows:
            print("  ".join(f"{_fmt(row.get(k)):>14}" for k in keys))
    else:
        print(yaml.safe_dump(result, sort_keys=False, width=120))


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def cmd_keys_create(args: argparse.Namespace) -> int:
    import zmq.auth

    Path(args.dir).mkdir(parents=True, exist_ok=True)
    public, secret = zmq.auth.create_certificates(args.dir, args.name)
    print(f"public key: {public}\nsecret key: {secret}")
    return 0


def _add_bench(sub: Any) -> None:
    names = sorted(
        p.stem
        for p in (Path(__file__).resolve().parent.parent / "benchmarks").glob("*.py")
        if not p.stem.startswith("_")
    )
    bench = sub.add_parser("bench", help=f"benchmarks that print figures: {', '.join(names)}")
    bench.add_argument("name", choices=names)
    bench.add_argument("options", nargs=argparse.REMAINDER, help="the benchmark's own options (--json, ...)")
    bench.set_defaults(func=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    """Benchmarks import heavy libraries, so a benchmark's options are parsed only when it runs."""
    module = importlib.import_module(f"benchmarks.{args.name}")
    parser = argparse.ArgumentParser(prog=f"dtx bench {args.name}", description=module.__doc__)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    module.add_arguments(parser)
    options = parser.parse_args(args.options)
    result = module.run(options)
    if options.json:
        print(strict_json.dumps(result, indent=2))
    else:
        _print_table(result)
    return 0


def _add_launch(sub: Any) -> None:
    p = sub.add_parser("launch", help="start the nodes of a launch file")
    p.add_argument("file")
    p.add_argument("args", nargs="*", help="launch arguments name:=value")
    p.set_defaults(func=cmd_launch)


def _add_node(sub: Any) -> None:
    node = sub.add_parser("node", help="nodes on the bus").add_subparsers(dest="verb", required=True)
    p = node.add_parser("list")
    p.add_argument("--all", action="store_true", help="include nodes that have stopped")
    p.set_defaults(func=cmd_node_list)


def _add_topic(sub: Any) -> None:
    topic = sub.add_parser("topic", help="topics on the bus").add_subparsers(dest="verb", required=True)
    p = topic.add_parser("list")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=cmd_topic_list)
    p = topic.add_parser("echo")
    p.add_argument("topic")
    p.add_argument("--count", type=int, default=0, help="stop after N messages (0: never)")
    p.add_argument("--timeout", type=float, default=0.0, help="give up after S seconds without a message")
    p.add_argument("--full", action="store_true", help="print whole arrays")
    p.set_defaults(func=cmd_topic_echo)
    for verb, func in (("hz", cmd_topic_hz), ("bw", cmd_topic_bw)):
        p = topic.add_parser(verb)
        p.add_argument("topic")
        p.add_argument("--duration", type=float, default=5.0)
        p.set_defaults(func=func)


def _add_service(sub: Any) -> None:
    service = sub.add_parser("service", help="services on the bus").add_subparsers(dest="verb", required=True)
    service.add_parser("list").set_defaults(func=cmd_service_list)
    p = service.add_parser("call")
    p.add_argument("name")
    p.add_argument("request", nargs="?", default="{}", help='request fields as YAML, e.g. "{action: home}"')
    p.add_argument("--timeout", type=float, default=5.0)
    p.add_argument("--full", action="store_true")
    p.set_defaults(func=cmd_service_call)


def _add_bag(sub: Any) -> None:
    bag = sub.add_parser("bag", help="record, replay and inspect MCAP bags").add_subparsers(dest="verb", required=True)
    p = bag.add_parser("record")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("topics", nargs="*", help="topics to record (default: all, also later ones)")
    p.add_argument("--compression", choices=["none", "lz4", "zstd"], default="lz4")
    p.add_argument("--no-foxglove", action="store_true", help="skip the Foxglove copies of image/cloud topics")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0: at Ctrl-C)")
    p.set_defaults(func=cmd_bag_record)
    p = bag.add_parser("play")
    p.add_argument("file")
    p.add_argument("topics", nargs="*")
    p.add_argument("--rate", type=float, default=1.0, help="time scale (2: twice as fast)")
    p.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--clock", action="store_true", help="publish the bag's time on /clock")
    p.add_argument("--wait", type=float, default=1.0, help="seconds to wait for subscribers first")
    p.set_defaults(func=cmd_bag_play)
    p = bag.add_parser("info")
    p.add_argument("file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bag_info)


def _add_keys(sub: Any) -> None:
    keys = sub.add_parser("keys", help="CURVE key pairs").add_subparsers(dest="verb", required=True)
    p = keys.add_parser("create")
    p.add_argument("dir")
    p.add_argument("name")
    p.set_defaults(func=cmd_keys_create)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dtx", description="Deep Tactile Experience: lab command line")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_launch, _add_node, _add_topic, _add_service, _add_bag, _add_keys, _add_bench):
        add(sub)
    demo.add_commands(sub)
    calibrate.add_commands(sub)
    for package in COMMAND_PACKAGES:
        importlib.import_module(f"{package}.cli").add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from bus.registry import BusDirectoryError

    args = build_parser(argv).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BusDirectoryError as exc:
        print(f"dtx: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
