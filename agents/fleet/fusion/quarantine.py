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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

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
    seg = wf.points[wf.edges]
    length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
    k = np.maximum(1, np.ceil(length / step).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k) + 0.5) / k[owner]
    out: FloatArray = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
    return out, owner


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

    @classmethod
    def of(cls, fused: Wireframe, cfg: QuarantineConfig) -> FleetSamples:
        near, near_owner = _samples(fused, cfg.sample_m / 2)
        ref, ref_owner = _samples(fused, cfg.sample_m)
        return cls(fused, cfg, near, near_owner, _cell_codes(ref, cfg.cell_m), ref_owner)

    def view(self, bit: int | None) -> FleetView:
        """``FleetView.of(others_walls(self.fused, bit), self.cfg)``, from the samples."""
        keep = _others_keep(self.fused, bit)
        pts = self.near_points if keep is None else self.near_points[keep[self.near_owner]]
        codes = self.cell_codes if keep is None else self.cell_codes[keep[self.cell_owner]]
        near = cKDTree(pts, balanced_tree=False, compact_nodes=False) if len(pts) else None
        return FleetView(near, np.unique(codes))


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
    lo, hi = old.points.min(axis=0), old.points.max(axis=0)
    grow = sensor_range + reach_per_s * max(0.0, seconds) + cfg.growth_slack_m
    beyond = float(np.max(np.maximum(lo - grow - new.points, new.points - hi - grow)))
    if beyond > 0:
        return "extent_jump", f"walls {beyond:.0f} m beyond what {seconds:.1f} s could add to its last map"
    pts = wall_samples(new, cfg.sample_m)
    inside = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    metres, frac = _disagreement(inside, _near(old, cfg), cfg)
    if metres >= cfg.min_overlap_m and frac > cfg.max_disagree:
        return (
            "history_walls",
            f"{100 * frac:.0f} % of {metres:.0f} m of walls over {cfg.far_m:g} m from its last map",
        )
    return None


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
