"""Wire form of a message: multipart frames ``[topic, header, buffer...]``.

The header is msgpack: schema name and version, stamp (ns), sequence number, frame id, the
publisher id, the message's plain field values, and for each array its dtype and shape. Each
array travels as its own raw frame, so large arrays are sent without copying (ZeroMQ's
zero-copy path) and received as read-only views of the frame. Nothing is ever pickled.

Decoding trusts nothing: every check that can fail raises :class:`MessageError`, one error
type for callers to catch, with a sentence that says what was wrong.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from typing import Any

import msgpack
import numpy as np

from msgs.base import MESSAGE_TYPES, Header, Message

DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_HEADER_BYTES = 1024 * 1024
MAX_ARRAYS = 64
MAX_NDIM = 8
# No dimension may exceed the largest message: with a zero elsewhere in the shape the byte count
# still matches an empty buffer, and NumPy refuses such shapes with its own error.
MAX_DIMENSION = DEFAULT_MAX_MESSAGE_BYTES
# Only plain little-endian numeric types cross the bus: no objects, no strings, no records.
ALLOWED_DTYPES = frozenset(["|b1", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8"])
_ARRAY_REF = "__array__"
_HEADER_FIELDS = (("s", str), ("v", int), ("t", int), ("q", int), ("f", str), ("p", str), ("d", dict), ("a", list))


class MessageError(ValueError):
    """A frame sequence that is not a valid message (or a message that cannot be sent)."""


@dataclasses.dataclass(frozen=True)
class Envelope:
    """A decoded message with the wire facts around it."""

    topic: str
    message: Message
    publisher: str
    size_bytes: int


def encode(topic: str, message: Message, publisher: str = "", header: Header | None = None) -> list[Any]:
    """Frames for ``message`` on ``topic``: bytes for the topic and header, arrays as buffers.
    ``header``: the one to send in place of ``message.header`` (a publisher's stamp and sequence
    number), so that no copy of the message is made per send."""
    if not isinstance(message, Message) or not message.SCHEMA:
        raise MessageError(f"cannot send {type(message).__name__}: not a registered msgs type")
    arrays: list[np.ndarray] = []
    values = _flatten(message, arrays, path=type(message).__name__, skip_header=True)
    header = message.header if header is None else header
    wire_header = {
        "s": message.SCHEMA,
        "v": message.VERSION,
        "t": int(header.stamp_ns),
        "q": int(header.seq),
        "f": header.frame_id,
        "p": publisher,
        "d": values,
        "a": [[a.dtype.str, list(a.shape)] for a in arrays],
    }
    # Arrays are laid out C-contiguous so that the receiver's frombuffer(shape) is exact.
    buffers = [np.ascontiguousarray(a).data.cast("B") if a.size else b"" for a in arrays]
    return [topic.encode(), msgpack.packb(wire_header, use_bin_type=True), *buffers]


def decode(frames: typing.Sequence[Any], max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Envelope:
    """Validate and decode frames (bytes, memoryviews or zmq.Frame) into an :class:`Envelope`."""
    if len(frames) < 2:
        raise MessageError(f"expected at least 2 frames (topic, header), got {len(frames)}")
    views = [_as_view(f) for f in frames]
    size = sum(v.nbytes for v in views)
    if size > max_bytes:
        raise MessageError(f"message of {size} bytes exceeds the limit of {max_bytes} bytes")
    try:
        topic = bytes(views[0]).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MessageError("topic frame is not UTF-8") from exc
    if views[1].nbytes > MAX_HEADER_BYTES:
        raise MessageError(f"header of {views[1].nbytes} bytes exceeds {MAX_HEADER_BYTES} bytes")
    try:
        header = msgpack.unpackb(views[1], raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise MessageError(f"header is not valid msgpack: {exc}") from exc
    if not isinstance(header, dict):
        raise MessageError("header is not a map")
    for key, kind in _HEADER_FIELDS:
        if type(header.get(key)) is not kind:  # msgpack gives exact types; a bool is no int
            raise MessageError(f"header field {key!r} missing or not {kind.__name__}")
    cls = MESSAGE_TYPES.get(header["s"])
    if cls is None:
        raise MessageError(f"unknown schema {header['s']!r}")
    if header["v"] != cls.VERSION:
        raise MessageError(
            f"{header['s']} version {header['v']} is incompatible with this build's version {cls.VERSION}"
        )
    if header["t"] < 0 or header["q"] < 0:
        raise MessageError("stamp and sequence number must be non-negative")
    specs = header["a"]
    if len(specs) > MAX_ARRAYS:
        raise MessageError(f"{len(specs)} arrays exceed the limit of {MAX_ARRAYS}")
    if len(views) != 2 + len(specs):
        raise MessageError(f"header announces {len(specs)} arrays but {len(views) - 2} buffers came")
    try:
        message = _message_from(cls, header, specs, views[2:])
    except MessageError:
        raise
    except Exception as exc:  # whatever a check above missed is still the sender's fault, never ours
        raise MessageError(f"{header['s']}: cannot be built from its fields ({type(exc).__name__}: {exc})") from exc
    return Envelope(topic=topic, message=message, publisher=header["p"], size_bytes=size)


def _message_from(cls: type, header: dict[str, Any], specs: list[Any], buffers: list[memoryview]) -> Message:
    arrays = [_array_from(spec, view, i) for i, (spec, view) in enumerate(zip(specs, buffers))]
    used: set[int] = set()
    fields = _unflatten(cls, header["d"], arrays, used, path=cls.__name__, top=True)
    if len(used) != len(arrays):
        raise MessageError(f"{len(arrays) - len(used)} buffers are not referenced by any field")
    return cls(header=Header(stamp_ns=header["t"], seq=header["q"], frame_id=header["f"]), **fields)


def _as_view(frame: Any) -> memoryview:
    buffer = getattr(frame, "buffer", frame)  # zmq.Frame exposes its memory as .buffer
    try:
        return memoryview(buffer).cast("B")
    except TypeError as exc:
        raise MessageError(f"frame of type {type(frame).__name__} is not a byte buffer") from exc


def _array_from(spec: Any, view: memoryview, index: int) -> np.ndarray:
    if not (isinstance(spec, list) and len(spec) == 2 and isinstance(spec[0], str) and isinstance(spec[1], list)):
        raise MessageError(f"array {index}: spec must be [dtype, shape]")
    dtype_str, shape = spec
    if not set(map(type, shape)) <= {int}:  # exact ints: no bool, no float, nothing unhashable
        raise MessageError(f"array {index}: shape {shape} must be at most {MAX_NDIM} non-negative ints")
    dtype, expected = _array_layout(dtype_str, tuple(shape), index)
    if expected != view.nbytes:
        raise MessageError(
            f"array {index}: shape {shape} of {dtype_str} needs {expected} bytes, buffer has {view.nbytes}"
        )
    return np.frombuffer(view, dtype=dtype).reshape(shape)


@functools.lru_cache(maxsize=256)
def _array_layout(dtype_str: str, shape: tuple[int, ...], index: int) -> tuple[np.dtype, int]:
    """(dtype, byte count) of an array spec whose dimensions are ints, or MessageError. Cached:
    a stream repeats a few layouts, and a checked one need not be checked again per message
    (a refused one raises, and is not cached)."""
    if dtype_str not in ALLOWED_DTYPES:
        raise MessageError(f"array {index}: dtype {dtype_str!r} not allowed (allowed: {sorted(ALLOWED_DTYPES)})")
    if len(shape) > MAX_NDIM or not all(d >= 0 for d in shape):
        raise MessageError(f"array {index}: shape {list(shape)} must be at most {MAX_NDIM} non-negative ints")
    if any(d > MAX_DIMENSION for d in shape):
        raise MessageError(f"array {index}: shape {list(shape)} has a dimension above {MAX_DIMENSION}")
    dtype = np.dtype(dtype_str)
    return dtype, dtype.itemsize * math.prod(shape)


def _flatten(obj: Any, arrays: list[np.ndarray], path: str, skip_header: bool = False) -> Any:
    # Ordered by how often each kind occurs in sensor messages; this runs on every publish.
    if isinstance(obj, np.ndarray):
        if obj.dtype.str not in ALLOWED_DTYPES:
            little = obj.dtype.newbyteorder("<")
            if little.str not in ALLOWED_DTYPES:
                raise MessageError(f"{path}: dtype {obj.dtype} cannot be sent")
            obj = obj.astype(little)
        arrays.append(obj)
        return {_ARRAY_REF: len(arrays) - 1}
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise MessageError(f"{path}: non-finite number {obj} cannot be sent in a header")
        return obj
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, (list, tuple)):
        return [_flatten(v, arrays, f"{path}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, dict):
        if not all(isinstance(k, str) for k in obj):
            raise MessageError(f"{path}: map keys must be strings")
        return {k: _flatten(v, arrays, f"{path}.{k}") for k, v in obj.items()}
    if isinstance(obj, np.generic):
        return _flatten(obj.item(), arrays, path)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            name: _flatten(getattr(obj, name), arrays, f"{path}.{name}")
            for name in _field_names(type(obj))
            if not (skip_header and name == "header")
        }
    raise MessageError(f"{path}: values of type {type(obj).__name__} cannot be sent")


@functools.cache
def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


Converter = typing.Callable[[Any, list[np.ndarray], set[int], str], Any]


@functools.cache
def _plan(cls: type, with_header: bool) -> tuple[tuple[str, Converter], ...]:
    """For each field of ``cls``, the function that checks and converts its wire value."""
    hints = typing.get_type_hints(cls)
    return tuple((name, _converter(hints[name])) for name in _field_names(cls) if with_header or name != "header")


def _unflatten(
    cls: type, values: Any, arrays: list[np.ndarray], used: set[int], path: str, top: bool = False
) -> dict[str, Any]:
    """Field values of ``cls`` from the header map; the top-level message's header travels apart."""
    if not isinstance(values, dict):
        raise MessageError(f"{path}: expected a map of fields")
    plan = _plan(cls, with_header=not top)
    if len(values) != len(plan) or any(name not in values for name, _ in plan):
        names = {name for name, _ in plan}
        raise MessageError(f"{path}: fields {sorted(values)} do not match {cls.__name__}'s {sorted(names)}")
    return {name: convert(values[name], arrays, used, f"{path}.{name}") for name, convert in plan}


