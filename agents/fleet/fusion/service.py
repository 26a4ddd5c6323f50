"""The fusion service: every robot's latest map -> one fleet map.

Two layers:

* :class:`FusionState`, the pure core (no zenoh, no rerun, no clock of its own): keeps each
  robot's latest :class:`~wire_codec.message.MapMessage`, recomputes the fused map, stores and
  restores itself on disk.
* :func:`serve`, the Zenoh shell: subscribes to ``robots/*/map`` (through :class:`Intake`, a
  bounded FIFO), ``robots/*/pose`` and ``robots/*/viz`` (only the latest per robot matters;
  only when it writes a Rerun recording, their only use) and ``alive/*``; publishes the fused map on every change and answers queries for it and for
  its counters (``fused/stats``); logs to Rerun.

Order independence: a robot's latest map is the one with the greatest ``(meta["boot"], seq,
sha256 of its bytes)``, whatever the order of arrival, and duplicates are no-ops. Robot ``k`` of
the sorted ids owns bit ``k`` of ``Wireframe.sources`` (``MapMessage.robots`` lists them), so at
most 64 robots.

Fleet frame and merge, per robot in sorted-id order (choices where the paper and the issue are
silent):

1. the map (in the robot's odometry frame) is moved by its start pose (``MapMessage.origin``);
2. if ``mapping.icp`` is available and ``FusionConfig.refine`` is on, a wireframe ICP aligns it
   to the fused map of the robots before it (the first robot is the anchor). The correction is
   kept only when it is small (``max_refine_m`` / ``max_refine_rad``): the start poses are
   known, ICP only removes residual odometry drift;
3. :func:`mapping.merge.merge` adds it to the fused map with the merge threshold
   ``FusionConfig.threshold`` (default 0.2 m, raised to the largest ``resolution`` among the
   robot maps if one is coarser). The fused map travels quantised at the finest robot
   resolution, with the threshold in its ``meta``.

Finally :func:`close_frontiers` removes frontiers of one robot that another robot's walls
close (see there).

Two paths (:meth:`FusionState.compute`), because step 2 is the expensive one (an ICP is 4-7 ms
of CPU on paper-small, a merge ~1 ms):

* the **full path** runs step 2 for every robot whose alignment is not current and is a
  deterministic function of the set of latest maps (property tests over permutations and
  duplicates). It runs when the service has had no new map for ``full_after_s`` (0.5 s) and
  before the final store write at exit;
* the **fast path**, on every batch of arrivals, reuses each robot's cached alignment and
  re-merges, from the first robot whose map or correction changed, every robot's aligned map
  in sorted-id order (partial folds are cached by prefix). It equals the full path's map once
  the alignments are current (:attr:`FusionState.converged`). The service runs no ICP inside
  a fast fuse: after publishing it re-aligns one robot the fuse found wanting it
  (:meth:`FusionState.realign`: its map grew or shrank by ``max(realign_vertices,
  realign_fraction * n)`` vertices, its start pose or boot changed, or its stale alignment is
  ``realign_s`` old), and the next fuse applies the new correction.

The service drains the whole inbox, fuses once and publishes once per loop iteration, so a
burst of maps costs one fold. The store is written by a background thread
(:class:`StoreWriter`); publish latencies go to an append-only ``latency.log``.

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
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from agents.errors import UserError
from agents.files.io import write_atomic, write_json
from agents.fleet.proc import freeze_heap
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind

MAX_ROBOTS = 64
DEFAULT_THRESHOLD = 0.2  # merge threshold (m) unless configured
DEFAULT_RESOLUTION = 0.05  # the fused map's quantisation step (m) while no robot map sets it
FUSION_ID = "fusion"
SNAPSHOT = "snapshot.msgpack"
MAX_LATENCIES = 100_000
LATENCY_LOG = "latency.log"
LATENCY_LOG_MAX_BYTES = 16 * 1024 * 1024
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")  # = agents.fleet.bus.check_name


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
    max_resolution_m : largest map resolution (a coarser one raises the default merge threshold).
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

    threshold : merge threshold in metres; None: ``DEFAULT_THRESHOLD`` (0.2 m), or the largest
        ``resolution`` of the robot maps when that is larger. The robots' resolution is their
        quantisation step, not a merge scale (robots quantise at 0.05 m by default).
    refine : align each robot's map to the rest with ``mapping.icp`` when that module exists.
    max_refine_m, max_refine_rad : largest accepted ICP correction.
    close_frontiers : apply :func:`close_frontiers` to the result.
    realign_vertices, realign_fraction : a fast fuse re-runs a robot's ICP alignment when its
        map's vertex count moved by more than ``max(realign_vertices, realign_fraction * n)``
        since the alignment (``n`` the count then), or its start pose or boot changed.
    realign_s : ... or when the alignment is this old (caller's clock, ``fuse(now=...)``) and
        no longer the one the full path would compute (own map or reference changed).
    max_realign_per_fuse : ICP runs at most per fast fuse (the robots earliest in sorted order
        first; the others keep their cached correction until a later fuse).
    """

    threshold: float | None = None
    refine: bool = True
    max_refine_m: float = 0.6
    max_refine_rad: float = math.radians(6.0)
    close_frontiers: bool = True
    realign_vertices: int = 8
    realign_fraction: float = 0.25
    realign_s: float = 10.0
    max_realign_per_fuse: int = 1


@dataclass(frozen=True)
class RobotEntry:
    """A robot's latest map as received: the message, its exact bytes, its order key and its
    content revision ``rev`` (a number that changes exactly when the map's content -- origin,
    resolution, wireframe arrays -- changes; a re-sent map with a new ``seq`` keeps it)."""

    message: MapMessage
    raw: bytes
    key: tuple[int, int, str]
    rev: int = 0


