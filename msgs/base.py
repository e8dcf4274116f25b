"""Message base: a typed, versioned dataclass with a header.

Every message class declares ``SCHEMA`` (a dotted name, unique on the bus) and ``VERSION``
(an integer bumped on any incompatible change). Fields are either plain values that travel
in the msgpack header (int, float, str, bool, lists/dicts of them) or ``numpy.ndarray``
values that travel as raw buffers beside it. See ``msgs.codec`` for the wire form.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, ClassVar

import numpy as np

MESSAGE_TYPES: dict[str, type["Message"]] = {}


@dataclasses.dataclass
class Header:
    """Stamp (ns since the Unix epoch, or simulated clock), sequence number, frame id."""

    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""

    @staticmethod
    def now(frame_id: str = "") -> "Header":
        return Header(stamp_ns=time.time_ns(), frame_id=frame_id)


@dataclasses.dataclass
class Message:
    SCHEMA: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1

    header: Header = dataclasses.field(default_factory=Header)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.SCHEMA:
            if cls.SCHEMA in MESSAGE_TYPES and MESSAGE_TYPES[cls.SCHEMA] is not cls:
                raise TypeError(f"message schema {cls.SCHEMA!r} defined twice")
            MESSAGE_TYPES[cls.SCHEMA] = cls


def empty(shape: tuple[int, ...] = (0,), dtype: Any = np.float32) -> Any:
    """Default factory helper for array fields."""
    return dataclasses.field(default_factory=lambda: np.zeros(shape, dtype=dtype))
