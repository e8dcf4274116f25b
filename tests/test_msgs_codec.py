"""The wire codec: round trips of every message, and every malformed input refused clearly."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import msgs
from msgs.codec import ALLOWED_DTYPES, MessageError, decode, encode


def _bytes(frames: list) -> list[bytes]:
    return [bytes(memoryview(f)) for f in frames]


def _forge(frames: list, **changes: object) -> list[bytes]:
    """Frames whose header has ``changes`` applied (what a buggy or hostile peer might send)."""
    header = msgpack.unpackb(bytes(frames[1]))
    header.update(changes)
    return [bytes(frames[0]), msgpack.packb(header), *_bytes(frames[2:])]


def assert_same(sent: object, got: object) -> None:
    if isinstance(sent, np.ndarray):
        assert isinstance(got, np.ndarray) and got.dtype == sent.dtype
        np.testing.assert_array_equal(got, sent)
    elif dataclasses.is_dataclass(sent):
        assert type(got) is type(sent)
        for field in dataclasses.fields(sent):
            assert_same(getattr(sent, field.name), getattr(got, field.name))
    else:
        assert got == sent


@pytest.mark.parametrize("msg_type", sorted(msgs.MESSAGE_TYPES.values(), key=lambda t: t.SCHEMA))
def test_every_message_type_round_trips_with_defaults(msg_type: type) -> None:
    message = msg_type()
    assert_same(message, decode(_bytes(encode("/t", message, "pub"))).message)


dtypes = st.sampled_from(sorted(ALLOWED_DTYPES)).map(np.dtype)
arrays = dtypes.flatmap(lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5)))


@settings(max_examples=150, deadline=None)
@given(
    points=arrays,
    colors=arrays,
    stamp=st.integers(0, 2**63 - 1),
    seq=st.integers(0, 2**63 - 1),
    frame_id=st.text(max_size=30),
)
def test_arrays_and_headers_round_trip(
    points: np.ndarray, colors: np.ndarray, stamp: int, seq: int, frame_id: str
) -> None:
    message = msgs.PointCloud(header=msgs.Header(stamp, seq, frame_id), points=points, colors=colors)
    envelope = decode(_bytes(encode("/cloud", message, "p1")))
    out = envelope.message
    assert (out.header.stamp_ns, out.header.seq, out.header.frame_id) == (stamp, seq, frame_id)
    for sent, got in ((points, out.points), (colors, out.colors)):
        assert got.dtype == sent.dtype and got.shape == sent.shape
        np.testing.assert_array_equal(got, sent)
    assert envelope.publisher == "p1" and envelope.topic == "/cloud"


@settings(max_examples=100, deadline=None)
@given(
    width=st.floats(allow_nan=False, allow_infinity=False),
    state=st.text(max_size=20),
    code=st.integers(-(2**63), 2**63 - 1),
)
def test_plain_values_round_trip(width: float, state: str, code: int) -> None:
    message = msgs.GripperState(width_m=width, state=state, status_code=code)
    assert decode(_bytes(encode("/g", message))).message == message


def test_big_endian_arrays_arrive_little_endian_with_the_same_values() -> None:
    values = np.arange(6, dtype=">f8").reshape(2, 3)
    out = decode(_bytes(encode("/c", msgs.PointCloud(points=values)))).message.points
    assert out.dtype == np.dtype("<f8")
    np.testing.assert_array_equal(out, values)


def test_non_contiguous_arrays_are_sent_as_their_values() -> None:
    values = np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2]
    out = decode(_bytes(encode("/c", msgs.PointCloud(points=values)))).message.points
    np.testing.assert_array_equal(out, values)


@settings(max_examples=300, deadline=None)
@given(frames=st.lists(st.binary(max_size=64), max_size=6))
def test_garbage_frames_only_ever_raise_message_error(frames: list[bytes]) -> None:
    with pytest.raises(MessageError):
        decode(frames)


@pytest.fixture
def good_frames() -> list:
    return encode("/depth", msgs.DepthImage(depth=np.zeros((4, 5), np.uint16)), "pub")


def test_truncated_frames_are_refused(good_frames: list) -> None:
    with pytest.raises(MessageError, match="announces"):
        decode(_bytes(good_frames)[:-1])
    with pytest.raises(MessageError, match="at least 2 frames"):
        decode(_bytes(good_frames)[:1])


def test_truncated_buffer_is_refused(good_frames: list) -> None:
    frames = _bytes(good_frames)
    frames[2] = frames[2][:-1]
    with pytest.raises(MessageError, match="needs 40 bytes"):
        decode(frames)


def test_extra_frame_is_refused(good_frames: list) -> None:
    with pytest.raises(MessageError, match="announces"):
        decode([*_bytes(good_frames), b"extra"])


def test_unknown_schema_is_refused(good_frames: list) -> None:
    with pytest.raises(MessageError, match="unknown schema 'dtx.nope'"):
        decode(_forge(good_frames, s="dtx.nope"))


def test_incompatible_version_is_refused(good_frames: list) -> None:
    with pytest.raises(MessageError, match="version 7 is incompatible"):
        decode(_forge(good_frames, v=7))


def test_shape_byte_count_mismatch_is_refused(good_frames: list) -> None:
    header = msgpack.unpackb(bytes(good_frames[1]))
    header["a"][0][1] = [5, 5]
    with pytest.raises(MessageError, match="needs 50 bytes, buffer has 40"):
        decode(_forge(good_frames, a=header["a"]))


def test_disallowed_dtype_is_refused(good_frames: list) -> None:
    header = msgpack.unpackb(bytes(good_frames[1]))
    header["a"][0][0] = "|O"
    with pytest.raises(MessageError, match="not allowed"):
        decode(_forge(good_frames, a=header["a"]))


@pytest.mark.parametrize("shape", [[True, 5], [4.0, 5], [4, -5], [[4], 5], [4, None], [1] * 9])
def test_a_checked_layout_does_not_let_a_look_alike_shape_through(good_frames: list, shape: list) -> None:
    """Array layouts are checked once and remembered: a shape equal to a remembered one
    (True == 1, 4.0 == 4) or not hashable is still refused as before."""
    decode(_bytes(good_frames))  # the (4, 5) uint16 layout is now remembered
    header = msgpack.unpackb(bytes(good_frames[1]))
    header["a"][0][1] = shape
    with pytest.raises(MessageError, match="must be at most 8 non-negative ints"):
        decode(_forge(good_frames, a=header["a"]))


def test_a_header_given_to_encode_replaces_the_messages_own() -> None:
    message = msgs.DepthImage(header=msgs.Header(stamp_ns=1, seq=2, frame_id="a"), depth=np.ones((2, 3), np.uint16))
    got = decode(encode("/d", message, "p", msgs.Header(stamp_ns=5, seq=6, frame_id="b"))).message
    assert (got.header.stamp_ns, got.header.seq, got.header.frame_id) == (5, 6, "b")
    assert message.header.seq == 2  # the message itself is left as it was
    np.testing.assert_array_equal(got.depth, message.depth)


def test_non_finite_numbers_are_refused_both_ways() -> None:
    with pytest.raises(MessageError, match="non-finite"):
        encode("/g", msgs.GripperState(width_m=math.nan))
    frames = encode("/g", msgs.GripperState(width_m=0.1))
    header = msgpack.unpackb(bytes(frames[1]))
    header["d"]["width_m"] = math.inf
    with pytest.raises(MessageError, match="non-finite"):
        decode(_forge(frames, d=header["d"]))


def test_wrong_field_types_and_names_are_refused() -> None:
    frames = encode("/g", msgs.GripperState(width_m=0.1))
    header = msgpack.unpackb(bytes(frames[1]))
    with pytest.raises(MessageError, match="expected str"):
        decode(_forge(frames, d={**header["d"], "state": 3}))
    with pytest.raises(MessageError, match="do not match"):
        decode(_forge(frames, d={**header["d"], "colour": "red"}))
    with pytest.raises(MessageError, match="non-negative"):
        decode(_forge(frames, t=-1))


def test_oversized_message_is_refused_before_arrays_are_built(good_frames: list) -> None:
    with pytest.raises(MessageError, match="exceeds the limit of 10 bytes"):
        decode(_bytes(good_frames), max_bytes=10)


def test_unsendable_values_are_refused_at_encode() -> None:
    with pytest.raises(MessageError, match="cannot be sent"):
        encode("/c", msgs.PointCloud(points=np.array(["a"], dtype=object)))
    with pytest.raises(MessageError, match="not a registered"):
        encode("/c", object())  # type: ignore[arg-type]


def test_a_zero_size_array_with_a_huge_dimension_is_refused() -> None:
    # The message that once killed every node: the byte count (0) matches the empty buffer,
    # and NumPy then refuses the shape with an error of its own.
    frames = encode("/x", msgs.Empty(), "fuzzer")
    header = msgpack.unpackb(bytes(frames[1]))
    header["a"] = [["<f4", [2**63 - 1, 0]]]
    with pytest.raises(MessageError, match="dimension above"):
        decode([bytes(frames[0]), msgpack.packb(header), b""])


_DIMENSIONS = st.one_of(st.integers(0, 4), st.sampled_from([2**31, 2**32, 2**62, 2**63 - 1, 2**64 - 1]))


@settings(max_examples=400, deadline=None)
@given(
    shape=st.lists(_DIMENSIONS, min_size=0, max_size=9),
    dtype=st.sampled_from(sorted(ALLOWED_DTYPES)),
    buffer=st.binary(max_size=32),
    field=st.sampled_from(["depth", "unused"]),
)
def test_any_announced_array_decodes_or_raises_message_error(
    shape: list[int], dtype: str, buffer: bytes, field: str
) -> None:
    frames = encode("/depth", msgs.DepthImage(depth=np.zeros((1, 1), np.uint16)), "fuzzer")
    header = msgpack.unpackb(bytes(frames[1]))
    header["a"] = [[dtype, shape]]
    header["d"][field] = {"__array__": 0}
    try:
        decode([bytes(frames[0]), msgpack.packb(header), buffer])
    except MessageError:
        pass


@settings(max_examples=400, deadline=None)
@given(data=st.data())
def test_mutated_headers_of_every_message_type_only_ever_raise_message_error(data: st.DataObject) -> None:
    msg_type = data.draw(st.sampled_from(sorted(msgs.MESSAGE_TYPES.values(), key=lambda t: t.SCHEMA)))
    frames = encode("/t", msg_type(), "fuzzer")
    header = msgpack.unpackb(bytes(frames[1]))
    plain = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(-(2**63), 2**64 - 1),
        st.floats(),
        st.text(max_size=8),
        st.lists(st.integers(0, 2**63), max_size=3),
    )
    for key in data.draw(st.lists(st.sampled_from(sorted(header)), max_size=3)):
        header[key] = data.draw(plain)
    if isinstance(header.get("d"), dict) and header["d"]:
        name = data.draw(st.sampled_from(sorted(header["d"])))
        header["d"][name] = data.draw(st.one_of(plain, st.just({"__array__": 0})))
    try:
        decode([bytes(frames[0]), msgpack.packb(header), *_bytes(frames[2:])])
    except MessageError:
        pass
