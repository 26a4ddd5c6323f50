"""What the fusion service accepts from the bus, and the bounded inbox in front of it.

* :class:`InputLimits`: sizes, rates and content bounds (choices, see there);
* :class:`Intake`: the bounded FIFO between Zenoh's callback thread and the fusion loop, which
  drops (and counts) payloads before anything is decoded; :func:`by_key` groups what it drains
  by robot key (only each key's newest payload is decoded);
* :func:`implausible`: the content checks of a decoded robot map; :func:`over_budget` and
  :func:`too_dense`: what one robot map may cost;
* :class:`DropLog`: at most one line per period summarising what was dropped.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

import wire_codec
from agents.fleet import validate
from agents.fleet.fusion.facts import MapFacts, facts_of
from mapping.wireframe import Wireframe
from wire_codec import MAX_ROBOTS
from wire_codec.message import MapMessage


@dataclass(frozen=True)
class InputLimits:
    """What the fusion service accepts on ``robots/<id>/map`` (choices; see
    :mod:`agents.fleet.fusion`).

    max_bytes : largest payload (256 KiB: a robot map of the largest built-in world is ~10 kB).
    max_vertices, max_edges : largest robot map (decoder limits, checked before allocating).
    max_extent_m : largest ``|x|`` or ``|y|`` of the origin and of every vertex in the fleet
        frame ("kilometres away" is absurd for a building).
    max_resolution_m : largest map resolution (a coarser one raises the default merge threshold).
    max_clock_skew_s : how far in the future a ``meta.boot`` or ``stamp_ns`` may lie (wall clocks
        of one fleet differ by NTP's error; 2 minutes is generous, and a map from the future is
        refused, not stored).
    rate_hz, burst : token bucket per key (robots send at most ~10 maps/s).
    queue_depth : payloads waiting per key (the oldest is dropped: maps are whole states).
    queue_bytes : bytes waiting over all keys.
    max_keys : keys tracked at once (rate buckets and side channels).
    pose_bytes, viz_bytes : largest pose / visualisation payload.
    max_robot_vertices, max_robot_wall_m : a robot map's budget (vertices, total wall length):
        the fusion's cost grows with them (ICP and merge), so one robot cannot buy more. The
        largest built-in world's robot maps have a few hundred vertices.
    max_cell_vertices, max_cell_wall_m : at most this many vertices and metres of walls in any
        square metre (cells of a 1 m grid): the cost of ICP and merge grows with the walls near
        each wall, so a budget-sized map stacked in a few square metres costs seconds; honest
        maps of the built-in worlds have at most 2 vertices and 2.1 m of walls in a cell.
    sensor_range_m, max_speed_mps, reach_slack_m : a robot's map lies within ``sensor_range_m +
        max_speed_mps * (time since its boot) + reach_slack_m`` of its start pose: it cannot
        have seen further (a lidar's range, a fast robot; checked with the fusion's clock).
    """

    max_bytes: int = 256 * 1024
    max_vertices: int = 20_000
    max_edges: int = 40_000
    max_extent_m: float = 1000.0
    max_resolution_m: float = 2.0
    max_clock_skew_s: float = 120.0
    rate_hz: float = 50.0
    burst: int = 100
    queue_depth: int = 64
    queue_bytes: int = 8 * 1024 * 1024
    max_keys: int = 4 * MAX_ROBOTS
    pose_bytes: int = 16 * 1024
    viz_bytes: int = 4 * 1024 * 1024
    max_robot_vertices: int = 3000
    max_robot_wall_m: float = 5000.0
    max_cell_vertices: int = 32
    max_cell_wall_m: float = 12.0
    sensor_range_m: float = 40.0
    max_speed_mps: float = 3.0
    reach_slack_m: float = 10.0

    def codec_limits(self) -> wire_codec.Limits:
        """The :class:`wire_codec.Limits` the decoder enforces for robot maps."""
        return wire_codec.Limits(
            max_bytes=self.max_bytes,
            max_vertices=min(self.max_vertices, self.max_robot_vertices),
            max_edges=self.max_edges,
            max_coordinate=self.max_extent_m,
            max_string=128,
        )


def implausible(
    msg: MapMessage, limits: InputLimits, now_ns: int | None = None, facts: MapFacts | None = None
) -> tuple[str, str] | None:
    """``(reason, detail)`` when a decoded robot map's content is absurd, else None.

    The field checks are :func:`agents.fleet.validate.robot_map`'s (reasons ``resolution``,
    ``extent``, ``meta``, ``seq``, ``stamp``); with ``now_ns`` also ``future``: ``meta.boot`` or
    ``stamp_ns`` more than ``max_clock_skew_s`` after ``now_ns`` (a map from the future would
    outrank every real one of its robot: it is refused, never stored). ``facts``: the
    wireframe's :class:`~agents.fleet.fusion.facts.MapFacts` (the vertices in the fleet frame
    are kept there, for the fleet test).
    """
    wf = msg.wireframe
    fleet_points = None
    if facts is not None and facts.wf is wf:
        f, origin = facts, msg.origin
        fleet_points = lambda: f.applied(origin)  # noqa: E731
    bad = validate.robot_map(msg, limits.max_extent_m, limits.max_resolution_m, fleet_points)
    if bad is not None:
        return bad
    if now_ns is not None:
        meta = msg.meta if isinstance(msg.meta, dict) else {}
        boot = int(meta.get("boot", 0))
        skew = limits.max_clock_skew_s * 1e9
        if boot > now_ns + skew:
            return "future", f"meta.boot is {(boot - now_ns) / 1e9:.0f} s in the future"
        if int(msg.stamp_ns) > now_ns + skew:
            return "future", f"stamp_ns is {(int(msg.stamp_ns) - now_ns) / 1e9:.0f} s in the future"
    return None


def over_budget(
    msg: MapMessage, limits: InputLimits, now_ns: int | None = None, facts: MapFacts | None = None
) -> tuple[str, str] | None:
    """``(reason, detail)`` when a robot map is beyond what one robot may cost or could have
    seen, else None: ``budget_vertices``, ``budget_walls`` (total wall length), ``budget_density``
    (:func:`content_budget`), ``reach`` (a vertex further from the start pose than the robot
    could have seen since its boot; only checked with ``now_ns``).

    ``facts``: the wireframe's :class:`~agents.fleet.fusion.facts.MapFacts` (ignored when they
    are another wireframe's), where :func:`content_budget`'s verdict and the farthest vertex's
    distance are kept: both are functions of the arrays (and the limits) alone, so a map sent
    again costs only the clock's part of the reach check."""
    wf = msg.wireframe
    f = facts_of(wf, facts)
    bad = f.get(("budget", limits), lambda: content_budget(wf, limits))
    if bad is not None:
        return bad
    if now_ns is not None and wf.n_vertices:
        meta = msg.meta if isinstance(msg.meta, dict) else {}
        elapsed = max(0.0, (now_ns - int(meta.get("boot", 0))) / 1e9)
        reach = limits.sensor_range_m + limits.max_speed_mps * elapsed + limits.reach_slack_m
        # odometry frame: from the start
        far = f.get(("far",), lambda: float(np.hypot(wf.points[:, 0], wf.points[:, 1]).max()))
        if far > reach:
            return (
                "reach",
                f"a vertex {far:.0f} m from the start, {elapsed:.0f} s after boot (reach {reach:.0f} m)",
            )
    return None


