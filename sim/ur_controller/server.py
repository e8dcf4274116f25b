"""The fake UR controller's process: :class:`FakeURController` starts it and talks to it over a
pipe; inside, the controller core (:mod:`sim.ur_controller.controller`) ticks at the state
rate and each interface accepts its clients on its own port of one loopback address (RTDE:
:mod:`sim.ur_controller.rtde`, dashboard: :mod:`sim.ur_controller.dashboard`, script:
:mod:`sim.ur_controller.script`).

The fake runs in its own (spawned) process, so its ticks keep the controller's pace whatever
the client's process does; tests drive it through :class:`FakeURController`. Every fake gets its own 127.x.y.z
address because the client's ports are fixed.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import socket
import threading
import time
from typing import Any, Callable, Sequence

from sim.ur_controller.controller import HOME_Q, Controller
from sim.ur_controller.dashboard import DASHBOARD_PORT, serve_dashboard
from sim.ur_controller.rtde import RTDE_PORT, serve_rtde
from sim.ur_controller.script import SCRIPT_PORT, serve_script
from sim.ur_controller.versions import DEFAULT_VERSION, SoftwareVersion


def _accept_loop(controller: Controller, listener: socket.socket, serve: Callable[[socket.socket], None]) -> None:
    while controller.running:
        try:
            sock, _ = listener.accept()
        except socket.timeout:
            continue
        except OSError:
            return  # the listener was closed by cut() or shutdown
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with controller.lock:
            controller.sockets.append(sock)
        threading.Thread(target=serve, args=(sock,), daemon=True).start()


def _listen(host: str, port: int) -> socket.socket:
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind((host, port))
    listener.listen(8)
    listener.settimeout(0.2)
    return listener


def _controller_process(
    pipe: multiprocessing.connection.Connection,
    host: str,
    state_rate_hz: float,
    initial_q: Sequence[float],
    version: SoftwareVersion,
) -> None:
    """Entry point of the fake's process: serve the ports, tick, and obey the test's pipe."""
    controller = Controller(host, state_rate_hz, initial_q, version)
    try:
        servers = {RTDE_PORT: serve_rtde, DASHBOARD_PORT: serve_dashboard, SCRIPT_PORT: serve_script}
        for port, serve in servers.items():
            listener = _listen(host, port)
            controller.listeners.append(listener)
            threading.Thread(
                target=_accept_loop, daemon=True, args=(controller, listener, lambda s, f=serve: f(controller, s))
            ).start()
    except OSError as error:
        pipe.send(("error", f"cannot listen on {host}: {error}"))
        return
    threading.Thread(target=_tick_loop, args=(controller,), daemon=True).start()
    pipe.send(("ready", None))
    actions: dict[str, Callable[[Any], Any]] = {
        "snapshot": lambda _: controller.snapshot(),
        "safety": controller.set_safety,
        "speed_slider": controller.set_speed_slider,
        "remote_control": lambda remote: controller.set_remote_control(bool(remote)),
        "cut": lambda _: controller.cut(),
        "fault": lambda fault_and_command: controller.inject_fault(*fault_and_command),
        "shutdown": lambda _: _shut_down(controller),
    }
    while controller.running:
        request, argument = pipe.recv()
        try:
            pipe.send(("ok", actions[request](argument)))
        except ValueError as error:  # a request this controller cannot carry out
            pipe.send(("error", str(error)))


def _shut_down(controller: Controller) -> None:
    controller.running = False
    controller.cut()


def _tick_loop(controller: Controller) -> None:
    """Tick at the state rate on a fixed schedule; after a stall, resume without bursts."""
    next_tick = time.monotonic()
    while controller.running:
        controller.tick()
        next_tick += controller.dt
        delay = next_tick - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_tick = time.monotonic()


class FakeURController:
    """Handle on a fake UR controller running in its own process on ``host`` (127.x.y.z).

    ``software_version`` is the PolyScope version it runs, e.g. "3.15" (CB3), "5.4" or "5.20"
    (e-Series; :mod:`sim.ur_controller.versions`); ``state_rate_hz`` defaults to the fastest
    RTDE rate of that version. Use as a context manager; ``start()`` raises OSError if the
    address is taken.
    """

    def __init__(
        self,
        host: str,
        state_rate_hz: float | None = None,
        initial_q: Sequence[float] = HOME_Q,
        software_version: str | None = None,
    ) -> None:
        self.host = host
        self.version = DEFAULT_VERSION if software_version is None else SoftwareVersion.parse(software_version)
        self.state_rate_hz = self.version.max_rtde_frequency_hz if state_rate_hz is None else state_rate_hz
        self.initial_q = tuple(float(v) for v in initial_q)
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe: multiprocessing.connection.Connection | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        context = multiprocessing.get_context("spawn")
        self._pipe, child_pipe = context.Pipe()
        self._process = context.Process(
            target=_controller_process,
            daemon=True,
            name=f"fake-ur-{self.host}",
            args=(child_pipe, self.host, self.state_rate_hz, self.initial_q, self.version),
        )
        self._process.start()
        child_pipe.close()
        if not self._pipe.poll(timeout_s):
            self.close()
            raise TimeoutError(f"fake UR controller on {self.host} did not start in {timeout_s} s")
        status, message = self._pipe.recv()
        if status != "ready":
            self.close()
            raise OSError(message)

    def snapshot(self) -> dict[str, Any]:
        """Joints (rad), TCP pose, safety, program state, the command register (0 once
        the client has finished a command), received commands (``time.monotonic_ns()`` at
        receipt, command number) and an event log."""
        return self._request("snapshot")

    def set_safety(self, safety: str) -> None:
        """Enter "protective_stop" or "emergency_stop" (motion halts), or back to "normal"."""
        self._request("safety", safety)

    def set_speed_slider(self, fraction: float) -> None:
        """The pendant's speed slider, 0-1: motions run at this fraction of their speed."""
        self._request("speed_slider", fraction)

    def set_remote_control(self, remote: bool) -> None:
        """Remote control (True) or local control (False) on the pendant of an e-Series
        controller; ValueError on a CB3, which has neither."""
        self._request("remote_control", remote)

    def inject_fault(self, fault: str, command: int = 0) -> None:
        """Make the controller fail to answer the next ``command`` (a command number; 0 for
        the dashboard's stop) the way ``fault`` says: "lose_command", "brief_done",
        "cut_on_command" or "refuse_dashboard_stop" (:mod:`sim.ur_controller.controller`)."""
        self._request("fault", (fault, command))

    def cut_connections(self) -> None:
        """Drop all client connections and refuse new ones."""
        self._request("cut")

    def close(self) -> None:
        if self._process is None:
            return
        if self._process.is_alive() and self._pipe is not None:
            try:
                self._request("shutdown")
            except (OSError, EOFError):
                pass
        self._process.join(timeout=5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        if self._pipe is not None:
            self._pipe.close()
        self._process = None

    def _request(self, request: str, argument: Any = None) -> Any:
        assert self._pipe is not None, "start() the fake controller first"
        self._pipe.send((request, argument))
        if not self._pipe.poll(10.0):
            raise TimeoutError(f"fake UR controller on {self.host} did not answer {request!r}")
        status, value = self._pipe.recv()
        if status == "error":
            raise ValueError(value)
        return value

    def __enter__(self) -> "FakeURController":
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
