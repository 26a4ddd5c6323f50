"""Strict decoding: hostile, corrupted and absurd payloads raise CodecError, and only that.

Payloads with a broken CRC only exercise the envelope, so most body tests re-seal the CRC
(``seal``) after mutating: the corruption then has to be caught by the body parser. Those runs
also compare the fast decoder with the literal reference decoder: both must reject, or both
must read the same map.
"""

from __future__ import annotations

import tracemalloc
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import wire_codec
from mapping.wireframe import Wireframe
from tests.test_codec_util import (
    FUSED,
    check_round_trip,
    fields_of,
    message,
    messages,
    random_wireframe,
    room,
    seal,
)
from wire_codec import reference
from wire_codec.bits import BitWriter
from wire_codec.codec import decode_with
from wire_codec.errors import DEFAULT_LIMITS, Limits

SMALL = message(room())
SMALL_BYTES = wire_codec.encode(SMALL)
FUSED_MSG = message(
    room().replace(sources=np.array([1, 3, 1, 2, 2, 4, 4, 4, 1, 7], dtype=np.uint64),
                   likelihood=np.linspace(0, 1, 10)),
    kind=FUSED,
    robots=("r1", "r2", "r3"),
    sender="fusion",
    frame="fleet",
)
FUSED_BYTES = wire_codec.encode(FUSED_MSG)


def outcome(data: Any, body_decoder: Any = None, limits: Limits = DEFAULT_LIMITS) -> Any:
    """The decoded message, or the CodecError class; any other exception fails the test."""
    try:
        if body_decoder is None:
            return wire_codec.decode(data, limits=limits)
        return decode_with(data, limits, body_decoder)
    except wire_codec.CodecError as exc:
        assert str(exc), "a CodecError always says why"
        assert "\n" not in str(exc)
        return type(exc)


def same_outcome(data: bytes) -> Any:
    """Fast and reference decoders agree: both reject, or both read the same map."""
    fast = outcome(data)
    slow = outcome(data, reference.decode_body)
    if isinstance(fast, type) or isinstance(slow, type):
        assert isinstance(fast, type) and isinstance(slow, type), (fast, slow)
        return fast
    a, b = fast.wireframe, slow.wireframe
    assert np.array_equal(a.points, b.points) and np.array_equal(a.edges, b.edges)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.likelihood, b.likelihood)
    assert np.array_equal(a.sources, b.sources)
    return fast


def with_body(data: bytes, body: bytes) -> bytes:
    f = fields_of(data)
    f[11] = body
    return seal(f)


# ---------------------------------------------------------------------------------------- bytes
@settings(max_examples=400, deadline=1000)
@given(st.binary(max_size=400))
def test_arbitrary_bytes_only_raise_codec_error(data: bytes) -> None:
    assert isinstance(outcome(data), type)


@settings(max_examples=200, deadline=1000)
@given(st.binary(max_size=200))
def test_arbitrary_bytes_behind_a_valid_looking_header(data: bytes) -> None:
    # Starts like a real message (fixarray 13, version 1) so the parse gets further.
    outcome(b"\x9d\x01" + data)
    outcome(SMALL_BYTES[:40] + data)


