"""The envelope: a msgpack array around the bit-packed body, sealed by a CRC-32 (FORMAT.md).

The message is one msgpack array of 13 elements::

    [version, kind, sender, seq, stamp_ns, pose, frame, origin, resolution_mm,
     robots, meta, body, crc32]

``pose`` and ``origin`` are ``[x_mm, y_mm, theta_urad]`` integers (millimetres and
microradians), ``resolution_mm`` is the grid step in whole millimetres, ``body`` is the
bit-packed wireframe (:mod:`wire_codec.body`) and ``crc32`` is the CRC-32 (zlib/IEEE 802.3)
of every byte before it, always written as a msgpack ``uint 32`` (``0xce`` and four bytes, big
endian), so a message always ends with those five bytes.

Precision of what travels (choices made where the issue was silent): poses to 1 mm and 1 µrad,
the resolution to 1 mm (the encoder quantises with the rounded value, so encoder and decoder use
the same grid), vertices to half a resolution step, likelihoods to 1/30.
"""

from __future__ import annotations

import math
import threading
import zlib
from collections.abc import Callable, Mapping
from typing import Any

import msgpack

from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.body import MAX_ROBOTS, MAX_ROBOTS_V1, EncodedBody, decode_body, encode_body
from wire_codec.errors import (
    DEFAULT_LIMITS,
    ChecksumError,
    CodecError,
    EncodeError,
    ExtraDataError,
    FormatError,
    LimitError,
    Limits,
    TruncatedError,
    VersionError,
)
from wire_codec.message import Header, MapMessage, MessageKind

VERSION = 2
"""The newest format version this module writes and reads. Bump it on any change to the bytes.

Version 2 differs from version 1 only in the bound on ``robots`` (4,096 instead of 64; the
masks are ``len(robots)`` bits in both). The encoder writes the *oldest* version a message
fits (:func:`version_for`): version 1 for every robot map and every fused map of at most 64
robots, byte for byte what it wrote before version 2 existed, so decoders of version 1 keep
reading them; version 2 only for more robots (a version-1 decoder says VersionError)."""

VERSIONS = (1, 2)
"""The format versions :func:`decode` reads."""

N_FIELDS = 13
MIN_MESSAGE_BYTES = 20
"""No valid message is shorter (array header, 12 one-byte-or-more fields, the 5-byte CRC)."""

MAX_UINT64 = (1 << 64) - 1
MAX_RESOLUTION_MM = 10**6
MAX_THETA_URAD = 3_141_593
_CRC_MARK = 0xCE
_KINDS = frozenset(k.value for k in MessageKind)


# ---------------------------------------------------------------------------------------- encode
def encode(message: MapMessage, *, cache: BodyCache | None = None) -> bytes:
    """Serialise a :class:`MapMessage` to bytes (FORMAT.md). The body is taken from ``cache``
    (default: a cache of the last 64 maps shared by every caller) when the same ``Wireframe``
    object was encoded before: the bytes are the same either way.

    Raises
    ------
    EncodeError
        When the message cannot travel: a field of the wrong type or out of range, a robot map
        with contributor masks or robots, a fused map with more than 4,096 robots
        (``MAX_ROBOTS``) or a mask bit beyond them, a vertex too far from the origin for the
        resolution, unpackable ``meta``.
    """
    return _encode(message, _shared_bodies if cache is None else cache)[0]


def version_for(n_robots: int) -> int:
    """The format version written for a message listing ``n_robots`` robots: 1 up to 64
    robots (every robot map), else 2."""
    return 1 if n_robots <= MAX_ROBOTS_V1 else 2


