"""Bytes <-> wireframe messages. See FORMAT.md.

``encode(MapMessage) -> bytes`` and ``decode(bytes, *, limits=Limits()) -> MapMessage``;
``peek(bytes, *, limits=Limits()) -> Header`` reads kind, sender, seq and stamp without the
body. Every decoding failure is a :class:`CodecError`. No I/O, no zenoh, no rerun.
"""

from wire_codec.body import MAX_ROBOTS, MAX_ROBOTS_V1
from wire_codec.codec import VERSION, VERSIONS, BodyCache, decode, encode, peek, version_for
from wire_codec.errors import (
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

__all__ = [
    "MAX_ROBOTS",
    "MAX_ROBOTS_V1",
    "VERSION",
    "VERSIONS",
    "BodyCache",
    "ChecksumError",
    "CodecError",
    "EncodeError",
    "ExtraDataError",
    "FormatError",
    "Header",
    "LimitError",
    "Limits",
    "MapMessage",
    "MessageKind",
    "TruncatedError",
    "VersionError",
    "decode",
    "encode",
    "peek",
    "version_for",
]