@dataclass(frozen=True)
class Alignment:
    """A robot's cached fleet-frame alignment (the slow path of :meth:`FusionState.compute`).

    correction : the ICP correction applied after the start pose (None: start pose only).
    rev : the :attr:`RobotEntry.rev` of the map it was computed for.
    n_vertices : that map's vertex count (the growth criterion of :class:`FusionConfig`).
    origin : that map's start pose and boot ``(x, y, theta, boot)``.
    at : the caller's clock when computed (None: unknown).
    reference : the fold prefix it was aligned against, ``(threshold, (robot, rev, correction),
        ...)`` of the robots before it; None when unknown (restored from a store).
    """

    correction: Pose | None
    rev: int
    n_vertices: int
    origin: tuple[float, float, float, int]
    at: float | None = None
    reference: tuple[Any, ...] | None = None


class LatencyWindow:
    """Publish latencies (ms): the last ``capacity`` in a ring buffer plus an all-time count.

    ``total`` counts every sample ever added (also across a restart when restored), so a reader
    can tell how many were recorded between two looks even when the window is full; the
    summary (:meth:`summary`) is over the window and cached until asked for a fresh one.
    """

    def __init__(self, capacity: int = MAX_LATENCIES) -> None:
        self.capacity = int(capacity)
        self._buf = np.zeros(self.capacity, dtype=np.float64)
        self._at = np.zeros(self.capacity, dtype=np.int64)  # when each was recorded (ns, 0: unknown)
        self._n = 0  # samples in the window
        self._head = 0  # next write position
        self.total = 0
        self._summary: dict[str, float | int | None] | None = None

    def extend(self, values: Iterable[float], at_ns: int = 0) -> None:
        """Add samples recorded at ``at_ns`` (wall clock, ns; 0: unknown)."""
        for v in values:
            self._buf[self._head] = float(v)
            self._at[self._head] = int(at_ns)
            self._head = (self._head + 1) % self.capacity
            self._n = min(self._n + 1, self.capacity)
            self.total += 1

    def _ordered(self, a: np.ndarray) -> np.ndarray:
        if self._n < self.capacity:
            return a[: self._n].copy()
        return np.concatenate([a[self._head :], a[: self._head]])

    def values(self) -> np.ndarray:
        """The window, oldest first (a copy)."""
        return self._ordered(self._buf)

    def tail(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The last ``min(k, len)`` samples and their record times (ns), oldest first."""
        v, t = self.values(), self._ordered(self._at)
        k = min(max(0, k), len(v))
        return v[len(v) - k :], t[len(t) - k :]

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[float]:
        return iter(self.values().tolist())

    def __eq__(self, other: object) -> bool:
        if isinstance(other, LatencyWindow):
            return self.total == other.total and np.array_equal(self.values(), other.values())
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def summary(self, fresh: bool = True) -> dict[str, float | int | None]:
        """``{n, total, p50, p99, max}`` over the window; ``fresh=False`` returns the summary
        computed last time (with the current ``n`` and ``total``) unless there is none."""
        if fresh or self._summary is None:
            self._summary = latency_summary(self.values())
        out = dict(self._summary)
        out["n"] = self._n
        out["total"] = self.total
        return out


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
    fuses / full_fuses : fused maps computed (fast path) / of them, full recomputes.
    alignments : ICP alignments run (the slow path).
    latencies_ms : the publish latencies (:class:`LatencyWindow`; ``latency_total`` counts all).
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
    fuses: int = 0
    full_fuses: int = 0
    alignments: int = 0
    malformed_by: dict[str, int] = field(default_factory=dict)
    rejected_by: dict[str, int] = field(default_factory=dict)
    absurd_by: dict[str, int] = field(default_factory=dict)
    latencies_ms: LatencyWindow = field(default_factory=LatencyWindow)

    @property
    def dropped(self) -> int:
        """Every map payload that was dropped, for whatever reason."""
        return self.malformed + self.rejected + self.absurd + self.oversized + self.rate_limited + self.overflow

    @property
    def latency_total(self) -> int:
        return self.latencies_ms.total

    def as_dict(self, fresh_latency: bool = True) -> dict[str, Any]:
        """The counters as JSON-ready values. ``fresh_latency=False`` reuses the last latency
        percentiles (computing them over 100,000 samples takes milliseconds)."""
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
            "fuses": self.fuses,
            "full_fuses": self.full_fuses,
            "alignments": self.alignments,
            "malformed_by": dict(sorted(self.malformed_by.items())),
            "rejected_by": dict(sorted(self.rejected_by.items())),
            "absurd_by": dict(sorted(self.absurd_by.items())),
            "latency_ms": self.latencies_ms.summary(fresh_latency),
        }


def latency_summary(lat_ms: Iterable[float]) -> dict[str, float | int | None]:
    a = lat_ms if isinstance(lat_ms, np.ndarray) else np.asarray(list(lat_ms), dtype=np.float64)
    if len(a) == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(a, [50, 99])
    return {"n": len(a), "p50": float(p50), "p99": float(p99), "max": float(a.max())}


def merge_threshold_of(msg: MapMessage) -> float:
    """The merge threshold a fused map was made with: its ``meta["threshold"]``; for maps
    without it (older services, which quantised the fused map at the threshold) its
    ``resolution``; ``DEFAULT_THRESHOLD`` when neither is a positive number. Maps are scored
    against the truth on a grid of this size (``mapping.metrics.evaluate``), as the paper does."""
    meta = msg.meta if isinstance(msg.meta, dict) else {}
    for v in (meta.get("threshold"), msg.resolution):
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            return float(v)
    return DEFAULT_THRESHOLD


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

    Notes
    -----
    Two paths compute the fused map (:meth:`compute`), both a left fold of
    :func:`mapping.merge.merge` over the robots' fleet-frame maps in sorted-id order:

    * the **full path** (``full=True``) aligns every robot afresh -- start pose, then ICP onto
      the fold of the robots before it -- and is a deterministic function of the set of
      latest maps (and the config): the fused map does not depend on the order or repetition
      of arrivals;
    * the **fast path** (default) reuses each robot's cached :class:`Alignment` and re-runs
      ICP only for robots whose map changed substantially (:class:`FusionConfig`), at most
      ``max_realign_per_fuse`` per fuse; its result is the same fold with the cached
      corrections, so it equals the full path's exactly once every alignment is current
      (:attr:`converged`). An alignment is current when it was computed for the robot's present
      map against the present prefix of the fold, whose robots' alignments are all current.

    The partial folds are cached under the prefix ``(threshold, (robot, rev, correction),
    ...)``, so a fuse recomputes only from the first robot whose map or correction changed.
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
        self.alignments: dict[str, Alignment] = {}
        self.converged = True  # the fused map is the full path's
        self.wanted: list[str] = []  # robots the last fast fuse wanted to re-align but had no budget for
        self.version = 0
        self.stats = FusionStats()
        self._rev = 0
        self._pending: dict[str, int] = {}  # robot -> stamp_ns of an accepted map not yet fused
        # the fold tree (see compute): node (lo, hi) -> (key, map, identity); leaves of the last compute
        self._nodes: dict[tuple[int, int], tuple[tuple[Any, ...], Wireframe, Any]] = {}
        self._leaves: list[tuple[Any, Wireframe]] = []
        self._references: list[tuple[Any, ...]] = []  # per fold position: the prefix before it
        self._prefix_maps: dict[int, tuple[tuple[Any, ...], Wireframe]] = {}  # k -> (key, map of robots < k)
        self.merges = 0  # merge_fn calls made (all paths; a cost counter)
        self._closed: tuple[tuple[Any, ...], Wireframe] | None = None  # the folded map after close_frontiers
        self._in_fleet: dict[str, tuple[int, Wireframe]] = {}  # robot -> (rev, map moved by its start pose)
        self._prepared: dict[str, tuple[tuple[Any, ...], Wireframe]] = {}  # robot -> (key, map ready to merge)
        self._lat_saved = 0  # latency_total already handed to a store job

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
        same = old is not None and _same_content(old.message, msg)
        if same:
            assert old is not None
            rev = old.rev
        else:
            self._rev += 1
            rev = self._rev
        self.robots[rid] = RobotEntry(msg, raw, key, rev)
        self.stats.accepted += 1
        if not same:
            self._pending.setdefault(rid, int(msg.stamp_ns))
        return not same

    # ------------------------------------------------------------------ fusion
    @property
    def threshold(self) -> float:
        """The merge threshold: ``config.threshold``; by default ``DEFAULT_THRESHOLD`` (0.2 m),
        or the largest robot-map resolution when that is coarser (two robots' copies of one
        corner may then be a whole quantisation step apart)."""
        if self.config.threshold is not None:
            return float(self.config.threshold)
        res = [float(e.message.resolution) for e in self.robots.values() if e.message.resolution > 0]
        return max([DEFAULT_THRESHOLD, *res])

    @property
    def resolution(self) -> float:
        """The fused map's quantisation step on the wire: the finest robot-map resolution (the
        fused map is no more precise than its inputs, and no coarser: quantising it at the
        merge threshold would throw away what the robots measured); ``DEFAULT_RESOLUTION``
        without robots."""
        res = [float(e.message.resolution) for e in self.robots.values() if e.message.resolution > 0]
        return min(res, default=DEFAULT_RESOLUTION)

    def robot_in_fleet(self, robot: str) -> Wireframe:
        """A robot's latest map in the fleet frame (start pose, then the ICP correction)."""
        wf = self._fleet_map(robot)
        corr = self.corrections.get(robot)
        return wf.transformed(corr) if corr is not None else wf

    def _fleet_map(self, rid: str) -> Wireframe:
        """The robot's map moved by its start pose (cached per content revision)."""
        e = self.robots[rid]
        hit = self._in_fleet.get(rid)
        if hit is not None and hit[0] == e.rev:
            return hit[1]
        m = e.message
        wf = m.wireframe.transformed(m.origin)
        self._in_fleet[rid] = (e.rev, wf)
        return wf

    def _ready(self, rid: str, corr: Pose | None, k: int) -> Wireframe:
        """The robot's map in the fleet frame with its correction, contributor bit ``k`` set."""
        e = self.robots[rid]
        key = (e.rev, corr, k)
        hit = self._prepared.get(rid)
        if hit is not None and hit[0] == key:
            return hit[1]
        m = e.message
        src = m.wireframe
        pose = m.origin if corr is None else corr.compose(m.origin)
        # one Wireframe (one validation) for origin, correction and contributor bit together
        wf = Wireframe(
            pose.apply(src.points), src.labels, src.edges, src.likelihood,
            np.full(src.n_edges, np.uint64(1) << np.uint64(k), dtype=np.uint64),
        )
        self._prepared[rid] = (key, wf)
        return wf

    def _wants_realign(self, al: Alignment | None, e: RobotEntry, current: bool, now: float | None) -> bool:
        """The fast path's test: re-run this robot's ICP now? (see :class:`FusionConfig`)."""
        if al is None:
            return True
        if current:
            return False
        cfg = self.config
        if al.rev != e.rev:
            if _origin_of(e.message) != al.origin:
                return True
            n = e.message.wireframe.n_vertices
            if abs(n - al.n_vertices) > max(cfg.realign_vertices, cfg.realign_fraction * al.n_vertices):
                return True
        return now is not None and (al.at is None or now - al.at >= cfg.realign_s)

    # ------------------------------------------------------------------ the fold tree
    def _merge(self, base: Wireframe, new: Wireframe, thr: float) -> Wireframe:
        if new.n_vertices == 0:
            return base
        if base.n_vertices == 0:
            return new
        self.merges += 1
        return self.merge_fn(base, new, thr)

    def _node(self, lo: int, hi: int, leaves: list[tuple[Any, Wireframe]], thr: float) -> tuple[Wireframe, Any]:
        """The fold of ``leaves[lo:hi]`` (see :meth:`compute`) and its identity: a leaf's item,
        or a digest of the node's map. Cached per ``(lo, hi)`` under ``(thr, identity of the
        left part, identity of the right part)``, so a change that leaves a partial result
        as it was (a wall another robot already reported) stops there."""
        if hi - lo == 1:
            return leaves[lo][1], leaves[lo][0]
        mid = _fold_split(lo, hi)
        left, kl = self._node(lo, mid, leaves, thr)
        right, kr = self._node(mid, hi, leaves, thr)
        key = (thr, kl, kr)
        hit = self._nodes.get((lo, hi))
        if hit is not None and hit[0] == key:
            return hit[1], hit[2]
        out = self._merge(left, right, thr)
        ident = _digest(out)
        self._nodes[(lo, hi)] = (key, out, ident)
        return out, ident

    def _prefix_map(self, k: int, leaves: list[tuple[Any, Wireframe]], thr: float) -> Wireframe:
        """The map of the robots before fold position ``k`` (what robot ``k`` is aligned onto):
        the tree's nodes that cover ``[0, k)``, merged left to right. For ``k <= 2`` and for
        fleets of up to three robots that is exactly the left fold of their maps."""
        parts: list[tuple[Wireframe, Any]] = []
        lo, hi = 0, len(leaves)
        while k > lo and hi - lo > 0:
            if k >= hi:
                parts.append(self._node(lo, hi, leaves, thr))
                break
            if hi - lo == 1:
                break
            mid = _fold_split(lo, hi)
            if k <= mid:
                hi = mid
            else:
                parts.append(self._node(lo, mid, leaves, thr))
                lo = mid
        key = (thr, *(ident for _, ident in parts))
        hit = self._prefix_maps.get(k)
        if hit is not None and hit[0] == key:
            return hit[1]
        acc = Wireframe.empty()
        for wf, _ in parts:
            acc = self._merge(acc, wf, thr)
        self._prefix_maps[k] = (key, acc)
        return acc

    def compute(
        self, full: bool = False, now: float | None = None, max_realign: int | None = None
    ) -> tuple[Wireframe, tuple[str, ...], dict[str, Pose]]:
        """The fused map of the current latest maps: ``(map, robot ids, corrections)``.

        ``full=True``: the full path, every alignment made current (a deterministic function
        of the set of latest maps); otherwise the fast path, which re-aligns at most
        ``max_realign`` robots (default ``config.max_realign_per_fuse``) chosen by
        :class:`FusionConfig`'s criteria, earliest in sorted order first. ``now`` is the
        caller's clock in seconds (for ``realign_s``). Updates :attr:`alignments` and
        :attr:`converged`; the cached partial folds change the cost, never the result.

        The fold: the robots' maps (fleet frame, correction applied, contributor bit set) in
        sorted-id order are the leaves of a fixed binary tree; a node over ``[lo, hi)`` is
        ``merge(node(lo, mid), node(mid, hi))`` with ``mid - lo`` the largest power of two
        below ``hi - lo`` (so up to three robots it is the left fold ``((r1, r2), r3)``; with
        16 a balanced tree). A changed robot costs the merges on its path to the root (4 of
        15 with 16 robots, against 8 on average for a left fold), and the nodes are cached.
        """
        cfg = self.config
        ids = tuple(sorted(self.robots))
        thr = self.threshold
        budget = len(ids) if full else (cfg.max_realign_per_fuse if max_realign is None else max_realign)
        prefix: tuple[Any, ...] = (thr,)
        exact = True
        corrections: dict[str, Pose] = {}
        alignments: dict[str, Alignment] = {}
        wanted: list[str] = []
        leaves: list[tuple[Any, Wireframe]] = []
        references: list[tuple[Any, ...]] = []
        for k, rid in enumerate(ids):
            e = self.robots[rid]
            al = self.alignments.get(rid)
            n = e.message.wireframe.n_vertices
            references.append(prefix)
            if k == 0 or not cfg.refine:
                # the anchor (and everyone without refinement): the start pose alone, by definition current
                if al is None or al.rev != e.rev or al.reference != prefix or al.correction is not None:
                    al = Alignment(None, e.rev, n, _origin_of(e.message), now, prefix)
            else:
                current = exact and al is not None and al.rev == e.rev and al.reference == prefix
                want = (not current) if full else self._wants_realign(al, e, current, now)
                if want and budget <= 0:
                    wanted.append(rid)
                elif want:
                    budget -= 1
                    wf0 = self._fleet_map(rid)
                    ref = self._prefix_map(k, leaves, thr)
                    corr_new = _refine(wf0, ref, thr, cfg) if ref.n_edges and wf0.n_edges else None
                    al = Alignment(corr_new, e.rev, n, _origin_of(e.message), now, prefix)
                    self.stats.alignments += 1
                    current = exact
                exact = current
            if al is not None:
                alignments[rid] = al
            corr = al.correction if al is not None else None
            if corr is not None:
                corrections[rid] = corr
            prefix = (*prefix, (rid, e.rev, corr))
            leaves.append(((rid, e.rev, corr, k), self._ready(rid, corr, k)))
        acc = self._node(0, len(leaves), leaves, thr)[0] if leaves else Wireframe.empty()
        for span in [p for p in self._nodes if p[1] > len(leaves)]:
            del self._nodes[span]
        for pos in [p for p in self._prefix_maps if p > len(leaves)]:
            del self._prefix_maps[pos]
        self._leaves = leaves
        self._references = references
        self.alignments = alignments
        self.wanted = wanted
        self.converged = exact
        for cache in (self._in_fleet, self._prepared):
            for rid in [r for r in cache if r not in self.robots]:
                del cache[rid]
        closed = (*prefix, self.config.close_frontiers)
        if self._closed is not None and self._closed[0] == closed:
            acc = self._closed[1]
        elif self.config.close_frontiers:
            acc = close_frontiers(acc, thr)
        self._closed = (closed, acc)
        return acc, ids, corrections

    def realign(self, now: float | None = None, limit: int = 1) -> list[str]:
        """The slow path on its own: re-run the ICP alignment of up to ``limit`` robots that the
        last fuse found wanting one (:attr:`wanted`, in fold order), each against the prefix of
        that fuse's fold. The fused map does not change; the next :meth:`fuse` uses the new
        alignments (and recomputes the fold where a correction changed).
        Lets a service publish first and align afterwards. Returns the robots aligned."""
        done: list[str] = []
        if not self.config.refine:
            return done
        position = {item[0]: k for k, (item, _) in enumerate(self._leaves)}
        thr = self.threshold
        for rid in list(self.wanted):
            if len(done) >= limit:
                break
            self.wanted.remove(rid)
            k = position.get(rid, 0)
            e = self.robots.get(rid)
            if e is None or k == 0:
                continue
            reference = self._references[k]
            if reference[0] != thr:
                continue  # the threshold changed since that fold: the next fuse decides
            acc = self._prefix_map(k, self._leaves, thr)
            wf0 = self._fleet_map(rid)
            corr = _refine(wf0, acc, thr, self.config) if acc.n_edges and wf0.n_edges else None
            n = e.message.wireframe.n_vertices
            self.alignments[rid] = Alignment(corr, e.rev, n, _origin_of(e.message), now, reference)
            self.stats.alignments += 1
            done.append(rid)
        return done

    def fuse(self, full: bool = False, now: float | None = None, max_realign: int | None = None) -> bool:
        """Recompute the fused map (:meth:`compute`); bump ``version`` and return True when it
        changed."""
        wf, ids, corr = self.compute(full, now, max_realign)
        self.stats.fuses += 1
        self.stats.full_fuses += int(full)
        self.corrections = corr
        changed = ids != self.fused_robots or not _same_wireframe(wf, self.fused)
        if changed:
            self.fused, self.fused_robots = wf, ids
            self.version += 1
        else:
            self._pending.clear()
        return changed

    def take_latencies(self, published_ns: int) -> list[float]:
        """Latency (ms) from each robot map that changed since the last fused publish to this
        publish at ``published_ns`` (same machine clock); recorded in ``stats.latencies_ms``
        (the last ``MAX_LATENCIES`` in the window, all in its ``total``)."""
        out = [max(0.0, (published_ns - s) / 1e6) for s in self._pending.values()]
        self._pending.clear()
        self.stats.latencies_ms.extend(out, published_ns)
        self.stats.published += 1
        return out

    def fused_message(self, stamp_ns: int, meta: dict[str, Any] | None = None) -> MapMessage:
        """The fused map as a ``FUSED_MAP`` message: quantised at :attr:`resolution`, ``meta``
        with ``version`` and the merge ``threshold`` (the scale its walls were merged at, and
        the grid its quality is scored on) plus ``meta``."""
        m: dict[str, Any] = {"version": self.version, "threshold": self.threshold}
        m.update(meta or {})
        return MapMessage(
            kind=MessageKind.FUSED_MAP,
            sender=self.sender,
            seq=self.version,
            stamp_ns=int(stamp_ns),
            pose=Pose.identity(),
            frame="fleet",
            origin=Pose.identity(),
            resolution=self.resolution,
            wireframe=self.fused,
            robots=self.fused_robots,
            meta=m,
        )

    def sim_time(self) -> float:
        """The latest simulated time any robot map carries (``meta["t"]``), 0 if none."""
        ts = [float(e.message.meta.get("t", 0.0)) for e in self.robots.values() if isinstance(e.message.meta, dict)]
        return max(ts, default=0.0)

    # ------------------------------------------------------------------ store
    def store_job(
        self,
        store: str | os.PathLike[str],
        robots: Iterable[str] | None = None,
        stamp_ns: int = 0,
        fresh_latency: bool = True,
    ) -> StoreJob:
        """What :meth:`save` writes, gathered now (cheap: references to bytes, the counters,
        the new latencies) and written later by :meth:`StoreJob.write`, possibly in another
        thread (:class:`StoreWriter`)."""
        ids = sorted(self.robots if robots is None else robots)
        lat = self.stats.latencies_ms
        new = min(lat.total - self._lat_saved, len(lat))
        first = lat.total - new + 1  # index of the first new sample (1-based, all-time)
        job = StoreJob(
            store=Path(store),
            version=self.version,
            stamp_ns=int(stamp_ns),
            robots={r: e.raw for r, e in sorted(self.robots.items())},
            views={r for r in ids if r in self.robots},
            fused_raw=encode_message(self.fused_message(stamp_ns)),
            alignments={
                r: (None if (c := self.corrections.get(r)) is None else [c.x, c.y, c.theta]) for r in self.fused_robots
            },
            state={
                "version": self.version,
                "robots": {
                    r: {"seq": e.key[1], "boot": e.key[0], "sha256": e.key[2]} for r, e in sorted(self.robots.items())
                },
                "fused": {"vertices": self.fused.n_vertices, "edges": self.fused.n_edges},
                "converged": self.converged,
                "stats": self.stats.as_dict(fresh_latency),
                "latency_total": lat.total,
                "latency_log": LATENCY_LOG,
            },
            latencies=[(first + i, v, t) for i, (v, t) in enumerate(zip(*(a.tolist() for a in lat.tail(new))))],
        )
        self._lat_saved = lat.total
        return job

    def save(self, store: str | os.PathLike[str], robots: Iterable[str] | None = None, stamp_ns: int = 0) -> None:
        """Write the state under ``store`` now (see :class:`StoreJob` for the files)."""
        self.store_job(store, robots, stamp_ns).write()

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
        recomputed from them: with the snapshot's stored alignments when it has them for every
        robot (so a map the fast path published comes back exactly), otherwise by the full
        path. It keeps the stored version when it equals the stored fused map; otherwise the
        version goes up. Unreadable files are skipped with a warning on stderr. The latency
        window is refilled from the tail of ``latency.log`` and its all-time count from
        ``state.json``.
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
        total = 0
        try:
            state = json.loads((d / "state.json").read_text())
            total = int(state.get("latency_total", 0) or 0)
        except (OSError, ValueError, TypeError, AttributeError):
            pass
        tail = read_latency_log(d, MAX_LATENCIES)
        st.stats.latencies_ms.extend(v for _, v in tail)
        st.stats.latencies_ms.total = max(total, tail[-1][0] if tail else 0, len(tail))
        st._lat_saved = st.stats.latencies_ms.total
        if st.robots:
            al = contents.alignments
            if al is not None and set(al) == set(st.robots):
                for rid, corr in al.items():
                    e = st.robots[rid]
                    st.alignments[rid] = Alignment(corr, e.rev, e.message.wireframe.n_vertices, _origin_of(e.message))
                st.fuse(max_realign=0)
            else:
                st.fuse(full=True)
        st._pending.clear()
        same = False
        if contents.fused is not None and st.robots:
            # compare as stored: through the codec
            again = decode_message(encode_message(st.fused_message(0))).wireframe
            same = again.almost_equal(contents.fused.wireframe, tol=1e-9, likelihood_tol=1e-9)
        st.version = contents.version if (same or not st.robots) else contents.version + 1
        return st


