"""``wire_codec.peek``: the envelope's first five fields without the body (FORMAT.md 2.2).

It must agree with ``decode`` on every golden vector, refuse whatever ``decode`` refuses in the
envelope (truncation, garbage, a broken CRC, bad header fields) with a ``CodecError`` and
nothing else, and never refuse what ``decode`` accepts.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import wire_codec
from tests.test_codec_golden import VERSIONED, _load
from tests.test_codec_util import FUSED, fields_of, message, room, seal
from wire_codec.errors import DEFAULT_LIMITS, Limits

SMALL_BYTES = wire_codec.encode(message(room(), seq=42, stamp_ns=123_456_789))
FUSED_BYTES = wire_codec.encode(
    message(room().replace(sources=np.array([1, 3, 1, 2, 2, 4, 4, 4, 1, 7], dtype=np.uint64)),
            kind=FUSED, robots=("r1", "r2", "r3"), sender="fusion", frame="fleet")
)


def peek_outcome(data: Any, limits: Limits = DEFAULT_LIMITS) -> Any:
    """The header, or the CodecError class; any other exception fails the test."""
    try:
        return wire_codec.peek(data, limits=limits)
    except wire_codec.CodecError as exc:
        assert str(exc) and "\n" not in str(exc)
        return type(exc)


def decode_outcome(data: Any, limits: Limits = DEFAULT_LIMITS) -> Any:
    try:
        return wire_codec.decode(data, limits=limits)
    except wire_codec.CodecError as exc:
        return type(exc)


def header_of(msg: wire_codec.MapMessage, version: int) -> wire_codec.Header:
    return wire_codec.Header(version, msg.kind, msg.sender, msg.seq, msg.stamp_ns)


@pytest.mark.parametrize(("version", "name"), [(v, n) for v, make in VERSIONED.items() for n in make()])
def test_golden_vectors_peek_as_they_decode(version: int, name: str) -> None:
    data = bytes.fromhex(_load(version)[name])
    msg = wire_codec.decode(data)
    head = wire_codec.peek(data)
    assert head == header_of(msg, version)
    assert isinstance(head.kind, wire_codec.MessageKind)
    assert wire_codec.peek(bytearray(data)) == wire_codec.peek(memoryview(data)) == head


def test_square_room_header_by_hand() -> None:
    # FORMAT.md's worked example: version 1, robot map, "r1", seq 42, stamp 123456789
    head = wire_codec.peek(bytes.fromhex(_load()["square_room"]))
    assert head == (1, wire_codec.MessageKind.ROBOT_MAP, "r1", 42, 123_456_789)


def test_kind_is_reported_not_judged() -> None:
    # a fused map peeks fine: telling a robot map from a fused one is the caller's business
    head = wire_codec.peek(FUSED_BYTES)
    assert head.kind == wire_codec.MessageKind.FUSED_MAP and head.sender == "fusion"
    assert wire_codec.peek(SMALL_BYTES).kind == wire_codec.MessageKind.ROBOT_MAP


def test_every_truncation_is_a_truncated_error() -> None:
    for data in (SMALL_BYTES, FUSED_BYTES):
        for cut in range(len(data)):
            assert peek_outcome(data[:cut]) is wire_codec.TruncatedError, cut


@pytest.mark.parametrize("data", ["text", None, 12, [1, 2], b"", b"\x9d", bytes(19), bytes(400)])
def test_non_payloads(data: Any) -> None:
    assert isinstance(peek_outcome(data), type)


def test_envelope_errors_as_decode_says_them() -> None:
    flipped = bytearray(SMALL_BYTES)
    flipped[5] ^= 0x20  # "r1" -> "R1": the sender is not what was sealed
    assert peek_outcome(bytes(flipped)) is wire_codec.ChecksumError
    wrong_version = bytearray(SMALL_BYTES)
    wrong_version[1] = 3
    assert peek_outcome(bytes(wrong_version)) is wire_codec.VersionError
    assert peek_outcome(SMALL_BYTES + b"\x00") is wire_codec.ExtraDataError
    assert peek_outcome(SMALL_BYTES, Limits(max_bytes=len(SMALL_BYTES) - 1)) is wire_codec.LimitError
    f = fields_of(SMALL_BYTES)
    assert peek_outcome(seal(f[:-1])) is wire_codec.FormatError  # 12 elements


def test_the_rest_is_not_read() -> None:
    # a broken body (or a broken later field) behind a valid CRC: decode refuses, peek does not
    f = fields_of(SMALL_BYTES)
    f[11] = b"\xff" * 8
    assert isinstance(decode_outcome(seal(f)), type)
    assert wire_codec.peek(seal(f)) == wire_codec.peek(SMALL_BYTES)
    f = fields_of(SMALL_BYTES)
    f[8] = 0  # resolution 0 mm
    assert decode_outcome(seal(f)) is wire_codec.FormatError
    assert wire_codec.peek(seal(f)).seq == 42


@settings(max_examples=400, deadline=1000)
@given(st.binary(max_size=400))
def test_garbage_only_raises_codec_error(data: bytes) -> None:
    out = peek_outcome(data)
    assert isinstance(out, type)
    assert isinstance(decode_outcome(data), type)
    assert isinstance(peek_outcome(b"\x9d\x01" + data), type)


@settings(max_examples=300, deadline=1000)
@given(st.data())
def test_peek_never_refuses_what_decode_accepts(data: st.DataObject) -> None:
    """Bit flips and cuts of real payloads: peek refuses whatever decode refuses in the
    envelope, and when decode accepts, peek returns its fields."""
    payload = bytearray(data.draw(st.sampled_from([SMALL_BYTES, FUSED_BYTES])))
    flips = data.draw(st.lists(st.integers(0, 8 * len(payload) - 1), max_size=3, unique=True))
    for bit in flips:
        payload[bit // 8] ^= 0x80 >> (bit % 8)
    cut = data.draw(st.integers(0, len(payload)))
    raw = bytes(payload[:cut])
    head, msg = peek_outcome(raw), decode_outcome(raw)
    if isinstance(msg, wire_codec.MapMessage):
        assert head == header_of(msg, raw[1])
    elif isinstance(head, type):
        assert isinstance(msg, type)
