"""Quarantine: a robot map that contradicts its robot's own history or the fleet's map is kept
aside, counted and shown, never merged (see ``ARCHITECTURE.md``, "Faults and hostile input").

Pure functions over wireframes plus :class:`Quarantine`, the record the fusion state keeps.
Both tests compare *where the maps overlap*, on points sampled along the walls:

* **history** (:func:`against_history`), the robot's new map against its last accepted one of
  the same boot, in its odometry frame: the new map may not reach beyond the old map's box by
  more than the robot could have seen since (``extent_jump``: sensor range + speed x seconds
  between the two maps + slack), and where the new walls lie inside the old map's box most of
  them must lie near an old wall (``history_walls``). A robot's best particle changes, and
  loop closures move walls, by decimetres to a metre; ``far_m`` is 1 m.
* **first map** (in :meth:`FusionState._inconsistent`): a robot's first accepted map may reach
  no further from its start than sensor range + speed x seconds since the fusion service first
  heard of the id + slack (``extent_jump``): its claimed boot may be as old as it likes.
* **fleet** (:func:`against_fleet`), the new map in the fleet frame against the walls the
  *other* robots contributed to the fused map: in the space the fleet has seen well (cells of
  ``cell_m`` holding a fleet wall: the wall and the free space beside it) most of the robot's
  walls must lie near a fleet wall (``fleet_walls``: walls in the fleet's free space). Rooms
  between the fleet's walls are not counted as seen: the fleet may not have entered them
  (with 16 robots in the museum, counting them quarantined an honest robot's new rooms).
  Robots of unknown start pose are not tested against the fleet (their frame is their own).

Each test judges only when at least ``min_overlap_m`` of the new walls lie in the overlap, so
a robot exploring new ground is never judged on a few metres.

:func:`against_history` and :func:`against_fleet` are the plain statements of the tests; the
fusion state runs :func:`history_judge` and :meth:`FleetSamples.judge`, which give their
verdicts and details exactly (tested) at a fraction of the cost (issue 21).
"""

from __future__ import annotations

from collections.abc import Set
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from agents.fleet.fusion.facts import MapFacts, facts_of
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]
MAX_JUDGED = 1000  # wall points whose distance is tested per map, at most (every k-th)


@dataclass(frozen=True)
class QuarantineConfig:
    """Thresholds of the consistency tests (choices, see the module's docstring).

    sample_m : walls are compared on points this far apart.
    far_m : a wall point further than this from the other map's walls disagrees.
    min_overlap_m : metres of new walls in the overlap below which a test does not judge.
    max_disagree : the largest fraction of disagreeing wall points in the overlap.
    cell_m : the grid of the fleet's seen space (cells holding a wall of another robot).
    growth_slack_m : added to the reach allowed between two maps (extent test).
    forget_after_s : a robot id none of whose maps was accepted for this long (every one
        refused or quarantined) is forgotten (:meth:`FusionState.forget_implausible`).
    """

    sample_m: float = 1.0
    far_m: float = 1.0
    min_overlap_m: float = 20.0
    max_disagree: float = 0.5
    cell_m: float = 4.0
    growth_slack_m: float = 10.0
    forget_after_s: float = 300.0


@dataclass
class Quarantined:
    """A robot's latest quarantined map: the message's bytes, why, and when (fusion's clock)."""

    raw: bytes
    reason: str
    detail: str
    at_ns: int
    count: int = 1


@dataclass
class Quarantine:
    """What the fusion state keeps aside: the latest quarantined map per robot."""

    maps: dict[str, Quarantined] = field(default_factory=dict)

    def put(self, rid: str, raw: bytes, reason: str, detail: str, at_ns: int) -> None:
        old = self.maps.get(rid)
        self.maps[rid] = Quarantined(raw, reason, detail, at_ns, (old.count + 1) if old else 1)

    def summary(self) -> dict[str, dict[str, object]]:
        """``{robot: {reason, detail, count, at_ns}}`` for ``fused/stats``."""
        return {
            rid: {"reason": q.reason, "detail": q.detail, "count": q.count, "at_ns": q.at_ns}
            for rid, q in sorted(self.maps.items())
        }