@dataclass
class StoreJob:
    """One write of the fusion store, gathered by :meth:`FusionState.store_job`.

    :meth:`write` writes, in this order: the new latencies appended to ``latency.log``
    (:func:`append_latency_log`); then ``snapshot.msgpack``, the authoritative copy, in one
    atomic write (temporary file, fsync, rename): ``{"format": 2, "version", "stamp_ns",
    "robots": {id: bytes as received}, "fused": fused map bytes, "alignments": {id: [x, y,
    theta] or None}}``, so a crash at any moment leaves either the old or the new snapshot;
    then views for people and tools, each atomic too: ``robots/<id>.wfm`` (those in
    :attr:`views`), ``fused.wfm`` and ``state.json`` (version, per-robot seq/boot/sha256,
    counters with the latency summary, ``latency_total``). ``state.json`` comes last, so a
    reader that sees its ``latency_total`` finds that many lines in the log.
    """

    store: Path
    version: int
    stamp_ns: int
    robots: dict[str, bytes]
    views: set[str]
    fused_raw: bytes
    alignments: dict[str, list[float] | None]
    state: dict[str, Any]
    latencies: list[tuple[int, float, int]]

    def then(self, newer: StoreJob) -> StoreJob:
        """This job followed by ``newer`` as one: newer contents, the views and latencies of both."""
        return StoreJob(
            newer.store, newer.version, newer.stamp_ns, newer.robots, self.views | newer.views, newer.fused_raw,
            newer.alignments, newer.state, self.latencies + newer.latencies,
        )

    def write(self) -> None:
        d = self.store
        if self.latencies:
            append_latency_log(d, self.latencies)
        snap = {
            "format": 2,
            "version": self.version,
            "stamp_ns": self.stamp_ns,
            "robots": self.robots,
            "fused": self.fused_raw,
            "alignments": self.alignments,
        }
        write_atomic(d / SNAPSHOT, bytes(msgpack.packb(snap, use_bin_type=True)))
        for rid in sorted(self.views):
            if rid in self.robots:
                write_atomic(d / "robots" / f"{rid}.wfm", self.robots[rid])
        write_atomic(d / "fused.wfm", self.fused_raw)
        write_json(d / "state.json", self.state)


