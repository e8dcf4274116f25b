"""The one config loader: typed dataclasses from YAML/JSON mappings, every refusal naming the key."""

from __future__ import annotations

import dataclasses
from typing import Literal

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from msgs.config import ConfigError, config_from_dict


@dataclasses.dataclass
class Limits:
    x_min_m: float = -0.4
    x_max_m: float = 0.4


@dataclasses.dataclass
class Device:
    port: str = "/dev/ttyUSB0"
    rate_hz: float = 30.0
    retries: int = 3
    mode: Literal["fast", "strict"] = "strict"
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    topics: list[str] = dataclasses.field(default_factory=list)
    calibration: str | None = None
    limits: Limits = dataclasses.field(default_factory=Limits)


def test_a_full_mapping_is_built_with_types_kept_and_ints_widened() -> None:
    text = """
    port: /dev/ttyACM0
    rate_hz: 15
    mode: fast
    offset_m: [0.01, 0, -0.02]
    topics: [/a, /b]
    limits: {x_min_m: -1, x_max_m: 0.5}
    """
    device = config_from_dict(Device, yaml.safe_load(text))
    assert device == Device("/dev/ttyACM0", 15.0, 3, "fast", (0.01, 0.0, -0.02), ["/a", "/b"], None, Limits(-1.0, 0.5))
    assert isinstance(device.rate_hz, float) and isinstance(device.offset_m, tuple)
    assert isinstance(device.limits.x_min_m, float)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"speed": 1}, r"unknown parameter\(s\) \['speed'\]; allowed: \['calibration', 'limits', 'mode'"),
        ({"limits": {"y_min_m": 0}}, r"limits: unknown parameter\(s\) \['limits.y_min_m'\]; allowed: \['x_max_m'"),
        ({"limits": {"x_min_m": "low"}}, r"limits.x_min_m must be float, got 'low'"),
        ({"limits": 3}, r"limits must be a mapping, got 3"),
        ({"port": yaml.safe_load("003726261447")}, r"port must be text, got 525951783 \(int\); quote it"),
        ({"rate_hz": True}, r"rate_hz must be float, got True"),
        ({"retries": 2.5}, r"retries must be int, got 2.5"),
        ({"retries": False}, r"retries must be int, got False"),
        ({"mode": "medium"}, r"mode must be one of \['fast', 'strict'\], got 'medium'"),
        ({"offset_m": [0.0, 0.0]}, r"offset_m must be a list of 3, got \[0.0, 0.0\]"),
        ({"offset_m": [0.0, "x", 0.0]}, r"offset_m\[1\] must be float, got 'x'"),
        ({"topics": "/a"}, r"topics must be a list, got '/a'"),
        ({"topics": ["/a", 7]}, r"topics\[1\] must be text, got 7"),
        ({"calibration": 5}, r"calibration must be text, got 5"),
    ],
)
def test_each_bad_value_is_refused_by_its_dotted_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        config_from_dict(Device, data)


def test_none_is_taken_only_where_the_type_allows_it() -> None:
    assert config_from_dict(Device, {"calibration": None}).calibration is None
    with pytest.raises(ConfigError, match="port must be text, got None"):
        config_from_dict(Device, {"port": None})


@given(st.one_of(st.integers(), st.floats(allow_nan=False), st.booleans(), st.text(), st.none()))
def test_a_float_field_takes_exactly_the_real_numbers(value: object) -> None:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        built = config_from_dict(Limits, {"x_min_m": value})
        assert isinstance(built.x_min_m, float) and built.x_min_m == float(value)
    else:
        with pytest.raises(ConfigError, match="x_min_m must be float"):
            config_from_dict(Limits, {"x_min_m": value})