class BodyCache:
    """Encoded bodies by ``Wireframe`` object (immutable: frozen, read-only arrays) and what else
    the body depends on (resolution, robot count), so that the same map sent again with a new
    envelope costs only the envelope. An entry holds its map, so the map's ``id`` cannot be
    reused while the entry lives; the oldest entry goes first once ``max_entries`` are held.
    Thread-safe.

    :func:`encode` keeps one of 64 entries for every caller (a robot's heartbeat and change
    probe, the fusion service's stored copy of what it published); a caller that sends a known
    set of maps over and over (a replayed recording) gives :func:`encode` its own, as large as
    the set."""

    def __init__(self, max_entries: int = 64) -> None:
        if max_entries < 1:
            raise ValueError(f"a body cache holds at least one entry, got {max_entries}")
        self.max_entries = int(max_entries)
        self._entries: dict[tuple[int, int, int | None], tuple[Wireframe, bytes]] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def holds(self, wf: Wireframe) -> bool:
        """Whether a body of ``wf`` (at any resolution) is held."""
        with self._lock:
            return any(entry[0] is wf for entry in self._entries.values())

    def body(self, wf: Wireframe, res_mm: int, n_robots: int | None) -> bytes:
        """The body bytes of ``wf`` at ``res_mm`` for ``n_robots`` (encoded on a miss)."""
        key = (id(wf), res_mm, n_robots)
        with self._lock:
            hit = self._entries.get(key)
        if hit is not None and hit[0] is wf:
            return hit[1]
        data = encode_body(wf, res_mm / 1e3, n_robots).data
        with self._lock:
            while len(self._entries) >= self.max_entries:
                self._entries.pop(next(iter(self._entries)))
            self._entries[key] = (wf, data)
        return data


_shared_bodies = BodyCache(64)


def encode_with_plan(message: MapMessage) -> tuple[bytes, EncodedBody]:
    """:func:`encode`, also returning the encoded body (with the vertex and edge order the
    decoder will produce), for tests and benchmarks."""
    out, body = _encode(message, None)
    assert body is not None
    return out, body