def append_latency_log(store: str | os.PathLike[str], samples: list[tuple[int, float, int]]) -> None:
    """Append ``<index> <ms> <published_ns>`` lines to ``<store>/latency.log`` (no fsync:
    statistics, not state); rotate it to ``latency.log.1`` first when it is over
    ``LATENCY_LOG_MAX_BYTES``. ``index`` counts every sample ever recorded (1, 2, ...),
    ``published_ns`` is the wall clock of the fused publish the sample ended at."""
    d = Path(store)
    d.mkdir(parents=True, exist_ok=True)
    path = d / LATENCY_LOG
    try:
        if path.stat().st_size > LATENCY_LOG_MAX_BYTES:
            os.replace(path, d / (LATENCY_LOG + ".1"))
    except FileNotFoundError:
        pass
    text = "".join(f"{i} {v:.3f} {t}\n" for i, v, t in samples)
    with open(path, "a", encoding="ascii") as fh:
        fh.write(text)


def read_latency_log(store: str | os.PathLike[str], last: int) -> list[tuple[int, float]]:
    """The last ``last`` ``(index, ms)`` samples of ``<store>/latency.log`` (and of
    ``latency.log.1`` when the current file holds fewer); unreadable lines are skipped."""
    d = Path(store)
    out: list[tuple[int, float]] = []
    for name in (LATENCY_LOG, LATENCY_LOG + ".1"):
        need = last - len(out)
        if need <= 0:
            break
        try:
            with open(d / name, "rb") as fh:
                size = fh.seek(0, os.SEEK_END)
                start = max(0, size - need * 24)
                fh.seek(start)
                data = fh.read()
        except OSError:
            continue
        lines = data.split(b"\n")
        if start > 0:
            lines = lines[1:]  # probably cut
        got: list[tuple[int, float]] = []
        for ln in lines:
            parts = ln.split()
            if len(parts) not in (2, 3):
                continue
            try:
                got.append((int(parts[0]), float(parts[1])))
            except ValueError:
                continue
        out = got[max(0, len(got) - need) :] + out
    return out