@functools.cache
def _converter(annotation: Any) -> Converter:
    origin = typing.get_origin(annotation)
    if annotation is np.ndarray:

        def array(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> np.ndarray:
            index = value.get(_ARRAY_REF) if isinstance(value, dict) and len(value) == 1 else None
            if not isinstance(index, int) or isinstance(index, bool):
                raise MessageError(f"{path}: expected an array reference")
            if not 0 <= index < len(arrays) or index in used:
                raise MessageError(f"{path}: array reference {index} is invalid or used twice")
            used.add(index)
            return arrays[index]

        return array
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):

        def nested(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> Any:
            return annotation(**_unflatten(annotation, value, arrays, used, path))

        return nested
    if annotation is float:

        def number(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> float:
            kind = type(value)  # exact types: msgpack gives int, float or bool (not a number)
            if kind is not float and kind is not int:
                raise MessageError(f"{path}: expected a number, got {kind.__name__}")
            if not math.isfinite(value):
                raise MessageError(f"{path}: non-finite number")
            return float(value)

        return number
    if annotation in (int, str, bool):

        def exact(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> Any:
            if type(value) is not annotation:
                raise MessageError(f"{path}: expected {annotation.__name__}, got {type(value).__name__}")
            return value

        return exact
    if origin is list:
        item = _converter(typing.get_args(annotation)[0])

        def sequence(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> list[Any]:
            if not isinstance(value, list):
                raise MessageError(f"{path}: expected a list")
            return [item(v, arrays, used, f"{path}[{i}]") for i, v in enumerate(value)]

        return sequence
    if origin is dict:
        item = _converter(typing.get_args(annotation)[1])

        def mapping(value: Any, arrays: list[np.ndarray], used: set[int], path: str) -> dict[str, Any]:
            if not isinstance(value, dict):
                raise MessageError(f"{path}: expected a map")
            return {k: item(v, arrays, used, f"{path}.{k}") for k, v in value.items()}

        return mapping
    raise TypeError(f"field type {annotation} is not supported on the wire")
