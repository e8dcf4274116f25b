"""WSG frame codec and CRC: properties over arbitrary frames, and resynchronisation."""

from __future__ import annotations

import struct

from hypothesis import given
from hypothesis import strategies as st

from drivers.gripper.protocol import (
    MAX_PAYLOAD_BYTES,
    PREAMBLE,
    FrameParser,
    crc16,
    encode_frame,
    encode_response,
    split_response,
)

command_ids = st.integers(min_value=0, max_value=255)
payloads = st.binary(max_size=MAX_PAYLOAD_BYTES)


def test_crc_of_preamble_matches_weiss_driver_constant():
    # Weiss' msg_receive() starts its running checksum at 0x50F5, "checksum over preamble".
    assert crc16(PREAMBLE) == 0x50F5


@given(command_ids, payloads)
def test_whole_frame_checks_to_zero(command_id, payload):
    assert crc16(encode_frame(command_id, payload)) == 0


@given(command_ids, payloads)
def test_frame_layout(command_id, payload):
    frame = encode_frame(command_id, payload)
    assert frame[:3] == PREAMBLE
    assert frame[3] == command_id
    assert struct.unpack_from("<H", frame, 4)[0] == len(payload)
    assert frame[6:-2] == payload


@given(command_ids, payloads)
def test_round_trip_through_parser(command_id, payload):
    assert FrameParser().feed(encode_frame(command_id, payload)) == [(command_id, payload)]


@given(command_ids, payloads, st.data())
def test_single_bit_flip_is_never_accepted(command_id, payload, data):
    frame = bytearray(encode_frame(command_id, payload))
    bit = data.draw(st.integers(min_value=0, max_value=len(frame) * 8 - 1))
    frame[bit // 8] ^= 1 << (bit % 8)
    assert crc16(bytes(frame)) != 0
    assert (command_id, payload) not in FrameParser().feed(bytes(frame))


@given(st.binary(max_size=40), command_ids, payloads)
def test_resynchronises_after_garbage(garbage, command_id, payload):
    # Trailing zeros complete any header the garbage may have faked, so it is rejected.
    stream = garbage + encode_frame(command_id, payload) + bytes(MAX_PAYLOAD_BYTES + 8)
    assert (command_id, payload) in FrameParser().feed(stream)


@given(command_ids, payloads, st.integers(min_value=1, max_value=8))
def test_frames_split_across_reads(command_id, payload, chunk):
    stream = encode_frame(command_id, payload) * 2
    parser, frames = FrameParser(), []
    for start in range(0, len(stream), chunk):
        frames += parser.feed(stream[start : start + chunk])
    assert frames == [(command_id, payload)] * 2


def test_extra_preamble_byte_before_frame():
    frame = encode_frame(0x25, b"\x01\x02")
    parser = FrameParser()
    assert parser.feed(b"\xaa" + frame) == [(0x25, b"\x01\x02")]
    assert parser.discarded_bytes == 1


def test_oversized_length_field_is_rejected_without_waiting():
    bogus = PREAMBLE + struct.pack("<BH", 0x43, MAX_PAYLOAD_BYTES + 1)
    frame = encode_frame(0x43, b"\x00\x00")
    assert FrameParser().feed(bogus + frame) == [(0x43, b"\x00\x00")]


def test_response_status_split():
    ((command_id, payload),) = FrameParser().feed(encode_response(0x43, 26, b"\x01"))
    assert command_id == 0x43
    assert split_response(payload) == (26, b"\x01")