@dataclass(frozen=True)
class StoreContents:
    """What :func:`read_store` found: the stored version, the stored fused map (None if
    unreadable), each robot's stored bytes, and the alignments the stored map was fused with
    (None when not stored: a format-1 snapshot or the views)."""

    version: int
    fused: MapMessage | None
    raw_robots: dict[str, bytes]
    from_snapshot: bool
    alignments: dict[str, Pose | None] | None = None

    def robots(self) -> dict[str, MapMessage]:
        """The stored robot maps, decoded (undecodable ones left out)."""
        out = {}
        for rid, raw in self.raw_robots.items():
            try:
                out[rid] = decode_message(raw)
            except ValueError:
                continue
        return out


def _read_alignments(doc: Any) -> dict[str, Pose | None] | None:
    if not isinstance(doc, dict):
        return None
    out: dict[str, Pose | None] = {}
    for rid, v in doc.items():
        if not isinstance(rid, str):
            return None
        if v is None:
            out[rid] = None
            continue
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)):
            return None
        try:
            out[rid] = Pose(float(v[0]), float(v[1]), float(v[2]))
        except ValueError:
            return None
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
                al = _read_alignments(snap.get("alignments"))
                return StoreContents(version, fused, dict(sorted(robots.items())), True, al)
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


def _origin_of(msg: MapMessage) -> tuple[float, float, float, int]:
    boot = msg.meta.get("boot", 0) if isinstance(msg.meta, dict) else 0
    return (msg.origin.x, msg.origin.y, msg.origin.theta, boot if isinstance(boot, int) else 0)