def content_budget(wf: Wireframe, limits: InputLimits) -> tuple[str, str] | None:
    """:func:`over_budget`'s tests of the arrays alone: ``budget_vertices``, ``budget_walls``
    (total wall length) and :func:`too_dense`. Cheap: one pass over the arrays (the wall
    lengths are computed once, for the budget and :func:`too_dense`)."""
    if wf.n_vertices > limits.max_robot_vertices:
        return "budget_vertices", f"{wf.n_vertices} vertices (budget {limits.max_robot_vertices})"
    lengths = None
    if wf.n_edges:
        seg = wf.points[wf.edges]
        lengths = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
        length = float(lengths.sum())
        if length > limits.max_robot_wall_m:
            return "budget_walls", f"{length:.0f} m of walls (budget {limits.max_robot_wall_m:g} m)"
    return too_dense(wf, limits, lengths)


DENSITY_STEP_M = 0.5  # walls are sampled this often to measure their length per cell

#: The most wall length one edge can put into one cell, as :func:`too_dense` measures it: its
#: samples in a 1 m cell lie on a run of at most sqrt(2) m (the cell's diagonal), at most
#: ``run / spacing + 1`` of them, each weighing the spacing (at most ``DENSITY_STEP_M``):
#: sqrt(2) + 0.5 = 1.91 m, rounded up to leave room for rounding.
EDGE_CELL_BOUND_M = 2.0

#: Cells of a map's bounding box up to which :func:`too_dense` counts per cell with a dense
#: ``bincount`` (256 KiB of float64) instead of sorting the cell codes (``np.unique``).
DENSE_CELLS = 32_768


