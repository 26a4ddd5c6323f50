"""The fusion service: every robot's latest map -> one fleet map.

Two layers:

* :class:`FusionState`, the pure core (no zenoh, no rerun, no clock of its own): keeps each
  robot's latest :class:`~wire_codec.message.MapMessage`, recomputes the fused map, stores and
  restores itself on disk.
* :func:`serve`, the Zenoh shell: subscribes to ``robots/*/map`` (through :class:`Intake`, a
  bounded FIFO), ``robots/*/pose`` and ``robots/*/viz`` (only the latest per robot matters)
  and ``alive/*``; publishes the fused map on every change and answers queries for it and for
  its counters (``fused/stats``); logs to Rerun.

Order independence, by construction: the fused map is a function of the *set* of latest robot
maps only. A robot's latest map is the one with the greatest ``(meta["boot"], seq, sha256 of its
bytes)``, whatever the order of arrival, and duplicates are no-ops; the fused map is then
recomputed from scratch, visiting robots in sorted-id order. Robot ``k`` of the sorted ids owns
bit ``k`` of ``Wireframe.sources`` (``MapMessage.robots`` lists them), so at most 64 robots.

Fleet frame, in three steps per robot (choices where the paper and the issue are silent):

1. the map (in the robot's odometry frame) is moved by its start pose (``MapMessage.origin``);
2. if ``mapping.icp`` is available and ``FusionConfig.refine`` is on, a wireframe ICP aligns it
   to the fused map of the robots before it (sorted order; the first robot is the anchor).
   The correction is kept only when it is small (``max_refine_m`` / ``max_refine_rad``): the
   start poses are known, ICP only removes residual odometry drift;
3. :func:`mapping.merge.merge` adds it to the fused map with the merge threshold
   ``FusionConfig.threshold`` (default: the largest ``resolution`` among the robot maps).

Finally :func:`close_frontiers` removes frontiers of one robot that another robot's walls
close (see there).

Hostile or broken input (choices; the counters are in :class:`FusionStats`, served on
``wiremap/<fleet>/fused/stats`` and written to the store's ``state.json``):

* in Zenoh's thread, before anything is decoded (:class:`Intake`): a payload over
  ``InputLimits.max_bytes`` is dropped (``oversized``); each key has a token bucket
  (``rate_hz``, ``burst``; ``rate_limited``); each key's queue holds at most ``queue_depth``
  payloads (the oldest goes: maps are whole states) and all queues together at most
  ``queue_bytes`` (``overflow``); at most ``max_keys`` keys are tracked. Memory is bounded by
  ``queue_bytes`` plus one payload per side channel and robot, whatever arrives;
* in the main thread (:meth:`FusionState.offer`): the codec with the fusion's tighter
  :class:`~wire_codec.Limits` (``malformed``, by error class); a key whose id chunk is not a
  valid name, a fused map on a robot key, an envelope sender that differs from the key, a 65th
  robot (``rejected``, by reason); a decodable map with absurd content -- coordinates beyond
  ``max_extent_m`` in the fleet frame, a resolution over ``max_resolution_m``, a non-finite or
  negative ``meta.t``, a ``meta.boot`` that is not an integer or lies in the future
  (``absurd``, by reason).

Every drop is counted; :class:`DropLog` prints at most one line per ``period`` summarising them.
The fused map is only ever recomputed from accepted maps, so the last good map keeps being
served.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from agents.errors import UserError
from agents.io import write_atomic, write_json
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind

MAX_ROBOTS = 64
DEFAULT_THRESHOLD = 0.2
FUSION_ID = "fusion"
SNAPSHOT = "snapshot.msgpack"
MAX_LATENCIES = 100_000
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")  # = agents.bus.check_name


# ---------------------------------------------------------------------- codec access
def _codec() -> tuple[Callable[[MapMessage], bytes], Callable[[bytes], MapMessage], type[Exception]]:
    import wire_codec

    try:
        from wire_codec import CodecError, decode, encode  # type: ignore[attr-defined]
    except ImportError as exc:  # the codec is written by another helper
        raise RuntimeError(f"wire_codec.encode/decode are not available yet: {exc}") from None
    del wire_codec
    return encode, decode, CodecError


def encode_message(msg: MapMessage) -> bytes:
    return _codec()[0](msg)


def decode_message(data: bytes, limits: Any = None) -> MapMessage:
    """Decode codec bytes; raises ``ValueError`` (``CodecError``) on malformed payloads.

    ``limits`` is a :class:`wire_codec.Limits` (default: the codec's)."""
    if limits is None:
        return _codec()[1](data)
    from wire_codec import decode

    return decode(data, limits=limits)


@dataclass(frozen=True)
class InputLimits:
    """What the fusion service accepts on ``robots/<id>/map`` (choices; see the module docstring).

    max_bytes : largest payload (256 KiB: a robot map of the largest built-in world is ~10 kB).
    max_vertices, max_edges : largest robot map (decoder limits, checked before allocating).
    max_extent_m : largest ``|x|`` or ``|y|`` of the origin and of every vertex in the fleet
        frame ("kilometres away" is absurd for a building).
    max_resolution_m : largest map resolution (it becomes the merge threshold).
    max_clock_skew_s : how far in the future a ``meta.boot`` may lie (wall clocks differ).
    rate_hz, burst : token bucket per key (robots send at most ~10 maps/s).
    queue_depth : payloads waiting per key (the oldest is dropped: maps are whole states).
    queue_bytes : bytes waiting over all keys.
    max_keys : keys tracked at once (rate buckets and side channels).
    pose_bytes, viz_bytes : largest pose / visualisation payload.
    """

    max_bytes: int = 256 * 1024
    max_vertices: int = 20_000
    max_edges: int = 40_000
    max_extent_m: float = 1000.0
    max_resolution_m: float = 2.0
    max_clock_skew_s: float = 3600.0
    rate_hz: float = 50.0
    burst: int = 100
    queue_depth: int = 64
    queue_bytes: int = 8 * 1024 * 1024
    max_keys: int = 4 * MAX_ROBOTS
    pose_bytes: int = 16 * 1024
    viz_bytes: int = 4 * 1024 * 1024

    def codec_limits(self) -> Any:
        """The :class:`wire_codec.Limits` the decoder enforces for robot maps."""
        from wire_codec import Limits

        return Limits(
            max_bytes=self.max_bytes,
            max_vertices=self.max_vertices,
            max_edges=self.max_edges,
            max_coordinate=self.max_extent_m,
            max_string=128,
        )


def implausible(msg: MapMessage, limits: InputLimits, now_ns: int | None = None) -> tuple[str, str] | None:
    """``(reason, detail)`` when a decoded robot map's content is absurd, else None.

    Reasons: ``resolution`` (not in ``(0, max_resolution_m]``), ``extent`` (origin or a vertex
    beyond ``max_extent_m`` in the fleet frame), ``meta`` (``boot`` not a non-negative int,
    ``t`` not a finite non-negative number, ``step`` not an int), ``future`` (``boot`` more than
    ``max_clock_skew_s`` after ``now_ns``; only checked when ``now_ns`` is given).
    """
    res = float(msg.resolution)
    if not (0.0 < res <= limits.max_resolution_m):
        return "resolution", f"resolution {res:g} m (limit {limits.max_resolution_m:g} m)"
    ext = limits.max_extent_m
    o = msg.origin
    if max(abs(o.x), abs(o.y)) > ext:
        return "extent", f"origin ({o.x:.1f}, {o.y:.1f}) is over {ext:g} m away"
    wf = msg.wireframe
    if wf.n_vertices:
        far = float(np.abs(o.apply(wf.points)).max())
        if not math.isfinite(far) or far > ext:
            return "extent", f"a vertex is {far:.1f} m from the fleet origin (limit {ext:g} m)"
    meta = msg.meta if isinstance(msg.meta, dict) else {}
    boot = meta.get("boot", 0)
    if isinstance(boot, bool) or not isinstance(boot, int) or boot < 0:
        return "meta", f"meta.boot {boot!r} is not a non-negative integer"
    if now_ns is not None and boot > now_ns + limits.max_clock_skew_s * 1e9:
        return "future", f"meta.boot is {(boot - now_ns) / 1e9:.0f} s in the future"
    t = meta.get("t", 0.0)
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
        return "meta", f"meta.t {t!r} is not a finite non-negative number"
    step = meta.get("step", 0)
    if isinstance(step, bool) or not isinstance(step, int):
        return "meta", f"meta.step {step!r} is not an integer"
    return None


# ---------------------------------------------------------------------- frontier closing
def close_frontiers(wf: Wireframe, threshold: float, max_angle: float = math.radians(20.0)) -> Wireframe:
    """Remove frontiers that another wall of the fused map closes.

    A frontier vertex ``v`` (where a wall leaves what its robot saw) is *closed* when it lies
    within ``threshold`` of the interior of an edge ``e`` that does not touch it (more than
    ``threshold`` from both of ``e``'s ends): someone saw the wall go on. Then (choices; the
    paper only says such frontiers should disappear):

    * each wall at ``v`` that runs along ``e`` (within ``max_angle``, same direction) is
      covered by ``e``: it is dropped when its other end ``u`` also lies along ``e``;
      otherwise it is re-attached from ``v`` to ``e``'s nearer end, so that the wall stays one
      connected chain (``u`` -> end of ``e``), keeping its likelihood and sources;
    * if walls at an angle to ``e`` remain at ``v``, ``v`` is where that wall meets ``e``: a
      real corner, relabelled ``NOMINAL``;
    * a vertex left without walls is dropped.

    An edge that runs opposite to one of ``v``'s walls is the back of a thin wall and does not
    close ``v``. When several edges close ``v``, the one of lowest index is used. Decisions are made on the
    input map and applied together.
    """
    fr = np.flatnonzero(wf.labels == Label.FRONTIER)
    if len(fr) == 0 or wf.n_edges == 0:
        return wf
    P, E = wf.points, wf.edges
    A = P[E[:, 0]]
    D = P[E[:, 1]] - A
    L = np.hypot(D[:, 0], D[:, 1])
    ok = L > 1e-12
    dirs = np.zeros_like(D)
    dirs[ok] = D[ok] / L[ok, None]
    cos_max = math.cos(max_angle)

    def coords(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc-length along, and distance across, every edge for point p."""
        rel = p - A
        t = rel[:, 0] * dirs[:, 0] + rel[:, 1] * dirs[:, 1]
        d = np.abs(dirs[:, 0] * rel[:, 1] - dirs[:, 1] * rel[:, 0])
        return t, d

    drop_edge = np.zeros(wf.n_edges, dtype=bool)
    edges = E.copy()
    relabel: list[int] = []
    for v in fr.tolist():
        touches = (E[:, 0] == v) | (E[:, 1] == v)
        t, d = coords(P[v])
        closing = np.flatnonzero(ok & ~touches & (d <= threshold) & (t > threshold) & (t < L - threshold))
        if len(closing) == 0:
            continue
        inc = np.flatnonzero(touches)
        # an edge running the other way is the back of a thin wall, not a continuation
        usable = [int(k) for k in closing if not np.any(ok[inc] & (dirs[inc] @ dirs[k] <= -cos_max))]
        if not usable:
            continue
        k = usable[0]
        at_angle = 0
        for j in inc.tolist():
            if not ok[j] or float(dirs[j] @ dirs[k]) < cos_max:
                at_angle += 1
                continue
            end_v = 0 if E[j, 0] == v else 1
            u = int(E[j, 1 - end_v])
            tu = float((P[u] - A[k]) @ dirs[k])
            du = abs(float(dirs[k, 0] * (P[u] - A[k])[1] - dirs[k, 1] * (P[u] - A[k])[0]))
            if du <= threshold and -threshold <= tu <= L[k] + threshold:
                drop_edge[j] = True  # entirely along e: covered
                continue
            w = int(E[k, 0]) if tu < 0 else int(E[k, 1])
            if float(np.hypot(*(P[w] - P[u]))) <= threshold:
                drop_edge[j] = True
            else:
                edges[j, end_v] = w
        if at_angle:
            relabel.append(v)
    if not drop_edge.any() and np.array_equal(edges, E) and not relabel:
        return wf
    labels = wf.labels.copy()
    labels[relabel] = Label.NOMINAL
    keep = ~drop_edge & (edges[:, 0] != edges[:, 1])
    out = Wireframe(P, labels, edges[keep], wf.likelihood[keep], wf.sources[keep])
    return out.compacted()


# ---------------------------------------------------------------------- the pure core
MergeFn = Callable[[Wireframe, Wireframe, float], Wireframe]


def default_merge(base: Wireframe, new: Wireframe, threshold: float) -> Wireframe:
    """:func:`mapping.merge.merge` with ``MergeConfig(threshold=threshold)``."""
    from mapping.merge import MergeConfig, merge

    return merge(base, new, MergeConfig(threshold=threshold))


@dataclass(frozen=True)
class FusionConfig:
    """Fusion parameters.

    threshold : merge threshold in metres; None: the largest ``resolution`` of the robot maps
        (``DEFAULT_THRESHOLD`` when there are none).
    refine : align each robot's map to the rest with ``mapping.icp`` when that module exists.
    max_refine_m, max_refine_rad : largest accepted ICP correction.
    close_frontiers : apply :func:`close_frontiers` to the result.
    """

    threshold: float | None = None
    refine: bool = True
    max_refine_m: float = 0.6
    max_refine_rad: float = math.radians(6.0)
    close_frontiers: bool = True


@dataclass(frozen=True)
class RobotEntry:
    """A robot's latest map as received: the message, its exact bytes, its order key."""

    message: MapMessage
    raw: bytes
    key: tuple[int, int, str]


@dataclass
class FusionStats:
    """Counters of the fusion service (one process lifetime; see the module docstring).

    received : payloads offered to :meth:`FusionState.offer` (decoded or not).
    accepted : became their robot's latest map; duplicates / outdated: identical to, or older
        than, the latest (not errors: maps are re-sent).
    malformed / rejected / absurd : dropped in :meth:`FusionState.offer`; ``*_by`` break them
        down by codec error class or reason.
    oversized / rate_limited / overflow : dropped by :class:`Intake` before decoding.
    side_dropped : pose and visualisation payloads dropped (too big, bad key, undecodable).
    published : fused versions published.
    """

    received: int = 0
    accepted: int = 0
    duplicates: int = 0
    outdated: int = 0
    malformed: int = 0
    rejected: int = 0
    absurd: int = 0
    oversized: int = 0
    rate_limited: int = 0
    overflow: int = 0
    side_dropped: int = 0
    published: int = 0
    malformed_by: dict[str, int] = field(default_factory=dict)
    rejected_by: dict[str, int] = field(default_factory=dict)
    absurd_by: dict[str, int] = field(default_factory=dict)
    latencies_ms: list[float] = field(default_factory=list)

    @property
    def dropped(self) -> int:
        """Every map payload that was dropped, for whatever reason."""
        return self.malformed + self.rejected + self.absurd + self.oversized + self.rate_limited + self.overflow

    def as_dict(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "accepted": self.accepted,
            "duplicates": self.duplicates,
            "outdated": self.outdated,
            "malformed": self.malformed,
            "rejected": self.rejected,
            "absurd": self.absurd,
            "oversized": self.oversized,
            "rate_limited": self.rate_limited,
            "overflow": self.overflow,
            "dropped": self.dropped,
            "side_dropped": self.side_dropped,
            "published": self.published,
            "malformed_by": dict(sorted(self.malformed_by.items())),
            "rejected_by": dict(sorted(self.rejected_by.items())),
            "absurd_by": dict(sorted(self.absurd_by.items())),
            "latency_ms": latency_summary(self.latencies_ms),
        }


def latency_summary(lat_ms: Iterable[float]) -> dict[str, float | int | None]:
    a = np.asarray(list(lat_ms), dtype=np.float64)
    if len(a) == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    return {
        "n": len(a),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


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


class FusionState:
    """The fusion service's state, without any I/O but the store.

    Parameters
    ----------
    config : :class:`FusionConfig`.
    sender : the id in the fused messages' envelope.
    merge_fn : ``merge_fn(base, new, threshold) -> Wireframe``; default
        :func:`mapping.merge.merge` (tests may pass another).
    limits : :class:`InputLimits` for :meth:`offer`.
    """

    def __init__(
        self,
        config: FusionConfig | None = None,
        sender: str = FUSION_ID,
        merge_fn: MergeFn | None = None,
        limits: InputLimits | None = None,
    ) -> None:
        self.config = config or FusionConfig()
        self.sender = sender
        self.merge_fn: MergeFn = merge_fn or default_merge
        self.limits = limits or InputLimits()
        self._codec_limits = self.limits.codec_limits()
        self.last_drop: tuple[str, str, str] | None = None  # (counter, reason, detail) of the last drop
        self.robots: dict[str, RobotEntry] = {}
        self.fused: Wireframe = Wireframe.empty()
        self.fused_robots: tuple[str, ...] = ()
        self.corrections: dict[str, Pose] = {}
        self.version = 0
        self.stats = FusionStats()
        self._pending: dict[str, int] = {}  # robot -> stamp_ns of an accepted map not yet fused
        self._chain: list[tuple[Any, Wireframe, Pose | None]] = []  # compute()'s prefix cache

    # ------------------------------------------------------------------ input
    def offer(self, data: bytes, key_robot: str | None = None, now_ns: int | None = None) -> bool:
        """Decode and :meth:`add` a payload from ``robots/<key_robot>/map``.

        Returns whether the robot's latest map changed. Dropped and counted (the reason also
        in :attr:`last_drop`): a payload the codec refuses under :class:`InputLimits`
        (``malformed``); a fused map, a sender that is not a valid robot id or does not match
        the key, a robot beyond the 64th (``rejected``); absurd content (``absurd``, see
        :func:`implausible`; ``now_ns`` enables the clock check).
        """
        self.stats.received += 1
        self.last_drop = None
        raw = bytes(data)
        try:
            msg = decode_message(raw, self._codec_limits)
        except ValueError as exc:
            return self._drop("malformed", type(exc).__name__, str(exc))
        if msg.kind != MessageKind.ROBOT_MAP:
            return self._drop("rejected", "not_robot_map", f"a {msg.kind.name} on a robot key")
        if not _NAME_RE.match(msg.sender):
            return self._drop("rejected", "bad_sender", f"sender {msg.sender[:80]!r} is not a robot id")
        if key_robot is not None and msg.sender != key_robot:
            return self._drop("rejected", "sender_mismatch", f"sender {msg.sender!r} on the key of {key_robot!r}")
        bad = implausible(msg, self.limits, now_ns)
        if bad is not None:
            return self._drop("absurd", *bad)
        return self._add(msg, raw)

    def reject_key(self, key: str) -> bool:
        """Count a payload that arrived on a key whose id chunk is not a valid robot id."""
        self.stats.received += 1
        self.last_drop = None
        return self._drop("rejected", "bad_key", f"{key[:120]!r} does not name a robot")

    def _drop(self, counter: str, reason: str, detail: str) -> bool:
        setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        by: dict[str, int] = getattr(self.stats, f"{counter}_by")
        by[reason] = by.get(reason, 0) + 1
        self.last_drop = (counter, reason, detail)
        return False

    def add(self, msg: MapMessage) -> bool:
        """Add a robot map given as a message: it is encoded and decoded first, so that the
        state holds exactly what would have travelled (the codec quantises coordinates)."""
        return self.offer(encode_message(msg), msg.sender)

    def _add(self, msg: MapMessage, raw: bytes) -> bool:
        rid = msg.sender
        key = order_key(msg, raw)
        old = self.robots.get(rid)
        if old is not None:
            if key == old.key:
                self.stats.duplicates += 1
                return False
            if key < old.key:
                self.stats.outdated += 1
                return False
        elif len(self.robots) >= MAX_ROBOTS:
            return self._drop("rejected", "too_many_robots", f"{rid!r} would be robot {MAX_ROBOTS + 1}")
        self.robots[rid] = RobotEntry(msg, raw, key)
        self.stats.accepted += 1
        same = old is not None and _same_map(old.message, msg)
        if not same:
            self._pending.setdefault(rid, int(msg.stamp_ns))
        return not same

    # ------------------------------------------------------------------ fusion
    @property
    def threshold(self) -> float:
        if self.config.threshold is not None:
            return float(self.config.threshold)
        res = [float(e.message.resolution) for e in self.robots.values() if e.message.resolution > 0]
        return max(res) if res else DEFAULT_THRESHOLD

    def robot_in_fleet(self, robot: str) -> Wireframe:
        """A robot's latest map in the fleet frame (start pose, then the ICP correction)."""
        m = self.robots[robot].message
        wf = m.wireframe.transformed(m.origin)
        corr = self.corrections.get(robot)
        return wf.transformed(corr) if corr is not None else wf

    def compute(self) -> tuple[Wireframe, tuple[str, ...], dict[str, Pose]]:
        """The fused map of the current latest maps.

        A pure function of the set of latest maps (and the config). The partial results after
        each robot are cached under the keys of the robots so far (a prefix of the sorted ids),
        so when only a late robot's map changed, the prefix before it is reused; this changes
        the cost, never the result.
        """
        ids = tuple(sorted(self.robots))
        thr = self.threshold
        acc = Wireframe.empty()
        corrections: dict[str, Pose] = {}
        chain: list[tuple[Any, Wireframe, Pose | None]] = []
        prefix: tuple[Any, ...] = (thr, self.config)
        cached = self._chain
        for k, rid in enumerate(ids):
            prefix = (*prefix, rid, self.robots[rid].key)
            if k < len(cached) and cached[k][0] == prefix:
                _, acc, corr = cached[k]
                if corr is not None:
                    corrections[rid] = corr
                chain.append(cached[k])
                continue
            cached = []  # the prefix differs from here on
            m = self.robots[rid].message
            wf = m.wireframe.transformed(m.origin)
            wf = wf.replace(sources=np.full(wf.n_edges, np.uint64(1) << np.uint64(k), dtype=np.uint64))
            corr = None
            if self.config.refine and acc.n_edges and wf.n_edges:
                corr = _refine(wf, acc, thr, self.config)
                if corr is not None:
                    corrections[rid] = corr
                    wf = wf.transformed(corr)
            if wf.n_vertices:
                acc = wf if acc.n_vertices == 0 else self.merge_fn(acc, wf, thr)
            chain.append((prefix, acc, corr))
        self._chain = chain
        if self.config.close_frontiers:
            acc = close_frontiers(acc, thr)
        return acc, ids, corrections

    def fuse(self) -> bool:
        """Recompute the fused map; bump ``version`` and return True when it changed."""
        wf, ids, corr = self.compute()
        self.corrections = corr
        changed = ids != self.fused_robots or not wf.almost_equal(self.fused, tol=1e-9)
        if changed:
            self.fused, self.fused_robots = wf, ids
            self.version += 1
        else:
            self._pending.clear()
        return changed

    def take_latencies(self, published_ns: int) -> list[float]:
        """Latency (ms) from each robot map that changed since the last fused publish to this
        publish at ``published_ns`` (same machine clock); recorded in ``stats`` (the last
        ``MAX_LATENCIES`` only)."""
        out = [max(0.0, (published_ns - s) / 1e6) for s in self._pending.values()]
        self._pending.clear()
        self.stats.latencies_ms.extend(out)
        if len(self.stats.latencies_ms) > MAX_LATENCIES:  # bounded memory: a sliding window
            del self.stats.latencies_ms[: len(self.stats.latencies_ms) - MAX_LATENCIES]
        self.stats.published += 1
        return out

    def fused_message(self, stamp_ns: int, meta: dict[str, Any] | None = None) -> MapMessage:
        m = {"version": self.version}
        m.update(meta or {})
        return MapMessage(
            kind=MessageKind.FUSED_MAP,
            sender=self.sender,
            seq=self.version,
            stamp_ns=int(stamp_ns),
            pose=Pose.identity(),
            frame="fleet",
            origin=Pose.identity(),
            resolution=self.threshold,
            wireframe=self.fused,
            robots=self.fused_robots,
            meta=m,
        )

    def sim_time(self) -> float:
        """The latest simulated time any robot map carries (``meta["t"]``), 0 if none."""
        ts = [float(e.message.meta.get("t", 0.0)) for e in self.robots.values() if isinstance(e.message.meta, dict)]
        return max(ts, default=0.0)

    # ------------------------------------------------------------------ store
    def save(self, store: str | os.PathLike[str], robots: Iterable[str] | None = None, stamp_ns: int = 0) -> None:
        """Write the state under ``store``.

        First ``snapshot.msgpack``, the authoritative copy, in one atomic write (temporary
        file, fsync, rename): ``{"format": 1, "version", "stamp_ns", "robots": {id: bytes as
        received}, "fused": fused map bytes}``, so a crash at any moment leaves either the old
        or the new snapshot, never robot maps from one save and a fused map from another.
        Then views for people and tools, each atomic too: ``robots/<id>.wfm`` (only
        ``robots`` when given), ``fused.wfm`` and ``state.json`` (version, per-robot
        seq/boot/sha256, counters, the last 10,000 latencies).
        """
        d = Path(store)
        fused_raw = encode_message(self.fused_message(stamp_ns))
        snap = {
            "format": 1,
            "version": self.version,
            "stamp_ns": int(stamp_ns),
            "robots": {r: e.raw for r, e in sorted(self.robots.items())},
            "fused": fused_raw,
        }
        write_atomic(d / SNAPSHOT, bytes(msgpack.packb(snap, use_bin_type=True)))
        for rid in sorted(self.robots if robots is None else robots):
            if rid in self.robots:
                write_atomic(d / "robots" / f"{rid}.wfm", self.robots[rid].raw)
        write_atomic(d / "fused.wfm", fused_raw)
        write_json(
            d / "state.json",
            {
                "version": self.version,
                "robots": {
                    r: {"seq": e.key[1], "boot": e.key[0], "sha256": e.key[2]} for r, e in sorted(self.robots.items())
                },
                "fused": {"vertices": self.fused.n_vertices, "edges": self.fused.n_edges},
                "stats": self.stats.as_dict(),
                "latencies_ms": [round(x, 3) for x in self.stats.latencies_ms[-10_000:]],
            },
        )

    @classmethod
    def load(
        cls,
        store: str | os.PathLike[str],
        config: FusionConfig | None = None,
        sender: str = FUSION_ID,
        merge_fn: MergeFn | None = None,
        limits: InputLimits | None = None,
    ) -> FusionState:
        """Resume from :meth:`save`'s files (an absent or empty store gives a fresh state).

        The robot maps come from ``snapshot.msgpack`` (or, in a store without one, from
        ``robots/*.wfm``) and pass the same checks as maps from the bus. The fused map is
        recomputed from them (so it is the same map) and keeps the stored version when it
        equals the stored fused map; otherwise the version goes up. Unreadable files are
        skipped with a warning on stderr.
        """
        st = cls(config, sender, merge_fn, limits)
        d = Path(store)
        if not d.exists():
            return st
        if not d.is_dir():
            raise UserError(f"{d}: not a directory")
        def warn(text: str) -> None:
            sys.stderr.write(f"wiremap fuse: {text}\n")

        contents = read_store(d, warn=warn)
        for rid, raw in contents.raw_robots.items():
            if not st.offer(raw, rid) and st.last_drop is not None:
                sys.stderr.write(f"wiremap fuse: skipping stored map of {rid}: {st.last_drop[2]}\n")
        st.stats = FusionStats()
        try:
            state = json.loads((d / "state.json").read_text())
            st.stats.latencies_ms = [float(x) for x in state.get("latencies_ms", [])]
        except (OSError, ValueError, TypeError, AttributeError):
            pass
        if st.robots:
            st.fuse()
        st._pending.clear()
        same = False
        if contents.fused is not None and st.robots:
            # compare as stored: through the codec
            again = decode_message(encode_message(st.fused_message(0))).wireframe
            same = again.almost_equal(contents.fused.wireframe, tol=1e-9, likelihood_tol=1e-9)
        version = contents.version
        st.version = version if (same or not st.robots) else version + 1
        return st
        if not d.is_dir():
            raise UserError(f"{d}: not a directory")
        for f in sorted((d / "robots").glob("*.wfm")):
            try:
                raw = f.read_bytes()
                msg = decode_message(raw)
            except (OSError, ValueError) as exc:
                sys.stderr.write(f"wiremap fuse: skipping {f}: {exc}\n")
                continue
            st._add(msg, raw)
        st.stats = FusionStats()
        version = 0
        old_fused: Wireframe | None = None
        try:
            state = json.loads((d / "state.json").read_text())
            version = int(state.get("version", 0))
            st.stats.latencies_ms = [float(x) for x in state.get("latencies_ms", [])]
        except (OSError, ValueError, TypeError, AttributeError):
            pass
        try:
            fm = decode_message((d / "fused.wfm").read_bytes())
            old_fused = fm.wireframe
            version = max(version, int(fm.seq))
        except (OSError, ValueError):
            pass
        if st.robots:
            st.fuse()
        st._pending.clear()
        same = False
        if old_fused is not None and st.robots:
            # compare as stored: through the codec
            again = decode_message(encode_message(st.fused_message(0))).wireframe
            same = again.almost_equal(old_fused, tol=1e-9, likelihood_tol=1e-9)
        st.version = version if (same or not st.robots) else version + 1
        return st



@dataclass(frozen=True)
class StoreContents:
    """What :func:`read_store` found: the stored version, the stored fused map (None if
    unreadable) and each robot's stored bytes."""

    version: int
    fused: MapMessage | None
    raw_robots: dict[str, bytes]
    from_snapshot: bool

    def robots(self) -> dict[str, MapMessage]:
        """The stored robot maps, decoded (undecodable ones left out)."""
        out = {}
        for rid, raw in self.raw_robots.items():
            try:
                out[rid] = decode_message(raw)
            except ValueError:
                continue
        return out


def read_store(store: str | os.PathLike[str], warn: Callable[[str], None] | None = None) -> StoreContents:
    """Read a fusion store without fusing anything (for :meth:`FusionState.load`, tests and
    tools).

    ``snapshot.msgpack`` is used when it is readable and the ``robots/*.wfm`` views agree
    with it: every view file decodes and is the snapshot's map of that robot or an older one
    of it (a save interrupted between the snapshot and the views leaves older views). A view
    that is newer, unreadable or not in the snapshot was changed by hand, and then the views
    win (``robots/*.wfm``, ``fused.wfm``, ``state.json``), unreadable files skipped with a
    warning.
    """
    d = Path(store)
    say = warn or (lambda _t: None)
    views: dict[str, bytes] = {}
    for f in sorted((d / "robots").glob("*.wfm")):
        try:
            views[f.stem] = f.read_bytes()
        except OSError as exc:
            views[f.stem] = b""
            say(f"cannot read {f}: {exc}")
    snap_path = d / SNAPSHOT
    if snap_path.is_file():
        try:
            snap = msgpack.unpackb(snap_path.read_bytes(), raw=False)
            robots = snap["robots"]
            if not (isinstance(robots, dict) and all(isinstance(k, str) and isinstance(v, bytes) for k, v in robots.items())):
                raise ValueError("robots is not a map of id -> bytes")
            version = int(snap["version"])
            fused: MapMessage | None = None
            try:
                fused = decode_message(snap["fused"])
            except (ValueError, TypeError):
                say(f"{snap_path}: the fused map in it is unreadable")
            hand_edited = _views_disagree(robots, views)
            if hand_edited is None:
                return StoreContents(version, fused, dict(sorted(robots.items())), True)
            say(f"{hand_edited}: using robots/*.wfm rather than {SNAPSHOT}")
        except (OSError, ValueError, TypeError, KeyError, msgpack.UnpackException) as exc:
            say(f"{snap_path} is unreadable ({type(exc).__name__}: {exc}); using robots/*.wfm")
    raw: dict[str, bytes] = {}
    for rid, data in views.items():
        try:
            decode_message(data)
        except ValueError as exc:
            say(f"skipping {d / 'robots' / (rid + '.wfm')}: {exc}")
            continue
        raw[rid] = data
    version = 0
    try:
        version = int(json.loads((d / "state.json").read_text()).get("version", 0))
    except (OSError, ValueError, TypeError, AttributeError):
        pass
    fused = None
    try:
        fused = decode_message((d / "fused.wfm").read_bytes())
        version = max(version, int(fused.seq))
    except (OSError, ValueError):
        pass
    return StoreContents(version, fused, raw, False)


def _views_disagree(snapshot: dict[str, bytes], views: dict[str, bytes]) -> str | None:
    """Why the ``robots/*.wfm`` views cannot come from a (possibly interrupted) save of
    ``snapshot``, or None when they can."""
    for rid, data in views.items():
        if rid not in snapshot:
            return f"robots/{rid}.wfm is not in the snapshot"
        if data == snapshot[rid]:
            continue
        try:
            view_key = order_key(decode_message(data), data)
            snap_key = order_key(decode_message(snapshot[rid]), snapshot[rid])
        except ValueError:
            return f"robots/{rid}.wfm is unreadable"
        if view_key > snap_key:
            return f"robots/{rid}.wfm is newer than the snapshot"
    return None


def _same_map(a: MapMessage, b: MapMessage) -> bool:
    return a.origin.almost_equal(b.origin, 1e-12, 1e-12) and a.wireframe.almost_equal(b.wireframe, tol=1e-12)


def _refine(source: Wireframe, target: Wireframe, threshold: float, cfg: FusionConfig) -> Pose | None:
    """A small rigid correction (fleet frame) of ``source`` onto ``target`` by
    :func:`mapping.icp.icp`, or None.

    ICP rotates about its frame's origin, so both maps are first expressed in a frame at the
    centroid of ``source``'s vertices and the correction is brought back to the fleet frame
    (``F * C * F^-1``). None when the module is absent, ICP does not accept its result, or the
    correction exceeds ``cfg.max_refine_m`` / ``cfg.max_refine_rad`` (the start pose alone is
    trusted then).
    """
    try:
        from mapping.icp import icp  # written by another helper
    except ImportError:
        return None
    if source.n_vertices == 0 or target.n_vertices == 0:
        return None
    c = source.points.mean(axis=0)
    F = Pose(float(c[0]), float(c[1]), 0.0)
    Finv = F.inverse()
    try:
        res = icp(source.transformed(Finv), target.transformed(Finv))
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not getattr(res, "accepted", False):
        return None
    pose = F.compose(res.correction).compose(Finv)
    if math.hypot(pose.x, pose.y) > cfg.max_refine_m or abs(pose.theta) > cfg.max_refine_rad:
        return None
    if math.hypot(pose.x, pose.y) < 1e-6 and abs(pose.theta) < 1e-7:
        return None
    return pose


# ---------------------------------------------------------------------- the zenoh shell
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
        self._queues: dict[str, deque[tuple[int, bytes]]] = {}
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
                _, old = q.popleft()
                self._bytes -= len(old)
                self.overflow += 1
                dropped = "overflow"
            data = payload if isinstance(payload, bytes) else bytes(payload.to_bytes())
            self._arrival += 1
            q.append((self._arrival, data))
            self._bytes += len(data)
            self._cond.notify()
            return dropped

    def drain(self, timeout: float = 0.0) -> list[tuple[str, bytes]]:
        """Everything waiting, oldest first; waits up to ``timeout`` for the first payload."""
        with self._cond:
            if not self._queues and timeout > 0:
                self._cond.wait(timeout)
            items = [(n, k, d) for k, q in self._queues.items() for n, d in q]
            self._queues.clear()
            self._bytes = 0
        items.sort(key=lambda x: x[0])
        return [(k, d) for _, k, d in items]

    @property
    def queued_bytes(self) -> int:
        with self._cond:
            return self._bytes


class DropLog:
    """Rate-limited reporting of dropped payloads: the first drop is reported at once, later
    ones at most once per ``period`` seconds, as one line with the counts per reason since the
    last line and the last drop's key and detail. Thread-safe."""

    def __init__(self, say: Callable[[str], None], period: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
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
            line = f"dropped {n} payload{'s' if n != 1 else ''}{since} ({parts}); last on {key}: {detail[:200]}"
            self._counts.clear()
            self._said = now
            self.lines += 1
        self.say(line)
        return line


def rss_kb(pid: int | str = "self") -> int | None:
    """Resident set size of a process in KiB (``VmRSS`` in ``/proc``; None elsewhere)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


@dataclass
class ServeOptions:
    """Options of the fusion service process (``wiremap fuse``).

    store : state directory (resume from it, save to it); None: memory only.
    rrd : Rerun recording file; None: no recording.
    serve_viewer : also serve the recording live on this port (needs ``rrd``).
    world : a world name or file, to draw the ground truth in the recording.
    recording_id : Rerun recording id (processes sharing it make one recording).
    heartbeat_s : re-publish the current fused map at least this often (idempotent).
    min_interval_s : fuse at most this often (maps arriving meanwhile are batched).
    save_interval_s : write the store at most this often (each write fsyncs; the last state
        is always written at exit, so a crash (kill -9) loses at most this much, which the
        robots' next heartbeat maps restore). 0: on every change.
    limits : :class:`InputLimits` (what is accepted from the bus).
    drop_log_s : at most one "dropped ..." line per this many seconds (:class:`DropLog`).
    config : :class:`FusionConfig`.
    """

    store: str | None = None
    rrd: str | None = None
    serve_viewer: int | None = None
    world: str | None = None
    recording_id: str | None = None
    heartbeat_s: float = 3.0
    min_interval_s: float = 0.0
    save_interval_s: float = 1.0
    config: FusionConfig = field(default_factory=FusionConfig)
    limits: InputLimits = field(default_factory=InputLimits)
    drop_log_s: float = 5.0


class FusionService:
    """The Zenoh shell around :class:`FusionState` (see :func:`serve`)."""

    def __init__(self, session: Any, keys: Any, opts: ServeOptions, log: Callable[[str], None] | None = None) -> None:
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.keys = keys
        self.opts = opts
        self.say = log or (lambda _s: None)
        self.state = (
            FusionState.load(opts.store, opts.config, limits=opts.limits)
            if opts.store
            else FusionState(opts.config, limits=opts.limits)
        )
        self.recorder: Any = None
        if opts.rrd:
            from agents.rerun_log import FleetRecorder

            self.recorder = FleetRecorder(opts.rrd, serve_port=opts.serve_viewer, recording_id=opts.recording_id)
            if opts.world:
                try:
                    from agents.sim.world import load_world

                    self.recorder.log_truth(load_world(opts.world).truth)
                except (UserError, OSError, ValueError) as exc:
                    self.say(f"cannot draw the world {opts.world!r}: {exc}")
        self.lock = threading.Lock()
        self.current: bytes | None = None  # the last published fused map (the queryable's answer)
        self.version_stamp_ns = 0
        self.intake = Intake(opts.limits)
        self.drops = DropLog(self._say_drop, opts.drop_log_s)
        self._side: dict[str, dict[str, bytes]] = {"pose": {}, "viz": {}}
        self._side_dropped = 0
        self.alive: set[str] = set()
        self.seen_alive: set[str] = set()
        self._gone_during_query: set[str] = set()
        self.liveliness_ready = False
        self.stale: list[str] = []
        self.last_put = time.monotonic()
        self.last_fuse = 0.0
        self.last_say = 0.0
        self.dirty: set[str] = set()
        self.unsaved: set[str] = set()
        self.last_save = 0.0
        self.started = time.monotonic()
        self._stats_doc = b"{}"
        self._stats_at = -math.inf
        self._stats_version: tuple[int, tuple[str, ...]] = (-1, ())
        self._entities: list[Any] = []
        if self.state.version > 0 and self.state.robots:
            self.version_stamp_ns = time.time_ns()
            self.current = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
            self.say(f"resumed fused v{self.state.version} from {opts.store} ({len(self.state.robots)} robots)")

    def _say_drop(self, line: str) -> None:
        self.say(line)
        if self.recorder is not None:
            self.recorder.log_text(self.state.sim_time(), line, level="WARN")

    # ------------------------------------------------------------------ zenoh callbacks (zenoh threads)
    def _on_map(self, sample: Any) -> None:
        key = str(sample.key_expr)
        payload = sample.payload
        reason = self.intake.put(key, payload)
        if reason is not None:
            self.drops.note(reason, key, f"{len(payload)} bytes")

    def _on_side(self, kind: str, max_bytes: int, sample: Any) -> None:
        key = str(sample.key_expr)
        payload = sample.payload
        rid = self.keys.robot_of(key)
        with self.lock:
            slot = self._side[kind]
            if rid is None or len(payload) > max_bytes or (rid not in slot and len(slot) >= self.opts.limits.max_keys):
                self._side_dropped += 1
                return
            slot[rid] = payload.to_bytes()  # only the latest per robot matters

    def _on_pose(self, sample: Any) -> None:
        self._on_side("pose", self.opts.limits.pose_bytes, sample)

    def _on_viz(self, sample: Any) -> None:
        self._on_side("viz", self.opts.limits.viz_bytes, sample)

    def _on_query(self, query: Any) -> None:
        with self.lock:
            data = self.current
        if data is not None:
            query.reply(self.keys.fused_map, data)

    def _on_stats_query(self, query: Any) -> None:
        with self.lock:
            data = self._stats_doc
        query.reply(self.keys.fusion_stats, data, encoding=self._zenoh.Encoding.APPLICATION_JSON)

    def _on_alive(self, sample: Any) -> None:
        rid = self.keys.robot_of(str(sample.key_expr))
        if rid is None:
            return
        with self.lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.alive.add(rid)
                self.seen_alive.add(rid)
                self._gone_during_query.discard(rid)
            else:
                self.alive.discard(rid)
                self._gone_during_query.add(rid)

    # ------------------------------------------------------------------ main thread
    def start(self) -> None:
        """Declare everything. The liveliness tokens alive now are fetched before the first
        publication (a liveliness query, ``wait`` up to 2 s), so that a resumed map's stale
        list is right from the start: a robot is *stale* when the fused map holds its walls
        and no token of it is alive (after the start-up query)."""
        s = self.session
        # liveliness first, so the alive set is complete when the first maps come in
        self._entities.append(s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True))
        with self.lock:
            self._gone_during_query.clear()
        try:
            for reply in s.liveliness().get(self.keys.all_alive, timeout=2.0):
                ok = reply.ok
                rid = None if ok is None else self.keys.robot_of(str(ok.key_expr))
                if rid is not None:
                    with self.lock:
                        if rid not in self._gone_during_query:
                            self.alive.add(rid)
                            self.seen_alive.add(rid)
        except self._zenoh.ZError as exc:  # pragma: no cover - the subscriber still works
            self.say(f"liveliness query failed: {exc}")
        self.liveliness_ready = True
        self._entities.append(s.declare_queryable(self.keys.fused_map, self._on_query, complete=True))
        self._entities.append(s.declare_queryable(self.keys.fusion_stats, self._on_stats_query, complete=True))
        self._entities.append(s.declare_subscriber(self.keys.all_maps, self._on_map))
        self._entities.append(s.declare_subscriber(self.keys.all_poses, self._on_pose))
        self._entities.append(s.declare_subscriber(self.keys.all_viz, self._on_viz))
        self._update_stale(publish=False)
        if self.current is not None:
            self.current = encode_message(self.state.fused_message(self.version_stamp_ns, self._meta()))
            self._put(self.current)
        self._update_stats(force=True)

    def _meta(self) -> dict[str, Any]:
        return {"stale": list(self.stale), "t": self.state.sim_time()}

    def _put(self, data: bytes) -> None:
        self.session.put(self.keys.fused_map, data, congestion_control=self._zenoh.CongestionControl.BLOCK)
        self.last_put = time.monotonic()

    def _publish_new_version(self) -> None:
        st = self.state
        self.version_stamp_ns = time.time_ns()
        data = encode_message(st.fused_message(self.version_stamp_ns, self._meta()))
        with self.lock:
            self.current = data
        self._put(data)
        lat = st.take_latencies(time.time_ns())
        if self.recorder is not None:
            self.recorder.log_fused(st.sim_time(), st.fused, st.fused_robots, st.version, max(lat) if lat else None)
        now = time.monotonic()
        if now - self.last_say >= 1.0:
            self.last_say = now
            self.say(
                f"fused v{st.version}: {st.fused.n_vertices} vertices, {st.fused.n_edges} edges, "
                f"{len(data)} bytes, robots {' '.join(st.fused_robots)}"
            )

    def _take(self, items: list[tuple[str, bytes]]) -> None:
        st = self.state
        now_ns = time.time_ns()
        for key, data in items:
            rid = self.keys.robot_of(key)
            if rid is None:
                st.reject_key(key)
            elif st.offer(data, rid, now_ns):
                self.dirty.add(rid)
            if st.last_drop is not None:
                counter, reason, detail = st.last_drop
                self.drops.note(counter, key, f"{reason}: {detail}")

    def _update_stale(self, publish: bool = True) -> None:
        """Recompute the stale list; on a change re-publish the same version with the new
        metadata and mark the robots in the recording."""
        st = self.state
        if not self.liveliness_ready:
            return
        with self.lock:
            stale = sorted(r for r in st.fused_robots if r not in self.alive)
        if stale == self.stale:
            return
        went, back = sorted(set(stale) - set(self.stale)), sorted(set(self.stale) - set(stale))
        self.stale = stale
        if went:
            self.say(f"stale robots: {' '.join(went)} (liveliness token gone; their last maps are kept)")
        if back:
            self.say(f"robots back: {' '.join(back)}")
        if self.recorder is not None:
            t = st.sim_time()
            for rid in went + back:
                if rid in st.robots:
                    self.recorder.log_robot_status(rid, t, rid in went, st.robot_in_fleet(rid))
        if publish and self.current is not None:
            # same version and stamp, new metadata: robots that left are flagged
            data = encode_message(st.fused_message(self.version_stamp_ns, self._meta()))
            with self.lock:
                self.current = data
            self._put(data)

    def stats_doc(self) -> dict[str, Any]:
        """The counters document served on ``fused/stats`` (JSON)."""
        st = self.state
        self._sync_counters()
        with self.lock:
            alive = sorted(self.alive)
        return {
            "version": st.version,
            "fused": {"vertices": st.fused.n_vertices, "edges": st.fused.n_edges, "robots": list(st.fused_robots)},
            "stale": list(self.stale),
            "alive": alive,
            "robots": {
                r: {"seq": e.key[1], "boot": e.key[0], "stamp_ns": int(e.message.stamp_ns)}
                for r, e in sorted(st.robots.items())
            },
            "stats": st.stats.as_dict(),
            "queued_bytes": self.intake.queued_bytes,
            "drop_log_lines": self.drops.lines,
            "rss_kb": rss_kb(),
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def _sync_counters(self) -> None:
        s = self.state.stats
        s.oversized, s.rate_limited, s.overflow = self.intake.oversized, self.intake.rate_limited, self.intake.overflow
        with self.lock:
            s.side_dropped = self._side_dropped

    def _update_stats(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._stats_at < 0.2:
            return
        self._stats_at = now
        self._stats_version = (self.state.version, tuple(self.stale))
        data = json.dumps(self.stats_doc()).encode()
        with self.lock:
            self._stats_doc = data

    def poll(self, timeout: float = 0.05) -> None:
        """One iteration: take the maps that arrived, fuse, publish, store, log."""
        st = self.state
        self._take(self.intake.drain(timeout))
        now = time.monotonic()
        if self.dirty and now - self.last_fuse >= self.opts.min_interval_s:
            self.last_fuse = now
            changed = sorted(self.dirty)
            self.dirty.clear()
            if st.fuse():
                self._update_stale(publish=False)  # the new version carries the right stale list
                self._publish_new_version()
            self.unsaved.update(changed)
            if self.recorder is not None:
                for rid in changed:
                    if rid in st.robots:
                        t = float(st.robots[rid].message.meta.get("t", 0.0))
                        self.recorder.log_robot_map(rid, t, st.robot_in_fleet(rid))
        if self.opts.store and self.unsaved and time.monotonic() - self.last_save >= self.opts.save_interval_s:
            self._sync_counters()
            st.save(self.opts.store, sorted(self.unsaved), self.version_stamp_ns)
            self.unsaved.clear()
            self.last_save = time.monotonic()
        self._poll_side_channels()
        self._update_stale()
        if self.current is not None and time.monotonic() - self.last_put > self.opts.heartbeat_s:
            self._put(self.current)  # maps are whole states: re-publishing is idempotent
        self.drops.flush()
        # at once when the published map changed (a querier that saw it sees its counters),
        # otherwise at most every 0.2 s
        self._update_stats(force=self._stats_version != (self.state.version, tuple(self.stale)))

    def _poll_side_channels(self) -> None:
        from agents.bus import decode_pose, decode_viz

        st = self.state
        with self.lock:
            raw_poses, raw_viz = self._side["pose"], self._side["viz"]
            self._side = {"pose": {}, "viz": {}}
        poses: dict[str, dict[str, Any]] = {}
        viz: dict[str, dict[str, Any]] = {}
        bad = 0
        for rid, data in raw_poses.items():
            try:
                poses[rid] = decode_pose(data)
            except ValueError:
                bad += 1
        for rid, data in raw_viz.items():
            try:
                viz[rid] = decode_viz(data)
            except ValueError:
                bad += 1
        if bad:
            with self.lock:
                self._side_dropped += bad
        if self.recorder is None:
            return
        for rid, p in sorted(poses.items()):
            origin = st.robots[rid].message.origin if rid in st.robots else None
            est = p["fleet"] if origin is None else origin.compose(p["odom"])
            self.recorder.log_robot_pose(rid, p["t"], est, p["truth"])
        for rid, v in sorted(viz.items()):
            if rid in st.robots:
                m = st.robots[rid].message
                self.recorder.log_robot_viz(rid, v["t"], m.origin, v["pose"], v["scan"], v["particles"], v["weights"])

    def close(self) -> None:
        """Fuse and publish the maps still queued, undeclare everything, save, close the
        recording."""
        st = self.state
        try:
            self._take(self.intake.drain(0.0))
            if self.dirty:
                self.dirty.clear()
                if st.fuse():
                    self._publish_new_version()
        finally:
            for ent in reversed(self._entities):
                try:
                    ent.undeclare()
                except Exception:  # already undeclared or session closed
                    pass
            self._entities.clear()
            self._sync_counters()
            self.drops.flush(force=True)
            if self.opts.store:
                st.save(self.opts.store, None, self.version_stamp_ns)
            if self.recorder is not None:
                self.recorder.close()


def serve(
    session: Any, keys: Any, opts: ServeOptions, stop: threading.Event, log: Callable[[str], None] | None = None
) -> FusionState:
    """Run the fusion service on an open Zenoh session until ``stop`` is set.

    Maps arrive through a callback into the bounded :class:`Intake` (zenoh's thread only
    checks sizes and rates and copies bytes); poses and visualisation through callbacks that
    keep the latest payload per robot. The main thread decodes, fuses, publishes, stores and
    logs; the queryables' callbacks answer with the last published bytes (fused map) and the
    last counters document (``fused/stats``) under a lock. Returns the final state (saved when
    ``opts.store`` is set).
    """
    svc = FusionService(session, keys, opts, log)
    try:
        svc.start()
        svc.say("fusion service ready")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc.state
