"""The fusion tree across processes: which robots a regional fuser takes, and the root's merge
of the regional fusers' partial maps. Pure (no zenoh): the Zenoh shells are
:mod:`agents.fleet.fusion.regional` and :mod:`agents.fleet.fusion.root`.

The one-process fold (:meth:`FusionState.compute`) is a fixed binary tree over the robots in
sorted-id order: a node over ``[lo, hi)`` merges ``node(lo, mid)`` and ``node(mid, hi)`` with
``mid = fold_split(lo, hi)``. A **group** of robots whose sorted ids are a node's span (a
*subtree*: contiguous, and the tree splits exactly there) can be folded by a process of its own:
its fold is the same shape translated (``fold_split`` only depends on ``hi - lo``). The root
then rebuilds the tree above the groups from their partial maps. That is the choice made here
(the single-process fold is not changed): :func:`fold_groups` gives the subtrees ``wiremap run
--fusers K`` and ``wiremap bench fleet --fusers K`` assign, and :class:`RootState` checks that
the partials it holds are subtrees of the fleet-wide tree (``exact``); when they are not (a glob
or hash group, a robot in two partials during a takeover) it folds the partials as leaves in the
order of their first robot, still with fleet-wide provenance, and says so (``exact = False``).

What differs from one process even with subtree groups (measured in
``tests/test_fusion_tree.py``): a partial travels through the codec, quantised at its
resolution (each vertex within ``res / 2``) and with likelihoods in steps of 1/15; the root's
merge and the alignment of a group's robots onto the groups before it (the ICP prefix, see
:class:`~agents.fleet.fusion.regional.RegionalService`) start from those quantised partials.
Frontiers are closed only at the root (a partial is a node of the tree, not a fused map).

Provenance: a partial's ``robots`` are its group's sorted ids and bit ``j`` of its sources is
``robots[j]``; the root maps bit ``j`` to the fleet-wide position of ``robots[j]``
(:func:`remap_sources`).
"""

from __future__ import annotations

import fnmatch
import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agents.errors import UserError
from mapping.fleet import close_frontiers, fold_split
from mapping.se2 import Pose
from mapping.wireframe import Wireframe, as_masks
from wire_codec.message import MapMessage, MessageKind

__all__ = [
    "GroupKeys",
    "Partial",
    "RobotSelector",
    "RootState",
    "fold_groups",
    "fold_nodes",
    "fold_ranges",
    "is_fold_node",
    "prefix_spans",
    "remap_sources",
    "wire_snap",
]


# ---------------------------------------------------------------------- keys
@dataclass(frozen=True)
class GroupKeys:
    """The keys of the tree in a fleet (``prefix`` is ``wiremap/<fleet>``)."""

    prefix: str

    def group_map(self, name: str) -> str:
        return f"{self.prefix}/groups/{name}/map"

    def group_stats(self, name: str) -> str:
        return f"{self.prefix}/groups/{name}/stats"

    def fuser_token(self, name: str) -> str:
        return f"{self.prefix}/fusers/{name}"

    @property
    def all_groups(self) -> str:
        return f"{self.prefix}/groups/*/map"

    @property
    def all_fusers(self) -> str:
        return f"{self.prefix}/fusers/*"

    def group_of(self, key: str) -> str | None:
        """The group name in ``.../groups/<name>/map`` or ``.../fusers/<name>``."""
        head = self.prefix.split("/")
        parts = str(key).split("/")
        if parts[: len(head)] != head:
            return None
        rest = parts[len(head):]
        if len(rest) == 3 and rest[0] == "groups" and rest[2] == "map":
            return rest[1]
        if len(rest) == 2 and rest[0] == "fusers":
            return rest[1]
        return None