def _per_cell(xy: np.ndarray, weights: np.ndarray | None = None) -> float:
    """The largest count (or sum of ``weights``) of the points ``xy`` in one 1 m grid cell.

    Where the points' bounding box spans at most ``DENSE_CELLS`` cells, one ``bincount`` over
    the cells' indices in the box; else ``np.unique`` over one integer code per cell (the
    coordinates are bounded by the codec's limits), then ``bincount`` over the inverse. Both
    add each cell's weights one by one in the points' order, so the sums are bit for bit the
    same (and so the verdicts of :func:`too_dense`)."""
    c = np.floor(xy).astype(np.int64)
    lo = c.min(axis=0)
    span = c.max(axis=0) - lo + 1
    if int(span[0]) * int(span[1]) <= DENSE_CELLS:
        index = (c[:, 0] - lo[0]) * span[1] + (c[:, 1] - lo[1])
        return float(np.bincount(index, weights=weights).max())
    cells, inv = np.unique((c[:, 0] << 32) + c[:, 1], return_inverse=True)
    return float(np.bincount(inv, weights=weights, minlength=len(cells)).max())


def too_dense(
    wf: Wireframe, limits: InputLimits, lengths: np.ndarray | None = None
) -> tuple[str, str] | None:
    """``("budget_density", detail)`` when a square metre of the map (a 1 m grid cell) holds
    more than ``limits.max_cell_vertices`` vertices or ``limits.max_cell_wall_m`` metres of
    walls (measured on points every ``DENSITY_STEP_M`` along the walls), else None.

    ``lengths``: the edges' lengths when the caller has them (:func:`over_budget`). Skipped
    because they cannot fail, so that small maps cost almost nothing (issue 21: this was a
    quarter of a robot map's intake): the vertex count when the map has at most
    ``max_cell_vertices`` vertices, the wall length when ``EDGE_CELL_BOUND_M`` per edge cannot
    reach ``max_cell_wall_m``. The counts themselves are :func:`_per_cell`'s, the same numbers
    as before these shortcuts."""
    if wf.n_vertices == 0:
        return None
    if wf.n_vertices > limits.max_cell_vertices:
        most = int(_per_cell(wf.points))
        if most > limits.max_cell_vertices:
            return (
                "budget_density",
                f"{most} vertices in one square metre (budget {limits.max_cell_vertices})",
            )
    if wf.n_edges == 0 or EDGE_CELL_BOUND_M * wf.n_edges <= limits.max_cell_wall_m:
        return None
    seg = wf.points[wf.edges]
    length = np.hypot(*(seg[:, 1] - seg[:, 0]).T) if lengths is None else lengths
    k = np.maximum(1, np.ceil(length / DENSITY_STEP_M).astype(np.int64))  # samples per edge (midpoints)
    owner = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k) + 0.5) / k[owner]
    pts = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
    metres = _per_cell(pts, (length / k)[owner])
    if metres > limits.max_cell_wall_m:
        return (
            "budget_density",
            f"{metres:.0f} m of walls in one square metre (budget {limits.max_cell_wall_m:g} m)",
        )
    return None


def by_key(items: Sequence[tuple[str, bytes, int]]) -> list[tuple[str, list[tuple[bytes, int]]]]:
    """The payloads of one drained batch (:meth:`Intake.drain_timed`: ``(key, bytes, arrival
    ns)`` in arrival order) grouped by key: each key's ``(bytes, arrival ns)`` in arrival order,
    the keys in the order of their newest payload's arrival (the one the fusion decodes,
    :meth:`~agents.fleet.fusion.state.FusionState.offer_latest`)."""
    groups: dict[str, list[tuple[bytes, int]]] = {}
    last: dict[str, int] = {}
    for i, (key, data, at) in enumerate(items):
        groups.setdefault(key, []).append((data, at))
        last[key] = i
    return [(key, groups[key]) for key in sorted(groups, key=last.__getitem__)]