@settings(max_examples=300, deadline=1000)
@given(st.data())
def test_bit_flips_are_rejected(data: st.DataObject) -> None:
    payload = bytearray(data.draw(st.sampled_from([SMALL_BYTES, FUSED_BYTES])))
    flips = data.draw(st.lists(st.integers(0, 8 * len(payload) - 1), min_size=1, max_size=4, unique=True))
    for bit in flips:
        payload[bit // 8] ^= 0x80 >> (bit % 8)
    # CRC-32 detects every burst of up to 32 bits and any odd number of flipped bits.
    assert isinstance(outcome(bytes(payload)), type)


def test_every_truncation_is_a_truncated_error() -> None:
    for data in (SMALL_BYTES, FUSED_BYTES):
        for cut in range(len(data)):
            assert outcome(data[:cut]) is wire_codec.TruncatedError, cut


@settings(max_examples=100, deadline=1000)
@given(st.binary(min_size=1, max_size=50))
def test_extension_is_rejected(extra: bytes) -> None:
    assert outcome(SMALL_BYTES + extra) is wire_codec.ExtraDataError


# ---------------------------------------------------------------------------------------- body
@settings(max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_bodies_behind_a_valid_crc(data: st.DataObject) -> None:
    base = data.draw(st.sampled_from([SMALL_BYTES, FUSED_BYTES]))
    body = bytearray(fields_of(base)[11])
    how = data.draw(st.sampled_from(["flip", "truncate", "extend", "splice"]))
    if how == "flip":
        for bit in data.draw(st.lists(st.integers(0, 8 * len(body) - 1), min_size=1, max_size=6)):
            body[bit // 8] ^= 0x80 >> (bit % 8)
    elif how == "truncate":
        del body[data.draw(st.integers(0, len(body) - 1)) :]
    elif how == "extend":
        body += data.draw(st.binary(min_size=1, max_size=8))
    else:
        at = data.draw(st.integers(0, len(body)))
        body[at:at] = data.draw(st.binary(min_size=1, max_size=8))
    same_outcome(with_body(base, bytes(body)))


@settings(max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=120), st.sampled_from([SMALL_BYTES, FUSED_BYTES]))
def test_random_bodies_behind_a_valid_crc(body: bytes, base: bytes) -> None:
    same_outcome(with_body(base, body))


def test_body_mutations_sweep_with_reference() -> None:
    # Deterministic sweep: every single-bit flip and every truncation of a mixed-label map.
    rng = np.random.default_rng(11)
    wf = random_wireframe(rng, 12, "rect", "rings", 0.2, None, "random", "random")
    base = check_round_trip(message(wf))
    body = fields_of(base)[11]
    for bit in range(8 * len(body)):
        b = bytearray(body)
        b[bit // 8] ^= 0x80 >> (bit % 8)
        same_outcome(with_body(base, bytes(b)))
    for cut in range(len(body)):
        assert same_outcome(with_body(base, body[:cut])) is wire_codec.TruncatedError


def test_trailing_body_bytes_and_padding() -> None:
    body = fields_of(SMALL_BYTES)[11]
    assert outcome(with_body(SMALL_BYTES, body + b"\x00")) is wire_codec.ExtraDataError
    empty = wire_codec.encode(message(Wireframe.empty()))
    assert fields_of(empty)[11] == b"\x80"  # n = 0, then seven zero padding bits
    assert outcome(with_body(empty, b"\x81")) is wire_codec.ExtraDataError
    assert outcome(with_body(empty, b"")) is wire_codec.TruncatedError


def _body(*parts: tuple[str, Any]) -> bytes:
    w = BitWriter()
    for kind, value in parts:
        if kind == "eg":
            w.eg(value)
        else:
            w.scalar(value[0], value[1])
    return w.to_bytes()


def test_huge_vertex_claims_are_rejected_before_allocating() -> None:
    claims = {
        10**6: wire_codec.LimitError,  # beyond the default limit
        99_999: wire_codec.TruncatedError,  # within it, but 100 bytes cannot hold it
    }
    for n, error in claims.items():
        body = _body(("eg", n)) + bytes(100)
        payload = with_body(SMALL_BYTES, body)
        tracemalloc.start()
        assert outcome(payload) is error
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        # (how fast: `wiremap bench speed --pieces`, codec_reject_claim_us)
        assert peak < 200_000, (n, peak)
    with pytest.raises(wire_codec.LimitError):
        wire_codec.decode(SMALL_BYTES, limits=Limits(max_vertices=5))
    with pytest.raises(wire_codec.LimitError):
        wire_codec.decode(SMALL_BYTES, limits=Limits(max_edges=5))
    with pytest.raises(wire_codec.LimitError):
        wire_codec.decode(SMALL_BYTES, limits=Limits(max_bytes=len(SMALL_BYTES) - 1))
    with pytest.raises(wire_codec.LimitError):
        wire_codec.decode(SMALL_BYTES, limits=Limits(max_coordinate=5.0))


def test_huge_explicit_edge_count_is_rejected() -> None:
    # Two vertices, no chain edge, then a claim of 10**6 explicit edges.
    w = BitWriter()
    w.eg(2)
    w.scalar(0, 12)  # k1 = k2 = k3 = 0
    w.scalar(0b00, 2)  # no turns
    w.scalar(0b00, 2)  # both general
    w.scalar(0b00, 2)  # general turn bits
    w.scalar(0b0000, 4)  # major and minor signs
    w.scalar(0b1111, 4)  # moves: two majors and two minors, all zero (EG0 "1")
    w.scalar(0, 4)  # labels: constant nominal
    w.scalar(0, 1)  # no chain edge
    w.scalar(0, 1)  # no reverse bits
    w.eg(10**6)
    payload = with_body(SMALL_BYTES, w.to_bytes() + bytes(10))
    assert outcome(payload) is wire_codec.LimitError
    assert outcome(payload, reference.decode_body) is wire_codec.LimitError


def test_long_exp_golomb_prefix_is_a_format_error() -> None:
    assert outcome(with_body(SMALL_BYTES, bytes(20))) is wire_codec.FormatError  # 160 zero bits
    assert outcome(with_body(SMALL_BYTES, bytes(3))) is wire_codec.TruncatedError  # 24 zero bits


def test_default_limits_admit_a_5000_vertex_fused_map() -> None:
    rng = np.random.default_rng(5)
    wf = random_wireframe(rng, 5000, "rect", "rings", 0.2, 64, "mostly", "random")
    msg = message(wf, kind=FUSED, robots=tuple(f"r{k}" for k in range(64)), sender="fusion", frame="fleet")
    data = wire_codec.encode(msg)
    assert len(data) < DEFAULT_LIMITS.max_bytes
    out = wire_codec.decode(data)
    assert out.wireframe.n_vertices == 5000 and out.wireframe.n_edges == wf.n_edges


# ---------------------------------------------------------------------------------------- envelope
def _resealed(index: int, value: Any, base: bytes = SMALL_BYTES) -> bytes:
    f = fields_of(base)
    f[index] = value
    return seal(f)


@pytest.mark.parametrize(
    ("index", "value", "error"),
    [
        (0, 3, wire_codec.VersionError),
        (0, 300, wire_codec.VersionError),
        (0, "1", wire_codec.VersionError),
        (1, 3, wire_codec.FormatError),
        (1, True, wire_codec.FormatError),
        (2, "", wire_codec.FormatError),
        (2, b"r1", wire_codec.FormatError),
        (2, "x" * 300, wire_codec.LimitError),
        (3, -1, wire_codec.FormatError),
        (3, 1.0, wire_codec.FormatError),
        (4, True, wire_codec.FormatError),
        (4, float("nan"), wire_codec.FormatError),
        (5, [float("nan"), 0, 0], wire_codec.FormatError),
        (5, [0, 0], wire_codec.FormatError),
        (5, [0, 0, 4_000_000], wire_codec.FormatError),
        (5, [2**62, 0, 0], wire_codec.LimitError),
        (6, None, wire_codec.FormatError),
        (7, [0.5, 0, 0], wire_codec.FormatError),
        (8, 0, wire_codec.FormatError),
        (8, -200, wire_codec.FormatError),
        (8, float("inf"), wire_codec.FormatError),
        (8, 0.2, wire_codec.FormatError),
        (8, 10**7, wire_codec.FormatError),
        (9, ["r1"], wire_codec.FormatError),  # a robot map with robots
        (9, "r1", wire_codec.FormatError),
        (10, [], wire_codec.FormatError),
        (10, {"t": msgpack.ExtType(5, b"x")}, wire_codec.FormatError),
        (10, {"t": msgpack.Timestamp(1, 0)}, wire_codec.FormatError),
        (11, "not bytes", wire_codec.FormatError),
    ],
)
def test_bad_envelope_fields(index: int, value: Any, error: type) -> None:
    data = _resealed(index, value)
    assert outcome(data) is error
    if index < 5:  # the header: wire_codec.peek refuses it the same way (FORMAT.md 2.2)
        with pytest.raises(error) as exc:
            wire_codec.peek(data)
        assert str(exc.value) and "\n" not in str(exc.value)


def test_bad_fused_envelopes() -> None:
    assert outcome(_resealed(9, ["a", "a", "b"], FUSED_BYTES)) is wire_codec.FormatError
    assert outcome(_resealed(9, [f"r{k}" for k in range(65)], FUSED_BYTES)) is wire_codec.LimitError
    # version 2 raises the bound to 4,096 robots (and a decoder's Limits may lower it)
    f = fields_of(FUSED_BYTES)
    f[0], f[9] = 2, [f"r{k}" for k in range(4097)]
    assert outcome(seal(f)) is wire_codec.LimitError
    f[9] = [f"r{k}" for k in range(65)]
    with pytest.raises(wire_codec.LimitError, match="at most 64"):
        wire_codec.decode(seal(f), limits=Limits(max_robots=64))
    # a version-2 envelope around a map that version 1 could carry reads the same
    f = fields_of(FUSED_BYTES)
    f[0] = 2
    same = wire_codec.decode(seal(f))
    assert same.robots == wire_codec.decode(FUSED_BYTES).robots
    assert np.array_equal(same.wireframe.sources, wire_codec.decode(FUSED_BYTES).wireframe.sources)
    # Two robots instead of three: the body's masks no longer line up.
    assert isinstance(outcome(_resealed(9, ["a", "b"], FUSED_BYTES)), type)
    # A robot map's body read as fused (or the reverse) does not parse cleanly.
    assert isinstance(outcome(_resealed(1, 1, FUSED_BYTES)), type)
    assert isinstance(outcome(_resealed(1, 2, SMALL_BYTES)), type)


def test_envelope_shape_errors() -> None:
    f = fields_of(SMALL_BYTES)
    assert outcome(seal(f[:-1])) is wire_codec.FormatError  # 12 elements
    assert outcome(seal([*f, 0])) is wire_codec.FormatError  # 14 elements
    assert outcome(seal([3, *f[1:-1]])) is wire_codec.VersionError  # another version's shape
    # CRC written as a small int instead of uint32.
    head = SMALL_BYTES[:-5]
    assert outcome(head + msgpack.packb(zlib_crc(head))) is wire_codec.FormatError
    assert outcome(msgpack.packb({"a": 1}) + bytes(20)) is wire_codec.ExtraDataError
    assert outcome(msgpack.packb(list(range(1, 21)))) is wire_codec.FormatError
    assert outcome(msgpack.packb(list(range(20)))) is wire_codec.VersionError  # "version 0"
    deep = b"\x91" * 100_000 + b"\x00"
    assert outcome(deep) is wire_codec.FormatError
    assert outcome(b"\x9d\x01" + b"\xdd\xff\xff\xff\xff" + bytes(30)) is wire_codec.LimitError


def zlib_crc(data: bytes) -> int:
    import zlib

    return zlib.crc32(data) & 0xFF  # deliberately not the CRC: only its encoding is tested


def test_wrong_version_detected_before_the_crc() -> None:
    payload = bytearray(SMALL_BYTES)
    payload[1] = 3  # the CRC is now wrong too, but the version is the reason given
    assert outcome(bytes(payload)) is wire_codec.VersionError


def test_checksum_mismatch() -> None:
    payload = bytearray(SMALL_BYTES)
    payload[-1] ^= 1
    assert outcome(bytes(payload)) is wire_codec.ChecksumError
    payload = bytearray(SMALL_BYTES)
    payload[5] ^= 0x20  # inside the sender string "r1" -> "R1"
    assert outcome(bytes(payload)) is wire_codec.ChecksumError


@pytest.mark.parametrize("data", ["text", None, 12, [1, 2], b"", b"\x9d"])
def test_non_payloads(data: Any) -> None:
    assert isinstance(outcome(data), type)


def test_error_hierarchy() -> None:
    for cls in (
        wire_codec.TruncatedError,
        wire_codec.ExtraDataError,
        wire_codec.ChecksumError,
        wire_codec.VersionError,
        wire_codec.LimitError,
        wire_codec.FormatError,
        wire_codec.EncodeError,
    ):
        assert issubclass(cls, wire_codec.CodecError) and issubclass(cls, ValueError)
    with pytest.raises(ValueError, match="max_bytes"):
        Limits(max_bytes=-1)
    with pytest.raises(ValueError, match="max_coordinate"):
        Limits(max_coordinate=float("nan"))


def test_fuzzer_finds_stay_fixed() -> None:
    # Each body was found by tests/fuzz_codec.py; both decoders must reject it.
    # 496949fc: one vertex, label section "flags" with dominant value 3 and the only vertex an
    # exception (the reference decoder used to accept it).
    for body_hex in ["496949fc"]:
        payload = with_body(SMALL_BYTES, bytes.fromhex(body_hex))
        assert outcome(payload) is wire_codec.FormatError
        assert outcome(payload, reference.decode_body) is wire_codec.FormatError


# ---------------------------------------------------------------------------------------- small reader
def _vectorised_outcome(body: bytes, res_mm: int, n_robots: int | None) -> Any:
    from wire_codec import body as body_mod

    saved = body_mod.SMALL_BODY_BYTES
    body_mod.SMALL_BODY_BYTES = -1
    try:
        return body_mod.decode_body(body, res_mm, n_robots, DEFAULT_LIMITS)
    except wire_codec.CodecError as exc:
        return type(exc)
    finally:
        body_mod.SMALL_BODY_BYTES = saved


@settings(max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.data())
def test_small_body_reader_accepts_only_what_the_vectorised_reader_reads(
    msg: Any, data: st.DataObject
) -> None:
    """Small bodies are read in plain Python first; it must return exactly the vectorised
    reader's map, and decline (None) whatever that reader rejects -- on valid bodies and on
    mutated ones."""
    from wire_codec.body import _decode_small

    f = fields_of(wire_codec.encode(msg))
    body, res_mm = f[11], f[8]
    n_robots = len(f[9]) if f[1] == FUSED.value else None
    bodies = [body]
    for _ in range(5):
        b = bytearray(body)
        how = data.draw(st.sampled_from(["flip", "truncate", "splice"]))
        if how == "flip" and b:
            for bit in data.draw(st.lists(st.integers(0, 8 * len(b) - 1), min_size=1, max_size=3)):
                b[bit // 8] ^= 0x80 >> (bit % 8)
        elif how == "truncate" and b:
            del b[data.draw(st.integers(0, len(b) - 1)) :]
        else:
            at = data.draw(st.integers(0, len(b)))
            b[at:at] = data.draw(st.binary(min_size=1, max_size=4))
        bodies.append(bytes(b))
    for k, b in enumerate(bodies):
        small = _decode_small(b, res_mm, n_robots, DEFAULT_LIMITS)
        vec = _vectorised_outcome(b, res_mm, n_robots)
        if small is None:
            # declined: only an empty map or a body the vectorised reader rejects
            assert k > 0 or isinstance(vec, type) or vec.n_vertices == 0
            continue
        assert not isinstance(vec, type), vec
        for name in ("points", "labels", "edges", "likelihood", "sources"):
            x, y = getattr(small, name), getattr(vec, name)
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
