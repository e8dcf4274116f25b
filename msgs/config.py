"""Typed configuration from plain data: a config dataclass from a mapping read from YAML or JSON
(launch-file parameters, device backends, model and training configs, effect parameters).

One loader for all of them, written here rather than taken from dacite or draccus: those
convert silently where a lab file must be refused (``true`` for a number, ``3`` for a serial
port, an octal-looking serial read as an int), and report an unknown key without the
allowed ones. Rules:

- an unknown key is an error naming it by dotted path, with the allowed keys;
- an int is widened to a float field (a bool never counts as a number; an int too large for a
  float is an error naming the key);
- a text field takes only text: an unquoted serial or port in YAML arrives as a number;
- ``Literal[...]`` fields take one of their values; ``X | None`` takes None too;
- ``list[T]`` and ``tuple[T, ...]`` take a list (each element checked; tuples are made
  tuples); a nested config dataclass takes a mapping; ``Any`` and bare containers pass.
"""

from __future__ import annotations

import dataclasses
import sys
import types
import typing
from typing import Any, Literal, TypeVar

C = TypeVar("C")
# An int beyond this has no float (float() raises OverflowError).
_LARGEST_FLOAT = int(sys.float_info.max)


class ConfigError(ValueError):
    """A mapping that does not fit its config dataclass; the text names the key's dotted path."""


def config_from_dict(config_class: type[C], data: Any, noun: str = "parameter", path: str = "") -> C:
    """``config_class`` built from ``data``, every value checked against its field's type.
    ``noun`` names the keys in messages ("parameter", "generator setting")."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path or config_class.__name__} must be a mapping, got {data!r}")
    fields = {field.name: field for field in dataclasses.fields(config_class)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = f"{path}: " if path else ""
        dotted = [f"{path}.{key}" if path else key for key in unknown]
        raise ConfigError(f"{where}unknown {noun}(s) {dotted}; allowed: {sorted(fields)}")
    hints = typing.get_type_hints(config_class)
    values = {key: _checked(hints[key], value, f"{path}.{key}" if path else key, noun) for key, value in data.items()}
    try:
        return config_class(**values)
    except TypeError as exc:  # a required field left out
        raise ConfigError(f"{path or config_class.__name__}: {exc}") from None


def _checked(expected: Any, value: Any, path: str, noun: str) -> Any:
    origin = typing.get_origin(expected)
    if expected is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(expected)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in (o for o in options if o is not type(None)):
            try:
                return _checked(option, value, path, noun)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{path} must be one of {options}, got {value!r}")
    if origin is Literal:
        allowed = typing.get_args(expected)
        if value not in allowed or isinstance(value, bool) != any(isinstance(a, bool) for a in allowed):
            raise ConfigError(f"{path} must be one of {list(allowed)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(expected) and isinstance(expected, type):
        return config_from_dict(expected, value, noun, path)
    if origin in (list, tuple):
        return _sequence(expected, origin, value, path, noun)
    base = origin or expected
    if base is float and isinstance(value, int) and not isinstance(value, bool):
        if abs(value) > _LARGEST_FLOAT:
            raise ConfigError(f"{path} must be a float, got a {value.bit_length()}-bit integer too large for one")
        return float(value)
    if base is str and not isinstance(value, str):
        raise ConfigError(f"{path} must be text, got {value!r} ({type(value).__name__}); quote it in the launch file")
    if base in (int, float) and isinstance(value, bool):
        raise ConfigError(f"{path} must be {base.__name__}, got {value!r}")
    if base is tuple and isinstance(value, list):
        return tuple(value)
    if isinstance(base, type) and not isinstance(value, base):
        raise ConfigError(f"{path} must be {base.__name__}, got {value!r}")
    return value


def _sequence(expected: Any, origin: type, value: Any, path: str, noun: str) -> Any:
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{path} must be a list, got {value!r}")
    args = typing.get_args(expected)
    if origin is list or (len(args) == 2 and args[1] is Ellipsis):
        items = [_checked(args[0], item, f"{path}[{i}]", noun) for i, item in enumerate(value)] if args else list(value)
    else:
        if len(value) != len(args):
            raise ConfigError(f"{path} must be a list of {len(args)}, got {value!r}")
        items = [_checked(arg, item, f"{path}[{i}]", noun) for i, (arg, item) in enumerate(zip(args, value))]
    return items if origin is list else tuple(items)