def _fold_split(lo: int, hi: int) -> int:
    """Where the fold tree splits ``[lo, hi)`` (``hi - lo >= 2``): after the largest power of
    two below ``hi - lo``."""
    p = 1
    while 2 * p < hi - lo:
        p *= 2
    return lo + p


def _digest(wf: Wireframe) -> bytes:
    """A digest of a wireframe's arrays (shapes included): equal maps, equal digests."""
    h = hashlib.blake2b(digest_size=16)
    for a in (wf.points, wf.labels, wf.edges, wf.likelihood, wf.sources):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


def _same_content(a: MapMessage, b: MapMessage) -> bool:
    """Exactly the same map for fusion: start pose, resolution and wireframe arrays (the codec
    decodes the same content to the same arrays)."""
    return (
        a.origin.as_tuple() == b.origin.as_tuple()
        and float(a.resolution) == float(b.resolution)
        and _same_arrays(a.wireframe, b.wireframe)
    )


def _same_arrays(a: Wireframe, b: Wireframe) -> bool:
    return (
        a.points.shape == b.points.shape
        and a.edges.shape == b.edges.shape
        and np.array_equal(a.points, b.points)
        and np.array_equal(a.labels, b.labels)
        and np.array_equal(a.edges, b.edges)
        and np.array_equal(a.likelihood, b.likelihood)
        and np.array_equal(a.sources, b.sources)
    )


