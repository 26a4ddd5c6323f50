"""What the fusion's intake computes from one robot map's wireframe, kept with the map (issue 21).

A robot sends the same map again and again: a filter's map between two changes, a heartbeat,
a replay robot whose recording has one frame (at 64 synthetic robots about 45 % of the maps
the fusion takes in). Such a payload's body is byte for byte the body of the robot's latest
accepted map: :meth:`~agents.fleet.fusion.state.FusionState.offer` then skips reading the body
(the codec's body decoder is a function of the body's bytes, the resolution and the limits
alone, so it would return the same arrays) and hands on the latest map's :class:`Wireframe`
object itself, with its :class:`MapFacts`. Every check still runs on the new message (the
envelope, its header, fields and CRC, the content checks, the budgets and reach, the seq
jump, the restart rule, the work budget, both consistency tests against the robot's history
and the fleet's present map); what is not computed again are the values below, each a pure
function of the wireframe's arrays and of the arguments it is asked with, which are part of
its key: so every check gives the answer the full path gives, by construction.

Kept per wireframe (keys, see the callers):

* ``("budget", limits)``: :func:`~agents.fleet.fusion.intake.content_budget`'s verdict (vertex
  and wall budgets, density);
* ``("far",)``: the largest distance of a vertex from the robot's start (the reach check);
* ``("samples", step)``: :func:`~agents.fleet.fusion.quarantine._samples`, points along the
  walls and their edges (the history test; the fleet test on the moved map);
* ``("near", step)``: the k-d tree of the history test's reference points;
* ``("applied", origin bits)``: the vertices moved by the start pose into the fleet frame
  (the extent check, :func:`agents.fleet.validate.robot_map`), and ``("moved", origin bits)``:
  the map moved so, with its own :class:`MapFacts` (the fleet test).

Nothing is kept between two different maps of a robot: a map whose body differs is decoded
and computed from scratch, as before.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

from mapping.se2 import Pose
from mapping.wireframe import FloatArray, Wireframe

T = TypeVar("T")

#: Values kept per wireframe at most (the keys are a handful; more only for a map sent with
#: ever new start poses: the oldest is forgotten).
MAX_FACTS = 16


class MapFacts:
    """Memoised pure functions of one (immutable) :class:`Wireframe` (see the module)."""

    __slots__ = ("_memo", "wf")

    def __init__(self, wf: Wireframe) -> None:
        self.wf = wf
        self._memo: dict[Hashable, Any] = {}

    def get(self, key: Hashable, compute: Callable[[], T]) -> T:
        """The value under ``key``, computed by ``compute()`` the first time (an exception is
        passed on and nothing is kept)."""
        memo = self._memo
        if key in memo:
            value: T = memo[key]
            return value
        value = compute()
        if len(memo) >= MAX_FACTS:
            memo.pop(next(iter(memo)))
        memo[key] = value
        return value

    def applied(self, pose: Pose) -> FloatArray:
        """``pose.apply(self.wf.points)`` (kept, read-only): the points in the fleet frame."""
        def compute() -> FloatArray:
            out = pose.apply(self.wf.points)
            out.setflags(write=False)
            return out

        return self.get(("applied", pose_bits(pose)), compute)

    def moved(self, pose: Pose) -> MapFacts:
        """The facts of ``self.wf.transformed(pose)``, that is ``moved_to`` the points
        :meth:`applied` gives (kept: the same pose, bit for bit, gives the same object)."""
        return self.get(("moved", pose_bits(pose)), lambda: MapFacts(self.wf.moved_to(self.applied(pose))))


def facts_of(wf: Wireframe, facts: MapFacts | None) -> MapFacts:
    """``facts`` when they are ``wf``'s, else new (empty) facts of ``wf``."""
    return facts if facts is not None and facts.wf is wf else MapFacts(wf)


def pose_bits(pose: Pose) -> bytes:
    """The pose's three floats as bytes: equal exactly when every bit is (``0.0`` and ``-0.0``
    differ)."""
    return struct.pack("<3d", pose.x, pose.y, pose.theta)