def wall_samples(wf: Wireframe, step: float) -> FloatArray:
    """Points at most ``step`` apart along every wall (edge midpoints of equal pieces)."""
    return _samples(wf, step)[0]


def _samples(wf: Wireframe, step: float) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`wall_samples` and the edge each point lies on. Every point depends on its own edge
    only, so the points of a subset of the edges are exactly these points of those edges."""
    if wf.n_edges == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    # fewer numpy calls than the plain statement (a robot map has a handful of walls: their
    # fixed cost was most of it), the same operations on the same values (tested)
    seg = wf.points[wf.edges]
    a = seg[:, 0]
    d = seg[:, 1] - a
    length = np.hypot(d[:, 0], d[:, 1])
    k = np.ceil(length / step).astype(np.int64)
    np.maximum(k, 1, out=k)
    owner = np.repeat(np.arange(len(k)), k)
    start = np.cumsum(k) - k
    t = (np.arange(len(owner)) - start[owner] + 0.5) / k[owner]
    out: FloatArray = a[owner] + t[:, None] * d[owner]
    return out, owner


def _samples_of(
    wf: Wireframe, step: float, facts: MapFacts | None
) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`_samples`, kept in ``facts`` (when they are ``wf``'s)."""
    return facts_of(wf, facts).get(("samples", step), lambda: _readonly(_samples(wf, step)))


def _readonly(arrays: tuple[FloatArray, NDArray[np.int64]]) -> tuple[FloatArray, NDArray[np.int64]]:
    """The arrays, made read-only (they are kept and shared: :class:`MapFacts`)."""
    for a in arrays:
        a.setflags(write=False)
    return arrays


def _near(walls: Wireframe, cfg: QuarantineConfig) -> cKDTree | None:
    """A k-d tree of points every ``sample_m / 2`` along ``walls`` (None without walls): a
    point within ``far_m`` of a wall is within ``far_m + sample_m / 4`` of one of them."""
    pts = wall_samples(walls, cfg.sample_m / 2)
    return cKDTree(pts, balanced_tree=False, compact_nodes=False) if len(pts) else None


