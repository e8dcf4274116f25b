"""How a dtx message is stored in an MCAP bag (bus.bag writes and reads the bags).

A dtx message is stored in its own encoding: the channel's message encoding is
``dtx/msgpack+buffers``, the data is the wire header and array buffers each prefixed by its
length (uint64 little-endian), and the schema record (encoding ``dtx/jsonschema``) is a JSON
Schema of the message's fields with each array's dtype and shape, so a bag explains itself to a
tool in any language (docs/bag-format.md).
"""

from __future__ import annotations

import dataclasses
import json
import struct
import typing
from typing import Any

import numpy as np

from msgs.base import Message

MESSAGE_ENCODING = "dtx/msgpack+buffers"
SCHEMA_ENCODING = "dtx/jsonschema"
_LENGTH = struct.Struct("<Q")


class BagError(ValueError):
    """A bag that cannot be written or read."""


def pack_frames(frames: list[Any]) -> bytes:
    """Header and buffers (everything after the topic frame) as one length-prefixed blob."""
    parts: list[Any] = []
    for frame in frames:
        view = memoryview(getattr(frame, "buffer", frame)).cast("B")
        parts += [_LENGTH.pack(view.nbytes), view]
    return b"".join(parts)


def unpack_frames(topic: str, data: bytes | memoryview) -> list[Any]:
    view = memoryview(data).cast("B")
    frames: list[Any] = [topic.encode()]
    offset = 0
    while offset < view.nbytes:
        if offset + 8 > view.nbytes:
            raise BagError(f"{topic}: record ends inside a length prefix")
        (length,) = _LENGTH.unpack_from(view, offset)
        offset += 8
        if offset + length > view.nbytes:
            raise BagError(f"{topic}: record announces {length} bytes, {view.nbytes - offset} left")
        frames.append(view[offset : offset + length])
        offset += length
    return frames


def schema_description(msg_type: type[Message]) -> bytes:
    """The message's fields as a JSON Schema (draft 2020-12) of the header map ``d``, arrays
    with their dtype and shape: a tool in another language decodes a channel from the bag
    alone (docs/bag-format.md), without reading this code."""
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"dtx:{msg_type.SCHEMA}/{msg_type.VERSION}",
        "title": msg_type.SCHEMA,
        "description": (msg_type.__doc__ or "").strip(),
        "x-dtx-version": msg_type.VERSION,
        "x-dtx-payload": "length-prefixed frames (uint64 LE): msgpack header {s,v,t,q,f,p,d,a}, then one "
        "raw little-endian C-order buffer per entry of a ([dtype, shape]); this schema "
        "describes d. See docs/bag-format.md and docs/wire-protocol.md.",
        **_object_schema(msg_type, skip_header=True),
    }
    return json.dumps(schema).encode()


def _object_schema(cls: type, skip_header: bool = False) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    defaults = cls()  # the defaults give each array's dtype and rank
    names = [f.name for f in dataclasses.fields(cls) if not (skip_header and f.name == "header")]
    return {
        "type": "object",
        "additionalProperties": False,
        "required": names,
        "properties": {name: _field_schema(hints[name], getattr(defaults, name)) for name in names},
    }


def _field_schema(annotation: Any, default: Any) -> dict[str, Any]:
    if annotation is np.ndarray:
        return {
            "type": "object",
            "additionalProperties": False,
            "required": ["__array__"],
            "properties": {
                "__array__": {
                    "type": "integer",
                    "minimum": 0,
                    "description": "index of this array's buffer (and of its entry in a)",
                }
            },
            "x-dtx-array": {
                "dtype": default.dtype.str,
                "shape": [d or None for d in default.shape],
                "description": "dtype as this field is usually sent, shape with null for "
                "a dimension of any length; the record's a is authoritative",
            },
        }
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        return _object_schema(annotation)
    simple = {int: "integer", float: "number", str: "string", bool: "boolean"}
    if annotation in simple:
        return {"type": simple[annotation]}
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is list:
        return {"type": "array", "items": _field_schema(args[0], None)}
    if origin is dict:
        return {"type": "object", "additionalProperties": _field_schema(args[1], None)}
    raise BagError(f"field type {annotation} has no JSON Schema")
