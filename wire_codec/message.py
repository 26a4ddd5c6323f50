"""The message that travels: a wireframe with its sender's metadata.

``wire_codec.encode(MapMessage) -> bytes`` and ``wire_codec.decode(bytes) -> MapMessage``;
``wire_codec.peek(bytes) -> Header`` reads the envelope's first fields alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, NamedTuple

from mapping.se2 import Pose
from mapping.wireframe import Wireframe


class MessageKind(IntEnum):
    ROBOT_MAP = 1  # one robot's best wireframe, in the robot's own odometry frame
    FUSED_MAP = 2  # the fusion service's map, in the fleet frame


@dataclass(frozen=True)
class MapMessage:
    """A map with its sender's metadata.

    Attributes
    ----------
    kind : robot map or fused map.
    sender : robot id (``r1``) or the fusion service's id.
    seq : sender's sequence number (fused: the fused map's version), increasing.
    stamp_ns : sender's clock when the map was made, nanoseconds since the epoch (or sim time).
    pose : sender's pose estimate in ``frame`` (identity for the fused map).
    frame : the frame the map's coordinates are in (``"odom/r1"``, ``"fleet"``).
    origin : the sender's start pose in the fleet frame (known start poses; identity for fused).
    resolution : quantisation step of the coordinates in metres (the merge threshold).
    wireframe : the map.
    robots : for a fused map, contributor bit k of ``wireframe.sources`` is ``robots[k]``.
    meta : small extra facts (e.g. ``{"stale": ["r2"]}``); msgpack-able values only.
    """

    kind: MessageKind
    sender: str
    seq: int
    stamp_ns: int
    pose: Pose
    frame: str
    origin: Pose
    resolution: float
    wireframe: Wireframe
    robots: tuple[str, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)


class Header(NamedTuple):
    """The first five fields of a message's envelope, as :func:`wire_codec.peek` reads them
    without decoding the body (FORMAT.md, section 2.2).

    Attributes
    ----------
    version : the format version (1 or 2).
    kind : robot map or fused map.
    sender : the sender's id.
    seq : the sender's sequence number.
    stamp_ns : the sender's clock when the map was made (ns).
    """

    version: int
    kind: MessageKind
    sender: str
    seq: int
    stamp_ns: int