# ---------------------------------------------------------------------- the wire's grid
def merge_on_grid(merge_fn: Any, a: Wireframe, b: Wireframe, thr: float, grid: float) -> Wireframe:
    """One node of the fold: an empty side leaves the other as it is; otherwise ``merge_fn(a, b,
    thr)`` snapped to the wire's grid (:func:`wire_snap`), so that a subtree can be a regional
    fuser's partial map without changing the fold above it."""
    if b.n_vertices == 0:
        return a
    if a.n_vertices == 0:
        return b
    return wire_snap(merge_fn(a, b, thr), grid)


def wire_snap(wf: Wireframe, resolution: float) -> Wireframe:
    """``wf`` as the codec would bring it back at ``resolution``: vertices on the grid of
    ``round(resolution, mm)`` (the decoder's arithmetic, ``q * res_mm / 1000``), likelihoods
    in fifteenths. The fold tree's nodes are snapped so (:meth:`FusionState._merge`), so any
    subtree can travel between processes as a partial map without changing what is merged
    above it: decoding the partial gives the node's values exactly."""
    from wire_codec.body import LIKELIHOOD_LEVELS

    if wf.n_vertices == 0:
        return wf
    res_mm = max(1, round(resolution * 1e3))
    pts = np.rint(wf.points / (res_mm / 1e3)) * res_mm / 1e3
    lik = np.rint(wf.likelihood * LIKELIHOOD_LEVELS) / LIKELIHOOD_LEVELS
    # (same shapes, finite values: == over every element is array_equal)
    if bool((pts == wf.points).all()) and bool((lik == wf.likelihood).all()):
        return wf
    return wf.moved_to(pts, likelihood=lik)  # likelihoods rounded within [0, 1]: still valid


# ---------------------------------------------------------------------- robot selection
_HASH = re.compile(r"^hash:(\d+)/(\d+)$")
_RANGE = re.compile(r"^range:([A-Za-z0-9_.\-]*):([A-Za-z0-9_.\-]*)$")


def robot_hash(rid: str) -> int:
    """A stable 64-bit hash of a robot id (first 8 bytes of its SHA-256)."""
    return int.from_bytes(hashlib.sha256(rid.encode()).digest()[:8], "big")


@dataclass(frozen=True)
class RobotSelector:
    """The robots of a regional fuser (``wiremap fuse --robots PATTERN``).

    ``PATTERN`` is one of:

    * ``range:LO:HI``: the ids ``LO <= id < HI`` in sorted order (Python's string order, the
      fold's), either end may be empty (``range::r5`` every id before ``r5``, ``range:r5:``
      ``r5`` and after). Ranges that meet end to end cover every id there can be, so a robot
      that joins later lands in exactly one group; and the groups stay contiguous in the
      fold's order, so they are the fold's subtrees (``meta.exact``) whenever the counts
      allow (:func:`fold_ranges`; ``wiremap run --fusers K`` uses these);
    * ``hash:I/K``: the robots whose :func:`robot_hash` modulo ``K`` is ``I`` (stable as the
      fleet grows, every id in exactly one of the ``K``, but not a subtree of the fold, so the
      root's map is then a fold of the partials, see the module docstring);
    * comma-separated glob patterns over robot ids (``r1*``, ``r0[1-8]``, ``r01,r02``; ``*`` any
      run of characters, ``?`` one, ``[..]`` a set), a robot is in the group when one of them
      matches. A list of plain ids covers those robots only: a robot that joins later is in
      no group (the root lists it in ``uncovered``).
    """

    text: str
    globs: tuple[str, ...] = ()
    bucket: tuple[int, int] | None = None
    _re: Any = field(default=None, compare=False, repr=False)
    span: tuple[str, str | None] | None = None  # range:LO:HI as (LO, HI or None for open)

    @classmethod
    def parse(cls, text: str) -> RobotSelector:
        t = str(text).strip()
        m = _HASH.match(t)
        if m:
            i, k = int(m.group(1)), int(m.group(2))
            if k < 1 or not 0 <= i < k:
                raise UserError(f"--robots {text!r}: hash:I/K needs K >= 1 and 0 <= I < K")
            return cls(t, (), (i, k))
        m = _RANGE.match(t)
        if m:
            lo, hi = m.group(1), m.group(2) or None
            if hi is not None and hi <= lo:
                raise UserError(f"--robots {text!r}: range:LO:HI needs LO < HI")
            return cls(t, span=(lo, hi))
        if t.startswith("range:"):
            raise UserError(f"--robots {text!r}: range:LO:HI with LO and HI robot ids or empty")
        globs = tuple(g.strip() for g in t.split(",") if g.strip())
        if not globs:
            raise UserError(f"--robots {text!r}: give glob patterns over robot ids or hash:I/K")
        for g in globs:
            if "/" in g:
                raise UserError(f"--robots {text!r}: a pattern matches one robot id, no '/'")
        rx = re.compile("|".join(f"(?:{fnmatch.translate(g)})" for g in globs))
        return cls(t, globs, None, rx)

    def matches(self, rid: str) -> bool:
        if self.bucket is not None:
            i, k = self.bucket
            return robot_hash(rid) % k == i
        if self.span is not None:
            lo, hi = self.span
            return lo <= rid and (hi is None or rid < hi)
        return bool(self._re.match(rid))

    def key_chunk(self) -> str:
        """A Zenoh chunk that covers the group, for the subscription (so that routers forward
        only those robots' maps across their links): one glob made of literal characters and
        ``*`` becomes that chunk (``*`` -> ``$*``); anything else ``*`` (filtered here)."""
        if len(self.globs) == 1 and re.fullmatch(r"[A-Za-z0-9_.\-*]+", self.globs[0]):
            g = self.globs[0]
            return "*" if g == "*" else g.replace("*", "$*")
        return "*"


