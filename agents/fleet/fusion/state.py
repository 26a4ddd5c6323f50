"""The fusion core: every robot's latest map -> one fleet map, without any I/O but the store.

:class:`FusionState` keeps each robot's latest :class:`~wire_codec.message.MapMessage`
(:class:`RobotEntry`), each robot's cached alignment (:class:`Alignment`) and the fold tree of
the fused map (see :meth:`FusionState.compute` and ``ARCHITECTURE.md``, "Fusion rules"). The
map algorithms it uses are in :mod:`mapping.fleet` (frontier closing, map-to-map alignment,
the tree's shape) and :mod:`mapping.merge`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from agents.errors import UserError
from agents.fleet.bus import valid_name
from agents.fleet.fusion.budget import WorkBudget
from agents.fleet.fusion.codec import decode_message, encode_message, order_key, peek_header
from agents.fleet.fusion.facts import MapFacts, facts_of
from agents.fleet.fusion.frames import (
    FleetFrames,
    FramesConfig,
    RegistrationRecord,
    fold_maps,
    origin_unknown,
)
from agents.fleet.fusion.intake import InputLimits, implausible, over_budget
from agents.fleet.fusion.quarantine import (
    FleetSamples,
    Quarantine,
    QuarantineConfig,
    history_judge,
    key_set,
)
from agents.fleet.fusion.stats import MAX_LATENCIES, FusionStats
from agents.fleet.fusion.store import LATENCY_LOG, StoreDamaged, StoreJob, read_latency_log, read_store
from agents.fleet.fusion.tree import merge_on_grid, prefix_spans, wire_snap
from mapping.fleet import align_maps, close_frontiers, fold_split
from mapping.se2 import Pose
from mapping.wireframe import Wireframe, mask_array
from wire_codec import MAX_ROBOTS
from wire_codec.body import decode_body
from wire_codec.errors import Limits
from wire_codec.message import MapMessage, MessageKind

#: How long (seconds) a map claiming a restart waits for its robot's liveliness token.
RESTART_HOLD_S = 5.0

DEFAULT_THRESHOLD = 0.2  # merge threshold (m) unless configured
DEFAULT_RESOLUTION = 0.05  # the fused map's quantisation step (m) while no robot map sets it
FUSION_ID = "fusion"
LATE_GRACE_NS = 3 * 10**9  # robots heard of this soon after start were already running (heartbeat 2 s)
MAX_TRANSPORT_NS = 60 * 10**9  # a map's latency sample is at most this plus the fuse (forged stamps)


MergeFn = Callable[[Wireframe, Wireframe, float], Wireframe]

#: Drops that judge the payload itself: :meth:`FusionState.offer_latest` then tries the one before.
PAYLOAD_DROPS = ("malformed", "rejected", "absurd")


@dataclass(frozen=True)
class Taken:
    """What :meth:`FusionState.offer_latest` did with one key's payloads.

    changed : the robot's latest map changed.
    index : the payload decoded last (the one taken, or the oldest one tried when every one
        tried was dropped), an index into the payloads given.
    drops : ``(counter, reason, detail)`` of every payload dropped, in the order they were
        looked at: the walk back from the newest, then the older ones refused by their header
        alone, oldest first.
    """

    changed: bool
    index: int
    drops: tuple[tuple[str, str, str], ...] = ()


def _not_robots_own(kind: MessageKind, sender: str, key_robot: str | None) -> tuple[str, str] | None:
    """``(reason, detail)`` when a payload's header says it is not a robot map of the robot
    whose key it came on (:meth:`FusionState.offer` after decoding, :meth:`FusionState.offer_latest`
    from the header alone), else None."""
    if kind != MessageKind.ROBOT_MAP:
        return "not_robot_map", f"a {kind.name} on a robot key"
    if not valid_name(sender):
        return "bad_sender", f"sender {sender[:80]!r} is not a robot id"
    if key_robot is not None and sender != key_robot:
        return "sender_mismatch", f"sender {sender!r} on the key of {key_robot!r}"
    return None


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
    refine : align each robot's map to the robots before it (:func:`mapping.fleet.align_maps`).
    max_refine_m, max_refine_rad : largest accepted ICP correction.
    close_frontiers : apply :func:`mapping.fleet.close_frontiers` to the result.
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
    gen: int = 0  # the robot's liveliness generation when this boot was first accepted
    since_ns: int = 0  # when this boot was first accepted (the fusion's clock, ns; 0: unknown)
    at_ns: int = 0  # when this map was accepted (0: unknown)
    # the payload's body and resolution (mm) as they travelled, when known: a payload with the
    # same body is not read again (FusionState.offer); the facts computed from the wireframe
    body: tuple[bytes, int] | None = None
    facts: MapFacts | None = None


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
    The fused map is a fold of :func:`mapping.merge.merge` over the robots' fleet-frame maps in
    sorted-id order, shaped as a fixed binary tree (:meth:`compute`). Two paths compute it:

    * the **full path** (``full=True``) aligns every robot afresh -- start pose, then ICP onto
      the map of the robots before it (:meth:`_prefix_map`) -- and is a deterministic function
      of the set of latest maps (and the config): the fused map does not depend on the order or
      repetition of arrivals;
    * the **fast path** (default) reuses each robot's cached :class:`Alignment` and re-runs
      ICP only for robots whose map changed substantially (:class:`FusionConfig`), at most
      ``max_realign_per_fuse`` per fuse; its result is the same tree with the cached
      corrections, so it equals the full path's exactly once every alignment is current
      (:attr:`converged`). An alignment is current when it was computed for the robot's present
      map against the present prefix ``(threshold, (robot, rev, correction), ...)`` of the
      robots before it, whose alignments are all current.

    The tree's nodes are cached by the identity of their two inputs (a leaf: ``(robot, rev,
    correction, k)``; a node: the content digest of its map), so a fuse re-merges only the
    nodes above the robots whose map or correction changed, and stops where a node's map came
    out unchanged.
    """

    def __init__(
        self,
        config: FusionConfig | None = None,
        sender: str = FUSION_ID,
        merge_fn: MergeFn | None = None,
        limits: InputLimits | None = None,
        frames: FramesConfig | None = None,
        quarantine: QuarantineConfig | None = None,
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
        self._prepared: dict[
            str, tuple[tuple[Any, ...], Wireframe]
        ] = {}  # robot -> (key, map ready to merge)
        self._lat_saved = 0  # latency_total already handed to a store job
        self.store_report: list[str] = []  # what load found damaged and how it was recovered
        # ordering that cannot be frozen from outside (see _add): a robot's restart is learned
        # from the bus (note_alive), not from the boot number its maps claim
        self.restart_by_token = False
        self.token_gen: dict[str, int] = {}
        # the latest map per robot refused as boot_without_restart, for a token still on its way
        self._held_restart: dict[str, tuple[bytes, MapMessage, int]] = {}
        self.forgotten: dict[str, str] = {}  # robot id -> why it was forgotten (kept in the store)
        self._since: dict[str, int] = {}  # restored since_ns per robot (load)
        self.store_rewrite: set[str] = set()  # views load found damaged (written again by the next save)
        self.exit_error: str | None = None  # the final store write failed (the service's last line)
        # robots of unknown start pose (meta origin_unknown): the registration graph (frames.py)
        self.frames = FleetFrames(frames)
        self._island_cache: dict[str, tuple[tuple[Any, ...], tuple[str, ...], Wireframe]] = {}
        # consistency (quarantine.py; None: off): maps that contradict their robot's history or
        # the fleet are kept aside, never merged; ids that never sent a plausible map are forgotten
        self.quarantine_config = quarantine
        self.quarantine = Quarantine()
        self._fleet_samples: FleetSamples | None = None  # the fused map's, judges every robot (quarantine)
        self._first_seen: dict[str, int] = {}  # robot id -> first map (ns) while none was accepted
        self._born_ns: int | None = None  # the first offer with a clock (see _inconsistent)
        # a work budget per robot (budget.py; None: off): maps of a robot whose fusion CPU
        # budget is spent wait in `held` (the latest only) until release_held
        self.budget: WorkBudget | None = None
        self.held: dict[str, tuple[MapMessage, bytes]] = {}
        self._aligning = 0.0  # CPU seconds of alignments in the running compute (charged apart)
        # a regional fuser's (agents.fleet.fusion.regional): (identity, map) of the robots before
        # its group in the fleet-wide fold, the start of every alignment prefix; None: this
        # state's first robot is the anchor
        self.base: tuple[Any, Wireframe] | None = None
        self._grid = DEFAULT_RESOLUTION  # the fold's grid (wire_snap) in the current compute

    # ------------------------------------------------------------------ input
    def offer(self, data: bytes, key_robot: str | None = None, now_ns: int | None = None) -> bool:
        """Decode and :meth:`add` a payload from ``robots/<key_robot>/map``.

        Returns whether the robot's latest map changed. Dropped and counted (the reason also
        in :attr:`last_drop`): a payload the codec refuses under :class:`InputLimits`
        (``malformed``); a fused map, a sender that is not a valid robot id or does not match
        the key, a robot beyond the ``wire_codec.MAX_ROBOTS``-th, 4,096 (``rejected``); absurd
        content (``absurd``, see
        :func:`implausible`; ``now_ns`` enables the clock check).

        A payload whose body is byte for byte the body of its key's robot's latest accepted
        map, at the same resolution (a map sent again), is decoded without reading the body:
        its wireframe is the latest map's object, with its :class:`~agents.fleet.fusion.facts.MapFacts`
        (values computed from the arrays, kept). Everything else is read and checked as for
        any payload, every check below runs, and each gives the answer it gives on a fresh
        decode (see :mod:`agents.fleet.fusion.facts`); counted in ``stats.same_body``.
        """
        self.stats.received += 1
        self.last_drop = None
        raw = bytes(data)
        if now_ns is not None and self._born_ns is None:
            self._born_ns = now_ns  # the first payload with a clock: when this state began listening
        if now_ns is not None and key_robot is not None and key_robot not in self.robots:
            self._note_unproven(key_robot, now_ns)
        prior = self.robots.get(key_robot) if key_robot is not None else None
        try:
            msg, body, facts = self._decode(raw, prior)
        except ValueError as exc:
            return self._drop("malformed", type(exc).__name__, str(exc))
        refused = _not_robots_own(msg.kind, msg.sender, key_robot)
        if refused is not None:
            return self._drop("rejected", *refused)
        bad = implausible(msg, self.limits, now_ns, facts)
        if bad is None:
            bad = over_budget(msg, self.limits, now_ns, facts)
        if bad is not None:
            return self._drop("absurd", *bad)
        return self._add(msg, raw, now_ns, body, facts)

    def _decode(
        self, raw: bytes, prior: RobotEntry | None
    ) -> tuple[MapMessage, tuple[bytes, int] | None, MapFacts]:
        """:func:`decode_message` under the state's limits, also returning the body's bytes and
        resolution (mm) and the wireframe's facts; a robot map's body equal, byte for byte and
        at the same resolution, to ``prior``'s (the robot's latest accepted map) is not read
        again: its wireframe is ``prior``'s (the body decoder is a function of the body's bytes,
        the resolution, the kind and the limits alone, and the limits are this state's)."""
        same = prior.body if prior is not None else None
        read: dict[str, Any] = {}

        def body_decoder(data: bytes, res_mm: int, n_robots: int | None, limits: Limits) -> Wireframe:
            read["body"] = (data, res_mm)
            if same is not None and n_robots is None and res_mm == same[1] and data == same[0]:
                assert prior is not None
                read["same"] = True
                return prior.message.wireframe
            return decode_body(data, res_mm, n_robots, limits)

        msg = decode_message(raw, self._codec_limits, body_decoder)
        if read.get("same"):
            assert prior is not None
            self.stats.same_body += 1
            return msg, read["body"], facts_of(msg.wireframe, prior.facts)
        return msg, read.get("body"), MapFacts(msg.wireframe)

    def offer_latest(self, payloads: Sequence[bytes], key_robot: str, now_ns: int | None = None) -> Taken:
        """:meth:`offer` for the payloads of one robot key drained together, oldest first:
        only the newest is decoded.

        A robot map is a whole state, and the payloads of one key are one robot's puts in order
        (Zenoh delivers a publisher's puts in order; the key's id is the robot's), so of the
        maps that waited together only the newest matters: decoding the others cost most of the
        fusion loop at 64 robots x 10 Hz (issue 21). Choices:

        * The newest payload goes through :meth:`offer` with every check (codec, kind, sender,
          absurd content, budgets and reach, seq jump, restart, work budget, quarantine): the
          map taken is always fully validated, skipping lets no map in unchecked.
        * When it is dropped for what it is (``malformed``, ``rejected``, ``absurd``), the
          payload before it is offered, and so on: a corrupted or forged last payload does not
          cost the robot the valid map that waited beside it (which the service took before
          this change). At worst every payload is decoded, as before. Any other outcome --
          accepted, duplicate, outdated, held for the work budget, quarantined -- ends the walk.
        * The payloads older than the one that ended the walk are not decoded; their header is
          read (:func:`wire_codec.peek`: envelope and CRC). One whose header fails is counted
          ``malformed`` (by error class), one whose header names a fused map or another
          sender ``rejected`` (``not_robot_map``, ``bad_sender``, ``sender_mismatch``), as
          decoding it would have; the others ``superseded``. So ``dropped`` still counts the
          payloads broken as a whole or spoofed; a skipped payload with a sound header and a
          bad body goes unseen (a newer map of its robot was taken instead). ``received``
          counts every payload.
        * Latency stays honest: when the map taken changes the robot's map, its latency starts
          at the oldest publish stamp among it and the superseded payloads (each counted at
          most ``MAX_TRANSPORT_NS`` old, as in :meth:`_add`), since the fused map that takes
          the newest map is also the answer to the ones that waited beside it. Headers that
          failed give no stamp. A map held for the work budget or quarantined gives no
          latency sample now, as before (those were skipped before too: ``held`` keeps the
          latest only).
        * Rate limits and queue bounds (:class:`~agents.fleet.fusion.intake.Intake`) act per
          payload before this, unchanged. The consistency checks (:meth:`_inconsistent`) and
          the seq-jump check compare the map taken with the robot's last *accepted* map and
          the time since it was accepted, never with a skipped map: skipping only widens the
          step they judge, so a robot cannot walk its walls away through skipped maps. A
          robot's work budget is charged for the checks that ran.
        * Across a restart (two boots on one key in one batch) the newest in arrival order is
          taken even when an older payload of the batch had the other boot.

        Returns a :class:`Taken`; :attr:`last_drop` is left as the last payload looked at set it.
        """
        if not payloads:
            raise ValueError("offer_latest needs at least one payload")
        drops: list[tuple[str, str, str]] = []
        i = len(payloads) - 1
        changed = False
        while i >= 0:
            changed = self.offer(payloads[i], key_robot, now_ns)
            if self.last_drop is not None:
                drops.append(self.last_drop)
            if self.last_drop is None or self.last_drop[0] not in PAYLOAD_DROPS or i == 0:
                break
            i -= 1
        stamps: list[int] = []
        for raw in payloads[:i]:
            self.stats.received += 1
            self.last_drop = None
            try:
                head = peek_header(raw, self._codec_limits)
            except ValueError as exc:
                self._drop("malformed", type(exc).__name__, str(exc))
                drops.append(("malformed", type(exc).__name__, str(exc)))
                continue
            refused = _not_robots_own(head.kind, head.sender, key_robot)
            if refused is not None:
                self._drop("rejected", *refused)
                drops.append(("rejected", *refused))
            else:
                self.stats.superseded += 1
                stamps.append(head.stamp_ns)
        if changed and stamps and key_robot in self._pending:
            oldest = min(stamps)
            if now_ns is not None:
                oldest = max(oldest, now_ns - MAX_TRANSPORT_NS)
            self._pending[key_robot] = min(self._pending[key_robot], oldest)
        return Taken(changed, max(i, 0), tuple(drops))

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

    def note_alive(self, rid: str, now_ns: int | None = None) -> None:
        """The robot's liveliness token appeared (a new session of it): its next map may come
        from a new boot (see :meth:`_add`).

        A restarted robot's first map can arrive before its token does (they travel apart). Such
        a map was refused as ``boot_without_restart`` and held; if the token now appears within
        :data:`RESTART_HOLD_S` of that map, the map is taken after all (and leaves the
        ``rejected`` count), so an honest restart loses nothing while a map claiming a restart
        that never shows on the bus stays refused."""
        self.token_gen[rid] = self.token_gen.get(rid, 0) + 1
        held = self._held_restart.pop(rid, None)
        if held is None:
            return
        raw, msg, at_ns = held
        now = time.time_ns() if now_ns is None else now_ns
        if now - at_ns > RESTART_HOLD_S * 1e9:
            return
        accepted = self.stats.accepted
        self._add(msg, raw, now)
        if self.stats.accepted > accepted:
            self.stats.rejected -= 1
            by = self.stats.rejected_by
            by["boot_without_restart"] -= 1
            if by["boot_without_restart"] <= 0:
                del by["boot_without_restart"]

    def forget(self, rid: str, why: str) -> bool:
        """Remove every trace of a robot (its map, alignment, caches, quarantined map); the store
        records ``why`` (:attr:`forgotten`). Returns whether it had a map."""
        had = self.robots.pop(rid, None) is not None
        for cache in (self.alignments, self.corrections, self._in_fleet, self._prepared, self._pending,
                      self.quarantine.maps, self._first_seen, self.token_gen, self.held, self._held_restart):  # fmt: skip  # noqa: E501
            cache.pop(rid, None)
        if self.budget is not None:
            self.budget.forget(rid)
        self.forgotten[rid] = why[:200]
        return had

    # ------------------------------------------------------------------ consistency (quarantine.py)
    def _note_unproven(self, rid: str, now_ns: int) -> None:
        """Remember when a robot id without an accepted map first sent one (bounded)."""
        if rid not in self._first_seen:
            if len(self._first_seen) >= 4 * MAX_ROBOTS:
                del self._first_seen[min(self._first_seen, key=self._first_seen.__getitem__)]
            self._first_seen[rid] = now_ns

    def _charge(self, rid: str, seconds: float) -> None:
        if self.budget is not None:
            self.budget.charge(rid, seconds, time.monotonic())

    def release_held(self, now_ns: int) -> list[str]:
        """Take the held maps of robots whose work budget has refilled (:meth:`_add` again,
        every check included). Returns the robots whose latest map changed."""
        changed: list[str] = []
        if self.budget is None:
            return changed
        now = time.monotonic()
        for rid in [r for r in self.held if self.budget.allowed(r, now)]:
            msg, raw = self.held.pop(rid)
            if self._add(msg, raw, now_ns):
                changed.append(rid)
        return changed

    def forget_implausible(self, now_ns: int) -> list[str]:
        """Forget the robot ids none of whose maps was accepted (each refused or quarantined)
        for ``forget_after_s`` since their first. Returns them."""
        cfg = self.quarantine_config
        if cfg is None:
            return []
        due = [
            r
            for r, t in self._first_seen.items()
            if r not in self.robots and now_ns - t >= cfg.forget_after_s * 1e9
        ]
        for rid in due:
            self.forget(rid, f"never plausible: no map accepted in {cfg.forget_after_s:.0f} s")
        return due

    def _inconsistent(
        self, msg: MapMessage, old: RobotEntry | None, now_ns: int | None, facts: MapFacts | None = None
    ) -> tuple[str, str] | None:
        """Why ``msg`` contradicts its robot's last accepted map of the same boot or the other
        robots' walls (:mod:`agents.fleet.fusion.quarantine`), else None. ``facts``: the
        wireframe's (:mod:`agents.fleet.fusion.facts`; the samples are kept there)."""
        cfg = self.quarantine_config
        if cfg is None or now_ns is None:
            return None
        wf = msg.wireframe
        lim = self.limits
        if (
            old is not None and old.at_ns and _origin_of(old.message) == _origin_of(msg)
        ):  # same boot and start
            seconds = (now_ns - old.at_ns) / 1e9
            owf = old.message.wireframe
            bad = history_judge(wf, owf, seconds, lim.max_speed_mps, lim.sensor_range_m, cfg,
                                key_set(owf, old.facts), facts, old.facts)
            if bad is not None:
                return bad
        elif (
            old is None
            and wf.n_vertices
            and self._first_seen.get(msg.sender, now_ns) - (self._born_ns or now_ns) > LATE_GRACE_NS
        ):
            # a robot's first map: no further from its start than it could have gone since the
            # fusion first heard of it (its claimed boot may be as old as it likes), except
            # within the fleet's known extent (a robot joining a mapped building late). Not for
            # robots already sending when this state began (a restart without store, a takeover
            # in a fusion tree): those are held to their claimed boot (over_budget's reach).
            heard = (now_ns - self._first_seen.get(msg.sender, now_ns)) / 1e9
            reach = lim.sensor_range_m + lim.max_speed_mps * heard + cfg.growth_slack_m
            out = np.hypot(wf.points[:, 0], wf.points[:, 1]) > reach
            if np.any(out) and self.fused.n_vertices:
                lo = self.fused.points.min(axis=0) - lim.sensor_range_m
                hi = self.fused.points.max(axis=0) + lim.sensor_range_m
                fleet = msg.origin.apply(wf.points[out])
                out[out] = ~np.all((fleet >= lo) & (fleet <= hi), axis=1)
            if np.any(out):
                far = float(np.hypot(wf.points[out, 0], wf.points[out, 1]).max())
                return "extent_jump", (f"a first map reaching {far:.0f} m from the start and out of the "
                                       f"fleet's extent, heard of {heard:.0f} s ago")  # fmt: skip
        if origin_unknown(msg) or self.fused.n_edges == 0:
            return None
        rid = msg.sender
        bit = self.fused_robots.index(rid) if rid in self.fused_robots else None
        samples = self._fleet_samples
        if samples is None or samples.fused is not self.fused or samples.cfg != cfg:
            samples = self._fleet_samples = FleetSamples.of(self.fused, cfg)
        moved = facts_of(wf, facts).moved(msg.origin)
        return samples.judge(moved.wf, bit, moved)

    def _add(
        self, msg: MapMessage, raw: bytes, now_ns: int | None = None, body: tuple[bytes, int] | None = None,
        facts: MapFacts | None = None,
    ) -> bool:
        rid = msg.sender
        key = order_key(msg, raw)
        given = msg
        if self.frames.active or origin_unknown(msg):
            msg = self._place(msg, raw)
        old = self.robots.get(rid)
        gen = self.token_gen.get(rid, 0)
        since = now_ns or 0
        if old is not None:
            if key == old.key:
                self.stats.duplicates += 1
                return False
            restarted = key[0] != old.key[0]
            if restarted and self.restart_by_token:
                # a different boot supersedes the robot's maps only after its liveliness token
                # came back (a restart seen on the bus), whichever boot is larger: a map with a
                # boot from the future cannot freeze the robot, nor one from the past
                if gen <= old.gen:
                    if key[0] < old.key[0]:
                        self.stats.outdated += 1
                        return False
                    self._held_restart[rid] = (raw, given, now_ns if now_ns is not None else time.time_ns())
                    return self._drop("rejected", "boot_without_restart",
                                      f"{rid!r} claims boot {key[0]} but its session did not restart")
            elif key < old.key:
                self.stats.outdated += 1
                return False
            else:
                since = old.since_ns
                if now_ns is not None and old.at_ns and not restarted:
                    # a robot numbers its maps one by one: a seq far ahead of what it could
                    # have sent since (rate limit x time) is a forged or corrupted map
                    dt = max(0.0, (now_ns - old.at_ns) / 1e9)
                    allowed = old.key[1] + self.limits.burst + self.limits.rate_hz * dt
                    if key[1] > allowed:
                        return self._drop("absurd", "seq_jump",
                                          f"seq {key[1]} after {old.key[1]} {dt:.1f} s ago")
        elif len(self.robots) >= MAX_ROBOTS:
            return self._drop("rejected", "too_many_robots", f"{rid!r} would be robot {MAX_ROBOTS + 1}")
        if self.budget is not None and now_ns is not None and not self.budget.allowed(rid, time.monotonic()):
            self.held[rid] = (msg, raw)  # its fusion budget is spent: fused later (release_held)
            self.stats.held += 1
            return False
        self.held.pop(rid, None)
        t0 = time.thread_time()
        facts = facts_of(msg.wireframe, facts)
        bad = self._inconsistent(msg, old, now_ns, facts)
        self._charge(rid, time.thread_time() - t0)
        if bad is not None:
            self.quarantine.put(rid, raw, *bad, now_ns or 0)
            return self._drop("quarantined", *bad)
        self.quarantine.maps.pop(rid, None)
        self._first_seen.pop(rid, None)
        self.forgotten.pop(rid, None)
        same = old is not None and _same_content(old.message, msg)
        if same:
            assert old is not None
            rev = old.rev
        else:
            self._rev += 1
            rev = self._rev
        self.robots[rid] = RobotEntry(msg, raw, key, rev, gen, since, now_ns or 0, body, facts)
        self.stats.accepted += 1
        if not same:
            # a stamp over MAX_TRANSPORT_S old counts as that old: a forged stamp from the past
            # cannot fill the latency summary with centuries
            stamp = int(msg.stamp_ns) if now_ns is None else max(int(msg.stamp_ns), now_ns - MAX_TRANSPORT_NS)
            self._pending.setdefault(rid, stamp)
        return not same

    # ------------------------------------------------------------------ unknown start poses
    def _place(self, msg: MapMessage, raw: bytes) -> MapMessage:
        """A map of a robot of unknown origin gets its registered pose in the fleet frame as
        ``origin`` (the identity while it is an island: it is not fused then); a robot that
        now sends a known origin leaves the registration graph."""
        rid = msg.sender
        old = self.robots.get(rid)
        if old is not None and order_key(msg, raw) <= old.key:
            return msg  # a duplicate or an outdated map: _add drops it
        fr = self.frames
        if origin_unknown(msg):
            fr.track(rid)
            pose = fr.fleet_pose(rid) or Pose.identity()
            msg = replace(msg, origin=pose)
        else:
            fr.forget(rid)
        fr.has_known = any(r not in fr.root for r in (*self.robots, rid))
        return msg

    def _replace_origins(self) -> list[str]:
        """After a change of the registration graph: every unknown robot's entry gets its new
        fleet pose as ``origin`` (and a new revision when it changed). Returns the robots moved."""
        moved = []
        for rid in sorted(self.frames.root):
            e = self.robots.get(rid)
            if e is None:
                continue
            pose = self.frames.fleet_pose(rid) or Pose.identity()
            if pose.as_tuple() != e.message.origin.as_tuple():
                self._rev += 1
                self.robots[rid] = RobotEntry(replace(e.message, origin=pose), e.raw, e.key, self._rev,
                                              body=e.body, facts=e.facts)
                self._pending.setdefault(rid, int(e.message.stamp_ns))
                moved.append(rid)
        return moved

    def fleet_ids(self) -> tuple[str, ...]:
        """The robots fused into the fleet map, sorted: all of them, but for robots of unknown
        origin that are not (yet) registered into the fleet frame (islands)."""
        if not self.frames.active:
            return tuple(sorted(self.robots))
        return tuple(r for r in sorted(self.robots) if self.frames.in_fleet(r))

    def _own_length(self, rid: str) -> float:
        wf = self.robots[rid].message.wireframe
        return float(wf.edge_lengths().sum()) if wf.n_edges else 0.0

    def _component_length(self, members: tuple[str, ...], root: str | None) -> float:
        if root is None or root == self.frames.fleet_component():
            return sum(self._own_length(r) for r in self.fleet_ids())
        return sum(self._own_length(r) for r in members if r in self.robots)

    def _component_map(self, members: tuple[str, ...], root: str | None) -> Wireframe:
        """A component's map in its root's frame; the fleet's is the fused map (in the fleet
        frame), recomputed when the fused robots are not the fleet's present members."""
        if root is None or root == self.frames.fleet_component():
            ids = self.fleet_ids()
            if ids == self.fused_robots:
                return self.fused
            thr = self.threshold
            return fold_maps((self.robot_in_fleet(r) for r in ids), lambda a, b: self._merge(a, b, thr))
        return self.island_map(root, members)

    def island_map(self, root: str, members: tuple[str, ...] | None = None) -> Wireframe:
        """An island's map in its root's frame: its members' maps moved by their poses in that
        frame, merged in sorted order (cached until a member's map or pose changes)."""
        fr = self.frames
        ms = tuple(members) if members is not None else fr.components().get(root, ())
        ms = tuple(m for m in ms if m in self.robots)
        thr = self.threshold
        key = (thr, *((m, self.robots[m].rev, fr.pose[m].as_tuple()) for m in ms))
        hit = self._island_cache.get(root)
        if hit is not None and hit[0] == key:
            return hit[2]
        wf = fold_maps(
            (self.robots[m].message.wireframe.transformed(fr.pose[m]) for m in ms),
            lambda a, b: self._merge(a, b, thr)
        )
        if self.config.close_frontiers and len(ms) > 1:
            wf = close_frontiers(wf, thr)
        self._island_cache[root] = (key, ms, wf)
        return wf

    def island_key(self, root: str) -> Any:
        """What an island's cached map was made from (changes exactly when it changes)."""
        hit = self._island_cache.get(root)
        return None if hit is None else hit[0]

    def islands(self) -> dict[str, tuple[tuple[str, ...], Wireframe]]:
        """Root -> (members, map in the root's frame) of every island (robots of unknown origin
        not registered into the fleet frame)."""
        out = {}
        for root, ms in self.frames.islands().items():
            ms = tuple(m for m in ms if m in self.robots)
            if ms:
                out[root] = (ms, self.island_map(root, ms))
        for gone in [r for r in self._island_cache if r not in out]:
            del self._island_cache[gone]
        return out

    def register_step(self, t: float | None = None, now: float | None = None) -> RegistrationRecord | None:
        """One registration attempt of the registration graph (:mod:`.frames`), the pair it
        finds due (``t``: the robots' clock, for the second look at a pending join; ``now``: the
        service's clock for the retry of maps that stopped growing); on acceptance the moved
        robots get their fleet poses (the next :meth:`fuse` includes them).
        None when no pair is due (and always for known-start fleets)."""
        if not self.frames.active:
            return None
        pair = self.frames.next_pair(self._component_length, now, t)
        if pair is None:
            return None
        rec = self.frames.attempt(pair, self._component_map, t, now)
        if rec.accepted:
            self._replace_origins()
        return rec

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
        key = (e.rev, corr, k, self._grid)
        hit = self._prepared.get(rid)
        if hit is not None and hit[0] == key:
            return hit[1]
        m = e.message
        src = m.wireframe
        pose = m.origin if corr is None else corr.compose(m.origin)
        # one Wireframe for origin, correction and contributor bit together (moved_to: only
        # the moved points are checked)
        masks = mask_array(src.n_edges, 1 << k)  # uint64 up to bit 63, Python ints past it
        wf = wire_snap(src.moved_to(pose.apply(src.points), sources=masks), self._grid)
        self._prepared[rid] = (key, wf)
        return wf

    def _align(self, source: Wireframe, reference: Wireframe) -> Pose | None:
        """The ICP correction of a robot's fleet-frame map onto the map of the robots before it
        (:func:`mapping.fleet.align_maps` within ``max_refine_m`` / ``max_refine_rad``)."""
        return align_maps(source, reference, self.config.max_refine_m, self.config.max_refine_rad)

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
        self.merges += bool(base.n_vertices and new.n_vertices)
        return merge_on_grid(self.merge_fn, base, new, thr, self._grid)

    def _node(
        self, lo: int, hi: int, leaves: list[tuple[Any, Wireframe]], thr: float
    ) -> tuple[Wireframe, Any]:
        """The fold of ``leaves[lo:hi]`` (see :meth:`compute`) and its identity: a leaf's item,
        or a digest of the node's map. Cached per ``(lo, hi)`` under ``(thr, identity of the
        left part, identity of the right part)``, so a change that leaves a partial result
        as it was (a wall another robot already reported) stops there."""
        if hi - lo == 1:
            return leaves[lo][1], leaves[lo][0]
        mid = fold_split(lo, hi)
        left, kl = self._node(lo, mid, leaves, thr)
        right, kr = self._node(mid, hi, leaves, thr)
        key = (thr, kl, kr)
        hit = self._nodes.get((lo, hi))
        if hit is not None and hit[0] == key:
            return hit[1], hit[2]
        out = self._merge(left, right, thr)
        ident = out.content_digest()
        self._nodes[(lo, hi)] = (key, out, ident)
        return out, ident

    def _prefix_map(self, k: int, leaves: list[tuple[Any, Wireframe]], thr: float) -> Wireframe:
        """The map of the robots before fold position ``k`` (what robot ``k`` is aligned onto):
        the tree's nodes that cover ``[0, k)``, merged left to right. For ``k <= 2`` and for
        fleets of up to three robots that is exactly the left fold of their maps."""
        parts = [self._node(lo, hi, leaves, thr) for lo, hi in prefix_spans(k, len(leaves))]
        if self.base is not None:
            parts.insert(0, (self.base[1], self.base[0]))
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
        :attr:`converged`; the cached tree nodes change the cost, never the result.

        The fold: the robots' maps (fleet frame, correction applied, contributor bit set) in
        sorted-id order are the leaves of a fixed binary tree; a node over ``[lo, hi)`` is
        ``merge(node(lo, mid), node(mid, hi))`` with ``mid - lo`` the largest power of two
        below ``hi - lo`` (so up to three robots it is the left fold ``((r1, r2), r3)``; with
        16 a balanced tree). A changed robot costs the merges on its path to the root (4 of
        15 with 16 robots, against 8 on average for a left fold), and the nodes are cached.
        """
        cfg = self.config
        ids = self.fleet_ids()
        thr = self.threshold
        self._grid = self.resolution
        budget = len(ids) if full else (cfg.max_realign_per_fuse if max_realign is None else max_realign)
        prefix: tuple[Any, ...] = (thr,) if self.base is None else (thr, self.base[0])
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
            if (k == 0 and self.base is None) or not cfg.refine:
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
                    t_align = time.thread_time()
                    corr_new = self._align(wf0, ref) if ref.n_edges and wf0.n_edges else None
                    self._charge(rid, time.thread_time() - t_align)
                    self._aligning += time.thread_time() - t_align
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
            if e is None or (k == 0 and self.base is None):
                continue
            reference = self._references[k]
            if reference[0] != thr:
                continue  # the threshold changed since that fold: the next fuse decides
            acc = self._prefix_map(k, self._leaves, thr)
            wf0 = self._fleet_map(rid)
            t_align = time.thread_time()
            corr = self._align(wf0, acc) if acc.n_edges and wf0.n_edges else None
            self._charge(rid, time.thread_time() - t_align)
            n = e.message.wireframe.n_vertices
            self.alignments[rid] = Alignment(corr, e.rev, n, _origin_of(e.message), now, reference)
            self.stats.alignments += 1
            done.append(rid)
        return done

    def fuse(self, full: bool = False, now: float | None = None, max_realign: int | None = None) -> bool:
        """Recompute the fused map (:meth:`compute`); bump ``version`` and return True when it
        changed."""
        who = [r for r in self._pending if r in self.robots]  # the robots whose new maps this fuse takes
        t0 = time.thread_time()
        self._aligning = 0.0
        wf, ids, corr = self.compute(full, now, max_realign)
        if who:  # the fuse's cost besides alignments (charged to their robots), shared
            share = max(0.0, time.thread_time() - t0 - self._aligning) / len(who)
            for rid in who:
                self._charge(rid, share)
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

    def pending_stamps(self) -> list[int]:
        """The publish stamps (ns) of the robot maps fused since the last publish."""
        return list(self._pending.values())

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
        if self.frames.active:  # robots of unknown origin: who is registered, the islands
            m["frames"] = self.frames.summary()
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

    def _robot_times(self) -> list[float]:
        return [
            float(e.message.meta.get("t", 0.0))
            for e in self.robots.values()
            if isinstance(e.message.meta, dict)
        ]

    def sim_time(self) -> float:
        """The latest simulated time any robot map carries (``meta["t"]``), 0 if none."""
        return max(self._robot_times(), default=0.0)

    def registration_clock(self) -> float:
        """The robots' clock a pending join waits on (:mod:`.frames`): the lower median of the
        times their maps carry, 0 if none. Not the latest: one robot (a stolen one's far-future
        ``t``, which validation allows up to ``MAX_SIM_T``) must not end every wait at once,
        and with it the second look that keeps a copy from merging."""
        ts = sorted(self._robot_times())
        return ts[(len(ts) - 1) // 2] if ts else 0.0

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
                r: (None if (c := self.corrections.get(r)) is None else [c.x, c.y, c.theta])
                for r in self.fused_robots
            },
            state={
                "version": self.version,
                "robots": {
                    r: {"seq": e.key[1], "boot": e.key[0], "sha256": e.key[2]}
                    for r, e in sorted(self.robots.items())
                },
                "fused": {"vertices": self.fused.n_vertices, "edges": self.fused.n_edges},
                "converged": self.converged,
                "stats": self.stats.as_dict(fresh_latency),
                "latency_total": lat.total,
                "latency_log": LATENCY_LOG,
                # every registration attempt kept (FramesConfig.history), for report.json
                **({"registrations": [r.as_dict() for r in self.frames.records]}
                   if self.frames.active else {}),
            },
            latencies=[
                (first + i, v, t) for i, (v, t) in enumerate(zip(*(a.tolist() for a in lat.tail(new))))
            ],
            extra=self.extra_doc(),
            forgotten=set(self.forgotten),
        )
        self._lat_saved = lat.total
        return job

    def extra_doc(self) -> dict[str, Any]:
        """What the snapshot keeps besides the maps: robots forgotten and why, when each robot's
        boot was first accepted."""
        return {
            "forgotten": dict(sorted(self.forgotten.items())),
            "since_ns": {r: e.since_ns for r, e in sorted(self.robots.items())},
        }

    def restore_extra(self, extra: dict[str, Any]) -> None:
        """Inverse of :meth:`extra_doc` (values that are not what it writes are ignored)."""
        f = extra.get("forgotten")
        if isinstance(f, dict):
            self.forgotten = {k: str(v)[:200] for k, v in f.items() if valid_name(k)}
        since = extra.get("since_ns")
        self._since = (
            {
                k: v
                for k, v in since.items()
                if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 1 << 63
            }
            if isinstance(since, dict)
            else {}
        )

    def save(
        self, store: str | os.PathLike[str], robots: Iterable[str] | None = None, stamp_ns: int = 0
    ) -> None:
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
        reset: bool = False,
        now_ns: int | None = None,
    ) -> FusionState:
        """Resume from :meth:`save`'s files (an absent or empty store gives a fresh state).

        The files are checked and recovered from each other (:func:`read_store`; what was
        damaged is in :attr:`store_report`, and the views to write again in
        :attr:`store_rewrite`). A store that cannot be recovered raises
        :class:`~agents.fleet.fusion.store.StoreDamaged`, unless ``reset``: then its files are
        moved aside (``damaged-<ns>/``, nothing is deleted) and the state starts empty at a
        version from the wall clock (milliseconds), above any version a fusion service could
        have published, so that versions never go backwards for a subscriber.
        Stored maps pass the checks of the bus at ``now_ns`` (default: now): a map from the
        future is dropped and reported.

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

        try:
            contents = read_store(d, warn=warn)
        except StoreDamaged as exc:
            if not reset:
                raise
            aside = d / f"damaged-{time.time_ns()}"
            aside.mkdir()
            for f in list(d.iterdir()):
                if f != aside and not f.name.startswith("damaged-"):
                    os.replace(f, aside / f.name)
            warn(f"{exc}; --reset: its files are in {aside}, starting empty")
            st.version = time.time_ns() // 1_000_000
            st.store_report = [f"reset: damaged files moved to {aside}"]
            return st
        st.store_report = list(contents.damaged)
        st.store_rewrite = set(contents.rewrite)
        st.restore_extra(contents.extra)
        now = time.time_ns() if now_ns is None else now_ns
        for rid, raw in contents.raw_robots.items():
            if rid in st.forgotten:
                continue
            if not st.offer(raw, rid, now) and st.last_drop is not None:
                line = f"stored map of {rid} refused: {st.last_drop[1]}: {st.last_drop[2]}"
                st.store_report.append(line)
                warn(line)
            elif rid in st.robots:
                e = st.robots[rid]
                st.robots[rid] = dataclasses.replace(e, since_ns=st._since.get(rid, e.since_ns), at_ns=0)
        st.stats = FusionStats()
        total = 0
        try:
            state = json.loads((d / "state.json").read_text())
            total = int(state.get("latency_total", 0) or 0)
        except (OSError, ValueError, TypeError, AttributeError, OverflowError):
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
                    st.alignments[rid] = Alignment(corr, e.rev, e.message.wireframe.n_vertices,
                                                   _origin_of(e.message))
                st.fuse(max_realign=0)
            else:
                st.fuse(full=True)
        st._pending.clear()
        same = False
        if contents.fused is not None and st.robots:
            # compare as stored: through the codec
            again = decode_message(encode_message(st.fused_message(0))).wireframe
            same = again.almost_equal(contents.fused.wireframe, tol=1e-9, likelihood_tol=1e-9)
        empty_before = contents.fused is None or contents.fused.wireframe.n_edges == 0
        st.version = contents.version if (same or (not st.robots and empty_before)) else contents.version + 1
        return st


def _origin_of(msg: MapMessage) -> tuple[float, float, float, int]:
    boot = msg.meta.get("boot", 0) if isinstance(msg.meta, dict) else 0
    return (msg.origin.x, msg.origin.y, msg.origin.theta, boot if isinstance(boot, int) else 0)


def _same_content(a: MapMessage, b: MapMessage) -> bool:
    """Exactly the same map for fusion: start pose, resolution and wireframe arrays (the codec
    decodes the same content to the same arrays)."""
    return (
        a.origin.as_tuple() == b.origin.as_tuple()
        and float(a.resolution) == float(b.resolution)
        and a.wireframe.content_digest() == b.wireframe.content_digest()
    )


def _same_wireframe(a: Wireframe, b: Wireframe) -> bool:
    """Identical arrays, or the same graph up to vertex and edge order (1e-9)."""
    if a is b or a.content_digest() == b.content_digest():
        return True
    if a.n_vertices != b.n_vertices or a.n_edges != b.n_edges:
        return False
    return a.almost_equal(b, tol=1e-9)
