"""Map messages as the fusion service handles them: bytes <-> :class:`MapMessage` and the order
of a robot's maps.

The fusion decodes robot maps with tighter :class:`wire_codec.Limits` than the codec's default
(:meth:`agents.fleet.fusion.intake.InputLimits.codec_limits`).
"""

from __future__ import annotations

import hashlib

import wire_codec
from wire_codec.codec import BodyDecoder, decode_with
from wire_codec.message import MapMessage


def encode_message(msg: MapMessage) -> bytes:
    """The codec bytes of ``msg`` (:func:`wire_codec.encode`)."""
    return wire_codec.encode(msg)


def decode_message(
    data: bytes, limits: wire_codec.Limits | None = None, body_decoder: BodyDecoder | None = None
) -> MapMessage:
    """Decode codec bytes.

    Parameters
    ----------
    data : bytes
    limits : wire_codec.Limits, optional
        What the decoder accepts (default: the codec's).
    body_decoder : optional
        Reads the body (``(body, resolution_mm, n_robots, limits) -> Wireframe``, as
        :func:`wire_codec.body.decode_body`; :func:`wire_codec.codec.decode_with`); default the
        codec's.

    Raises
    ------
    wire_codec.CodecError
        (a ``ValueError``) on a malformed payload or one beyond ``limits``.
    """
    if body_decoder is not None:
        return decode_with(data, wire_codec.Limits() if limits is None else limits, body_decoder)
    if limits is None:
        return wire_codec.decode(data)
    return wire_codec.decode(data, limits=limits)


def peek_header(data: bytes, limits: wire_codec.Limits | None = None) -> wire_codec.Header:
    """Kind, sender, seq and stamp of codec bytes without decoding the body
    (:func:`wire_codec.peek`: the envelope and its CRC are checked).

    Raises
    ------
    wire_codec.CodecError
        (a ``ValueError``) on a payload whose envelope is malformed or beyond ``limits``.
    """
    if limits is None:
        return wire_codec.peek(data)
    return wire_codec.peek(data, limits=limits)


def order_key(msg: MapMessage, raw: bytes) -> tuple[int, int, str]:
    """``(boot, seq, sha256)``: a restarted robot (new ``meta["boot"]``) supersedes its old
    maps even though its ``seq`` starts again; the hash breaks (unexpected) ties the same way
    whatever the arrival order."""
    boot = msg.meta.get("boot", 0) if isinstance(msg.meta, dict) else 0
    try:
        boot = int(boot)
    except (TypeError, ValueError):
        boot = 0
    return (boot, int(msg.seq), hashlib.sha256(raw).hexdigest())