# ---------------------------------------------------------------------- the fold's subtrees
def is_fold_node(lo: int, hi: int, n: int) -> bool:
    """Whether ``[lo, hi)`` is a node of the fold tree over ``n`` leaves."""
    a, b = 0, n
    while True:
        if (a, b) == (lo, hi):
            return True
        if b - a < 2 or not (a <= lo and hi <= b):
            return False
        mid = fold_split(a, b)
        if hi <= mid:
            b = mid
        elif lo >= mid:
            a = mid
        else:
            return False


def fold_nodes(n: int, k: int) -> list[tuple[int, int]]:
    """``k`` spans that are nodes of the fold tree over ``n`` leaves and cover it: start from
    the root, split the widest span (the first of equal ones) at its ``fold_split`` until
    there are ``k`` (or every span is a leaf). With ``n`` a power of two and ``k`` too, equal
    groups; 48 robots in 2 make 32 + 16."""
    if n <= 0:
        return []
    spans = [(0, n)]
    while len(spans) < k:
        widest = max(range(len(spans)), key=lambda j: (spans[j][1] - spans[j][0], -j))
        lo, hi = spans[widest]
        if hi - lo < 2:
            break
        mid = fold_split(lo, hi)
        spans[widest: widest + 1] = [(lo, mid), (mid, hi)]
    return spans


def fold_groups(ids: Sequence[str], k: int) -> list[list[str]]:
    """The robots (sorted ids) of :func:`fold_nodes`' ``k`` subtrees."""
    s = sorted(ids)
    return [s[lo:hi] for lo, hi in fold_nodes(len(s), k)]


def fold_ranges(ids: Sequence[str], k: int) -> list[str]:
    """``range:LO:HI`` patterns (:class:`RobotSelector`) for :func:`fold_groups`' ``k``
    subtrees of ``ids``: group ``g`` from its first id to the next group's first id, the first
    group open below and the last open above. Each group takes the same robots as the list of
    its ids, and every id not in ``ids`` (a robot that joins later) falls in exactly one."""
    groups = [g for g in fold_groups(ids, k) if g]
    firsts = [g[0] for g in groups]
    return [f"range:{'' if j == 0 else lo}:{firsts[j + 1] if j + 1 < len(firsts) else ''}"
            for j, lo in enumerate(firsts)]


