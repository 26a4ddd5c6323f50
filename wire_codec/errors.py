"""Codec errors and decoding limits.

Every failure of :func:`wire_codec.decode` is a :class:`CodecError`; the subclass says which kind
of failure it is, and the message says where. The hierarchy mirrors msgpack's
(``OutOfData``, ``ExtraData``, ``FormatError``) with a few wire-map specific additions.
:class:`CodecError` derives from :class:`ValueError` so that callers that already catch
``ValueError`` for "bad input" keep working.
"""

from __future__ import annotations

from dataclasses import dataclass


class CodecError(ValueError):
    """Base class: the payload is not a valid wire-map message (or a message cannot be encoded)."""


class TruncatedError(CodecError):
    """The payload ends before the message does (out of data)."""


class ExtraDataError(CodecError):
    """Bytes (or non-zero padding bits) follow the end of the message."""


class ChecksumError(CodecError):
    """The CRC-32 in the envelope does not match the bytes it covers."""


class VersionError(CodecError):
    """The payload declares a format version this decoder does not speak."""


class LimitError(CodecError):
    """The payload is, or claims to be, larger than the decoder's :class:`Limits` allow."""


class FormatError(CodecError):
    """The payload is malformed, internally inconsistent or carries absurd values."""


class EncodeError(CodecError):
    """The message cannot be represented in the wire format (raised by ``encode`` only)."""


@dataclass(frozen=True)
class Limits:
    """Upper bounds a decoder enforces before allocating anything proportional to them.

    Parameters
    ----------
    max_bytes : int
        Largest accepted payload, envelope included. Checked first, on ``len(data)``.
    max_vertices : int
        Largest vertex count a body may declare.
    max_edges : int
        Largest edge count a body may declare.
    max_coordinate : float
        Largest accepted ``|x|`` or ``|y|`` of a vertex or of a pose, in metres.
    max_string : int
        Longest accepted sender, frame or robot id, in UTF-8 bytes.
    max_robots : int
        Most robots a fused map may list (the format's own bound is 4,096; version 1: 64).

    The defaults comfortably admit a 5,000-vertex fused map of a 64-robot fleet (about 20 kB).
    """

    max_bytes: int = 1 << 20
    max_vertices: int = 100_000
    max_edges: int = 200_000
    max_coordinate: float = 1.0e7
    max_string: int = 256
    max_robots: int = 4096

    def __post_init__(self) -> None:
        for name in ("max_bytes", "max_vertices", "max_edges", "max_string", "max_robots"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"Limits.{name} must be a non-negative int, got {value!r}")
        if not (self.max_coordinate > 0.0 and self.max_coordinate < float("inf")):
            raise ValueError(
                f"Limits.max_coordinate must be positive and finite, got {self.max_coordinate!r}"
            )


DEFAULT_LIMITS = Limits()
