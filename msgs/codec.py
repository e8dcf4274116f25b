"""Wire form of a message: multipart frames ``[topic, header, buffer...]``.

The header is msgpack: schema name and version, stamp (ns), sequence number, frame id, the
publisher id, the message's plain field values, and for each array its dtype and shape. Each
array travels as its own raw frame, so large arrays are sent without copying (ZeroMQ's
zero-copy path) and received as views of the frame. Nothing is ever pickled.

Decoding trusts nothing: every check that can fail raises :class:`MessageError`, one error
type for callers to catch, with a sentence that says what was wrong and in which field.

Both directions run on every message of every node, so their Python work per message is kept
small (issue 18: a paced sensor message finds the interpreter's caches cold, and then each
call costs several times its warm price): per-class plans are computed once, exact-type checks
come first, and the path of a refused field is put together only when something is refused.
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
_WIRE_DTYPES = {np.dtype(name): name for name in ALLOWED_DTYPES}
_ARRAY_REF = "__array__"
_HEADER_FIELDS = (("s", str), ("v", int), ("t", int), ("q", int), ("f", str), ("p", str), ("d", dict), ("a", list))
_HEADER_KEYS = tuple(key for key, _ in _HEADER_FIELDS)
_HEADER_KINDS = tuple(kind for _, kind in _HEADER_FIELDS)


class MessageError(ValueError):
    """A frame sequence that is not a valid message (or a message that cannot be sent)."""


class _Refused(Exception):
    """A value refused inside a message: ``what`` was wrong, ``where`` the field path below the
    message, which each level adds to as the error passes (paths cost nothing until then)."""

    def __init__(self, what: str, where: str = "") -> None:
        super().__init__(what)
        self.what, self.where = what, where

    def inside(self, step: str) -> _Refused:
        return _Refused(self.what, step + self.where)

    def error(self, message_type: type) -> MessageError:
        return MessageError(f"{message_type.__name__}{self.where}: {self.what}")


class Envelope(typing.NamedTuple):
    """A decoded message with the wire facts around it (a tuple: immutable, and made on every
    message at a third of a frozen dataclass's cost)."""

    topic: str
    message: Message
    publisher: str
    size_bytes: int


# -- encoding -----------------------------------------------------------------------------


def encode(topic: str, message: Message, publisher: str = "", header: Header | None = None) -> list[Any]:
    """Frames for ``message`` on ``topic``: bytes for the topic and header, arrays as buffers.
    ``header``: the one to send in place of ``message.header`` (a publisher's stamp and sequence
    number), so that no copy of the message is made per send."""
    cls: type = type(message)
    names = _SENT_FIELDS.get(cls)
    if names is None:
        if not isinstance(message, Message) or not message.SCHEMA:
            raise MessageError(f"cannot send {cls.__name__}: not a registered msgs type")
        names = _SENT_FIELDS[cls] = tuple(n for n in _field_names(cls) if n != "header")
    arrays: list[np.ndarray] = []
    try:
        values = _flatten_fields(message, names, arrays)
    except _Refused as exc:
        raise exc.error(cls) from None
    header = message.header if header is None else header
    wire_header = {
        "s": message.SCHEMA,
        "v": message.VERSION,
        "t": int(header.stamp_ns),
        "q": int(header.seq),
        "f": header.frame_id,
        "p": publisher,
        "d": values,
        "a": [[_WIRE_DTYPES[a.dtype], list(a.shape)] for a in arrays],
    }
    # Arrays are laid out C-contiguous so that the receiver's (shape, buffer) view is exact.
    buffers = [np.ascontiguousarray(a).data.cast("B") if a.size else b"" for a in arrays]
    return [topic.encode(), msgpack.packb(wire_header, use_bin_type=True), *buffers]


# Field names sent in the header map, per message class (its header travels apart) and per
# nested dataclass (all of them).
_SENT_FIELDS: dict[type, tuple[str, ...]] = {}
_DATACLASS_FIELDS: dict[type, tuple[str, ...]] = {}


def _flatten_fields(obj: Any, names: tuple[str, ...], arrays: list[np.ndarray]) -> dict[str, Any]:
    flat = {}
    for name in names:
        value = getattr(obj, name)
        kind = type(value)
        # Arrays and plain values, nearly every field, are taken here: a call per field costs
        # more than the field.
        if kind is np.ndarray and value.dtype in _WIRE_DTYPES:
            arrays.append(value)
            flat[name] = {_ARRAY_REF: len(arrays) - 1}
        elif kind is int or kind is str or kind is bool or (kind is float and math.isfinite(value)):
            flat[name] = value
        else:
            try:
                flat[name] = _flatten(value, arrays)
            except _Refused as exc:
                raise exc.inside(f".{name}") from None
    return flat


def _flatten_map(values: dict[str, Any], arrays: list[np.ndarray]) -> dict[str, Any]:
    flat = {}
    for key, value in values.items():
        try:
            flat[key] = _flatten(value, arrays)
        except _Refused as exc:
            raise exc.inside(f".{key}") from None
    return flat


def _flatten_list(values: list[Any] | tuple[Any, ...], arrays: list[np.ndarray]) -> list[Any]:
    flat = []
    for i, value in enumerate(values):
        kind = type(value)
        if kind is int or kind is str or kind is bool or (kind is float and math.isfinite(value)):
            flat.append(value)  # as in _flatten_fields
            continue
        try:
            flat.append(_flatten(value, arrays))
        except _Refused as exc:
            raise exc.inside(f"[{i}]") from None
    return flat


def _flatten(obj: Any, arrays: list[np.ndarray]) -> Any:
    """The header value of ``obj``; its arrays join ``arrays``. Exact types first: they are
    what messages hold, and the checks for subclasses cost more."""
    kind = type(obj)
    if kind is np.ndarray:
        arrays.append(obj if obj.dtype in _WIRE_DTYPES else _little_endian(obj))
        return {_ARRAY_REF: len(arrays) - 1}
    if kind is float:
        return _finite(obj)
    if kind is int or kind is str or kind is bool or obj is None:
        return obj
    names = _DATACLASS_FIELDS.get(kind)
    if names is not None:
        return _flatten_fields(obj, names, arrays)
    if kind is list:
        return _flatten_list(obj, arrays)
    return _flatten_other(obj, arrays)


def _flatten_other(obj: Any, arrays: list[np.ndarray]) -> Any:
    if isinstance(obj, np.ndarray):
        arrays.append(obj if obj.dtype in _WIRE_DTYPES else _little_endian(obj))
        return {_ARRAY_REF: len(arrays) - 1}
    if isinstance(obj, float):
        return _finite(obj)
    if isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, (list, tuple)):
        return _flatten_list(obj, arrays)
    if isinstance(obj, dict):
        if not all(isinstance(k, str) for k in obj):
            raise _Refused("map keys must be strings")
        return _flatten_map(obj, arrays)
    if isinstance(obj, np.generic):
        return _flatten(obj.item(), arrays)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        names = _DATACLASS_FIELDS[type(obj)] = _field_names(type(obj))
        return _flatten_fields(obj, names, arrays)
    raise _Refused(f"values of type {type(obj).__name__} cannot be sent")