def prefix_spans(k: int, n: int) -> list[tuple[int, int]]:
    """The fold tree's nodes that cover ``[0, k)`` (left to right): what robot ``k`` is aligned
    onto (:meth:`FusionState._prefix_map` merges these nodes)."""
    out: list[tuple[int, int]] = []
    lo, hi = 0, n
    while k > lo and hi - lo > 0:
        if k >= hi:
            out.append((lo, hi))
            break
        if hi - lo == 1:
            break
        mid = fold_split(lo, hi)
        if k <= mid:
            hi = mid
        else:
            out.append((lo, mid))
            lo = mid
    return out


def remap_sources(sources: np.ndarray, positions: Sequence[int]) -> np.ndarray:
    """Masks with bit ``j`` moved to bit ``positions[j]`` (a partial's local robot order to the
    fleet-wide one), of any width (:func:`mapping.wireframe.as_masks`: ``uint64`` while every
    mask fits, Python ints past bit 63). Work per distinct mask (a map has few)."""
    if len(sources) == 0 or list(positions) == list(range(len(positions))):
        return as_masks(sources)
    vals = [int(v) for v in sources.tolist()]
    table: dict[int, int] = {}
    for mask in set(vals):
        m = 0
        j = 0
        rest = mask
        while rest:
            if rest & 1:
                m |= 1 << positions[j]
            rest >>= 1
            j += 1
        table[mask] = m
    return as_masks([table[v] for v in vals])


# ---------------------------------------------------------------------- the root
@dataclass(frozen=True)
class Partial:
    """A group's latest partial map as received: the message, its order key ``(boot,
    version)``, the robot publish stamps it newly includes (``meta.stamps``)."""

    group: str
    message: MapMessage
    key: tuple[int, int]
    stamps: tuple[int, ...] = ()


def partial_key(msg: MapMessage) -> tuple[int, int]:
    meta = msg.meta if isinstance(msg.meta, dict) else {}
    boot = meta.get("boot", 0)
    return (boot if isinstance(boot, int) else 0, int(msg.seq))