class Intake:
    """The bounded inbox between Zenoh's callback thread and the fusion loop.

    :meth:`put` runs in Zenoh's thread and decides, before copying or decoding anything,
    whether a payload may wait: not over ``limits.max_bytes`` (``oversized``), within its key's
    token bucket (``rate_hz`` refilled, ``burst`` deep; ``rate_limited``), at most
    ``max_keys`` keys at once (idle buckets are forgotten first), at most ``queue_depth``
    payloads per key (the oldest is dropped) and ``queue_bytes`` in all (the new one is
    dropped); both count as ``overflow``. :meth:`drain` hands the waiting payloads to the
    main thread in arrival order. Thread-safe.
    """

    def __init__(self, limits: InputLimits, clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self.clock = clock
        self._cond = threading.Condition()
        self._queues: dict[str, deque[tuple[int, bytes, int]]] = {}  # (arrival number, bytes, wall ns)
        self._buckets: dict[str, list[float]] = {}  # key -> [tokens, last refill]
        self._bytes = 0
        self._arrival = 0
        self.arrived = 0
        self.oversized = 0
        self.rate_limited = 0
        self.overflow = 0

    def _bucket(self, key: str, now: float) -> list[float] | None:
        b = self._buckets.get(key)
        if b is None:
            if len(self._buckets) >= self.limits.max_keys:
                # forget buckets that have refilled (they carry no information) and keys
                # with nothing queued
                full = float(self.limits.burst)
                for k, (tok, t) in list(self._buckets.items()):
                    if min(full, tok + (now - t) * self.limits.rate_hz) >= full and k not in self._queues:
                        del self._buckets[k]
                if len(self._buckets) >= self.limits.max_keys:
                    return None
            b = self._buckets[key] = [float(self.limits.burst), now]
        return b

    def put(self, key: str, payload: Any) -> str | None:
        """Queue ``payload`` (bytes, or anything with ``len()`` and ``to_bytes()``) from ``key``;
        returns None, or the counter it was dropped under."""
        size = len(payload)
        lim = self.limits
        with self._cond:
            self.arrived += 1
            if size > lim.max_bytes:
                self.oversized += 1
                return "oversized"
            now = self.clock()
            b = self._bucket(key, now)
            if b is None:
                self.overflow += 1
                return "overflow"
            b[0] = min(float(lim.burst), b[0] + (now - b[1]) * lim.rate_hz)
            b[1] = now
            if b[0] < 1.0:
                self.rate_limited += 1
                return "rate_limited"
            b[0] -= 1.0
            if self._bytes + size > lim.queue_bytes:
                self.overflow += 1
                return "overflow"
            q = self._queues.setdefault(key, deque())
            dropped = None
            if len(q) >= lim.queue_depth:
                _, old, _ = q.popleft()
                self._bytes -= len(old)
                self.overflow += 1
                dropped = "overflow"
            data = payload if isinstance(payload, bytes) else bytes(payload.to_bytes())
            self._arrival += 1
            q.append((self._arrival, data, time.time_ns()))
            self._bytes += len(data)
            self._cond.notify()
            return dropped

    def drain(self, timeout: float = 0.0) -> list[tuple[str, bytes]]:
        """Everything waiting, oldest first; waits up to ``timeout`` for the first payload."""
        return [(k, d) for k, d, _ in self.drain_timed(timeout)]

    def drain_timed(self, timeout: float = 0.0) -> list[tuple[str, bytes, int]]:
        """:meth:`drain` with each payload's arrival time (wall clock, ns)."""
        with self._cond:
            if not self._queues and timeout > 0:
                self._cond.wait(timeout)
            items = [(n, k, d, t) for k, q in self._queues.items() for n, d, t in q]
            self._queues.clear()
            self._bytes = 0
        items.sort(key=lambda x: x[0])
        return [(k, d, t) for _, k, d, t in items]

    @property
    def queued_bytes(self) -> int:
        with self._cond:
            return self._bytes

    @property
    def empty(self) -> bool:
        """Whether no payload is waiting."""
        with self._cond:
            return not self._queues


class DropLog:
    """Rate-limited reporting of dropped payloads: the first drop is reported at once, later
    ones at most once per ``period`` seconds, as one line with the counts per reason since the
    last line and the last drop's key and detail. Thread-safe."""

    def __init__(
        self, say: Callable[[str], None], period: float = 5.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.say = say
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._last: tuple[str, str] | None = None
        self._said = -math.inf
        self.lines = 0

    def note(self, reason: str, key: str, detail: str = "") -> None:
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1
            self._last = (key, f"{reason}: {detail}" if detail else reason)

    def flush(self, force: bool = False) -> str | None:
        """Say the summary line if one is due (or ``force``); returns it."""
        now = self.clock()
        with self._lock:
            if not self._counts or (not force and now - self._said < self.period):
                return None
            n = sum(self._counts.values())
            parts = ", ".join(f"{c} {r}" for r, c in sorted(self._counts.items()))
            key, detail = self._last or ("?", "")
            since = "" if self._said == -math.inf else f" in the last {now - self._said:.0f} s"
            line = (
                f"dropped {n} payload{'s' if n != 1 else ''}{since} ({parts}); last on {key}: {detail[:200]}"
            )
            self._counts.clear()
            self._said = now
            self.lines += 1
        self.say(line)
        return line
