"""Hardware backends, one package per device kind (LeRobot style).

Every backend keeps the contract of :class:`Device`: ``connect()`` opens and checks the
device, ``read()`` returns its latest message, ``disconnect()`` releases it, and it works as
a context manager. Every call that waits on the device has a deadline, set in the backend's
config: it returns or raises the kind's error (a :class:`DeviceTimeoutError` when the device
did not answer in time) within it, so no node can block forever on a silent device. Each ``drivers/<kind>/`` declares its kind's contract in ``base.py``
(:class:`Device` plus the kind's commands and return types), holds the real backends and the
simulated one side by side behind it, and exposes ``make_backend(params)``:
``params["backend"]`` picks the class, the remaining keys fill its config dataclass
(msgs.config). Backends are imported only when chosen, so a lab without OpenNI2 can still run
the GelSight, and the simulation needs no hardware library at all.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import importlib
import queue
import threading
from collections.abc import Callable
from typing import Any, ClassVar, Self, TypeVar

from msgs.config import ConfigError, config_from_dict


class DeviceError(RuntimeError):
    """A device failure told to people: ``reason`` says what is wrong and, where an operator
    can act on it, ``fix`` says what to do (``dtx hw check`` prints them on a line each)."""

    def __init__(self, reason: str, fix: str = "") -> None:
        super().__init__(f"{reason}; fix: {fix}" if fix else reason)
        self.reason = reason
        self.fix = fix


class DeviceNotConnectedError(DeviceError):
    """A device read or commanded before ``connect()`` or after ``disconnect()``."""


class DeviceTimeoutError(DeviceError):
    """A device did not answer a call within the call's deadline."""


T = TypeVar("T")


def call_with_deadline(
    call: Callable[[], T],
    deadline_s: float,
    what: str,
    timeout_error: type[DeviceError] = DeviceTimeoutError,
    on_return: Callable[[], None] | None = None,
) -> T:
    """``call()``'s result or error if it comes within ``deadline_s``, else ``timeout_error``.

    For vendor calls that wait on the device with no deadline of their own (or one of minutes,
    as ur_rtde's 300 s): the call runs in a daemon thread and is abandoned when late, so it
    must release the GIL while it waits (pybind11 bindings that declare ``gil_scoped_release``
    do). ``on_return`` runs in that thread when the call really returns, late or not: the
    place to release a lock that must stay held while the device may still act on the call.
    """
    outcome: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()

    def run() -> None:
        try:
            outcome.put((True, call()))
        except BaseException as error:  # noqa: BLE001 - handed to the waiting thread, which raises it
            outcome.put((False, error))
        finally:
            if on_return is not None:
                on_return()

    threading.Thread(target=run, name=f"deadline: {what}", daemon=True).start()
    try:
        returned, value = outcome.get(timeout=deadline_s)
    except queue.Empty:
        raise timeout_error(f"{what}: no answer within {deadline_s:g} s") from None
    if returned:
        return value  # type: ignore[no-any-return]
    raise value


class Device(abc.ABC):
    """What every backend of every kind does; the kind's ``base.py`` adds its commands and
    names its not-connected error (a DeviceNotConnectedError that is also the kind's error,
    so a node catching the kind's errors catches it too)."""

    NOT_CONNECTED: ClassVar[type[DeviceNotConnectedError]] = DeviceNotConnectedError

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool:
        """True between a successful ``connect()`` and ``disconnect()``."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the device and check it can work; raise the kind's error, with the fix, if not.
        Like every call that waits on the device, it ends within the deadline its config sets."""

    @abc.abstractmethod
    def read(self) -> Any:
        """The device's latest state or frame, as the message its node publishes."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the device; safe to call twice or after a failed ``connect()``."""

    def identify(self) -> str:
        """What the connected device reports about itself (model, software version), for
        ``dtx hw check``; empty where it reports nothing."""
        return ""

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.disconnect()


F = TypeVar("F", bound=Callable[..., Any])


def requires_connection(method: F) -> F:
    """Make a device method raise DeviceNotConnectedError unless the device is connected."""

    @functools.wraps(method)
    def checked(self: Device, *args: Any, **kwargs: Any) -> Any:
        if not self.is_connected:
            raise type(self).NOT_CONNECTED(
                f"{type(self).__name__}.{method.__name__}: the device is not connected; call connect() first"
            )
        return method(self, *args, **kwargs)

    return checked  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class BackendEntry:
    """Where a backend lives: ``module`` holds both ``backend_class`` and ``config_class``."""

    module: str
    backend_class: str
    config_class: str


D = TypeVar("D", bound=Device)


def build_backend(
    contract: type[D], kind: str, params: dict[str, Any], backends: dict[str, BackendEntry], **extras: Any
) -> D:
    """Build the ``kind`` backend ``params["backend"]`` names, its config from the other params;
    ``extras`` are handed to the backend's constructor beside the config. The backend keeps
    ``contract`` (the kind's :class:`Device` subclass).

    Raises ValueError naming the allowed backends, or (msgs.config.ConfigError) the key and
    what it allows when ``params`` asks for something that does not exist or has the wrong type.
    """
    remaining = dict(params)
    choice = remaining.pop("backend", None)
    if choice not in backends:
        raise ValueError(f"{kind}: unknown backend {choice!r}; allowed: {sorted(backends)}")
    entry = backends[choice]
    module = importlib.import_module(entry.module)
    try:
        config = config_from_dict(getattr(module, entry.config_class), remaining)
    except ConfigError as exc:
        raise ConfigError(f"{kind} backend {choice!r}: {exc}") from None
    backend = getattr(module, entry.backend_class)(config, **extras)
    if not isinstance(backend, contract):
        raise TypeError(f"{entry.module}.{entry.backend_class} does not keep the {contract.__name__} contract")
    return backend