class RootState:
    """The root fuser's core: each group's latest partial, and their fold.

    :meth:`compute` returns the fleet's fused map: robots = the union of the partials' robots,
    sorted; when every partial's robots are a node of the fold tree over them (and no robot is
    in two partials) the tree above the partials is the one-process tree (``exact``),
    otherwise the partials are folded as leaves ordered by their first robot. Then frontiers
    are closed (:func:`mapping.fleet.close_frontiers`) as one process does.
    """

    def __init__(self, threshold: float | None = None, merge_fn: Any = None, sender: str = "fusion") -> None:
        from agents.fleet.fusion.state import default_merge

        self.threshold_cfg = threshold
        self.merge_fn = merge_fn or default_merge
        self.sender = sender
        self.partials: dict[str, Partial] = {}
        self.fused = Wireframe.empty()
        self.fused_robots: tuple[str, ...] = ()
        self.exact = True
        self.version = 0
        self.merges = 0
        self._cache: dict[tuple[int, int], tuple[Any, Wireframe]] = {}
        self._leaves: dict[str, tuple[Any, Wireframe]] = {}
        self._pending: list[int] = []  # robot stamps newly included, not yet published
        self._group_pending: list[int] = []  # partial stamps newly included
        self.refused: dict[str, int] = {}  # partials refused per group: over MAX_ROBOTS robots in all

    def offer(self, group: str, msg: MapMessage) -> bool:
        """Keep ``msg`` if it is the group's newest partial (by ``(meta.boot, version)``)."""
        if msg.kind != MessageKind.FUSED_MAP:
            return False
        key = partial_key(msg)
        old = self.partials.get(group)
        if old is not None and key <= old.key:
            return False
        from wire_codec import MAX_ROBOTS

        others = {r for g, p in self.partials.items() if g != group for r in p.message.robots}
        if len(others | set(msg.robots)) > MAX_ROBOTS:
            # a fused map carries at most MAX_ROBOTS robots (4,096; wire_codec/FORMAT.md 3.6):
            # the partial that would make one more is refused, the group's last one (if any)
            # stays in the map
            self.refused[group] = self.refused.get(group, 0) + 1
            return False
        meta = msg.meta if isinstance(msg.meta, dict) else {}
        stamps = tuple(int(s) for s in meta.get("stamps", []) if isinstance(s, int))
        self.partials[group] = Partial(group, msg, key, stamps)
        self._pending.extend(stamps)
        self._group_pending.append(int(msg.stamp_ns))
        return True

    @property
    def threshold(self) -> float:
        from agents.fleet.fusion.state import DEFAULT_THRESHOLD, merge_threshold_of

        if self.threshold_cfg is not None:
            return float(self.threshold_cfg)
        return max([DEFAULT_THRESHOLD, *(merge_threshold_of(p.message) for p in self.partials.values())])

    @property
    def resolution(self) -> float:
        from agents.fleet.fusion.state import DEFAULT_RESOLUTION

        res = [float(p.message.resolution) for p in self.partials.values() if p.message.resolution > 0]
        return min(res, default=DEFAULT_RESOLUTION)

    def _leaf(self, p: Partial, index: dict[str, int]) -> Wireframe:
        """The partial with its sources in fleet-wide bits (cached per partial and positions)."""
        m = p.message
        pos = tuple(index[r] for r in m.robots)
        hit = self._leaves.get(p.group)
        if hit is not None and hit[0] == (p.key, pos):
            return hit[1]
        wf = m.wireframe
        out = Wireframe(wf.points, wf.labels, wf.edges, wf.likelihood, remap_sources(wf.sources, pos))
        self._leaves[p.group] = ((p.key, pos), out)
        return out

    def _merge(self, a: Wireframe, b: Wireframe, thr: float) -> Wireframe:
        self.merges += bool(a.n_vertices and b.n_vertices)
        return merge_on_grid(self.merge_fn, a, b, thr, self.resolution)

    def layout(self) -> tuple[tuple[str, ...], list[tuple[int, int, Partial]], bool]:
        """The fleet's sorted ids, each partial's span ``(lo, hi, partial)`` in fold order, and
        whether the partials are subtrees of the fold over those ids."""
        parts = [p for p in self.partials.values() if p.message.robots]
        ids = tuple(sorted({r for p in parts for r in p.message.robots}))
        index = {r: k for k, r in enumerate(ids)}
        spans: list[tuple[int, int, Partial]] = []
        exact = sum(len(p.message.robots) for p in parts) == len(ids)
        for p in parts:
            ks = sorted(index[r] for r in p.message.robots)
            lo, hi = ks[0], ks[-1] + 1
            if hi - lo != len(ks) or not is_fold_node(lo, hi, len(ids)):
                exact = False
            spans.append((lo, hi, p))
        spans.sort(key=lambda s: (s[0], s[2].group))
        return ids, spans, exact

    def compute(self) -> tuple[Wireframe, tuple[str, ...], bool]:
        thr = self.threshold
        ids, spans, exact = self.layout()
        index = {r: k for k, r in enumerate(ids)}
        leaves = [((s[2].group, s[2].key), self._leaf(s[2], index)) for s in spans]
        if not leaves:
            return Wireframe.empty(), (), True
        if exact:
            by_span = {(lo, hi): leaf for (lo, hi, _), leaf in zip(spans, leaves)}

            def node(lo: int, hi: int) -> tuple[Any, Wireframe]:
                if (lo, hi) in by_span:
                    return by_span[(lo, hi)]
                mid = fold_split(lo, hi)
                return self._cached((lo, hi), node(lo, mid), node(mid, hi), thr)

            acc = node(0, len(ids))[1]
        else:
            # not subtrees: the partials are the leaves of a fold of their own
            def pnode(lo: int, hi: int) -> tuple[Any, Wireframe]:
                if hi - lo == 1:
                    return leaves[lo]
                mid = fold_split(lo, hi)
                return self._cached((-lo - 1, -hi - 1), pnode(lo, mid), pnode(mid, hi), thr)

            acc = pnode(0, len(leaves))[1]
        return close_frontiers(acc, thr), ids, exact

    def _cached(
        self, span: tuple[int, int], a: tuple[Any, Wireframe], b: tuple[Any, Wireframe], thr: float
    ) -> tuple[Any, Wireframe]:
        key = (thr, a[0], b[0])
        hit = self._cache.get(span)
        if hit is not None and hit[0] == key:
            return key, hit[1]
        out = self._merge(a[1], b[1], thr)
        self._cache[span] = (key, out)
        return key, out

    def fuse(self) -> bool:
        """Recompute; bump the version and return True when the map or robots changed."""
        from agents.fleet.fusion.state import _same_wireframe

        wf, ids, exact = self.compute()
        self.exact = exact
        if ids != self.fused_robots or not _same_wireframe(wf, self.fused):
            self.fused, self.fused_robots = wf, ids
            self.version += 1
            return True
        return False

    def take_latencies(self, published_ns: int) -> tuple[list[float], list[float]]:
        """``(robot publish -> fused publish, partial publish -> fused publish)`` in ms for the
        maps and partials included since the last call."""
        e2e = [max(0.0, (published_ns - s) / 1e6) for s in self._pending]
        lvl = [max(0.0, (published_ns - s) / 1e6) for s in self._group_pending]
        self._pending.clear()
        self._group_pending.clear()
        return e2e, lvl

    def fused_message(self, stamp_ns: int, meta: dict[str, Any] | None = None) -> MapMessage:
        m: dict[str, Any] = {"version": self.version, "threshold": self.threshold, "exact": self.exact,
                             "groups": sorted(self.partials)}
        m.update(meta or {})
        return MapMessage(
            kind=MessageKind.FUSED_MAP, sender=self.sender, seq=self.version, stamp_ns=int(stamp_ns),
            pose=Pose.identity(), frame="fleet", origin=Pose.identity(), resolution=self.resolution,
            wireframe=self.fused, robots=self.fused_robots, meta=m,
        )

    def prefix_before(self, robot_ids: Sequence[str]) -> tuple[Any, Wireframe] | None:
        """For a group whose robots are ``robot_ids``: the map of the robots before its first
        one in the fleet-wide fold (the tree's nodes covering ``[0, lo)``, each folded from the
        partials, merged left to right) and its identity; None when it is the first group, or
        the nodes are not made of whole partials (then its first robot is an anchor).
        Frontiers are not closed (the one-process prefix is not either)."""
        own = sorted(robot_ids)
        if not own:
            return None
        others = {g: p for g, p in self.partials.items() if not set(p.message.robots) & set(own)}
        ids = tuple(sorted({r for p in others.values() for r in p.message.robots} | set(own)))
        index = {r: k for k, r in enumerate(ids)}
        lo = index[own[0]]
        if lo == 0:
            return None
        spans = {}
        for p in others.values():
            ks = sorted(index[r] for r in p.message.robots)
            spans[(ks[0], ks[-1] + 1)] = p
        thr = self.threshold
        leaves = {sp: ((p.group, p.key), self._leaf(p, index)) for sp, p in spans.items()}

        def node(a: int, b: int) -> tuple[Any, Wireframe] | None:
            if (a, b) in leaves:
                return leaves[(a, b)]
            if b - a < 2:
                return None
            mid = fold_split(a, b)
            left, right = node(a, mid), node(mid, b)
            if left is None or right is None:
                return None
            return self._cached((-(10**6) - a, -(10**6) - b), left, right, thr)

        acc: tuple[Any, Wireframe] | None = None
        for a, b in prefix_spans(lo, len(ids)):
            part = node(a, b)
            if part is None:
                return None
            acc = part if acc is None else ((acc[0], part[0]), self._merge(acc[1], part[1], thr))
        return acc
