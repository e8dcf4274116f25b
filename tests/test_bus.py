"""Topics and services between real ZeroMQ sockets: discovery, slow joiners, drops, bad peers."""

from __future__ import annotations

import contextlib
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
import zmq.auth

import msgs
from bus.context import PeerConfig, TransportConfig
from bus.pubsub import Bus
from bus.registry import Endpoint, Registry
from bus.security import CurveConfig, SecurityError
from bus.services import ServiceCallError
from msgs.codec import decode, encode


@pytest.fixture
def buses(registry: Registry) -> Iterator[tuple[Bus, Bus]]:
    a, b = Bus("a", registry), Bus("b", registry)
    yield a, b
    a.close()
    b.close()


@contextlib.contextmanager
def pumping(*owners: object) -> Iterator[None]:
    """Service publishers' join events and servers' requests, as a node's executor would."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            for owner in owners:
                if hasattr(owner, "serve_ready"):
                    owner.serve_ready()
                else:
                    owner.service_subscriptions()
            time.sleep(0.002)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def test_subscriber_finds_publisher_by_topic_name(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    publisher = a.publisher("/gripper/state", msgs.GripperState)
    subscriber = b.subscriber("/gripper/state", msgs.GripperState)
    assert publisher.wait_for_subscribers(1, 5.0)
    publisher.publish(msgs.GripperState(width_m=0.04, header=msgs.Header(frame_id="tcp")))
    envelope = subscriber.receive(5.0)
    assert envelope is not None
    assert envelope.message.width_m == 0.04
    assert envelope.message.header.frame_id == "tcp"
    assert envelope.message.header.seq == 1 and envelope.message.header.stamp_ns > 0


def test_latched_topic_reaches_a_late_subscriber(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    publisher = a.publisher("/scene", msgs.GripperState, latched=True)
    publisher.publish(msgs.GripperState(width_m=1.0))
    publisher.publish(msgs.GripperState(width_m=2.0))
    with pumping(publisher):
        first = b.subscriber("/scene", msgs.GripperState).receive(5.0)
        late = b.subscriber("/scene", msgs.GripperState)
        second = late.receive(5.0)
    assert first is not None and first.message.width_m == 2.0
    assert second is not None and second.message.width_m == 2.0


def test_latched_resend_is_not_delivered_twice(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    publisher = a.publisher("/latched", msgs.GripperState, latched=True)
    with pumping(publisher):
        early = b.subscriber("/latched", msgs.GripperState)
        early.receive(0.5)
        publisher.publish(msgs.GripperState(width_m=3.0))
        assert early.receive(5.0) is not None
        b.subscriber("/latched", msgs.GripperState).receive(5.0)  # a join makes the publisher resend
        assert early.receive(0.5) is None
    assert early.counters.duplicates == 1


def test_wait_for_subscribers_times_out_without_any(buses: tuple[Bus, Bus]) -> None:
    publisher = buses[0].publisher("/nobody", msgs.Log)
    assert not publisher.wait_for_subscribers(1, 0.2)


def test_sequence_gaps_are_counted_as_drops(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    publisher = a.publisher("/arm", msgs.ArmState)
    subscriber = b.subscriber("/arm", msgs.ArmState)
    assert publisher.wait_for_subscribers(1, 5.0)
    publisher.publish(msgs.ArmState())
    publisher.seq += 4  # four messages lost on the way
    publisher.publish(msgs.ArmState())
    assert subscriber.receive(5.0) and subscriber.receive(5.0)
    assert subscriber.counters.dropped == 4 and subscriber.counters.received == 2


def test_a_stranger_sending_garbage_is_counted_and_ignored(buses: tuple[Bus, Bus], registry: Registry) -> None:
    _, b = buses
    stranger_context = zmq.Context()
    stranger = stranger_context.socket(zmq.XPUB)
    address = registry.socket_address("stranger")
    stranger.bind(address)
    registry.advertise(Endpoint("topic", "/depth", address, "stranger", os.getpid(), msgs.DepthImage.SCHEMA))
    subscriber = b.subscriber("/depth", msgs.DepthImage)
    stranger.recv()  # subscription arrived
    stranger.send_multipart([b"/depth", b"\xff\x00garbage"])
    stranger.send_multipart([b"/depth"])
    good = msgs.DepthImage(depth=np.ones((2, 2), np.uint16))
    stranger.send_multipart(encode("/depth", good, "stranger"))
    envelope = subscriber.receive(5.0)
    stranger_context.destroy(linger=0)
    assert envelope is not None and envelope.message.depth.sum() == 4
    assert subscriber.counters.malformed == 2


def test_oversized_message_is_dropped_and_the_subscriber_lives_on(
    registry: Registry, caplog: pytest.LogCaptureFixture
) -> None:
    a = Bus("a", registry)
    b = Bus("b", registry, TransportConfig(max_message_bytes=4096))
    publisher = a.publisher("/cloud", msgs.PointCloud)
    subscriber = b.subscriber("/cloud", msgs.PointCloud)
    assert publisher.wait_for_subscribers(1, 5.0)
    publisher.publish(msgs.PointCloud(points=np.zeros((10_000, 3), np.float32)))
    received = None
    deadline = time.monotonic() + 10
    while received is None and time.monotonic() < deadline:  # we reconnect after ZeroMQ's refusal
        publisher.publish(msgs.PointCloud(points=np.zeros((10, 3), np.float32)))
        received = subscriber.receive(0.2)
    a.close()
    b.close()
    assert received is not None and received.message.points.shape == (10, 3)
    assert (subscriber.counters.connection_resets, subscriber.counters.publishers_gone) == (1, 0)
    assert "oversized or malformed" in caplog.text and "went away" not in caplog.text


def test_a_publisher_killed_with_9_is_a_publisher_gone_not_bad_data(
    registry: Registry, bus_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """kill -9 of a publishing process: its subscriber says the publisher went away and counts it
    so, not as an oversized or malformed message (what it used to log)."""
    talker = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import time, msgs\n"
            "from bus.pubsub import Bus\n"
            "publisher = Bus('talker').publisher('/state', msgs.GripperState)\n"
            "while True:\n"
            "    publisher.publish(msgs.GripperState(width_m=0.01))\n"
            "    time.sleep(0.02)\n",
        ],
        env={**os.environ, "DTX_BUS_DIR": str(bus_dir)},
    )
    with contextlib.closing(Bus("listener", registry)) as bus:
        subscriber = bus.subscriber("/state", msgs.GripperState)
        try:
            assert subscriber.receive(60.0) is not None, "the talker never published"
            talker.kill()
            # Not reaped yet, as a launcher has not yet noticed: the killed talker's entry stands.
            deadline = time.monotonic() + 30
            while subscriber.counters.publishers_gone == 0 and time.monotonic() < deadline:
                subscriber.receive(0.1)
        finally:
            talker.kill()
            talker.wait()
        subscriber.discover(force=True)  # any verdict still pending is given
    assert (subscriber.counters.publishers_gone, subscriber.counters.connection_resets) == (1, 0)
    assert "went away" in caplog.text and "oversized" not in caplog.text


def test_a_publisher_of_another_type_is_not_heard(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    wrong = a.publisher("/state", msgs.Log)
    subscriber = b.subscriber("/state", msgs.GripperState)
    wrong.publish(msgs.Log(text="not a gripper state"))
    assert subscriber.receive(0.3) is None
    assert subscriber.publisher_count == 0


def test_remapped_topic_is_used(registry: Registry) -> None:
    a = Bus("a", registry, remaps={"/state": "/left/state"})
    b = Bus("b", registry)
    publisher = a.publisher("/state", msgs.GripperState)
    assert publisher.topic == "/left/state"
    subscriber = b.subscriber("/left/state", msgs.GripperState)
    assert publisher.wait_for_subscribers(1, 5.0)
    publisher.publish(msgs.GripperState())
    assert subscriber.receive(5.0) is not None
    a.close()
    b.close()


def _double(request: msgs.GripperCommand) -> msgs.GripperState:
    if request.width_m < 0:
        raise ValueError("width must be positive")
    return msgs.GripperState(width_m=2 * request.width_m)


def test_service_call_error_reply_and_recovery(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    server = a.service("/double", msgs.GripperCommand, msgs.GripperState, _double)
    with pumping(server):
        client = b.client("/double", msgs.GripperCommand, msgs.GripperState)
        assert client.call(msgs.GripperCommand(width_m=0.02)).width_m == pytest.approx(0.04)
        with pytest.raises(ServiceCallError, match="width must be positive") as failure:
            client.call(msgs.GripperCommand(width_m=-1.0))
        assert failure.value.code == "handler_error"
        wrong = b.client("/double", msgs.Log, msgs.GripperState)
        with pytest.raises(ServiceCallError) as wrong_type:
            wrong.call(msgs.Log())
        assert wrong_type.value.code == "wrong_type"
        assert client.call(msgs.GripperCommand(width_m=0.5)).width_m == pytest.approx(1.0)


def test_service_answers_garbage_with_an_error_reply(buses: tuple[Bus, Bus]) -> None:
    a, _ = buses
    server = a.service("/double", msgs.GripperCommand, msgs.GripperState, _double)
    context = zmq.Context()
    with pumping(server):
        stranger = context.socket(zmq.DEALER)
        stranger.connect(server.address)
        stranger.send_multipart([b"/double", b"not msgpack at all \xc1"])
        assert stranger.poll(5000)
        reply = decode(stranger.recv_multipart()).message
    context.destroy(linger=0)
    assert isinstance(reply, msgs.ServiceError) and reply.code == "bad_request"
    assert server.counters.malformed == 1


def test_a_broken_request_whose_p_and_q_can_be_read_gets_them_back(buses: tuple[Bus, Bus]) -> None:
    """A client matches a reply to its request by q: an error reply without it would be lost."""
    a, _ = buses
    server = a.service("/double", msgs.GripperCommand, msgs.GripperState, _double)
    good = encode("/double", msgs.GripperCommand(width_m=0.1), "planner-7")
    header = msgpack.unpackb(good[1])
    broken = [
        [b"/double", msgpack.packb({**header, "q": 41, "t": 1.5})],  # t a float
        [b"/double", msgpack.packb({**header, "q": 42, "s": "dtx.nothing.Here"})],  # unknown schema
        [b"/double", msgpack.packb({**header, "q": 43, "v": 99})],  # another version
        [b"/double", msgpack.packb({**header, "q": 44, "d": {**header["d"], "extra": 1}})],
    ]
    context = zmq.Context()
    with pumping(server):
        stranger = context.socket(zmq.DEALER)
        stranger.connect(server.address)
        replies = []
        for frames in broken:
            stranger.send_multipart(frames)
            assert stranger.poll(5000)
            replies.append(decode(stranger.recv_multipart()))
    context.destroy(linger=0)
    assert [(r.publisher, r.message.header.seq) for r in replies] == [("planner-7", q) for q in (41, 42, 43, 44)]
    assert all(isinstance(r.message, msgs.ServiceError) and r.message.code == "bad_request" for r in replies)
    assert [r.message.text.split(" ")[:3] for r in replies][0] == ["header", "field", "'t'"]


def test_service_without_server_fails_fast_with_a_clear_error(buses: tuple[Bus, Bus]) -> None:
    client = buses[1].client("/absent", msgs.Empty, msgs.Empty)
    with pytest.raises(ServiceCallError, match="no server found"):
        client.call(msgs.Empty(), timeout_s=0.3)


def test_a_retried_request_runs_the_handler_once(buses: tuple[Bus, Bus]) -> None:
    a, b = buses
    calls = []

    def slow(request: msgs.GripperCommand) -> msgs.GripperState:
        calls.append(request.width_m)
        time.sleep(0.4)
        return msgs.GripperState(width_m=request.width_m)

    server = a.service("/slow", msgs.GripperCommand, msgs.GripperState, slow)
    with pumping(server):
        client = b.client("/slow", msgs.GripperCommand, msgs.GripperState)
        reply = client.call(msgs.GripperCommand(width_m=0.07), timeout_s=0.25, retries=3)
        time.sleep(0.5)
    assert reply.width_m == pytest.approx(0.07)
    assert calls == [0.07]
    assert server.counters.duplicates >= 1


def _keys(folder: Path, name: str) -> CurveConfig:
    zmq.auth.create_certificates(folder, name)
    return CurveConfig(secret_key_file=str(folder / f"{name}.key_secret"))


def test_tcp_with_curve_admits_known_clients_only(registry: Registry, tmp_path: Path) -> None:
    server_dir, clients_dir, strangers_dir = (tmp_path / d for d in ("server", "clients", "strangers"))
    for folder in (server_dir, clients_dir, strangers_dir):
        folder.mkdir()
    server_keys = _keys(server_dir, "server")
    client_keys = _keys(clients_dir, "planner")
    stranger_keys = _keys(strangers_dir, "stranger")
    server_config = CurveConfig(server_keys.secret_key_file, authorized_keys_dir=str(clients_dir))
    a = Bus("server", registry, TransportConfig(transport="tcp", curve=server_config))
    publisher = a.publisher("/estimates", msgs.Log)
    assert publisher.address.startswith("tcp://127.0.0.1:")
    friend = Bus("friend", registry, TransportConfig(curve=client_keys))
    stranger = Bus("stranger", registry, TransportConfig(curve=stranger_keys))
    heard = friend.subscriber("/estimates", msgs.Log)
    not_heard = stranger.subscriber("/estimates", msgs.Log)
    assert publisher.wait_for_subscribers(1, 5.0)
    time.sleep(0.3)
    publisher.publish(msgs.Log(text="secret"))
    got = heard.receive(5.0)
    assert got is not None and got.message.text == "secret"
    assert not_heard.receive(0.5) is None
    for bus in (a, friend, stranger):
        bus.close()


def test_missing_key_file_is_a_clear_error(registry: Registry, tmp_path: Path) -> None:
    config = CurveConfig(str(tmp_path / "absent.key_secret"), authorized_keys_dir=str(tmp_path))
    bus = Bus("x", registry, TransportConfig(transport="tcp", curve=config))
    with pytest.raises(SecurityError, match="not found"):
        bus.publisher("/t", msgs.Log)
    bus.close()


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_peer_on_another_machine_is_reached_through_the_launch_endpoints(tmp_path: Path) -> None:
    """Two registries stand for two machines: only the configured address and keys connect them."""
    keys = tmp_path / "keys"
    keys.mkdir()
    server_keys = _keys(keys, "robot_pc")
    client_keys = _keys(keys, "planner_pc")
    authorized = tmp_path / "authorized"
    authorized.mkdir()
    (authorized / "planner_pc.key").write_bytes((keys / "planner_pc.key").read_bytes())
    address = f"tcp://127.0.0.1:{_free_port()}"
    robot = Bus(
        "robot",
        Registry(tmp_path / "robot_machine"),
        TransportConfig(
            curve=CurveConfig(server_keys.secret_key_file, authorized_keys_dir=str(authorized)),
            endpoints={"/estimate": address, "/status": address.rsplit(":", 1)[0] + f":{_free_port()}"},
        ),
    )
    planner = Bus(
        "planner",
        Registry(tmp_path / "planner_machine"),
        TransportConfig(curve=client_keys, peers={"/estimate": PeerConfig(address, str(keys / "robot_pc.key"))}),
    )
    server = robot.service("/estimate", msgs.GripperCommand, msgs.GripperState, _double)
    assert server.address == address
    with pumping(server):
        reply = planner.client("/estimate", msgs.GripperCommand, msgs.GripperState).call(
            msgs.GripperCommand(width_m=0.25), timeout_s=5.0
        )
    assert reply.width_m == pytest.approx(0.5)
    robot.close()
    planner.close()


@pytest.fixture
def default_bus(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Where the default bus directory goes when the temporary directory is ``tmp_path``."""
    monkeypatch.delenv("DTX_BUS_DIR", raising=False)
    monkeypatch.setenv("DTX_DOMAIN", "rel")
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    return tmp_path / f"dtx-{os.getuid()}"


