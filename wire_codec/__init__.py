"""Bytes <-> wireframe messages. See FORMAT.md."""

from wire_codec.message import MapMessage, MessageKind

__all__ = ["MapMessage", "MessageKind"]