def _finite(number: float) -> float:
    if not math.isfinite(number):
        raise _Refused(f"non-finite number {number} cannot be sent in a header")
    return number


def _little_endian(array: np.ndarray) -> np.ndarray:
    """``array`` in an allowed dtype: a big-endian number converted; anything else refused."""
    little = array.dtype.newbyteorder("<")
    if little.str not in ALLOWED_DTYPES:
        raise _Refused(f"dtype {array.dtype} cannot be sent")
    return array.astype(np.dtype(little.str))


@functools.cache
def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


# -- decoding -----------------------------------------------------------------------------


def decode(frames: typing.Sequence[Any], max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Envelope:
    """Validate and decode frames (bytes, memoryviews or zmq.Frame) into an :class:`Envelope`."""
    if len(frames) < 2:
        raise MessageError(f"expected at least 2 frames (topic, header), got {len(frames)}")
    try:
        views = [memoryview(f).cast("B") for f in frames]  # a zmq.Frame is a buffer too
    except TypeError as exc:
        raise MessageError(f"every frame must be a byte buffer ({exc})") from exc
    size = sum(map(len, views))  # byte views: len is the byte count
    if size > max_bytes:
        raise MessageError(f"message of {size} bytes exceeds the limit of {max_bytes} bytes")
    try:
        topic = str(views[0], "utf-8")
    except UnicodeDecodeError as exc:
        raise MessageError("topic frame is not UTF-8") from exc
    header = _wire_header(views[1])
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
    except _Refused as exc:
        raise exc.error(cls) from None
    except MessageError:
        raise
    except Exception as exc:  # whatever a check above missed is still the sender's fault, never ours
        raise MessageError(f"{header['s']}: cannot be built from its fields ({type(exc).__name__}: {exc})") from exc
    return Envelope(topic, message, header["p"], size)


def _wire_header(view: memoryview) -> dict[str, Any]:
    """The msgpack header map, each of its fields of the right type."""
    if len(view) > MAX_HEADER_BYTES:
        raise MessageError(f"header of {len(view)} bytes exceeds {MAX_HEADER_BYTES} bytes")
    try:
        header = msgpack.unpackb(view, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise MessageError(f"header is not valid msgpack: {exc}") from exc
    if type(header) is not dict:
        raise MessageError("header is not a map")
    # msgpack gives exact types (a bool is no int); all eight are checked in one pass.
    if tuple(map(type, map(header.get, _HEADER_KEYS))) != _HEADER_KINDS:
        key, kind = next((k, t) for k, t in _HEADER_FIELDS if type(header.get(k)) is not t)
        raise MessageError(f"header field {key!r} missing or not {kind.__name__}")
    return header


def _message_from(cls: type, header: dict[str, Any], specs: list[Any], buffers: list[memoryview]) -> Message:
    arrays = [_array_from(spec, view, i) for i, (spec, view) in enumerate(zip(specs, buffers))]
    used: set[int] = set()
    fields = _fields_from(cls, header["d"], arrays, used, _plan(cls, False))
    if len(used) != len(arrays):
        raise MessageError(f"{len(arrays) - len(used)} buffers are not referenced by any field")
    return cls(header=Header(stamp_ns=header["t"], seq=header["q"], frame_id=header["f"]), **fields)


def _array_from(spec: Any, view: memoryview, index: int) -> np.ndarray:
    if not (type(spec) is list and len(spec) == 2 and type(spec[0]) is str and type(spec[1]) is list):
        raise MessageError(f"array {index}: spec must be [dtype, shape]")
    dtype_str, shape = spec
    if not set(map(type, shape)) <= {int}:  # exact ints: no bool, no float, nothing unhashable
        raise MessageError(f"array {index}: shape {shape} must be at most {MAX_NDIM} non-negative ints")
    dtype, expected = _array_layout(dtype_str, tuple(shape), index)
    if expected != len(view):
        raise MessageError(
            f"array {index}: shape {shape} of {dtype_str} needs {expected} bytes, buffer has {len(view)}"
        )
    return np.ndarray(shape, dtype, view)


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


Converter = typing.Callable[[Any, list[np.ndarray], set[int]], Any]
# Per field: its name, its converter, and the exact type a wire value may have to be taken as it
# is without the call (a plain field's declared type; None for the others; typed Any so that
# ``type(value) is plain`` leaves ``value`` a number for the finiteness check).
Plan = tuple[tuple[tuple[str, Converter, Any], ...], frozenset[str]]
_PLAIN_TYPES = (int, str, bool, float)


@functools.cache
def _plan(cls: type, with_header: bool) -> Plan:
    """For each field of ``cls``, the function that checks and converts its wire value; the
    names of those fields."""
    hints = typing.get_type_hints(cls)
    plan = tuple(
        (name, _converter(hints[name]), _plain_type(hints[name]))
        for name in _field_names(cls)
        if with_header or name != "header"
    )
    return plan, frozenset(name for name, _, _ in plan)


def _plain_type(annotation: Any) -> Any:
    return annotation if annotation in _PLAIN_TYPES else None


def _fields_from(cls: type, values: Any, arrays: list[np.ndarray], used: set[int], plan: Plan) -> dict[str, Any]:
    """Field values of ``cls`` from the header map, by its ``plan``."""
    if type(values) is not dict:
        raise _Refused("expected a map of fields")
    converters, names = plan
    if values.keys() != names:
        raise _Refused(f"fields {sorted(values)} do not match {cls.__name__}'s {sorted(names)}")
    return _converted(converters, values, arrays, used)


def _converted(
    converters: typing.Iterable[tuple[str, Converter, Any]],
    values: dict[str, Any],
    arrays: list[np.ndarray],
    used: set[int],
) -> dict[str, Any]:
    """Each named value of ``values`` converted by its converter (a field's, or a map's one)."""
    converted = {}
    for name, convert, plain in converters:
        value = values[name]
        # Plain values of the declared type, most of a header, are taken here: a call per
        # value costs more than the value.
        if type(value) is plain and (plain is not float or math.isfinite(value)):
            converted[name] = value
            continue
        try:
            converted[name] = convert(value, arrays, used)
        except _Refused as exc:
            raise exc.inside(f".{name}") from None
    return converted


@functools.cache
def _converter(annotation: Any) -> Converter:
    if annotation is np.ndarray:
        return _array_reference
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        plan = _plan(annotation, True)
        return lambda value, arrays, used: annotation(**_fields_from(annotation, value, arrays, used, plan))
    if annotation is float:
        return _number
    if annotation in (int, str, bool):
        return functools.partial(_exact, annotation)
    origin = typing.get_origin(annotation)
    if origin is list:
        item = typing.get_args(annotation)[0]
        return functools.partial(_sequence, _converter(item), _plain_type(item))
    if origin is dict:
        item = typing.get_args(annotation)[1]
        return functools.partial(_mapping, _converter(item), _plain_type(item))
    raise TypeError(f"field type {annotation} is not supported on the wire")


def _array_reference(value: Any, arrays: list[np.ndarray], used: set[int]) -> np.ndarray:
    index = value.get(_ARRAY_REF) if type(value) is dict and len(value) == 1 else None
    if type(index) is not int:
        raise _Refused("expected an array reference")
    if not 0 <= index < len(arrays) or index in used:
        raise _Refused(f"array reference {index} is invalid or used twice")
    used.add(index)
    return arrays[index]


def _number(value: Any, arrays: list[np.ndarray], used: set[int]) -> float:
    kind = type(value)  # exact types: msgpack gives int, float or bool (not a number)
    if kind is not float and kind is not int:
        raise _Refused(f"expected a number, got {kind.__name__}")
    if not math.isfinite(value):
        raise _Refused("non-finite number")
    return float(value)


def _exact(kind: type, value: Any, arrays: list[np.ndarray], used: set[int]) -> Any:
    if type(value) is not kind:
        raise _Refused(f"expected {kind.__name__}, got {type(value).__name__}")
    return value


def _sequence(item: Converter, plain: Any, value: Any, arrays: list[np.ndarray], used: set[int]) -> list[Any]:
    if type(value) is not list:
        raise _Refused("expected a list")
    items = []
    for i, v in enumerate(value):
        if type(v) is plain and (plain is not float or math.isfinite(v)):
            items.append(v)  # as in _converted
            continue
        try:
            items.append(item(v, arrays, used))
        except _Refused as exc:
            raise exc.inside(f"[{i}]") from None
    return items


def _mapping(item: Converter, plain: Any, value: Any, arrays: list[np.ndarray], used: set[int]) -> dict[str, Any]:
    if type(value) is not dict:
        raise _Refused("expected a map")
    return _converted(((key, item, plain) for key in value), value, arrays, used)