def test_the_default_bus_directory_is_private(default_bus: Path) -> None:
    registry = Registry()
    assert registry.root == default_bus / "rel"
    for path in (default_bus, default_bus / "rel", default_bus / "rel" / "sock"):
        assert path.stat().st_mode & 0o777 == 0o700, path


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a directory to another user needs root")
def test_a_bus_directory_another_user_made_first_is_refused(
    default_bus: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from bus.registry import BusDirectoryError
    from dtx.cli import main

    default_bus.mkdir(mode=0o700)
    os.chown(default_bus, 4242, 4242)
    with pytest.raises(BusDirectoryError, match="belongs to uid 4242, not to you"):
        Registry()
    assert main(["node", "list"]) == 2 and "belongs to uid 4242" in capsys.readouterr().err
    os.chown(default_bus, os.getuid(), os.getgid())
    default_bus.chmod(0o777)
    with pytest.raises(BusDirectoryError, match="writable by others"):
        Registry()
    default_bus.chmod(0o700)
    (default_bus / "rel").symlink_to(default_bus.parent)
    with pytest.raises(BusDirectoryError, match="not a directory"):
        Registry()
    explicit = default_bus.parent / "explicit"
    explicit.mkdir(mode=0o1777)
    explicit.chmod(0o1777)
    with pytest.raises(BusDirectoryError, match="writable by others"):
        Registry(explicit)


def test_a_flood_is_served_in_slices_and_logged_sparingly(registry: Registry, caplog: pytest.LogCaptureFixture) -> None:
    from bus.context import SLICE_MESSAGES

    bus = Bus("server", registry)
    server = bus.service("/echo", msgs.GripperCommand, msgs.GripperState, lambda r: msgs.GripperState())
    flooder = bus.context.socket(zmq.DEALER)
    flooder.connect(server.address)
    count = 3 * SLICE_MESSAGES
    for _ in range(count):
        flooder.send_multipart([b"/echo", b"\xc1 not msgpack"])
    deadline = time.monotonic() + 10.0
    while not server.sock.poll(100) and time.monotonic() < deadline:
        pass
    time.sleep(0.2)  # the whole flood is queued by now (local ipc)
    with caplog.at_level("WARNING", logger="dtx.bus"):
        served = []
        while server.counters.malformed < count and time.monotonic() < deadline:
            served.append(server.serve_ready())
    assert server.counters.malformed == count
    assert max(served) == SLICE_MESSAGES  # one slice per call, then the other sockets' turn
    assert len(caplog.records) <= 2  # reported once a second, not once a message
    flooder.close(linger=0)
    bus.close()


def test_a_publisher_refuses_an_oversized_message_before_allocating_it(registry: Registry) -> None:
    from bus.pubsub import MAX_SUBSCRIPTION_BYTES

    bus = Bus("camera", registry)
    publisher = bus.publisher("/camera/depth", msgs.DepthImage)
    assert publisher.sock.getsockopt(zmq.MAXMSGSIZE) == MAX_SUBSCRIPTION_BYTES
    attacker = bus.context.socket(zmq.XSUB)
    attacker.connect(publisher.address)
    # A "subscription" over the limit (not far over: libzmq 4.3.5's XSUB itself crashes sending
    # ~200 kB ones, in this process; the publisher, as measured from another process, does not).
    attacker.send(b"\x01" + bytes(MAX_SUBSCRIPTION_BYTES + 30_000))
    attacker.send(b"\x01/camera/depth")  # on a connection ZeroMQ has dropped by now
    listener = bus.subscriber("/camera/depth", msgs.DepthImage)
    assert publisher.wait_for_subscribers(1, 10.0)  # the honest subscriber still joins
    assert publisher.subscriptions == 1
    listener.close()
    attacker.close(linger=0)  # its queued 'subscription' can never be delivered
    bus.close()


def test_a_reused_request_number_with_other_content_is_refused_not_answered_from_the_cache(registry: Registry) -> None:
    from msgs.system import ServiceError

    bus = Bus("server", registry)
    server = bus.service("/echo", msgs.Log, msgs.Log, lambda r: msgs.Log(text=r.text))
    client = bus.context.socket(zmq.DEALER)
    client.connect(server.address)

    def ask(text: str) -> msgs.Message:
        client.send_multipart(encode("/echo", msgs.Log(text=text, header=msgs.Header(seq=7, stamp_ns=1)), "me"))
        deadline = time.monotonic() + 10.0
        while not client.poll(10) and time.monotonic() < deadline:
            server.serve_ready()
        return decode(client.recv_multipart()).message

    assert ask("first").text == "first"
    assert ask("first").text == "first" and server.counters.duplicates == 1  # a retry: from the cache
    refused = ask("second")
    assert isinstance(refused, ServiceError) and refused.code == "bad_request" and "already used" in refused.text
    client.close(linger=0)
    bus.close()


def test_an_oversized_request_is_refused_at_once_with_a_code(registry: Registry) -> None:
    server_bus = Bus("server", registry)
    server = server_bus.service("/echo", msgs.Log, msgs.Log, lambda r: msgs.Log(text=r.text))
    small = Bus("client", registry, TransportConfig(max_message_bytes=4096))
    with pumping(server):
        client = small.client("/echo", msgs.Log, msgs.Log)
        with pytest.raises(ServiceCallError) as refused:
            client.call(msgs.Log(text="x" * 10_000), timeout_s=30.0)
        assert refused.value.code == "request_too_large"
        assert client.call(msgs.Log(text="small"), timeout_s=30.0).text == "small"
    small.close()
    server_bus.close()


def test_the_entries_of_an_ended_process_are_forgotten_at_once(registry: Registry) -> None:
    """The launcher calls forget_process when a node ends, so a client in any language that
    reads the directory never picks the entry of a worker killed with -9."""
    mine = Endpoint("service", "/double", "ipc:///nowhere", "worker", 999_999_999, "dtx.x.Y")
    other = Endpoint("service", "/double", "ipc:///elsewhere", "worker", os.getpid(), "dtx.x.Y")
    dead, alive = registry.advertise(mine), registry.advertise(other)
    assert registry.forget_process(999_999_999) == 1
    assert not dead.exists() and alive.exists()


FIXTURE_NODES = Path(__file__).parent / "launch_fixtures"


def start_fixture_node(name: str, params: str) -> "subprocess.Popen[bytes]":
    """A counter node (tests/launch_fixtures) in a process of its own, on this test's bus."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(FIXTURE_NODES), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(
        [sys.executable, "-m", "fixture_nodes", "--name", name, "--params", params],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def kill_mid_call(server: "subprocess.Popen[bytes]") -> threading.Thread:
    """SIGKILL ``server`` a second after the caller found it (its request is in flight by then,
    held for hold_s), then reap it as a launcher does (a zombie's pid still answers kill(pid, 0))."""

    def kill() -> None:
        time.sleep(1.0)  # the call has been sent by then; a held request never answers before hold_s
        server.kill()
        server.wait()

    thread = threading.Thread(target=kill, daemon=True)
    thread.start()
    return thread


def test_a_call_whose_server_is_killed_fails_fast_with_server_died(registry: Registry) -> None:
    """Killing a server mid-call used to cost the caller its whole time-out (the patch
    extractor killed during registration stalled a session 60 s)."""
    server = start_fixture_node("holder", '{"hold_s": 600}')
    bus = Bus("caller", registry)
    try:
        client = bus.client("/hold", msgs.GripperCommand, msgs.GripperState)
        assert client.wait_for_service(60)
        timeout_s = 40.0
        killer = kill_mid_call(server)
        started = time.monotonic()
        with pytest.raises(ServiceCallError) as failure:
            client.call(msgs.GripperCommand(width_m=0.01), timeout_s=timeout_s, retries=0)
        waited = time.monotonic() - started
        killer.join()
        assert failure.value.code == "server_died", failure.value
        assert str(server.pid) in failure.value.text
        assert waited < timeout_s / 4  # a generous bound: the check runs every 0.25 s
    finally:
        server.kill()
        server.wait()
        bus.close()


def test_a_call_whose_server_is_killed_is_answered_by_its_respawn(registry: Registry) -> None:
    """The next attempt goes to the server that replaces the dead one, at once."""
    first = start_fixture_node("holder", '{"hold_s": 600}')
    bus = Bus("caller", registry)
    second = None
    try:
        client = bus.client("/hold", msgs.GripperCommand, msgs.GripperState)
        assert client.wait_for_service(60)

        def respawn() -> None:
            nonlocal second
            kill_mid_call(first).join()
            second = start_fixture_node("holder", '{"hold_s": 0}')

        threading.Thread(target=respawn, daemon=True).start()
        timeout_s = 60.0
        started = time.monotonic()
        reply = client.call(msgs.GripperCommand(width_m=0.01), timeout_s=timeout_s, retries=1)
        assert second is not None and reply.state == f"held by {second.pid}"
        assert time.monotonic() - started < timeout_s / 2  # not after the first attempt's time-out
    finally:
        for process in (first, second):
            if process is not None:
                process.kill()
                process.wait()
        bus.close()


def test_a_node_asked_to_stop_cancels_its_calls(registry: Registry) -> None:
    from bus.node import Node

    server = start_fixture_node("holder", '{"hold_s": 600}')
    node = Node("caller", registry=registry)
    try:
        client = node.create_client("/hold", msgs.GripperCommand, msgs.GripperState)
        assert client.wait_for_service(60)
        threading.Timer(1.0, node.request_shutdown).start()
        with pytest.raises(ServiceCallError) as failure:
            client.call(msgs.GripperCommand(width_m=0.01), timeout_s=120.0, retries=0)
        assert failure.value.code == "cancelled"
        assert server.poll() is None  # the server lives on; only the caller stopped waiting
    finally:
        server.kill()
        server.wait()
        node.close()


def test_frames_of_every_size_cross_a_socket_whole_and_in_order(tmp_path: Path) -> None:
    """send_frames copies small frames and hands large ones over without copying; recv_frames
    gathers one message's frames by their more-flags. Both ends see the same bytes."""
    from bus.context import ZERO_COPY_BYTES, recv_frames, send_frames

    context = zmq.Context()
    push, pull = context.socket(zmq.PUSH), context.socket(zmq.PULL)
    try:
        push.bind(f"ipc://{tmp_path}/frames.sock")
        pull.connect(f"ipc://{tmp_path}/frames.sock")
        large = np.arange(ZERO_COPY_BYTES * 2, dtype=np.uint8) % 251
        first = [b"/topic", b"", large.data.cast("B"), memoryview(b"tail")]
        second = [b"alone"]
        send_frames(push, first)
        send_frames(push, second)
        assert pull.poll(5000)
        assert [f.bytes for f in recv_frames(pull)] == [bytes(f) for f in first]
        assert [f.bytes for f in recv_frames(pull)] == second
        with pytest.raises(zmq.Again):
            recv_frames(pull, zmq.NOBLOCK)
    finally:
        context.destroy(linger=0)


def test_bench_bus_work_puts_dtx_beside_raw_pyzmq_for_each_payload() -> None:
    import argparse

    from benchmarks.bus import PAYLOADS, run

    rows = run(argparse.Namespace(work=True, repeats=1))
    assert [(r["impl"], r["payload_bytes"]) for r in rows] == [
        (impl, size) for size in PAYLOADS for impl in ("raw_pyzmq", "dtx")
    ]
    figures = ("send_us", "receive_us", "idle_send_us", "idle_receive_us")
    assert all(0 < r[key] < math.inf for r in rows for key in figures)
