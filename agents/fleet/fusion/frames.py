"""The registration graph: which robots of unknown start pose are in the fleet frame.

A robot that does not know where it started relative to the others says so in its map
message: ``meta["origin_unknown"] = True`` (:data:`ORIGIN_UNKNOWN`), with ``origin`` the
identity (its map is in its own odometry frame). Such a robot enters the fused map only once
global registration (:mod:`mapping.registration`) has placed it, and registration only runs
for such robots: a fleet of known start poses never registers anything and fuses exactly as
before.

Components
----------
Robots of unknown origin are grouped in *components*: sets of robots registered to each
other, each with its pose in the frame of the component's *root* (a member robot's odometry
frame). Every robot starts as a component of its own. One component is the *fleet*: its root
frame is the fleet frame and its members are fused into ``fused/map``; the others are
*islands*, each published on its own (``fused/islands/<root>``).

* With robots of known start pose, those robots are the fleet (the fleet frame is theirs);
  each component of unknown robots registers against their fused map.
* Otherwise, with an anchor (``wiremap fuse --anchor ID``) the fleet is the anchor's
  component, in the anchor's frame; without one the fleet is the component that formed by
  the first accepted registration, in the frame of its root. Until then the fused map is the
  lowest-id robot on its own (a provisional fleet of one).

Registration attempts (:meth:`FleetFrames.next_pair`): every pair of components, when it was
never tried for the present memberships, or when the wall length of either side grew by
``max(retry_growth_m, retry_growth_fraction * length)`` since the pair's last attempt (maps
grow by a scan at a time: re-registering on every update would cost ~0.1 s per map), or --
given the caller's clock -- when either side changed by ``retry_min_m`` and ``retry_after_s``
passed since that attempt: a map that stops growing short of the growth rule (a robot done, a
replayed stretch at its end) still gets its last word, at most every ``retry_after_s``. Pairs
with the fleet first, then larger maps first. The caller runs at most one attempt at a time
(the service: after a publish, when no map waits).

Joins: a registration the pair's two maps accept is checked against the rest of the fleet
first: when its overlap lands, at two distinct places, in any other component's map (a third
robot has seen the structure repeated), the building repeats it and the pair is refused
(:attr:`FramesConfig.recurrence`). Then it is only *pending*: the pair is tried again once the
robots' clock has run ``confirm_after_s`` on and both maps hold ``confirm_growth`` times the
wall matched (or ``confirm_max_s`` ran on), first of all pairs, and joined unless the
overlap now recurs in a map the fleet holds (the pair's own as they grew included). A join
makes the component holding the fleet (or anchor, or else the lower root id) keep its root,
and composes the other's poses with the registration's transform. Joins are never undone:
registration is tuned to refuse rather than guess (no false merge in its benchmark), and the
fleet waits for the evidence of every robot before it joins, so the graph only grows.

Everything here is pure (no zenoh, no clock of its own); :class:`FusionState` owns one
:class:`FleetFrames`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from mapping.registration import (
    MapFeatures,
    Registration,
    RegistrationConfig,
    conflict_of,
    prepare,
    recurrence_elsewhere,
    register_prepared,
)
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.message import MapMessage

ORIGIN_UNKNOWN = "origin_unknown"
FLEET = "fleet"  # the fleet component's name in records when it is the known-start robots


def origin_unknown(msg: MapMessage) -> bool:
    """Whether a robot map says its ``origin`` is not known (``meta["origin_unknown"] is True``)."""
    return isinstance(msg.meta, dict) and msg.meta.get(ORIGIN_UNKNOWN) is True


@dataclass(frozen=True)
class FramesConfig:
    """Settings of the registration graph.

    anchor : robot whose frame is the fleet frame (None: the first registration decides).
    retry_growth_m, retry_growth_fraction : a pair is tried again when a side's wall length
        grew by ``max(retry_growth_m, retry_growth_fraction * length_at_last_attempt)``.
    retry_after_s, retry_min_m : and, on the caller's clock (``now``), when a side's wall length
        moved by ``retry_min_m`` and ``retry_after_s`` passed since the last attempt (0: off).
        The CARMEN fleets of three robots left near-correct pairs refused on maps 10-50 m short
        of the growth rule, which the robots' final maps pass (docs/experiments.md, "The last
        word of a map that stopped growing").
    min_length_m : a component with less wall than this is not tried (registration needs
        8 m of matched wall anyway).
    confirm_after_s : a first acceptance only makes the join *pending*; once the robots' clock
        (the maps' time ``t`` given to :meth:`FleetFrames.attempt`) has run this long, the pair
        is looked at again, first of all pairs: the overlap matched at the first look is looked
        for in every map the fleet then holds, the pair's own as they grew included, and the
        pair is joined at the first look's transform unless it recurs (0, or no ``t``: join at
        the first acceptance). The second look does not register the grown maps again (a
        drifting map's growth puts a right transform's walls on seen-free space; the wait is
        for repetition). The wait runs on the robots' clock, which is what they saw meanwhile
        (a replayed log runs many times faster than the wall clock), and on the service's
        (``now``) only where the robots' clock stands still (a log's coarse stamps, robots
        done): there ``retry_after_s`` once no map changes. A late merge costs little, a wrong
        one the fleet map (``docs/experiments.md``, "Session 20").
    confirm_growth, confirm_max_s : the second look also waits (on the robots' clock) until
        each of the two maps holds ``confirm_growth`` times the wall the first look matched, or
        ``confirm_max_s`` at most: a match that covers most of a map (two robots that have each
        seen one office) can only be told from a copy once the maps reach past it, where a
        repeat shows (``docs/experiments.md``, "Session 21").
    confirm_conflict_fraction : when the first look matched at least this share of the smaller
        map (nothing in it outside the match could show a copy), the second look also scores
        the first look's transform on the pair's maps as they grew: more wall on seen-free space
        than acceptance allows (:func:`mapping.registration.conflict_of`) refuses it. One office
        row apart (a whole-map match), the grown maps carried 4.5 m of such wall against a
        limit of 4.2 m, right pairs 0 m; on the real logs the first looks match 10-70 % of the
        smaller map, and a drifting map's growth puts right transforms' walls on seen-free
        space (orebro: all three right joins refused when every second look checked it).
    recurrence : before a join, the overlap is looked for in every other component's map
        (:func:`mapping.registration.recurrence_elsewhere`); when it lands well in one of
        them at two distinct places, the building repeats it and the pair is refused, as when
        one of the two robots had itself seen it twice (the same limits: ``max_self_ratio``,
        or ``contested_self_ratio`` past ``contested_runner_up_ratio``).
    registration : :class:`mapping.registration.RegistrationConfig`.
    history : registration records kept (:attr:`FleetFrames.records`).
    """

    anchor: str | None = None
    retry_growth_m: float = 6.0
    retry_growth_fraction: float = 0.2
    retry_after_s: float = 5.0
    retry_min_m: float = 1.0
    min_length_m: float = 10.0
    confirm_after_s: float = 10.0
    confirm_growth: float = 2.0
    confirm_max_s: float = 60.0
    confirm_conflict_fraction: float = 0.8
    recurrence: bool = True
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    history: int = 200


@dataclass(frozen=True)
class Pending:
    """A first acceptance awaiting its second look: the registration and the two maps' features
    it was made on, the robots' clock and the service's (None without one) then, every
    component's wall length then (members -> metres, as :meth:`FleetFrames.next_pair` measured),
    and the roots of the two components it registered."""

    res: Registration
    fa: MapFeatures
    fb: MapFeatures
    t: float
    now: float | None
    lengths: dict[tuple[str, ...], float]
    pair: tuple[str, str]  # the two components' roots (frames) it registered


@dataclass(frozen=True)
class RegistrationRecord:
    """One registration attempt between two components (``b`` onto ``a``)."""

    t: float
    a: str
    b: str
    a_members: tuple[str, ...]
    b_members: tuple[str, ...]
    accepted: bool
    confidence: float
    support: float
    support_fraction: float
    reason: str
    transform: tuple[float, float, float] | None
    ms: float
    pending: bool = False  # accepted once, waiting for its confirming second look

    def as_dict(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 3),
            "a": self.a,
            "b": self.b,
            "a_members": list(self.a_members),
            "b_members": list(self.b_members),
            "accepted": self.accepted,
            "confidence": round(self.confidence, 4),
            "support_m": round(self.support, 2),
            "support_fraction": round(self.support_fraction, 4),
            "reason": self.reason,
            "transform": None if self.transform is None else [round(v, 6) for v in self.transform],
            "ms": round(self.ms, 1),
            "pending": self.pending,
        }

    def line(self) -> str:
        """One line for logs and ``wiremap watch``."""
        what = ("accepted" if self.accepted else "pending (joined on a second look)" if self.pending
                else f"refused ({self.reason})")
        return (
            f"registration {'+'.join(self.b_members)} -> {'+'.join(self.a_members)}: {what}, "
            f"confidence {self.confidence:.2f}, support {self.support:.1f} m ({self.support_fraction:.0%}), "
            f"{self.ms:.0f} ms"
        )


class FleetFrames:
    """The registration graph of the robots of unknown origin (module docstring)."""

    def __init__(self, config: FramesConfig | None = None) -> None:
        self.config = config or FramesConfig()
        self.root: dict[str, str] = {}  # unknown robot -> its component's root
        self.pose: dict[str, Pose] = {}  # unknown robot -> pose in its root's frame
        self.fleet_root: str | None = None  # root of the fleet component once decided
        self.has_known = False  # robots of known origin exist: they are the fleet
        self.records: list[RegistrationRecord] = []
        self.attempts = 0
        # (members a, members b) -> (length a, length b, clock) at the pair's last attempt
        self._tried: dict[tuple[tuple[str, ...], tuple[str, ...]], tuple[float, float, float | None]] = {}
        self.epoch = 0  # bumps on every change of membership or pose
        # (members a, members b) -> a first acceptance awaiting its second look
        self._pending: dict[tuple[tuple[str, ...], tuple[str, ...]], Pending] = {}
        self._lengths: dict[tuple[str, ...], float] = {}  # of the last next_pair, by members
        # the robots' clock as next_pair last saw it, and the service's time it first read so
        self._clock: tuple[float, float] | None = None

    # ------------------------------------------------------------------ membership
    @property
    def active(self) -> bool:
        """Whether any robot of unknown origin is tracked."""
        return bool(self.root)

    def track(self, rid: str) -> None:
        """Start tracking a robot of unknown origin (a component of its own)."""
        if rid not in self.root:
            self.root[rid] = rid
            self.pose[rid] = Pose.identity()
            self.epoch += 1

    def forget(self, rid: str) -> None:
        """A robot that now knows its origin (or is gone): drop it; its component's other
        members stay together, re-rooted at the lowest id when it was the root."""
        if rid not in self.root:
            return
        r = self.root.pop(rid)
        self.pose.pop(rid)
        self.epoch += 1
        if r == rid:
            rest = sorted(m for m, rr in self.root.items() if rr == rid)
            if rest:
                new = rest[0]
                inv = self.pose[new].inverse()
                for m in rest:
                    self.root[m] = new
                    self.pose[m] = inv.compose(self.pose[m])
                if self.fleet_root == rid:
                    self.fleet_root = new
            elif self.fleet_root == rid:
                self.fleet_root = None

    def components(self) -> dict[str, tuple[str, ...]]:
        """Root -> sorted members, of the unknown robots."""
        out: dict[str, list[str]] = {}
        for m, r in self.root.items():
            out.setdefault(r, []).append(m)
        return {r: tuple(sorted(ms)) for r, ms in sorted(out.items())}

    def fleet_component(self) -> str | None:
        """Root of the unknown robots' component that is the fleet (None: the known robots are
        the fleet and no unknown robot has joined them, or there is none)."""
        if self.has_known:
            return self.fleet_root  # set when a component joined the known robots
        if self.fleet_root is not None:
            return self.fleet_root
        anchor = self.config.anchor
        if anchor is not None and anchor in self.root:
            return self.root[anchor]
        if anchor is None and self.root:
            return self.root[min(self.root)]  # provisional: the lowest id on its own
        return None

    def in_fleet(self, rid: str) -> bool:
        """Whether a robot's map belongs in the fused map (robots of known origin always)."""
        if rid not in self.root:
            return True
        fc = self.fleet_component()
        return fc is not None and self.root[rid] == fc

    def fleet_pose(self, rid: str) -> Pose | None:
        """The pose of an unknown robot's odometry frame in the fleet frame (None: island)."""
        if not self.in_fleet(rid) or rid not in self.root:
            return None
        return self.pose[rid]

    def islands(self) -> dict[str, tuple[str, ...]]:
        """Root -> members of the components that are not the fleet."""
        fc = self.fleet_component()
        return {r: ms for r, ms in self.components().items() if r != fc}

    def summary(self) -> dict[str, Any]:
        """For ``fused/stats``, the fused map's ``meta`` and ``report.json``."""
        fc = self.fleet_component()
        registered = sorted(m for m in self.root if self.in_fleet(m))
        return {
            "anchor": self.config.anchor if self.config.anchor is not None else fc,
            "fleet_root": fc,
            "registered": registered,
            "islands": {r: list(ms) for r, ms in self.islands().items()},
            "poses": {m: [round(v, 6) for v in self.pose[m].as_tuple()] for m in registered},
            "attempts": self.attempts,
            "accepted": sum(1 for r in self.records if r.accepted),
            "registrations": [r.as_dict() for r in self.records[-4:]],
        }

    # ------------------------------------------------------------------ attempts
    def next_pair(
        self, lengths: Callable[[tuple[str, ...], str | None], float], now: float | None = None,
        t: float | None = None,
    ) -> tuple[str, str] | None:
        """The pair of components to try next ``(a, b)`` (``b`` registers onto ``a``; ``a`` may
        be :data:`FLEET`, the known robots' fused map), or None when none is due.

        ``lengths(members, root)`` is the wall length of a component's map (``root`` None for
        the known robots' fleet); ``now``: the caller's clock in seconds (None: only the growth
        rule); ``t``: the robots' clock, on which a pending join's second look falls due (first of
        all pairs)."""
        cfg = self.config
        if t is not None and now is not None and (self._clock is None or self._clock[0] != t):
            self._clock = (t, now)
        comps = self.components()
        fc = self.fleet_component()
        names: list[str] = list(comps)
        if self.has_known and fc is None:
            names.insert(0, FLEET)
        length: dict[str, float] = {}
        for n in names:
            length[n] = lengths(self._members(n, comps), None if n == FLEET else n)
        self._lengths = {self._members(n, comps): length[n] for n in names}
        held = set(self._lengths)
        for key in [k for k in self._pending if k[0] not in held or k[1] not in held]:
            # A side grew by a join since. When both sides are still their own roots, the
            # transform between their frames holds: the pending join goes on with the grown
            # components; otherwise (a side was joined into another frame) it is dropped.
            moved = self._pending.pop(key)
            a, b = moved.pair
            if a in comps and b in comps and a != b:
                self._pending.setdefault((comps[a], comps[b]), moved)
        best: tuple[tuple[int, float], tuple[str, str]] | None = None
        for i, x in enumerate(names):
            for y in names[i + 1:]:
                a, b = self._orient(x, y, fc)
                la, lb = length[a], length[b]
                if min(la, lb) < cfg.min_length_m:
                    continue
                key = (self._members(a, comps), self._members(b, comps))
                pend = self._pending.get(key)
                last = self._tried.get(key)
                if pend is not None:  # waits for its second look, and nothing else
                    confirm = due = t is not None and self._waited(pend, key, t, now)
                else:
                    confirm = False
                    due = last is None or _grew(la, last[0], cfg) or _grew(lb, last[1], cfg) \
                        or _settled(la, lb, now, last, cfg)
                if not due:
                    continue
                fleet_pair = a in (fc, FLEET) or b in (fc, FLEET)
                rank = (-1 if confirm else 0 if fleet_pair else 1, -(la + lb))
                if best is None or rank < best[0]:
                    best = (rank, (a, b))
        return None if best is None else best[1]

    def _members(self, name: str, comps: dict[str, tuple[str, ...]]) -> tuple[str, ...]:
        return (FLEET,) if name == FLEET else comps[name]

    def _orient(self, x: str, y: str, fc: str | None) -> tuple[str, str]:
        """``(a, b)``: ``a`` keeps its frame (the fleet, else the anchor's, else the lower root)."""
        if y in (FLEET, fc):
            return y, x
        if x in (FLEET, fc):
            return x, y
        anchor = self.config.anchor
        if anchor is not None and self.root.get(anchor) == y:
            return y, x
        return (x, y) if x < y else (y, x)

    def attempt(
        self,
        pair: tuple[str, str],
        maps: Callable[[tuple[str, ...], str | None], Wireframe],
        t: float | None = None,
        now: float | None = None,
    ) -> RegistrationRecord:
        """Register component ``b`` onto ``a`` (``maps(members, root)`` gives each one's map in
        its root frame, or the fleet frame for :data:`FLEET`) and join them when accepted.
        ``t``: the robots' clock (the record's time, and the one a pending join waits on: see
        :attr:`FramesConfig.confirm_after_s`); ``now``: the clock :meth:`next_pair` is given."""
        a, b = pair
        comps = self.components()
        ma, mb = self._members(a, comps), self._members(b, comps)
        wa = maps(ma, None if a == FLEET else a)
        wb = maps(mb, b)
        cfg = self.config
        rc = cfg.registration
        key = (ma, mb)
        t0 = time.perf_counter()
        prev = self._pending.get(key)
        pending = False
        if prev is not None and (t is None or not self._waited(prev, key, t, now)):
            # Tried before its second look is due (next_pair never offers it): it waits on.
            res, accepted, reason, pending = prev.res, False, prev.res.reason, True
        elif prev is not None:
            # The second look: the overlap matched at the first, against every map held now
            # (the pair's own as they grew too).
            del self._pending[key]
            res = prev.res
            own = (prepare(wa, rc), prepare(wb, rc))
            reason = self._recurs(prev.fa, prev.fb, res, (a, b), comps, maps, own) if cfg.recurrence else ""
            whole = res.support_fraction >= cfg.confirm_conflict_fraction
            if not reason and whole and res.transform is not None:
                conflict, limit = conflict_of(own[0], own[1], res.transform, rc)
                if conflict > limit:
                    reason = f"the grown maps put walls on seen-free space ({conflict:.1f} m)"
            accepted = not reason
        else:
            fa, fb = prepare(wa, rc), prepare(wb, rc)
            res = register_prepared(fa, fb, rc)
            accepted, reason = bool(res.accepted and res.transform is not None), res.reason
            if accepted and cfg.recurrence:
                reason = self._recurs(fa, fb, res, (a, b), comps, maps)
                accepted = not reason
            if accepted and cfg.confirm_after_s > 0 and t is not None:
                self._pending[key] = Pending(res, fa, fb, t, now, dict(self._lengths), (a, b))
                accepted, pending = False, True
        ms = 1000.0 * (time.perf_counter() - t0)
        self.attempts += 1
        # the lengths next_pair measured (the same measure as the growth test's)
        self._tried[key] = (self._lengths.get(ma, _length(wa)), self._lengths.get(mb, _length(wb)), now)
        if accepted and res.transform is not None:
            self._join(a, b, res.transform)
        rec = RegistrationRecord(
            t=0.0 if t is None else float(t), a=a, b=b, a_members=ma, b_members=mb, accepted=accepted,
            confidence=float(res.confidence), support=float(res.support),
            support_fraction=float(res.support_fraction),
            reason=reason, transform=None if res.transform is None else res.transform.as_tuple(), ms=ms,
            pending=pending,
        )
        self.records.append(rec)
        del self.records[: max(0, len(self.records) - self.config.history)]
        return rec

    def _waited(self, pend: Pending, key: tuple[tuple[str, ...], tuple[str, ...]], t: float,
                now: float | None) -> bool:
        """Whether a pending join's wait is over: ``confirm_after_s`` on the robots' clock and
        both maps grown to ``confirm_growth`` times the first look's matched wall (or
        ``confirm_max_s`` on that clock). Where that clock has not moved since the first look
        (a log whose stamps stand still), on the service's clock (``now``): ``confirm_after_s``,
        or ``retry_after_s`` when no component's map changed since. Where it moved and then
        stopped (the robots are done), ``retry_after_s`` of the service's clock after it
        stopped: no evidence is on its way."""
        cfg = self.config
        if t == pend.t and now is not None and pend.now is not None:
            still = pend.lengths == self._lengths
            wait = min(cfg.confirm_after_s, cfg.retry_after_s) if still else cfg.confirm_after_s
            return now - pend.now >= wait
        waited = t - pend.t
        if waited >= cfg.confirm_after_s:
            grown = min(self._lengths.get(key[0], 0.0), self._lengths.get(key[1], 0.0))
            if waited >= cfg.confirm_max_s or grown >= cfg.confirm_growth * pend.res.support:
                return True
        clock = self._clock
        return now is not None and clock is not None and clock[0] == t and now - clock[1] >= cfg.retry_after_s

    def _recurs(
        self, fa: MapFeatures, fb: MapFeatures, res: Registration, pair: tuple[str, str],
        comps: dict[str, tuple[str, ...]], maps: Callable[[tuple[str, ...], str | None], Wireframe],
        own: tuple[MapFeatures, MapFeatures] | None = None,
    ) -> str:
        """Why the accepted ``res`` (of ``fb`` onto ``fa``) must not join after all: its overlap
        recurs in another component's map, or in ``own`` (the pair's maps as they are now, at a
        second look) at a place besides the match ("" when it does not; see
        :attr:`FramesConfig.recurrence`)."""
        rc = self.config.registration
        names = [r for r in comps if r not in pair]
        if self.has_known and FLEET not in pair and self.fleet_component() is None:
            names.insert(0, FLEET)
        others = [(n, maps(self._members(n, comps), None if n == FLEET else n)) for n in names]
        feats = [(n, prepare(wf, rc)) for n, wf in others if _length(wf) >= self.config.min_length_m]
        if own is not None:
            feats += list(zip(pair, own))
        if not feats:
            return ""
        share, k = recurrence_elsewhere(fa, fb, res, [f for _, f in feats], rc)
        contested = res.runner_up_ratio > rc.contested_runner_up_ratio
        limit = rc.contested_self_ratio if contested else rc.max_self_ratio
        if k < 0 or share <= limit:
            return ""
        name = feats[k][0]
        who = "the fleet's" if name == FLEET else f"{'+'.join(comps[name])}'s"
        return f"repetitive: the overlap recurs in {who} map ({share:.0%})"

    def _join(self, a: str, b: str, transform: Pose) -> None:
        """Component ``b``'s root frame goes into ``a``'s by ``transform``."""
        for m in [m for m, r in self.root.items() if r == b]:
            self.pose[m] = transform.compose(self.pose[m])
            self.root[m] = a if a != FLEET else b
        if a == FLEET:
            # the known robots are the fleet: b's members keep root b, now in the fleet frame
            self.fleet_root = b
        elif self.fleet_root is None and not self.has_known:
            anchor = self.config.anchor
            if anchor is None or self.root.get(anchor) == a:
                self.fleet_root = a
        self.epoch += 1


def _length(wf: Wireframe) -> float:
    return float(wf.edge_lengths().sum()) if wf.n_edges else 0.0


def _grew(now: float, then: float, cfg: FramesConfig) -> bool:
    return now - then >= max(cfg.retry_growth_m, cfg.retry_growth_fraction * then)


def _settled(la: float, lb: float, now: float | None, last: tuple[float, float, float | None],
             cfg: FramesConfig) -> bool:
    """A side changed by ``retry_min_m`` and ``retry_after_s`` passed since the last attempt."""
    if now is None or last[2] is None or cfg.retry_after_s <= 0 or now - last[2] < cfg.retry_after_s:
        return False
    return abs(la - last[0]) >= cfg.retry_min_m or abs(lb - last[1]) >= cfg.retry_min_m


def fold_maps(maps: Iterable[Wireframe], merge: Callable[[Wireframe, Wireframe], Wireframe]) -> Wireframe:
    """A left fold of ``merge`` over ``maps`` (an island's map)."""
    acc: Wireframe | None = None
    for wf in maps:
        acc = wf if acc is None else merge(acc, wf)
    return acc if acc is not None else Wireframe.empty()


def finite_pose(p: Pose) -> bool:
    return all(math.isfinite(v) for v in p.as_tuple())