def _same_wireframe(a: Wireframe, b: Wireframe) -> bool:
    """Identical arrays, or the same graph up to vertex and edge order (1e-9)."""
    if a is b or _same_arrays(a, b):
        return True
    if a.n_vertices != b.n_vertices or a.n_edges != b.n_edges:
        return False
    return a.almost_equal(b, tol=1e-9)


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


_PAGE_KB = (os.sysconf("SC_PAGE_SIZE") // 1024) if hasattr(os, "sysconf") else 4


def rss_kb(pid: int | str = "self") -> int | None:
    """Resident set size of a process in KiB (``VmRSS`` in ``/proc``; None elsewhere).

    Read from ``/proc/<pid>/statm`` (resident pages, the same counter as ``VmRSS``; a third of
    the cost of ``status``, and the service reports it with every new version), else from
    ``status``."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as fh:
            return int(fh.read().split()[1]) * _PAGE_KB
    except (OSError, ValueError, IndexError):
        pass
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


class StoreWriter:
    """Writes :class:`StoreJob` s in a background thread, so that the fusion loop never waits
    for a disk (each store write fsyncs several files).

    :meth:`submit` hands over a job; a job still waiting when the next arrives is combined
    with it (:meth:`StoreJob.then`: the newest contents, every view and latency of both), so
    at most one write is ever queued and the files are written in order. :meth:`close` writes
    what is waiting and stops the thread. A failed write is reported through ``say`` (once per
    error message) and counted in :attr:`errors`; the next job writes everything again.
    """

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self.say = say or (lambda _s: None)
        self._cond = threading.Condition()
        self._job: StoreJob | None = None
        self._busy = False
        self._stop = False
        self.errors = 0
        self.written = 0
        self._last_error = ""
        self._thread = threading.Thread(target=self._run, name="fusion-store", daemon=True)
        self._thread.start()

    def submit(self, job: StoreJob) -> None:
        with self._cond:
            self._job = job if self._job is None else self._job.then(job)
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._job is None and not self._stop:
                    self._cond.wait()
                job, self._job = self._job, None
                if job is None:
                    return
                self._busy = True
            try:
                job.write()
                self.written += 1
            except OSError as exc:
                self.errors += 1
                text = f"cannot write the store {job.store}: {exc}"
                if text != self._last_error:
                    self._last_error = text
                    self.say(text)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until nothing is queued or being written; returns whether that happened."""
        with self._cond:
            return self._cond.wait_for(lambda: self._job is None and not self._busy, timeout)

    def close(self, timeout: float = 30.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)


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
        robots' next heartbeat maps restore). 0: on every change. The writes happen in a
        background thread (:class:`StoreWriter`).
    full_after_s : when no robot map has changed for this long and the fused map is not the
        full path's (:attr:`FusionState.converged`), recompute it by the full path.
    latency_summary_s : recompute the latency percentiles of ``fused/stats`` at most this often
        (the counters themselves are always current).
    align_wait_s : an ICP re-alignment (the slow path) runs after a publish when no map is
        waiting, or when none has run for this long even though maps keep waiting.
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
    full_after_s: float = 0.5
    latency_summary_s: float = 1.0
    align_wait_s: float = 0.5


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
            from agents.files.rerun_log import FleetRecorder

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
        self.refuse = False  # fuse at the next iteration even without new maps (a new alignment)
        self.last_align = -math.inf
        self.unsaved: set[str] = set()
        self.last_save = 0.0
        self.save_due = False  # the store is behind for another reason than robot maps
        self.last_change = time.monotonic()  # when a robot map last changed
        self._lat_at = -math.inf
        self.timing: dict[str, float] = dict.fromkeys(
            ("wait", "decode", "fuse", "publish", "align", "other", "iterations"), 0.0
        )
        self._timed = 0.0  # of this iteration's time, spent in _fuse
        self.transport_ms = LatencyWindow(10_000)  # robot publish -> inbox, of maps that changed
        self.writer = StoreWriter(self.say) if opts.store else None
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
        if self.recorder is not None:
            # poses and scans only feed the recording: without one, 10 Hz x robots of callbacks
            # (each taking the interpreter lock from the fusion loop) would be for nothing
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
        self._update_stats(force=True)  # before the put: whoever sees the map sees its counters
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

    def _take(self, items: list[tuple[str, bytes, int]]) -> None:
        st = self.state
        now_ns = time.time_ns()
        for key, data, arrived_ns in items:
            rid = self.keys.robot_of(key)
            if rid is None:
                st.reject_key(key)
            elif st.offer(data, rid, now_ns):
                self.dirty.add(rid)
                self.last_change = time.monotonic()
                # robot publish -> in the fusion service's inbox (transport and the robot's own put)
                self.transport_ms.extend([max(0.0, (arrived_ns - st.robots[rid].message.stamp_ns) / 1e6)])
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
            self._update_stats(force=True)
            self._put(data)

    def stats_doc(self) -> dict[str, Any]:
        """The counters document served on ``fused/stats`` (JSON)."""
        st = self.state
        self._sync_counters()
        fresh = self._fresh_latency()
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
            "stats": st.stats.as_dict(fresh),
            "converged": st.converged,
            "transport_ms": self.transport_ms.summary(fresh),
            "queued_bytes": self.intake.queued_bytes,
            "drop_log_lines": self.drops.lines,
            "rss_kb": rss_kb(),
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
        }

    def _fresh_latency(self) -> bool:
        """Whether the latency percentiles are due for a recomputation."""
        now = time.monotonic()
        if now - self._lat_at >= self.opts.latency_summary_s:
            self._lat_at = now
            return True
        return False

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
        """One iteration: take every map that arrived (the whole queue), fuse once (the fast
        path), publish once, hand the store to the writer thread, log. When no map has
        changed for ``full_after_s`` and the fused map is not the full path's, the full path
        runs instead (at most once per quiet period: afterwards it is converged)."""
        st = self.state
        clock = time.perf_counter
        t0 = clock()
        if self.dirty or self.refuse:
            # a fuse is due once min_interval_s has passed since the last: wait no longer
            due = self.last_fuse + self.opts.min_interval_s - time.monotonic()
            timeout = min(timeout, max(due, 0.0))
        items = self.intake.drain_timed(timeout)
        t1 = clock()
        self._take(items)
        t2 = clock()
        self.timing["wait"] += t1 - t0
        self.timing["decode"] += t2 - t1
        now = time.monotonic()
        if (self.dirty or self.refuse) and now - self.last_fuse >= self.opts.min_interval_s:
            self.last_fuse = now
            changed = sorted(self.dirty)
            self.dirty.clear()
            self.refuse = False
            self._fuse(full=False, now=now, max_realign=0)
            self.unsaved.update(changed)
            if self.recorder is not None:
                for rid in changed:
                    if rid in st.robots:
                        t = float(st.robots[rid].message.meta.get("t", 0.0))
                        self.recorder.log_robot_map(rid, t, st.robot_in_fleet(rid))
        elif (
            not self.dirty
            and not self.refuse
            and st.robots
            and not st.converged
            and now - self.last_change >= self.opts.full_after_s
        ):
            self._fuse(full=True, now=now)
            self.save_due = True  # the alignments (and maybe the map) changed
        if st.wanted and (self.intake.empty or now - self.last_align >= self.opts.align_wait_s):
            # the slow path after the publish: the maps just fused did not wait for ICP, nor
            # do maps already waiting (unless alignments have waited align_wait_s); the next
            # fuse applies the new alignment
            t = time.perf_counter()
            self.last_align = now
            if st.realign(now=now, limit=1):
                self.refuse = True  # fuse again even if no map arrives
            self.timing["align"] += time.perf_counter() - t
            self._timed += time.perf_counter() - t
        if (
            self.opts.store
            and (self.unsaved or self.save_due)
            and time.monotonic() - self.last_save >= self.opts.save_interval_s
        ):
            self._save_async()
        self._poll_side_channels()
        self._update_stale()
        if self.current is not None and time.monotonic() - self.last_put > self.opts.heartbeat_s:
            self._put(self.current)  # maps are whole states: re-publishing is idempotent
        self.drops.flush()
        # at once when the published map changed (a querier that saw it sees its counters),
        # otherwise at most every 0.2 s
        self._update_stats(force=self._stats_version != (self.state.version, tuple(self.stale)))
        self.timing["other"] += clock() - t2 - self._timed
        self._timed = 0.0
        self.timing["iterations"] += 1

    def _fuse(self, full: bool, now: float, max_realign: int | None = None) -> None:
        t0 = time.perf_counter()
        changed = self.state.fuse(full=full, now=now, max_realign=max_realign)
        t1 = time.perf_counter()
        if changed:
            self._update_stale(publish=False)  # the new version carries the right stale list
            self._publish_new_version()
        t2 = time.perf_counter()
        self.timing["fuse"] += t1 - t0
        self.timing["publish"] += t2 - t1
        self._timed += t2 - t0

    def timing_line(self) -> str:
        """Where the main loop's time went (seconds in total): waiting for maps, decoding,
        fusing, publishing, the rest."""
        t = self.timing
        parts = " ".join(f"{k} {t[k]:.2f}" for k in ("wait", "decode", "fuse", "publish", "align", "other"))
        tr = self.transport_ms.summary()
        transport = "" if tr["p50"] is None else f"; robot publish -> inbox ms: p50 {tr['p50']:.1f} p99 {tr['p99']:.1f}"
        return (
            f"main loop: {int(t['iterations'])} iterations, {self.state.stats.fuses} fuses; seconds: {parts}"
            f"{transport}"
        )

    def _save_async(self) -> None:
        assert self.opts.store is not None
        self._sync_counters()
        job = self.state.store_job(self.opts.store, sorted(self.unsaved), self.version_stamp_ns, self._fresh_latency())
        if self.writer is not None:
            self.writer.submit(job)
        else:  # pragma: no cover - a store always has a writer
            job.write()
        self.unsaved.clear()
        self.save_due = False
        self.last_save = time.monotonic()

    def _poll_side_channels(self) -> None:
        from agents.fleet.bus import decode_pose, decode_viz

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
        """Fuse and publish the maps still queued by the full path (the final map is the
        deterministic one), undeclare everything, write the store (after whatever the writer
        thread still had), close the recording."""
        st = self.state
        try:
            self._take(self.intake.drain_timed(0.0))
            if st.robots and (self.dirty or self.refuse or not st.converged):
                self.dirty.clear()
                self._fuse(full=True, now=time.monotonic())
        finally:
            for ent in reversed(self._entities):
                try:
                    ent.undeclare()
                except Exception:  # already undeclared or session closed
                    pass
            self._entities.clear()
            self._sync_counters()
            self.drops.flush(force=True)
            self.say(self.timing_line())
            if self.writer is not None:
                self.writer.close()
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
        freeze_heap()
        svc.say("fusion service ready")
        while not stop.is_set():
            svc.poll(0.05)
    finally:
        svc.close()
    return svc.state