def _encode(message: MapMessage, cache: BodyCache | None) -> tuple[bytes, EncodedBody | None]:
    if not isinstance(message, MapMessage):
        raise EncodeError(f"expected a MapMessage, got {type(message).__name__}")
    try:
        kind = MessageKind(message.kind)
    except ValueError:
        raise EncodeError(f"unknown message kind {message.kind!r}") from None
    sender = _check_str(message.sender, "sender", allow_empty=False)
    frame = _check_str(message.frame, "frame", allow_empty=True)
    seq = _check_uint(message.seq, "seq")
    stamp = _check_uint(message.stamp_ns, "stamp_ns")
    pose = _pose_out(message.pose, "pose")
    origin = _pose_out(message.origin, "origin")
    res = message.resolution
    if isinstance(res, bool) or not isinstance(res, (int, float)) or not math.isfinite(res):
        raise EncodeError(f"resolution must be a finite number of metres, got {res!r}")
    res_mm = round(res * 1e3)
    if not 1 <= res_mm <= MAX_RESOLUTION_MM:
        raise EncodeError(f"resolution must be between 1 mm and 1 km, got {res!r} m")
    wf = message.wireframe
    if not isinstance(wf, Wireframe):
        raise EncodeError(f"wireframe must be a Wireframe, got {type(wf).__name__}")
    robots = tuple(message.robots)
    for rid in robots:
        _check_str(rid, "robot id", allow_empty=False)
    if len(set(robots)) != len(robots):
        raise EncodeError(f"robot ids must be distinct, got {robots}")
    if kind == MessageKind.ROBOT_MAP:
        if robots:
            raise EncodeError("a robot map has no robots list (it is for fused maps)")
        if wf.n_edges and wf.sources.any():
            raise EncodeError("a robot map's edges must have no contributor bits (sources all zero)")
        n_robots: int | None = None
    else:
        if len(robots) > MAX_ROBOTS:
            raise EncodeError(f"a fused map has at most {MAX_ROBOTS} robots, got {len(robots)}")
        n_robots = len(robots)
    if not isinstance(message.meta, Mapping):
        raise EncodeError(f"meta must be a dict, got {type(message.meta).__name__}")
    meta = dict(message.meta)
    _check_meta(meta, EncodeError)
    body: EncodedBody | None = None
    if cache is not None:
        data = cache.body(wf, res_mm, n_robots)
    else:
        body = encode_body(wf, res_mm / 1e3, n_robots)
        data = body.data
    fields = [version_for(len(robots)), int(kind), sender, seq, stamp, pose, frame, origin, res_mm,
              list(robots), meta, data]
    try:
        packed = msgpack.packb(fields, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise EncodeError(f"meta cannot be packed: {exc}") from None
    # packb wrote a 12-element array header (0x9c); the CRC makes it 13 (0x9d).
    head = b"\x9d" + packed[1:]
    return head + bytes([_CRC_MARK]) + zlib.crc32(head).to_bytes(4, "big"), body


def _check_str(value: Any, name: str, *, allow_empty: bool) -> str:
    if not isinstance(value, str):
        raise EncodeError(f"{name} must be a str, got {type(value).__name__}")
    if not value and not allow_empty:
        raise EncodeError(f"{name} must not be empty")
    if len(value.encode("utf-8", "surrogatepass")) > DEFAULT_LIMITS.max_string:
        raise EncodeError(f"{name} is longer than {DEFAULT_LIMITS.max_string} bytes")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise EncodeError(f"{name} is not valid Unicode text") from None
    return value


def _check_uint(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_UINT64:
        raise EncodeError(f"{name} must be an int in 0..2**64-1, got {value!r}")
    return int(value)


def _pose_out(pose: Any, name: str) -> list[int]:
    if not isinstance(pose, Pose):
        raise EncodeError(f"{name} must be a Pose, got {type(pose).__name__}")
    x, y = round(pose.x * 1000.0), round(pose.y * 1000.0)
    if max(abs(x), abs(y)) > DEFAULT_LIMITS.max_coordinate * 1000.0:
        raise EncodeError(f"{name} is further than {DEFAULT_LIMITS.max_coordinate:g} m from the origin")
    return [x, y, round(pose.theta * 1e6)]


# ---------------------------------------------------------------------------------------- decode
def decode(data: bytes | bytearray | memoryview, *, limits: Limits = DEFAULT_LIMITS) -> MapMessage:
    """Parse bytes written by :func:`encode`.

    Parameters
    ----------
    data : the payload.
    limits : bounds checked before anything proportional to them is allocated.

    Returns
    -------
    MapMessage
        With the wireframe's vertices and edges in the encoder's order (FORMAT.md), every vertex
        within half a resolution step of the original, likelihoods within 1/30, poses within
        0.5 mm and 0.5 µrad.

    Raises
    ------
    LimitError
        Larger than ``limits`` (payload bytes, vertices, edges, coordinates).
    VersionError
        Another format version.
    TruncatedError
        The payload ends early.
    ExtraDataError
        Bytes after the message (or after the body's map, or non-zero padding bits).
    ChecksumError
        The CRC-32 does not match.
    FormatError
        Anything else malformed, inconsistent or absurd.

    Every failure is a :class:`CodecError`; nothing else escapes.
    """
    return decode_with(data, limits, decode_body)


BodyDecoder = Callable[[bytes, int, "int | None", Limits], Wireframe]


def decode_with(
    data: bytes | bytearray | memoryview, limits: Limits, body_decoder: BodyDecoder
) -> MapMessage:
    """:func:`decode` with another body decoder (the tests run :mod:`wire_codec.reference`)."""
    obj = _envelope(data, limits)
    version, kind, sender, seq, stamp = _header(obj, limits)
    pose_v, frame, origin_v, res_mm, robots_v, meta, body = obj[5:12]
    frame = _str_in(frame, "frame", limits, allow_empty=True)
    pose = _pose_in(pose_v, "pose", limits)
    origin = _pose_in(origin_v, "origin", limits)
    if not _is_int(res_mm) or not 1 <= res_mm <= MAX_RESOLUTION_MM:
        raise FormatError(f"resolution must be 1..{MAX_RESOLUTION_MM} mm, got {res_mm!r}")
    if not isinstance(robots_v, list):
        raise FormatError("robots must be an array")
    robots = tuple(_str_in(r, "robot id", limits, allow_empty=False) for r in robots_v)
    if len(set(robots)) != len(robots):
        raise FormatError("robot ids are not distinct")
    if kind == MessageKind.ROBOT_MAP:
        if robots:
            raise FormatError("a robot map carries a robots list")
        n_robots: int | None = None
    else:
        bound = MAX_ROBOTS_V1 if version == 1 else min(MAX_ROBOTS, limits.max_robots)
        if len(robots) > bound:
            raise LimitError(f"a version {version} fused map has at most {bound} robots, got {len(robots)}")
        n_robots = len(robots)
    if not isinstance(meta, dict):
        raise FormatError("meta must be a map")
    _check_meta(meta, FormatError)
    if not isinstance(body, bytes):
        raise FormatError("body must be msgpack bin")
    wf = body_decoder(body, res_mm, n_robots, limits)
    return MapMessage(
        kind=kind,
        sender=sender,
        seq=seq,
        stamp_ns=stamp,
        pose=pose,
        frame=frame,
        origin=origin,
        resolution=res_mm / 1e3,
        wireframe=wf,
        robots=robots,
        meta=meta,
    )


def peek(data: bytes | bytearray | memoryview, *, limits: Limits = DEFAULT_LIMITS) -> Header:
    """The envelope's first five fields (version, kind, sender, seq, stamp_ns) without decoding
    the body (FORMAT.md, section 2.2): for a reader that only has to know whose map a payload
    is and when it was made, e.g. to skip a robot map that a newer one supersedes.

    It makes :func:`decode`'s checks 1 to 6 of FORMAT.md 2.1 (size, version byte, one msgpack
    array of 13 elements spanning the payload, the CRC-32) and checks those five fields as
    :func:`decode` does; so the fields it returns are the ones the sender wrote (the CRC
    holds). It does not look at the other fields nor at the body: a payload it accepts may
    still fail :func:`decode`; one it refuses, :func:`decode` refuses too. The cost is the
    msgpack parse and the CRC (microseconds for a robot map), against hundreds of
    microseconds for the body.

    Raises
    ------
    LimitError, VersionError, TruncatedError, ExtraDataError, ChecksumError, FormatError
        As :func:`decode` for those checks. Every failure is a :class:`CodecError` (a
        ``ValueError``); nothing else escapes.
    """
    return _header(_envelope(data, limits), limits)


def _envelope(data: Any, limits: Limits) -> list[Any]:
    """Checks 1 to 6 of FORMAT.md 2.1: the payload as the envelope's 13 msgpack values, the
    CRC-32 verified."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise FormatError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > limits.max_bytes:
        raise LimitError(f"payload is {len(data)} bytes, the limit is {limits.max_bytes}")
    if len(data) >= 2 and 0x90 <= data[0] <= 0x9F and data[1] <= 0x7F and data[1] not in VERSIONS:
        raise VersionError(f"format version {data[1]}, this decoder reads versions 1 and 2")
    if len(data) < MIN_MESSAGE_BYTES:
        raise TruncatedError(f"payload is {len(data)} bytes, a message is at least {MIN_MESSAGE_BYTES}")
    obj = _unpack(data, limits)
    if not isinstance(obj, list) or len(obj) != N_FIELDS:
        if isinstance(obj, list) and obj and _is_int(obj[0]) and obj[0] not in VERSIONS:
            raise VersionError(f"format version {obj[0]}, this decoder reads versions 1 and 2")
        raise FormatError(f"expected a msgpack array of {N_FIELDS} fields")
    if data[-5] != _CRC_MARK or not _is_int(obj[-1]):
        raise FormatError("the message does not end with a uint32 CRC-32")
    crc = zlib.crc32(data[:-5])
    if obj[-1] != crc:
        raise ChecksumError(f"CRC-32 mismatch: payload says {obj[-1]:08x}, bytes give {crc:08x}")
    return obj


def _header(obj: list[Any], limits: Limits) -> Header:
    """The envelope's first five fields (:func:`_envelope`'s values), checked: what
    :func:`peek` returns and :func:`decode_with` starts from."""
    version, kind_v = obj[0], obj[1]
    if not _is_int(version) or version not in VERSIONS:
        raise VersionError(f"format version {version!r}, this decoder reads versions 1 and 2")
    if not _is_int(kind_v) or kind_v not in _KINDS:
        raise FormatError(f"unknown message kind {kind_v!r}")
    return Header(
        version=version,
        kind=MessageKind(kind_v),
        sender=_str_in(obj[2], "sender", limits, allow_empty=False),
        seq=_uint_in(obj[3], "seq"),
        stamp_ns=_uint_in(obj[4], "stamp_ns"),
    )


def _unpack(data: bytes, limits: Limits) -> Any:
    """One msgpack object spanning all of ``data``; every msgpack failure becomes a CodecError."""
    n = len(data)
    unpacker = msgpack.Unpacker(
        raw=False,
        strict_map_key=True,
        max_buffer_size=max(n, 1),
        max_str_len=n,
        max_bin_len=n,
        max_array_len=n,
        max_map_len=n // 2,
        max_ext_len=n,
    )
    try:
        unpacker.feed(data)
        obj = unpacker.unpack()
        end = unpacker.tell()
    except msgpack.OutOfData:
        raise TruncatedError("payload ends inside the msgpack envelope") from None
    except msgpack.StackError:
        raise FormatError("msgpack nesting too deep") from None
    except UnicodeDecodeError:
        raise FormatError("a msgpack string is not valid UTF-8") from None
    except ValueError as exc:
        if "exceeds max" in str(exc):
            raise LimitError(f"msgpack: {exc}") from None
        raise FormatError(f"msgpack: {exc or type(exc).__name__}") from None
    except Exception as exc:  # a third-party parser: whatever else it raises is a bad payload
        raise FormatError(f"msgpack: {type(exc).__name__}: {exc}") from None
    if end != n:
        raise ExtraDataError(f"{n - end} bytes follow the msgpack envelope")
    return obj


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _str_in(v: Any, name: str, limits: Limits, *, allow_empty: bool) -> str:
    if not isinstance(v, str):
        raise FormatError(f"{name} must be a string")
    if not v and not allow_empty:
        raise FormatError(f"{name} is empty")
    if len(v.encode("utf-8", "surrogatepass")) > limits.max_string:
        raise LimitError(f"{name} is longer than {limits.max_string} bytes")
    return v


def _uint_in(v: Any, name: str) -> int:
    if not _is_int(v) or v < 0:
        raise FormatError(f"{name} must be an unsigned integer, got {v!r}")
    return int(v)


def _pose_in(v: Any, name: str, limits: Limits) -> Pose:
    if not isinstance(v, list) or len(v) != 3 or not all(_is_int(c) for c in v):
        raise FormatError(f"{name} must be an array of three integers [x_mm, y_mm, theta_urad]")
    x, y, t = v
    if max(abs(x), abs(y)) > limits.max_coordinate * 1000.0:
        raise LimitError(f"{name} is further than {limits.max_coordinate:g} m from the origin")
    if abs(t) > MAX_THETA_URAD:
        raise FormatError(f"{name} heading {t} µrad is outside [-pi, pi]")
    return Pose(x / 1000.0, y / 1000.0, t / 1e6)


_META_SCALARS = (type(None), bool, int, float, str, bytes)


def _check_meta(meta: dict[Any, Any], error: type[CodecError]) -> None:
    """``meta`` holds only msgpack's plain types (no ext types), with string map keys.
    Iterative, so that a deeply nested payload cannot exhaust the Python stack."""
    stack: list[Any] = [meta]
    seen: set[int] = set()
    while stack:
        item = stack.pop()
        if isinstance(item, (msgpack.ExtType, msgpack.Timestamp)):
            raise error(f"meta may hold only plain msgpack values, got {type(item).__name__}")
        if isinstance(item, (dict, list, tuple)):
            if id(item) in seen:
                raise error("meta contains a container twice (or a cycle)")
            seen.add(id(item))
        if isinstance(item, dict):
            for key, value in item.items():
                if not isinstance(key, str):
                    raise error(f"meta map keys must be strings, got {type(key).__name__}")
                stack.append(value)
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
        elif isinstance(item, int) and not isinstance(item, bool) and not -(1 << 63) <= item <= MAX_UINT64:
            raise error("meta integer out of the 64-bit range")
        elif not isinstance(item, _META_SCALARS):
            raise error(f"meta may hold only plain msgpack values, got {type(item).__name__}")
