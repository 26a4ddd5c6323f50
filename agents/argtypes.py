"""argparse ``type=`` callables shared by the commands: a bad value is argparse's one-line
error and exit status 2, before anything runs."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T", int, float)


def _checked(
    name: str, read: Callable[[str], T], unread: str, ok: Callable[[T], bool], need: str
) -> Callable[[str], T]:
    """A ``type=`` callable: ``read(text)``, else ``"{unread}: 'text'"``; then ``ok(value)``,
    else ``"{need}, got 'text'"`` (both argparse's one-line error)."""

    def parse(text: str) -> T:
        try:
            v = read(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{unread}: {text!r}") from None
        if not ok(v):
            raise argparse.ArgumentTypeError(f"{need}, got {text!r}")
        return v

    parse.__name__ = parse.__qualname__ = name
    return parse


#: A finite number > 0.
positive_float = _checked("positive_float", float, "not a number", lambda v: math.isfinite(v) and v > 0.0,
                          "must be a positive number")
#: A whole number > 0.
positive_int = _checked("positive_int", int, "not an integer", lambda v: v > 0, "must be positive")
#: A number within [0, 1].
probability = _checked("probability", float, "not a number", lambda v: 0.0 <= v <= 1.0,
                       "must be within [0, 1]")
#: A TCP port, 0..65535.
port = _checked("port", int, "not a port number", lambda v: 0 <= v <= 65535, "port must be within 0..65535")
#: A finite number >= 0.
non_negative_float = _checked("non_negative_float", float, "not a number",
                              lambda v: math.isfinite(v) and v >= 0.0, "must be a number >= 0")
#: A whole number >= 0.
non_negative_int = _checked("non_negative_int", int, "not an integer", lambda v: v >= 0, "must be >= 0")
#: A picture's larger side in pixels: a whole number, at least 64.
image_size = _checked("image_size", int, "not an integer", lambda v: v >= 64, "must be at least 64 pixels")


def add_bag_topics(parser: argparse.ArgumentParser | argparse._ArgumentGroup, context: str = "") -> None:
    """``--scan-topic`` and ``--odom-topic``, the ROS bag topics every command that reads a bag
    takes (``context``: what the help says they go with, e.g. ``"with --rosbag: "``)."""
    parser.add_argument("--scan-topic", metavar="TOPIC",
                        help=f"{context}the sensor_msgs/LaserScan topic (default: the bag's only one)")
    parser.add_argument("--odom-topic", metavar="TOPIC",
                        help=f"{context}the nav_msgs/Odometry topic, or /tf (default: the bag's only "
                        "Odometry topic, else /tf)")


def scan_range(text: str) -> tuple[int, int]:
    """``--scans I0:I1``: scans ``I0`` to ``I1 - 1`` of a log (``0 <= I0 < I1``), as a ``type=``."""
    try:
        a, b = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be I0:I1, got {text!r}") from None
    if not 0 <= a < b:
        raise argparse.ArgumentTypeError(f"must be I0:I1 with 0 <= I0 < I1, got {text!r}")
    return a, b