def _disagreement(points: FloatArray, near: cKDTree | None, cfg: QuarantineConfig) -> tuple[float, float]:
    """(metres of walls at ``points`` judged, fraction of them further than ``far_m`` from the
    other map's walls, :func:`_near`), on at most ``MAX_JUDGED`` of the points."""
    if len(points) == 0:
        return 0.0, 0.0
    if near is None:
        return len(points) * cfg.sample_m, 1.0
    judged = points[:: -(-len(points) // MAX_JUDGED)]  # an even subsample: the fraction is what counts
    d, _ = near.query(judged, distance_upper_bound=cfg.far_m + cfg.sample_m / 4)
    return len(points) * cfg.sample_m, float(np.mean(~np.isfinite(d)))


@dataclass(frozen=True)
class FleetView:
    """The other robots' walls, prepared once per fused version: a k-d tree of points along
    them (:func:`_near`) and the cells of ``cell_m`` that hold one (the space they have seen
    well: a wall and the free space beside it)."""

    near: cKDTree | None
    cells: NDArray[np.int64]

    @classmethod
    def of(cls, fleet: Wireframe, cfg: QuarantineConfig) -> FleetView:
        ref = wall_samples(fleet, cfg.sample_m)
        return cls(_near(fleet, cfg), np.unique(_cell_codes(ref, cfg.cell_m)))


@dataclass(frozen=True)
class FleetSamples:
    """The fused map's wall samples, computed once per fused version, from which each robot's
    :class:`FleetView` (the walls of the *other* robots, :func:`others_walls`) is cut.

    The fusion judges each robot's new map against the fused map without that robot's own
    walls, so every robot has a view of its own, and a view was built for every map that
    arrived (the fused version changes with nearly every batch): sampling the walls twice and
    making a wireframe of the others' edges each time cost a third of a robot map's intake at
    64 robots (issue 21). Samples depend on their own edge only (:func:`_samples`), so the
    view of robot ``bit`` keeps the samples of the edges :func:`others_walls` keeps, in the
    same order: the same k-d tree input and the same cells, bit for bit (tested)."""

    fused: Wireframe
    cfg: QuarantineConfig
    near_points: FloatArray  # every sample_m / 2 along the walls (the k-d tree's points)
    near_owner: NDArray[np.int64]
    cell_codes: NDArray[np.int64]  # the cell of every point sample_m apart
    cell_owner: NDArray[np.int64]
    # for judge(): one k-d tree over every near point, the cells sorted (unique codes, and the
    # edges of the points in them grouped by cell)
    tree: cKDTree | None = None
    cells: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    cell_starts: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    cell_edges: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    @classmethod
    def of(cls, fused: Wireframe, cfg: QuarantineConfig) -> FleetSamples:
        near, near_owner = _samples(fused, cfg.sample_m / 2)
        ref, ref_owner = _samples(fused, cfg.sample_m)
        codes = _cell_codes(ref, cfg.cell_m)
        order = np.argsort(codes, kind="stable")
        cells, starts = np.unique(codes[order], return_index=True)
        tree = cKDTree(near, balanced_tree=False, compact_nodes=False) if len(near) else None
        return cls(fused, cfg, near, near_owner, codes, ref_owner, tree, cells, starts.astype(np.int64),
                   ref_owner[order])

    def view(self, bit: int | None) -> FleetView:
        """``FleetView.of(others_walls(self.fused, bit), self.cfg)``, from the samples."""
        keep = _others_keep(self.fused, bit)
        pts = self.near_points if keep is None else self.near_points[keep[self.near_owner]]
        codes = self.cell_codes if keep is None else self.cell_codes[keep[self.cell_owner]]
        near = cKDTree(pts, balanced_tree=False, compact_nodes=False) if len(pts) else None
        return FleetView(near, np.unique(codes))

    def judge(self, new: Wireframe, bit: int | None, facts: MapFacts | None = None) -> tuple[str, str] | None:
        """``against_fleet(new, self.view(bit), self.cfg)`` without building the view: the same
        verdict and detail (tested against it), at a fraction of the cost (issue 21).

        The view's k-d tree (the other robots' points) was built for every map that arrived;
        here one tree over all the fused map's points serves every robot. A point of ``new``
        agrees when some *kept* point (of an edge :func:`others_walls` keeps) lies within the
        bound: its ``K`` nearest points within the bound are asked for, and when all ``K`` are
        there and none is kept the point is asked again with ``4 K`` (at most all the points),
        so the answer is the one the view's tree gives (the same pairwise distances, the same
        bound). A cell is the view's when a kept edge has a point in it. The disagreement is
        only measured when the overlap is long enough to judge: below ``min_overlap_m`` the
        verdict does not depend on it. ``facts``: ``new``'s :class:`MapFacts` (its wall points
        and their cells are kept there: a map sent again is judged against the present fleet
        without sampling its walls again)."""
        cfg = self.cfg
        fused = self.fused
        if new.n_edges == 0 or fused.n_edges == 0:
            return None
        if len(self.cells) == 0:
            return None
        keep = _others_keep(fused, bit)
        kept = np.ones(fused.n_edges, dtype=bool) if keep is None else keep
        others = np.logical_or.reduceat(kept[self.cell_edges], self.cell_starts)  # cells of the view
        if not others.any():
            return None  # the view has no cells
        step, cell = cfg.sample_m, cfg.cell_m
        pts, codes = facts_of(new, facts).get(("cells", step, cell),
                                              lambda: _readonly(_points_cells(new, step, cell)))
        i = np.minimum(np.searchsorted(self.cells, codes), len(self.cells) - 1)
        inside = pts[(self.cells[i] == codes) & others[i]]
        if len(inside) == 0:
            metres, frac = 0.0, 0.0
        else:
            metres = len(inside) * cfg.sample_m
            if metres < cfg.min_overlap_m:
                return None
            judged = inside[:: -(-len(inside) // MAX_JUDGED)]  # as _disagreement subsamples
            frac = float(np.mean(~self._near_kept(judged, kept[self.near_owner], keep is None)))
        if metres >= cfg.min_overlap_m and frac > cfg.max_disagree:
            return "fleet_walls", f"{100 * frac:.0f} % of {metres:.0f} m of walls in the fleet's free space"
        return None

    def _near_kept(self, pts: FloatArray, kept: NDArray[np.bool_], all_kept: bool) -> NDArray[np.bool_]:
        """Whether a kept near point lies within ``far_m + sample_m / 4`` of each of ``pts``
        (what the view's tree answers with a finite distance)."""
        tree = self.tree
        assert tree is not None
        bound = self.cfg.far_m + self.cfg.sample_m / 4
        n = tree.n
        if all_kept:
            d, _ = tree.query(pts, distance_upper_bound=bound)
            found: NDArray[np.bool_] = np.isfinite(d)
            return found
        kept_or_none = np.append(kept, False)  # index n: no neighbour
        out = np.zeros(len(pts), dtype=bool)
        todo = np.arange(len(pts))
        k = 4
        while len(todo):
            k = min(k, n)
            _, idx = tree.query(pts[todo], k=[*range(1, k + 1)], distance_upper_bound=bound)
            hit = kept_or_none[idx].any(axis=1)
            out[todo[hit]] = True
            if k >= n:
                break
            todo = todo[~hit & (idx[:, -1] < n)]  # k points within the bound, none kept: ask for more
            k *= 4
        return out


def _points_cells(wf: Wireframe, step: float, cell: float) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`wall_samples` of ``wf`` and their cells (:meth:`FleetSamples.judge`)."""
    pts = wall_samples(wf, step)
    return pts, _cell_codes(pts, cell)


def _cell_codes(xy: FloatArray, cell: float) -> NDArray[np.int64]:
    c = np.floor(xy / cell).astype(np.int64)
    out: NDArray[np.int64] = (c[:, 0] << 32) + c[:, 1]
    return out


def against_history(
    new: Wireframe, old: Wireframe, seconds: float, reach_per_s: float, sensor_range: float,
    cfg: QuarantineConfig
) -> tuple[str, str] | None:
    """``(reason, detail)`` when ``new`` (a robot's map) contradicts ``old`` (its last accepted
    map of the same boot, ``seconds`` earlier, same frame), else None."""
    if old.n_vertices == 0 or new.n_vertices == 0:
        return None
    return _extent_jump(new, old, seconds, reach_per_s, sensor_range, cfg) or _history_walls(new, old, cfg)


def _extent_jump(
    new: Wireframe, old: Wireframe, seconds: float, reach_per_s: float, sensor_range: float,
    cfg: QuarantineConfig
) -> tuple[str, str] | None:
    """:func:`against_history`'s first test: walls farther beyond the old map's box than
    ``seconds`` of driving and the sensor's range could add."""
    lo, hi = old.points.min(axis=0), old.points.max(axis=0)
    grow = sensor_range + reach_per_s * max(0.0, seconds) + cfg.growth_slack_m
    beyond = float(np.max(np.maximum(lo - grow - new.points, new.points - hi - grow)))
    if beyond > 0:
        return "extent_jump", f"walls {beyond:.0f} m beyond what {seconds:.1f} s could add to its last map"
    return None


def _history_walls(
    new: Wireframe, old: Wireframe, cfg: QuarantineConfig, new_facts: MapFacts | None = None,
    old_facts: MapFacts | None = None
) -> tuple[str, str] | None:
    """:func:`against_history`'s second test: new walls within the old map's box, far from
    its walls. ``new_facts``, ``old_facts``: the maps' :class:`MapFacts` (keep the samples and
    the old map's k-d tree)."""
    lo, hi = old.points.min(axis=0), old.points.max(axis=0)
    pts = _samples_of(new, cfg.sample_m, new_facts)[0]
    inside = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    near = facts_of(old, old_facts).get(("near", cfg.sample_m / 2), lambda: _near(old, cfg))
    metres, frac = _disagreement(inside, near, cfg)
    if metres >= cfg.min_overlap_m and frac > cfg.max_disagree:
        return (
            "history_walls",
            f"{100 * frac:.0f} % of {metres:.0f} m of walls over {cfg.far_m:g} m from its last map",
        )
    return None


def edge_keys(wf: Wireframe) -> list[bytes]:
    """Each edge's two end points' coordinates as bytes (the same wall, exactly, has the same key)."""
    seg = np.ascontiguousarray(wf.segments().reshape(wf.n_edges, 4))
    keys = seg.view(np.dtype((np.void, 32))).ravel().tolist()
    return keys  # type: ignore[return-value]  # void items are bytes


def _keys_of(wf: Wireframe, facts: MapFacts | None) -> list[bytes]:
    """:func:`edge_keys`, kept in ``facts`` (when they are ``wf``'s)."""
    return facts_of(wf, facts).get(("keys",), lambda: edge_keys(wf))


def key_set(wf: Wireframe, facts: MapFacts | None = None) -> frozenset[bytes]:
    """The set of :func:`edge_keys` of ``wf`` (kept in ``facts``: a robot's accepted map is the
    old map of its next ones, and its keys were listed when it was the new one)."""
    return facts_of(wf, facts).get(("key_set",), lambda: frozenset(_keys_of(wf, facts)))


def _passes_itself(
    wf: Wireframe, seconds: float, reach_per_s: float, sensor_range: float, cfg: QuarantineConfig
) -> bool:
    """Whether :func:`against_history` passes a map judged against itself (the same arrays) for
    these parameters, known without computing it: when the growth it allows is not negative,
    ``far_m >= 1e-6``, the map has walls, ``sample_m > 0``, ``min_overlap_m > 0`` and
    ``max_disagree >= 0`` (each false for NaN). Why (tested against it):

    * ``extent_jump``: every point ``p`` lies in its own box ``[lo, hi]``, so ``lo - grow - p``
      and ``p - hi - grow`` are at most 0 when ``grow >= 0`` (floating-point subtraction is
      monotone and exact at equality), and ``beyond > 0`` is false; a NaN ``grow`` makes
      ``beyond`` NaN, also not above 0.
    * ``history_walls`` (as :func:`history_judge` decides it): the points in the overlap are
      all on walls of the old map, none can disagree, so either the overlap is under
      ``min_overlap_m`` (no verdict) or it holds a point and the disagreeing fraction is 0,
      not above ``max_disagree``.
    """
    grow = sensor_range + reach_per_s * max(0.0, seconds) + cfg.growth_slack_m
    return bool(
        not grow < 0 and cfg.far_m >= 1e-6 and wf.n_edges and cfg.sample_m > 0
        and cfg.min_overlap_m > 0 and cfg.max_disagree >= 0
    )


def history_judge(
    new: Wireframe, old: Wireframe, seconds: float, reach_per_s: float, sensor_range: float,
    cfg: QuarantineConfig, old_keys: Set[bytes] | None = None, new_facts: MapFacts | None = None,
    old_facts: MapFacts | None = None,
) -> tuple[str, str] | None:
    """:func:`against_history`'s verdict and detail (tested against it), without its k-d tree
    when the verdict cannot depend on it (issue 21).

    A wireframe grows: most of a robot's new walls are walls of its last map, exactly (the
    same end points). A point of such a wall lies within ``sample_m / 4`` of the old map's
    points (:func:`_near`), so it agrees whenever ``far_m`` is positive. Only the points of
    the other walls can disagree: when they are too few to pass ``max_disagree`` even if all
    disagreed, or the overlap is too short to judge, the map passes without the tree;
    otherwise its wall test judges it (:func:`_history_walls`). ``old_keys``: :func:`edge_keys`
    of ``old`` (computed when not given). ``new_facts``, ``old_facts``: the maps'
    :class:`MapFacts`, where the samples and the old map's k-d tree are kept. When ``new`` *is*
    ``old`` (a map sent again: the fusion hands on the same object, :mod:`~agents.fleet.fusion.facts`)
    every wall is an old wall, without comparing the keys; with the thresholds of any sensible
    configuration (:func:`_passes_itself`) such a map passes without a test."""
    if old.n_vertices == 0 or new.n_vertices == 0:
        return None
    if new is old and _passes_itself(new, seconds, reach_per_s, sensor_range, cfg):
        return None
    jump = _extent_jump(new, old, seconds, reach_per_s, sensor_range, cfg)
    if jump is not None:
        return jump
    if not cfg.far_m >= 1e-6 or new.n_edges == 0:  # a point on an old wall agrees with room to spare
        return _history_walls(new, old, cfg, new_facts, old_facts)
    lo, hi = old.points.min(axis=0), old.points.max(axis=0)
    pts, owner = _samples_of(new, cfg.sample_m, new_facts)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    n_inside = int(np.count_nonzero(inside))
    if n_inside * cfg.sample_m < cfg.min_overlap_m:
        return None
    if n_inside == 0:  # only with min_overlap_m <= 0: as the reference does
        return _history_walls(new, old, cfg, new_facts, old_facts)
    if new is old:  # the same arrays: every key is an old key
        kept = np.ones(new.n_edges, dtype=bool)
    else:
        known = old_keys if old_keys is not None else key_set(old, old_facts)
        kept = np.fromiter((k in known for k in _keys_of(new, new_facts)), dtype=bool, count=new.n_edges)
    judged = owner[inside][:: -(-n_inside // MAX_JUDGED)]  # as _disagreement subsamples
    if float(np.mean(~kept[judged])) <= cfg.max_disagree:
        return None  # even if every new wall's point disagreed
    return _history_walls(new, old, cfg, new_facts, old_facts)


def against_fleet(new: Wireframe, fleet: FleetView, cfg: QuarantineConfig) -> tuple[str, str] | None:
    """``(reason, detail)`` when ``new`` (a robot's map, fleet frame) puts walls where the
    other robots (``fleet``, :meth:`FleetView.of` their walls) have seen free space, else None."""
    if new.n_edges == 0 or len(fleet.cells) == 0:
        return None
    pts = wall_samples(new, cfg.sample_m)
    inside = pts[np.isin(_cell_codes(pts, cfg.cell_m), fleet.cells)]
    metres, frac = _disagreement(inside, fleet.near, cfg)
    if metres >= cfg.min_overlap_m and frac > cfg.max_disagree:
        return "fleet_walls", f"{100 * frac:.0f} % of {metres:.0f} m of walls in the fleet's free space"
    return None


def others_walls(fused: Wireframe, bit: int | None) -> Wireframe:
    """The fused map's edges some robot other than contributor ``bit`` reported (all of them
    when ``bit`` is None)."""
    keep = _others_keep(fused, bit)
    if keep is None:
        return fused
    return Wireframe(fused.points, fused.labels, fused.edges[keep], fused.likelihood[keep],
                     fused.sources[keep])


def _others_keep(fused: Wireframe, bit: int | None) -> NDArray[np.bool_] | None:
    """Which edges :func:`others_walls` keeps (None: all of them, the map itself)."""
    if bit is None or fused.n_edges == 0:
        return None
    if fused.sources.dtype == object or bit >= 64:  # masks past bit 63: Python ints
        mine = 1 << bit
        return np.array([(int(s) & ~mine) != 0 for s in fused.sources.tolist()], dtype=bool)
    keep: NDArray[np.bool_] = (fused.sources & ~(np.uint64(1) << np.uint64(bit))) != 0
    return keep
