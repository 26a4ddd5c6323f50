"""Wireframe merging (paper Sec. IV-E): the union of two wireframes, simplified.

The particle filter merges every (pose-corrected) scan into every particle, and the fleet's fusion
service merges whole robot maps into one fused map; both call :func:`merge`.

Overview of one merge (details and the choices made where the paper is silent are in
:func:`merge`'s Notes):

1. **Local part.** Only base edges whose bounding box meets the bounding box of ``new`` grown by
   ``2 * threshold`` (and the vertices they use) take part; everything else of ``base`` is
   re-appended untouched, so the cost follows the size of ``new``, not of the map.
2. **Vertex correspondence.** Base and new corners closer than ``threshold`` are paired
   one-to-one (cKDTree candidates, ``linear_sum_assignment`` when ambiguous) and combined --
   never the corners of the two faces of a wall about as thick as the threshold.
3. **Collinear groups.** Edges of the same direction, on the same line (within ``threshold``)
   and overlapping or touching in projection are grouped (transitively); a short noisy piece
   further off in direction only when it lies along the other edge's segment. Small inputs
   test all pairs; large ones (whole-map fusion) take candidate pairs from a uniform grid.
4. **Group resolution.** Each group becomes one wall from its farthest start to its farthest
   end; corners inside it vanish unless a wall leaves them into free space (a T-junction),
   where the wall is split. Likelihoods combine as ``1 - prod(1 - L)``, sources are OR-ed.
5. **Clean-up.** Every resolved wall must point like an edge it came from (else the split or
   the group is undone); degenerate, reversed and duplicate edges are combined or removed,
   unused corners dropped. :func:`merge_traced` also returns where each wall came from.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import reduce

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from mapping.wireframe import Label, Wireframe

__all__ = ["MergeConfig", "merge", "merge_all", "merge_traced", "normalize"]

_NOMINAL = int(Label.NOMINAL)
_FRONTIER = int(Label.FRONTIER)
_DENSE_SNAP_MAX = 4096  # candidate vertex pairs from a dense distance matrix up to this many entries
_DENSE_PAIRS_MAX = 160
_COS_45 = math.sqrt(0.5)
_DENSE_NEAR_MAX = 20000  # (corner, wall) pairs tested densely up to this many, else via a grid  # all edge pairs are tested up to this many local edges, else angle windows


@dataclass(frozen=True)
class MergeConfig:
    """Parameters of :func:`merge`.

    Parameters
    ----------
    threshold : float
        The merge threshold in metres (paper Sec. IV-E and V-A: 0.2 m for the small world, 0.4 m
        for the museum). It is the single length scale of the merge: corners closer than it are
        combined, a corner closer than it to a wall lies *on* the wall, collinear walls may be
        this far off each other's line, and collinear walls with a gap up to it are joined.
    angle_tol : float
        Collinearity tolerance in radians (default 10 degrees): two edges are parallel when
        their directions differ by at most this; in (0, pi/4].
    snap_to_lines : bool
        When true (default), a T-junction corner whose position comes from ``new`` and that
        splits a wall of ``base`` is moved onto that wall's line (onto the least-squares
        intersection when it splits two), if that moves it by at most ``threshold``: the split
        wall stays straight. Wall *ends* are never moved onto a line: beyond or near the end of a
        base wall its line is an extrapolation whose error grows with every extension (a wall
        growing scan by scan would drift), and the measured corner is as good. Corners already in
        ``base`` never move.
    cull : bool
        When true (default), only the part of ``base`` near ``new`` is processed (see the
        module docstring). ``False`` processes (normalises) the whole of ``base``, which is
        slower and only differs from the default where ``base`` itself is not normalised.

    Raises
    ------
    ValueError
        When ``threshold`` is not a positive finite number or ``angle_tol`` is outside (0, pi/4].
    """

    threshold: float = 0.2
    angle_tol: float = math.radians(10.0)
    snap_to_lines: bool = True
    cull: bool = True

    def __post_init__(self) -> None:
        thr = float(self.threshold)
        if not math.isfinite(thr) or thr <= 0.0:
            raise ValueError(f"merge threshold must be a positive number of metres, got {self.threshold!r}")
        tol = float(self.angle_tol)
        if not math.isfinite(tol) or not 0.0 < tol <= math.pi / 4.0:
            raise ValueError(f"angle_tol must be in (0, pi/4] radians, got {self.angle_tol!r}")
        object.__setattr__(self, "threshold", thr)
        object.__setattr__(self, "angle_tol", tol)


def normalize(wf: Wireframe, config: MergeConfig | None = None) -> Wireframe:
    """The merge simplification applied to one wireframe: ``merge(Wireframe.empty(), wf, config)``.

    Collinear overlapping walls are joined, interior frontier corners removed, T-junctions split,
    lone corners dropped. A normalised wireframe ``W`` satisfies ``merge(W, W)`` has the same
    corners and walls as ``W``.
    """
    return merge(Wireframe.empty(), wf, config)


def merge_all(wireframes: list[Wireframe], config: MergeConfig | None = None) -> Wireframe:
    """Left fold of :func:`merge` over ``wireframes`` in the given order (empty list: empty map).

    Fusion services that want an order-independent result should call this with the maps in a
    canonical order (e.g. sorted by robot id).
    """
    out = Wireframe.empty()
    for wf in wireframes:
        out = merge(out, wf, config)
    return out


# ---------------------------------------------------------------------------------------------
# helpers


def _snap_pairs(
    pb: NDArray[np.float64],
    pn: NDArray[np.float64],
    lab_b: NDArray[np.int64],
    lab_n: NDArray[np.int64],
    thr: float,
    allowed: Callable[[NDArray[np.intp], NDArray[np.intp]], NDArray[np.bool_]] | None = None,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """One-to-one pairs ``(rows into pb, cols into pn)`` within ``thr`` to combine.

    ``allowed(rows, cols)`` may veto candidate pairs before the assignment.

    Two frontiers take part in the assignment (so a frontier is not paired with another corner
    when the other wireframe has a frontier right there: merging the same scan twice stays a
    fixed point) but are not returned: frontiers are reconciled along their walls instead.
    """
    empty = np.zeros(0, dtype=np.intp)
    if len(pb) == 0 or len(pn) == 0:
        return empty, empty
    if len(pb) * len(pn) <= _DENSE_SNAP_MAX:
        d = np.hypot(pb[:, None, 0] - pn[None, :, 0], pb[:, None, 1] - pn[None, :, 1])
        r, c = np.nonzero(d <= thr)
        dist = d[r, c]
    else:
        sdm = cKDTree(pb).sparse_distance_matrix(cKDTree(pn), thr, output_type="ndarray")
        order = np.lexsort((sdm["j"], sdm["i"]))
        r = sdm["i"][order].astype(np.intp)
        c = sdm["j"][order].astype(np.intp)
        dist = sdm["v"][order]
    if len(r) and allowed is not None:
        keep = allowed(r, c)
        r, c, dist = r[keep], c[keep], dist[keep]
    if len(r) == 0:
        return empty, empty
    # r is sorted (nonzero / lexsort order): unique rows iff strictly increasing
    if not ((len(r) == 1 or bool(np.all(r[1:] != r[:-1]))) and int(np.bincount(c).max()) <= 1):
        ur, ri = np.unique(r, return_inverse=True)
        uc, ci = np.unique(c, return_inverse=True)
        big = 1e6 * (1.0 + thr)
        cost = np.full((len(ur), len(uc)), big)
        # among candidates, a corner prefers one with its own label (a nominal corner should
        # pair with the nominal corner of the new scan, not with a frontier that is closer)
        cost[ri, ci] = dist + thr * (lab_b[r] != lab_n[c])
        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] < big
        r, c = ur[rows[keep]].astype(np.intp), uc[cols[keep]].astype(np.intp)
    ok = (lab_b[r] != _FRONTIER) | (lab_n[c] != _FRONTIER)
    return r[ok], c[ok]


def _related(
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    u: NDArray[np.float64],
    length: NDArray[np.float64],
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    thr: float,
    cos_tol: float,
    a0: NDArray[np.float64],
    b0: NDArray[np.float64],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Filter pairs ``(i, j)`` to the collinear, same-direction, overlapping-or-touching ones.

    ``a``, ``b`` are the edges' ends after corners were combined, ``a0``, ``b0`` as measured.

    Two kinds of pair are related (see :func:`merge`, Notes, "Collinear groups"):

    * *parallel* (directions within ``angle_tol``): both ends of the shorter edge within ``thr``
      of the longer edge's line, and their extents along it overlapping or leaving a gap of at
      most ``thr`` (a wall continued by the next scan) -- also as measured: combining corners
      moves an end by up to ``thr``, and must not let a wall then bridge a wider gap;
    * *noisy* (a short edge up to 45 degrees off, its extent across the longer one's direction
      at most ``thr``): only when the short edge lies *along* the longer one -- both of its ends
      within ``thr`` of the longer edge's segment, not merely of its infinite line. A short wall
      bending away at the end of a long one (a door jamb next to a line-of-sight edge) is not a
      noisy piece of it.
    """
    cos = u[i, 0] * u[j, 0] + u[i, 1] * u[j, 1]
    shortest = np.minimum(length[i], length[j])
    sin = np.abs(u[i, 0] * u[j, 1] - u[i, 1] * u[j, 0])
    parallel = cos >= cos_tol
    same = parallel | ((cos >= _COS_45) & (shortest * sin <= thr))
    i, j, parallel = i[same], j[same], parallel[same]
    if len(i) == 0:
        return i, j
    swap = length[j] > length[i]
    lg = np.where(swap, j, i)  # the longer edge defines the line
    sh = np.where(swap, i, j)
    ul, al, ll = u[lg], a[lg], length[lg]
    ds, de = a[sh] - al, b[sh] - al
    off_s = ul[:, 0] * ds[:, 1] - ul[:, 1] * ds[:, 0]
    off_e = ul[:, 0] * de[:, 1] - ul[:, 1] * de[:, 0]
    ts = ul[:, 0] * ds[:, 0] + ul[:, 1] * ds[:, 1]
    te = ul[:, 0] * de[:, 0] + ul[:, 1] * de[:, 1]
    gap = np.maximum(ts - ll, -te)
    # the same gap between the ends as measured, along the same line
    def along_line(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(ul[:, 0] * (p[:, 0] - al[:, 0]) + ul[:, 1] * (p[:, 1] - al[:, 1]), dtype=np.float64)

    l0, l1 = along_line(a0[lg]), along_line(b0[lg])
    s0, s1 = along_line(a0[sh]), along_line(b0[sh])
    gap0 = np.maximum(np.minimum(s0, s1) - np.maximum(l0, l1), np.minimum(l0, l1) - np.maximum(s0, s1))
    on_line = (np.abs(off_s) <= thr) & (np.abs(off_e) <= thr)
    # distance of each end of the short edge to the long edge's segment
    out_s = np.maximum(np.maximum(-ts, ts - ll), 0.0)
    out_e = np.maximum(np.maximum(-te, te - ll), 0.0)
    along = (np.hypot(off_s, out_s) <= thr) & (np.hypot(off_e, out_e) <= thr)
    ok = on_line & np.where(parallel, gap <= thr, along) & (gap0 <= thr)
    return i[ok], j[ok]


def _cell_entries(
    lo: NDArray[np.float64], hi: NDArray[np.float64], cell: float, origin: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(owner, cell key)`` for every grid cell each box ``[lo, hi]`` touches."""
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    nx = c1[:, 0] - c0[:, 0] + 1
    cnt = nx * (c1[:, 1] - c0[:, 1] + 1)
    owner = np.repeat(np.arange(len(lo), dtype=np.int64), cnt)
    r = np.arange(int(cnt.sum()), dtype=np.int64) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    nxr = np.repeat(nx, cnt)
    cx = np.repeat(c0[:, 0], cnt) + r % nxr
    cy = np.repeat(c0[:, 1], cnt) + r // nxr
    return owner, cx * (1 << 31) + cy


def _box_pairs(
    lo1: NDArray[np.float64],
    hi1: NDArray[np.float64],
    lo2: NDArray[np.float64] | None,
    hi2: NDArray[np.float64] | None,
    cell: float,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Candidate pairs of boxes that share a grid cell (a superset of the overlapping pairs).

    With ``lo2 is None`` the pairs ``i < j`` within the first set, else pairs ``(i, j)`` of a box
    of the first set and one of the second. Sorted, without duplicates. The cost follows the
    number of (box, cell) incidences and of pairs sharing a cell, not the product of the sizes.
    """
    same = lo2 is None
    if lo2 is None or hi2 is None:
        lo2, hi2 = lo1, hi1
    n2 = len(lo2)
    origin = np.minimum(lo1.min(axis=0), lo2.min(axis=0))
    # keep the number of (box, cell) incidences linear in the input (long diagonal boxes)
    budget = 32 * (len(lo1) + len(lo2)) + 4096
    ext = np.concatenate([hi1 - lo1, hi2 - lo2]) if not same else hi1 - lo1
    while float(np.prod(np.floor(ext / cell) + 2.0, axis=1).sum()) > budget:
        cell *= 2.0
    o1, k1 = _cell_entries(lo1, hi1, cell, origin)
    o2, k2 = (o1, k1) if same else _cell_entries(lo2, hi2, cell, origin)
    order = np.argsort(k2, kind="stable")
    o2s, k2s = o2[order], k2[order]
    left = np.searchsorted(k2s, k1, side="left")
    right = np.searchsorted(k2s, k1, side="right")
    cnt = right - left
    first = np.repeat(o1, cnt)
    idx = np.repeat(left, cnt) + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    second = o2s[idx]
    if same:
        keep = first < second
        first, second = first[keep], second[keep]
    key = np.unique(first * n2 + second)
    return (key // n2).astype(np.intp), (key % n2).astype(np.intp)


_UPPER: dict[int, tuple[NDArray[np.intp], NDArray[np.intp]]] = {}


def _upper_pairs(k: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``np.triu_indices(k, 1)``, cached (read-only arrays)."""
    got = _UPPER.get(k)
    if got is None:
        i, j = np.triu_indices(k, 1)
        i.setflags(write=False)
        j.setflags(write=False)
        got = _UPPER[k] = (i, j)
    return got


def _not_other_face(
    pos: NDArray[np.float64], edges: NDArray[np.int64], nlb: int, thr: float, cos_tol: float
) -> Callable[[NDArray[np.intp], NDArray[np.intp]], NDArray[np.bool_]]:
    """Veto for :func:`_snap_pairs`: a base corner and a new corner (local ids ``r`` and
    ``nlb + c``) are not combined when a wall at one and a wall at the other point in opposite
    directions (within ``angle_tol``) along lines more than ``thr / 4`` apart: they are the two
    faces of a thick wall (or the two sides of a narrow gap), whose corners may lie within the
    threshold of each other, not two sightings of one corner. Two faces of a *thin* wall lie on
    one line and still share their corners."""

    def allowed(r: NDArray[np.intp], c: NDArray[np.intp]) -> NDArray[np.bool_]:
        out = np.ones(len(r), dtype=bool)
        if len(edges) == 0:
            return out
        a = pos[edges[:, 0]]
        d = pos[edges[:, 1]] - a
        n = np.hypot(d[:, 0], d[:, 1])
        u = d / np.where(n > 0.0, n, 1.0)[:, None]
        # vertex -> its edges, as slices of one sorted incidence list
        inc_v = np.concatenate([edges[:, 0], edges[:, 1]])
        inc_e = np.concatenate([np.arange(len(edges)), np.arange(len(edges))])
        order = np.argsort(inc_v, kind="stable")
        inc_v, inc_e = inc_v[order], inc_e[order]
        lo_r, hi_r = np.searchsorted(inc_v, r, "left"), np.searchsorted(inc_v, r, "right")
        lo_c, hi_c = np.searchsorted(inc_v, c + nlb, "left"), np.searchsorted(inc_v, c + nlb, "right")
        # every (candidate, base edge at its base corner, new edge at its new corner) triple
        nr, nc = hi_r - lo_r, hi_c - lo_c
        per = nr * nc
        k = np.repeat(np.arange(len(r)), per)
        if len(k) == 0:
            return out
        local = np.arange(len(k)) - np.repeat(np.cumsum(per) - per, per)
        fb = inc_e[lo_r[k] + local // nc[k]]
        fn = inc_e[lo_c[k] + local % nc[k]]
        ub, un = u[fb], u[fn]
        anti = ub[:, 0] * un[:, 0] + ub[:, 1] * un[:, 1] <= -cos_tol  # pointing opposite ways
        rel = a[fn] - a[fb]
        off = np.abs(ub[:, 0] * rel[:, 1] - ub[:, 1] * rel[:, 0])  # apart across the base wall
        veto = anti & (off > 0.25 * thr)
        if veto.any():
            out[np.unique(k[veto])] = False
        return out

    return allowed


def _pick_ends(
    starts: list[int],
    ends: list[int],
    pos: list[list[float]],
    dirs: list[list[float]],
    cos_tol: float,
) -> tuple[int, int] | None:
    """The first ``(s, e)`` (starts outer, ends inner, in the given preference order) whose
    wall ``pos[s] -> pos[e]`` lies within the angle of ``cos_tol`` of one of ``dirs``."""
    units = [(d[0] / n, d[1] / n) for d in dirs if (n := math.hypot(d[0], d[1])) > 0.0]
    for s in starts:
        sx, sy = pos[s]
        for e in ends:
            if e == s:
                continue
            dx, dy = pos[e][0] - sx, pos[e][1] - sy
            lim = cos_tol * math.hypot(dx, dy)
            if lim > 0.0 and any(ux * dx + uy * dy >= lim for ux, uy in units):
                return s, e
    return None


def _may_absorb(
    rv: int,
    rt: int,
    eds: list[int],
    vclass: dict[int, list[int]],
    inc_of: dict[int, list[int]],
    edges: list[list[int]],
    pos: list[list[float]],
    raw: list[list[float]],
    parent: list[int],
    cos_tol: float,
    pos0: list[list[float]],
    mate: list[int],
    thr: float,
) -> bool:
    """Whether the corners of class ``rv`` may join class ``rt`` (and move to ``pos[rt]``):

    * all the measured positions of the corners of both classes (``pos0[x]``, and ``pos0`` of
      the corner ``mate[x]`` combined with it) lie within ``thr`` of each other, so that
      no chain of combinations moves a corner farther than the threshold;
    * every wall of the moved corners other than ``eds`` (the group being resolved) still
      points within the angle of ``cos_tol`` of its measured direction ``raw`` (or collapses
      to nothing and is removed).
    """
    ids = [*vclass.get(rv, [rv]), *vclass.get(rt, [rt])]
    pts = [pos0[x] for x in ids] + [pos0[mate[x]] for x in ids if mate[x] >= 0]
    for i in range(len(pts)):
        for j in range(i):
            if math.hypot(pts[i][0] - pts[j][0], pts[i][1] - pts[j][1]) > thr:
                return False
    tx, ty = pos[rt]
    skip = set(eds)
    for v in vclass.get(rv, [rv]):
        for f in inc_of.get(v, ()):
            if f in skip:
                continue
            x, y = edges[f]
            if x == v:
                w = _find(parent, y)
                if w in (rv, rt):
                    continue
                dx, dy = pos[w][0] - tx, pos[w][1] - ty
            else:
                w = _find(parent, x)
                if w in (rv, rt):
                    continue
                dx, dy = tx - pos[w][0], ty - pos[w][1]
            if raw[f][0] * dx + raw[f][1] * dy < cos_tol * math.hypot(dx, dy) * math.hypot(*raw[f]):
                return False
    return True


def _find(parent: list[int], x: int) -> int:
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        parent[x], x = root, parent[x]
    return root


def _combine(liks: list[float]) -> float:
    """``1 - prod(1 - L)`` (paper Sec. IV-E), clipped to [0, 1] against rounding."""
    q = 1.0
    for lk in liks:
        q *= 1.0 - lk
    return min(1.0, max(0.0, 1.0 - q))


# ---------------------------------------------------------------------------------------------
# the merge


def merge(base: Wireframe, new: Wireframe, config: MergeConfig | None = None) -> Wireframe:
    """Merge ``new`` into ``base`` (paper Sec. IV-E); both must be in the same (world) frame.

    Parameters
    ----------
    base : Wireframe
        The current map (a particle, or the fused map). Its corners are the stable reference.
    new : Wireframe
        A scan already moved by the estimated pose, or another robot's map.
    config : MergeConfig, optional
        Thresholds; ``MergeConfig()`` when omitted.

    Returns
    -------
    Wireframe
        The merged wireframe. Vertex order: the surviving base corners in their order, then the
        surviving new corners in theirs. Edge order: the untouched (non-local) base edges in their
        order, then the merged local edges.

    Notes
    -----
    The paper (Sec. IV-E) gives the rules: corresponding corners within the merge threshold are
    combined; a corner falling on an edge is absorbed (no neighbour: removed and the collinear
    edges joined; neighbour on the same edge: the shorter edge absorbed; neighbour beyond the
    end: one edge spanning the two most distant end points); the result is a union; merged edge
    likelihoods are ``L = 1 - (1 - L1)(1 - L2)``. Edges of opposite direction are never merged
    (Sec. III-A, Fig. 5). The choices made where it is silent:

    * **Lone corners.** Corners of ``new`` without an edge are ignored, and local corners left
      without an edge are removed: a lone corner carries no wall and cannot be checked by a
      later scan. Base corners away from ``new`` are left as they are, used or not.
    * **Correspondence.** Pairs (base corner, new corner) within ``threshold`` (inclusive) are
      matched one-to-one. Without conflicts every candidate pair is taken; otherwise
      ``linear_sum_assignment`` on the candidate pairs with cost ``distance + threshold *
      [labels differ]`` (the most pairs, then same labels first, then the least distance: a
      base corner prefers the scan's nominal corner to a frontier that happens to be closer).
      Corners of the same wireframe are never combined by distance alone. Two *frontier*
      corners are never paired by distance: a frontier is not a corner but where sight of a
      wall ended, so two frontiers on one wall are reconciled by the wall (below), which keeps
      the farther one and lets the wall grow even when the robot advances less than
      ``threshold`` per scan.
    * **Combined corner.** Label: nominal beats occlusion beats frontier (a corner once seen as
      a real corner is a corner). Position: the one with the better label; for equal labels the
      base's (the map stays stable, and ``merge(merge(A, B), B)`` equals ``merge(A, B)``).
      No per-corner weights or averaging.
    * **Glimpses.** An edge shorter than ``threshold`` with a frontier end (a wall seen for
      less than the map's resolution: no reliable direction, no corner) is dropped.
    * **Opposite faces.** A base corner and a new corner are not combined when a wall at one
      and a wall at the other point in opposite directions (within ``angle_tol``) along lines
      more than ``threshold / 4`` apart: they are the two faces of a wall about as thick as
      the threshold (or the two sides of a narrow gap), not one corner seen twice; combining
      them would fold the wall into one line. The faces of a *thin* wall, on one line, still
      share their corners.
    * **Collinear groups.** Two edges are related when they point the same way and lie on one
      line (both ends of the shorter within ``threshold`` of the longer's line), either
      *parallel* (directions within ``angle_tol``) with projections on that line that overlap
      or leave a gap of at most ``threshold`` -- the gap also measured between the ends as
      measured, before corners were combined (combining moves an end by up to ``threshold``
      and must not let a wall then bridge a wider gap) -- or, for a short edge whose direction
      is noisy, up to 45 degrees off with its extent across the other's direction at most
      ``threshold``, but only when it lies *along* the longer edge: both of its ends within
      ``threshold`` of the longer edge's *segment*. (A 0.26 m door jamb 18 degrees off a 2.6 m
      line-of-sight edge that ends at its foot lies near that edge's line, not along it: it is
      not absorbed.) Groups are the transitive closure over *all* local edges (base, new, and
      both mixed), so a chain of collinear edges through a corner with nothing else attached is
      a group too and is joined.
    * **Group resolution.** Positions along the group are measured on the line of its
      reference edge (the longest base edge, else the longest edge). ``t0``/``t1`` are the
      smallest and largest positions of the group's corners. The start is chosen among the
      group's corners within ``threshold`` of ``t0``: best label; then, for real corners, base
      before new (a stable map) and for frontiers the farthest out (the wall grows); then
      farthest out, base first, lowest index. The end likewise near ``t1``. The first (start,
      end) in that order whose wall points within ``angle_tol`` of one of the group's edges as
      measured is taken; when none does (a short group of noisy pieces) the group's edges are
      left as they are. The other corners near either end are absorbed into that end (their
      other walls are re-attached to it) unless that would move a corner more than
      ``threshold`` from where any corner combined with it was measured (chains of
      combinations) or turn one of its other walls by more than ``angle_tol``.
      Corners strictly inside ``(t0 + threshold, t1 - threshold)`` leave the wall --
      frontiers always (the wall was seen to continue: the frontier disappears), others unless
      they are a T-junction. The resolved wall runs from the start corner to the end corner
      as they are (no line fit); see ``MergeConfig.snap_to_lines`` for T-junctions.
    * **T-junctions.** A corner (of either wireframe, not a frontier) within ``threshold`` of a
      wall's interior with another wall leaving it *into the wall's free side* (its left) splits
      the wall there and becomes nominal. Walls leaving into the solid side do not split: they
      belong to the other face of a thin or thick wall, or to the next room (so the corridor
      face of a thin wall stays one edge where an office wall meets its back). Each piece of a
      split wall combines the likelihoods of the edges that cover it (more than half of the
      piece or more than ``threshold`` of it; an edge covering no piece that much counts for
      the piece it overlaps most). With the final corner positions, a piece that does not point
      within ``angle_tol`` of one of the edges covering it (a split corner off the line, not
      snapped) undoes the split at the corner farther off the line; a wall that still does not
      point like its edges leaves them as they are. ``snap_to_lines`` never moves a corner
      more than ``threshold`` from where it (or the corner combined with it) was measured, nor
      when that would turn a wall ending there by more than ``angle_tol``.
    * **Clean-up.** Edges that end where they start (or have zero length) after combining
      corners are removed, and so are edges turned around by it (their ends were within the
      threshold of each other and moved past each other); duplicate directed edges are
      combined like any merge.
    * **Not handled here.** A false-positive wall (e.g. joining an occlusion to its frontier) is
      kept like any wall (the union); the filter's mutation step (Sec. IV-F) removes it. A
      frontier that leaves a wall but still has such an edge stays as that edge's end.

    Properties (tested): ``merge(W, W)`` has the corners and walls of ``W`` with likelihoods
    ``1 - (1 - L)^2`` when ``W`` is normalised (see :func:`normalize`); ``merge(merge(A, B), B)``
    has the geometry of ``merge(A, B)``; the result is deterministic. With the provenance of
    :func:`merge_traced`: a wall built from several input walls points within ``angle_tol`` of
    one of them (up to the turn ``asin(2 threshold / length)`` that combining corners may give
    an input wall), never the other way round, and leaves no gap longer than the threshold
    that none of them covered.

    References
    ----------
    Wireframe Mapping for Resource-Constrained Robots, Sec. III-A (labels, directions),
    IV-C (correspondences), IV-E (merging).
    """
    return _merge(base, new, config if config is not None else MergeConfig(), False)[0]


def merge_traced(
    base: Wireframe, new: Wireframe, config: MergeConfig | None = None
) -> tuple[Wireframe, list[list[int]]]:
    """:func:`merge`, and where each resulting wall came from.

    Returns
    -------
    merged : Wireframe
        Exactly ``merge(base, new, config)``.
    provenance : list of list of int
        For each edge of ``merged``, the input edges combined into it, sorted: ``k < m`` is
        ``base`` edge ``k`` and ``m + k`` is ``new`` edge ``k`` (``m = base.n_edges``). A wall
        split at a T-junction lists, for each piece, the edges that overlap that piece.
        Used to test what the merge may create (tests/test_merge.py) and to debug maps.
    """
    return _merge(base, new, config if config is not None else MergeConfig(), True)


def _merge(
    base: Wireframe, new: Wireframe, cfg: MergeConfig, trace: bool
) -> tuple[Wireframe, list[list[int]]]:
    """The body of :func:`merge`; with ``trace`` also the provenance of :func:`merge_traced`."""
    thr = cfg.threshold
    cos_tol = math.cos(cfg.angle_tol)
    sin_tol = math.sin(cfg.angle_tol)

    if new.n_edges == 0:
        return base, [[k] for k in range(base.n_edges)] if trace else []
    new = new.compacted()
    nb, nn = base.n_vertices, new.n_vertices
    mb = base.n_edges

    # ---- 1. the local part of base ------------------------------------------------------------
    if cfg.cull and mb:
        grow = 2.0 * thr
        lo = new.points.min(axis=0) - grow
        hi = new.points.max(axis=0) + grow
        seg = base.points[base.edges]
        smin, smax = seg.min(axis=1), seg.max(axis=1)
        local_e = (
            (smax[:, 0] >= lo[0]) & (smax[:, 1] >= lo[1]) & (smin[:, 0] <= hi[0]) & (smin[:, 1] <= hi[1])
        )
        bp = base.points
        local_v = (bp[:, 0] >= lo[0]) & (bp[:, 1] >= lo[1]) & (bp[:, 0] <= hi[0]) & (bp[:, 1] <= hi[1])
    else:
        local_e = np.ones(mb, dtype=bool)
        local_v = np.ones(nb, dtype=bool)
    local_v[base.edges[local_e].reshape(-1)] = True
    lb = np.flatnonzero(local_v)
    nlb = len(lb)
    nl = nlb + nn

    pos = np.concatenate([base.points[lb], new.points])
    lab = np.concatenate([base.labels[lb], new.labels]).astype(np.int64)
    is_new = np.zeros(nl, dtype=bool)
    is_new[nlb:] = True
    fixed = ~is_new  # position taken from base

    g2l = np.full(nb, -1, dtype=np.int64)
    g2l[lb] = np.arange(nlb)

    # ---- 2. vertex correspondence ---------------------------------------------------------------
    edges = np.concatenate([g2l[base.edges[local_e]], new.edges.astype(np.int64) + nlb])
    # glimpses: shorter than thr with a frontier end, as observed (before corners are combined):
    # the wall was seen for less than the map's resolution, no reliable direction, no corner
    ea, eb = pos[edges[:, 0]], pos[edges[:, 1]]
    glimpse = ((lab[edges[:, 0]] == _FRONTIER) | (lab[edges[:, 1]] == _FRONTIER)) & (
        np.hypot(eb[:, 0] - ea[:, 0], eb[:, 1] - ea[:, 1]) < thr
    )

    pos0 = pos.copy()  # positions as measured, before corners are combined
    raw_a = pos0[edges[:, 0]]  # edge starts and directions as measured
    raw_d = pos0[edges[:, 1]] - raw_a
    snap = np.arange(nl)
    mate = np.full(nl, -1, dtype=np.int64)  # the new corner each base corner was combined with
    r, c = _snap_pairs(pos[:nlb], pos[nlb:], lab[:nlb], lab[nlb:], thr, _not_other_face(pos, edges, nlb, thr, cos_tol))
    if len(r):
        cn = c + nlb
        better = lab[cn] < lab[r]
        pos[r[better]] = pos[cn[better]]
        fixed[r[better]] = False
        lab[r] = np.minimum(lab[r], lab[cn])
        snap[cn] = r
        mate[r] = cn

    edges = snap[edges]
    lik = np.concatenate([base.likelihood[local_e], new.likelihood])
    src = np.concatenate([base.sources[local_e], new.sources])
    e_new = np.zeros(len(edges), dtype=bool)
    e_new[int(local_e.sum()) :] = True
    orig = np.concatenate([np.flatnonzero(local_e), mb + np.arange(new.n_edges)])  # input edge ids

    a = pos[edges[:, 0]]
    b = pos[edges[:, 1]]
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    ok = (edges[:, 0] != edges[:, 1]) & (length > 0.0) & ~glimpse
    if not ok.all():
        edges, lik, src, e_new, orig = edges[ok], lik[ok], src[ok], e_new[ok], orig[ok]
        raw_a, raw_d = raw_a[ok], raw_d[ok]
        a, b, d, length = a[ok], b[ok], d[ok], length[ok]
    k = len(edges)
    u = d / np.where(length > 0.0, length, 1.0)[:, None]

    # ---- 3. collinear groups ------------------------------------------------------------------
    # candidate pairs: all of them for a few edges; else roughly the same direction and
    # bounding boxes within thr of each other
    if k <= _DENSE_PAIRS_MAX:
        pi_, pj_ = _upper_pairs(k)
    else:  # grid on the boxes grown by thr / 2, then the direction
        half = 0.5 * thr + 1e-12
        cell = max(4.0 * thr, float(np.median(length)))
        pi_, pj_ = _box_pairs(np.minimum(a, b) - half, np.maximum(a, b) + half, None, None, cell)
        same_dir = u[pi_, 0] * u[pj_, 0] + u[pi_, 1] * u[pj_, 1] >= _COS_45
        pi_, pj_ = pi_[same_dir], pj_[same_dir]
    pi_, pj_ = _related(a, b, u, length, pi_, pj_, thr, cos_tol, raw_a, raw_a + raw_d)
    eparent = list(range(k))
    for x, y in zip(pi_.tolist(), pj_.tolist()):
        rx, ry = _find(eparent, x), _find(eparent, y)
        if rx != ry:
            if rx < ry:
                eparent[ry] = rx
            else:
                eparent[rx] = ry
    comp = np.array([_find(eparent, x) for x in range(k)], dtype=np.int64) if k else np.zeros(0, np.int64)
    members: dict[int, list[int]] = {}
    for x in sorted({int(cx) for cx in comp[comp != np.arange(k)]}) if k else []:
        members[x] = []
    if members:
        for x in range(k):
            cx = int(comp[x])
            if cx in members:
                members[cx].append(x)

    # ---- 4a. spans of all groups (multi-edge groups in Python, singletons vectorised) --------
    vparent = list(range(nl))  # absorption of corners into wall ends
    lab_l = lab.tolist()
    is_new_l = is_new.tolist()
    pos_l = pos.tolist()
    a_l, b_l = a.tolist(), b.tolist()
    u_l = u.tolist()
    len_l = length.tolist()
    e_new_l = e_new.tolist()
    edges_l = edges.tolist()

    # per resolved multi-edge group: (component, start, end, base reference?, its length, edges)
    grp_info: list[tuple[int, int, int, bool, float, list[int]]] = []
    g_u: list[list[float]] = []
    g_o: list[list[float]] = []
    g_t0: list[float] = []
    g_t1: list[float] = []
    raw_l = raw_d.tolist()
    mate_l = mate.tolist()
    pos0_l = pos0.tolist()
    vclass: dict[int, list[int]] = {}  # absorbed corners per root (roots absorbing nothing: absent)
    inc_of: dict[int, list[int]] = {}  # local corner -> its edges (only filled for groups' corners)
    if members:
        for f, (x, y) in enumerate(edges_l):
            inc_of.setdefault(x, []).append(f)
            inc_of.setdefault(y, []).append(f)
    for cid, eds in members.items():
        ref = min(eds, key=lambda e: (e_new_l[e], -len_l[e], e))
        ux, uy = u_l[ref]
        ox, oy = a_l[ref]
        verts = sorted({v for e in eds for v in edges_l[e]})
        tv = {v: ux * (pos_l[v][0] - ox) + uy * (pos_l[v][1] - oy) for v in verts}
        t0 = min(tv.values())
        t1 = max(tv.values())
        # best label; real corners: base before new (a stable map), frontiers: farthest out
        starts = sorted(
            (v for v in verts if tv[v] <= t0 + thr),
            key=lambda v: (lab_l[v], lab_l[v] != _FRONTIER and is_new_l[v], tv[v], is_new_l[v], v),
        )
        ends = sorted(
            (v for v in verts if tv[v] >= t1 - thr),
            key=lambda v: (lab_l[v], lab_l[v] != _FRONTIER and is_new_l[v], -tv[v], is_new_l[v], v),
        )
        # the first (start, end) in that order whose wall points like one of its edges as
        # measured; none (a short group of noisy pieces): leave the edges as they are
        dirs = [raw_l[e] for e in eds]
        chosen = _pick_ends(starts, ends, pos_l, dirs, cos_tol)
        if chosen is None:
            continue
        s, e_ = chosen
        for v in verts:  # corners near an end are absorbed into it; those inside leave the wall
            if v == s or v == e_:
                continue
            near_s = tv[v] <= t0 + thr
            near_e = tv[v] >= t1 - thr
            if near_s and near_e:
                tgt = s if tv[v] - tv[s] <= tv[e_] - tv[v] else e_
            elif near_s:
                tgt = s
            elif near_e:
                tgt = e_
            else:
                continue
            rv, rt = _find(vparent, v), _find(vparent, tgt)
            if rv != rt and _may_absorb(
                rv, rt, eds, vclass, inc_of, edges_l, pos_l, raw_l, vparent, cos_tol, pos0_l, mate_l, thr
            ):
                vparent[rv] = rt
                vclass.setdefault(rt, [rt]).extend(vclass.pop(rv, [rv]))
        grp_info.append((cid, s, e_, not e_new_l[ref], len_l[ref], eds))
        g_u.append([ux, uy])
        g_o.append([ox, oy])
        g_t0.append(t0)
        g_t1.append(t1)

    n_multi = len(grp_info)
    singles = np.flatnonzero(comp == np.arange(k)) if k else np.zeros(0, dtype=np.intp)
    if members:
        singles = singles[[int(x) not in members for x in singles.tolist()]] if len(singles) else singles
    # also multi-edge groups skipped above pass their edges through as singletons
    handled = {cid for cid, *_ in grp_info}
    skipped = [e for cid, eds in members.items() if cid not in handled for e in eds]
    if skipped:
        singles = np.sort(np.concatenate([singles, np.asarray(skipped, dtype=singles.dtype)]))

    gu = np.concatenate([np.asarray(g_u, dtype=np.float64).reshape(-1, 2), u[singles]])
    go = np.concatenate([np.asarray(g_o, dtype=np.float64).reshape(-1, 2), a[singles]])
    gt0 = np.concatenate([np.asarray(g_t0, dtype=np.float64), np.zeros(len(singles))])
    gt1 = np.concatenate([np.asarray(g_t1, dtype=np.float64), length[singles]])
    ng = len(gu)

    # ---- 4b. T-junction candidates: corners near a wall's interior ---------------------------
    active = snap == np.arange(nl)
    cand_v = np.flatnonzero(active & (lab != _FRONTIER))
    splits: dict[int, list[int]] = {}
    if ng and len(cand_v):
        if ng * len(cand_v) <= _DENSE_NEAR_MAX:
            rel = pos[cand_v][:, None, :] - go[None, :, :]
            off = gu[None, :, 0] * rel[..., 1] - gu[None, :, 1] * rel[..., 0]
            tt = gu[None, :, 0] * rel[..., 0] + gu[None, :, 1] * rel[..., 1]
            near = (np.abs(off) <= thr) & (tt > gt0[None, :] + thr) & (tt < gt1[None, :] - thr)
            vi, gi = np.nonzero(near)
        else:  # many: candidate (corner, wall) pairs from a grid first
            ends0 = go + gt0[:, None] * gu
            ends1 = go + gt1[:, None] * gu
            pv = pos[cand_v]
            cell = max(4.0 * thr, float(np.median(gt1 - gt0)))
            vi, gi = _box_pairs(pv, pv, np.minimum(ends0, ends1) - thr, np.maximum(ends0, ends1) + thr, cell)
            rel = pv[vi] - go[gi]
            ug = gu[gi]
            off = ug[:, 0] * rel[:, 1] - ug[:, 1] * rel[:, 0]
            tt = ug[:, 0] * rel[:, 0] + ug[:, 1] * rel[:, 1]
            near = (np.abs(off) <= thr) & (tt > gt0[gi] + thr) & (tt < gt1[gi] - thr)
            vi, gi = vi[near], gi[near]
        if len(vi):
            group_of_edge = comp.tolist()
            gcomp = [info[0] for info in grp_info] + [int(comp[e]) for e in singles.tolist()]
            incident: dict[int, list[int]] = {}
            for f, (x, y) in enumerate(edges_l):
                incident.setdefault(x, []).append(f)
                incident.setdefault(y, []).append(f)
            for v, g in zip(cand_v[vi].tolist(), gi.tolist()):
                gx, gy = gu[g]
                own = gcomp[g]
                px, py = pos_l[v]
                for f in incident.get(v, ()):
                    if group_of_edge[f] == own:
                        continue
                    w = edges_l[f][1] if edges_l[f][0] == v else edges_l[f][0]
                    dx, dy = pos_l[w][0] - px, pos_l[w][1] - py
                    if gx * dy - gy * dx > sin_tol * math.hypot(dx, dy):
                        splits.setdefault(g, []).append(v)
                        break

    # ---- 4c. build the resolved walls ---------------------------------------------------------
    out_u: list[int] = []
    out_v: list[int] = []
    out_l: list[float] = []
    out_s: list[int] = []
    nominal: set[int] = set()
    constraints: dict[int, list[tuple[float, float, float, float]]] = {}
    pass_mask = np.zeros(k, dtype=bool)
    single_list = singles.tolist()
    src_l = [int(x) for x in src.tolist()]
    lik_l = lik.tolist()
    orig_l = orig.tolist()
    out_p: list[list[int]] = []

    todo: list[tuple[list[int], list[float], list[int], float, float, float, float]] = []

    def pieces(
        nodes: list[int], tn: list[float], eds: list[int], ux: float, uy: float, ox: float, oy: float
    ) -> list[tuple[int, int, list[int], list[int]]]:
        """The walls between consecutive ``nodes``, each with the edges that cover it (that
        count for its likelihood) and all the edges overlapping it (its provenance)."""
        npieces = len(nodes) - 1
        if npieces == 1:
            return [(nodes[0], nodes[1], eds, eds)]
        cover: list[list[int]] = [[] for _ in range(npieces)]
        touch: list[list[int]] = [[] for _ in range(npieces)]
        for e in eds:
            ta = ux * (a_l[e][0] - ox) + uy * (a_l[e][1] - oy)
            tb = ux * (b_l[e][0] - ox) + uy * (b_l[e][1] - oy)
            best, best_ov, hit = 0, -math.inf, False
            for p in range(npieces):
                ov = min(tb, tn[p + 1]) - max(ta, tn[p])
                if ov > 0.0:
                    touch[p].append(e)
                if ov > min(thr, 0.5 * (tn[p + 1] - tn[p])):
                    cover[p].append(e)
                    hit = True
                if ov > best_ov:
                    best, best_ov = p, ov
            if not hit:
                cover[best].append(e)
        out: list[tuple[int, int, list[int], list[int]]] = []
        for p in range(npieces):
            cov = cover[p]
            if not cov:  # no edge covers it well: the one overlapping it most
                ovs = [
                    min(ux * (b_l[e][0] - ox) + uy * (b_l[e][1] - oy), tn[p + 1])
                    - max(ux * (a_l[e][0] - ox) + uy * (a_l[e][1] - oy), tn[p])
                    for e in eds
                ]
                cov = [eds[int(np.argmax(ovs))]]
            out.append((nodes[p], nodes[p + 1], cov, sorted({*cov, *touch[p]})))
        return out

    for g in range(ng):
        spl = splits.get(g, [])
        if g >= n_multi:
            e = single_list[g - n_multi]
            if not spl:
                pass_mask[e] = True
                continue
            s, e_, eds, base_ref, ref_len = edges_l[e][0], edges_l[e][1], [e], not e_new_l[e], len_l[e]
        else:
            _, s, e_, base_ref, ref_len, eds = grp_info[g]
        ux, uy = gu[g].tolist()
        ox, oy = go[g].tolist()
        spl_sorted = sorted(set(spl), key=lambda v: (ux * (pos_l[v][0] - ox) + uy * (pos_l[v][1] - oy), v))
        nodes = [s, *spl_sorted, e_]
        tn = [ux * (pos_l[v][0] - ox) + uy * (pos_l[v][1] - oy) for v in nodes]
        nominal.update(spl_sorted)
        todo.append((nodes, tn, eds, ux, uy, ox, oy))
        if cfg.snap_to_lines and base_ref:
            for v, tv_ in zip(nodes[1:-1], tn[1:-1]):
                if 0.0 <= tv_ <= ref_len:  # inside the base wall: interpolation, never beyond
                    constraints.setdefault(v, []).append((ux, uy, ox, oy))

    # ---- 5. resolve corner absorption, labels and positions ---------------------------------
    root = np.array([_find(vparent, x) for x in range(nl)], dtype=np.int64)
    lab_out = lab.copy()
    if nominal:
        lab_out[list(nominal)] = _NOMINAL
    absorbed = np.flatnonzero(root != np.arange(nl))
    if len(absorbed):
        best_lab = lab_out.copy()
        np.minimum.at(best_lab, root, lab_out)
        for v in absorbed.tolist():  # a root worse-labelled than its class takes a best member's place
            rv = int(root[v])
            if lab_out[rv] > best_lab[rv] and lab_out[v] == best_lab[rv]:
                pos[rv] = pos[v]
                fixed[rv] = fixed[v]
                lab_out[rv] = lab_out[v]
        lab_out = best_lab

    walls_at: dict[int, list[tuple[int, bool, list[int]]]] = {}  # root -> (other end, starts?, edges)
    if constraints:
        root_l = root.tolist()
        ends_l = [(x, y, cov) for item in todo for x, y, cov, _ in pieces(*item)]
        ends_l += [(edges_l[e][0], edges_l[e][1], [e]) for e in np.flatnonzero(pass_mask).tolist()]
        for x, y, cov in ends_l:
            walls_at.setdefault(root_l[x], []).append((root_l[y], True, cov))
            walls_at.setdefault(root_l[y], []).append((root_l[x], False, cov))
        raw_c = raw_d.tolist()

        def turns_a_wall(rv: int, qx: float, qy: float) -> bool:
            for w, starts, cov in walls_at.get(rv, ()):
                if w == rv:
                    continue
                dx, dy = float(pos[w, 0]) - qx, float(pos[w, 1]) - qy
                if not starts:
                    dx, dy = -dx, -dy
                dd = math.hypot(dx, dy)
                if not any(raw_c[e][0] * dx + raw_c[e][1] * dy >= cos_tol * dd * math.hypot(*raw_c[e]) for e in cov):
                    return True
            return False

        for v, lines in constraints.items():
            rv = int(root[v])
            if fixed[rv]:
                continue
            px, py = float(pos[rv, 0]), float(pos[rv, 1])
            m00 = m01 = m11 = r0 = r1 = 0.0
            for ux, uy, ox, oy in lines:  # least squares over the lines' normal equations
                nx, ny = -uy, ux
                cst = nx * ox + ny * oy
                m00 += nx * nx
                m01 += nx * ny
                m11 += ny * ny
                r0 += nx * cst
                r1 += ny * cst
            det = m00 * m11 - m01 * m01
            if det > 1e-6 * (m00 + m11) ** 2:  # lines cross well: their (least-squares) intersection
                qx = (m11 * r0 - m01 * r1) / det
                qy = (m00 * r1 - m01 * r0) / det
            else:  # one line (or parallel ones): the projection on the first
                ux, uy, ox, oy = lines[0]
                tp = ux * (px - ox) + uy * (py - oy)
                qx, qy = ox + tp * ux, oy + tp * uy
            # never farther than thr from where any corner combined into it was measured
            # (combining and then snapping could otherwise move a corner twice)
            near = [int(rv), int(v)] + [int(mate[x]) for x in (rv, v) if mate[x] >= 0]
            # and never turning a wall that ends there away from the edges it comes from
            if all(math.hypot(qx - pos0[x, 0], qy - pos0[x, 1]) <= thr for x in near) and not turns_a_wall(
                rv, qx, qy
            ):
                pos[rv] = (qx, qy)

    # ---- 5b. emit the resolved walls, each pointing like one of the edges it covers ---------
    # (with the final corner positions: a split corner off the line, or a corner absorbed
    # elsewhere, can turn a short piece; then the split is undone, and a wall that still does not
    # point like its edges leaves them as they were)
    rx_l = root.tolist()
    fpos = pos.tolist()

    def points_like(x: int, y: int, cov: list[int]) -> bool:
        px, py = fpos[rx_l[x]]
        dx, dy = fpos[rx_l[y]][0] - px, fpos[rx_l[y]][1] - py
        dd = math.hypot(dx, dy)
        return dd > 0.0 and any(
            raw_l[e][0] * dx + raw_l[e][1] * dy >= cos_tol * dd * math.hypot(*raw_l[e]) for e in cov
        )

    for nodes, tn, eds, ux, uy, ox, oy in todo:
        while True:
            walls = pieces(nodes, tn, eds, ux, uy, ox, oy)
            bad = [p for p, (x, y, cov, _) in enumerate(walls) if not points_like(x, y, cov)]
            if not bad:
                for x, y, cov, prov_xy in walls:
                    out_u.append(x)
                    out_v.append(y)
                    out_l.append(_combine([lik_l[e] for e in cov]))
                    out_s.append(reduce(lambda p_, q_: p_ | q_, (src_l[e] for e in cov), 0))
                    if trace:
                        out_p.append([orig_l[e] for e in prov_xy])
                break
            if len(nodes) == 2:
                pass_mask[eds] = True
                break
            inner = [i for i in (bad[0], bad[0] + 1) if 0 < i < len(nodes) - 1]
            offs = [abs(ux * (fpos[rx_l[nodes[i]]][1] - oy) - uy * (fpos[rx_l[nodes[i]]][0] - ox)) for i in inner]
            drop = inner[int(np.argmax(offs))]  # the split corner farther off the line
            del nodes[drop]
            del tn[drop]

    # An edge left as it was but turned around by combining corners (its ends were within the
    # threshold of each other and moved past each other) is removed like a degenerate one.
    for e in np.flatnonzero(pass_mask).tolist():
        x, y = edges_l[e]
        px, py = fpos[rx_l[x]]
        qx, qy = fpos[rx_l[y]]
        if raw_l[e][0] * (qx - px) + raw_l[e][1] * (qy - py) <= 0.0:
            pass_mask[e] = False

    # ---- 6. assemble (global ids: base vertices, then new ones) --------------------------------
    total = nb + nn
    gid = np.concatenate([lb, nb + np.arange(nn)])
    all_pos = np.concatenate([base.points, new.points])
    all_lab = np.concatenate([base.labels, new.labels])
    all_pos[gid] = pos
    all_lab[gid] = lab_out.astype(np.uint8)
    gmap = np.arange(total)
    gmap[gid] = gid[root[snap]]
    far = ~local_e
    eu = np.concatenate(
        [
            gmap[base.edges[far, 0]],
            gid[root[np.asarray(out_u, dtype=np.int64)]],
            gid[root[edges[pass_mask, 0]]],
        ]
    )
    ev = np.concatenate(
        [
            gmap[base.edges[far, 1]],
            gid[root[np.asarray(out_v, dtype=np.int64)]],
            gid[root[edges[pass_mask, 1]]],
        ]
    )
    el = np.concatenate([base.likelihood[far], np.asarray(out_l, dtype=np.float64), lik[pass_mask]])
    es = np.concatenate([base.sources[far], np.asarray(out_s, dtype=np.uint64), src[pass_mask]])
    prov: list[list[int]] = []
    if trace:
        prov = [[x] for x in np.flatnonzero(far).tolist()] + out_p + [[x] for x in orig[pass_mask].tolist()]
    pu, pv = all_pos[eu], all_pos[ev]
    ok = (eu != ev) & ((pu[:, 0] != pv[:, 0]) | (pu[:, 1] != pv[:, 1]))
    if not ok.all():
        eu, ev, el, es = eu[ok], ev[ok], el[ok], es[ok]
        if trace:
            prov = [x for x, o in zip(prov, ok.tolist()) if o]
    if len(eu) > 1:
        key = eu * total + ev
        uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
        if len(uk) < len(key):  # duplicate directed edges: combined like any merge
            order = np.argsort(first, kind="stable")  # keep first-occurrence order
            q = np.ones(len(uk))
            np.multiply.at(q, inv, 1.0 - el)
            s_acc = np.zeros(len(uk), dtype=np.uint64)
            np.bitwise_or.at(s_acc, inv, es)
            eu, ev = eu[first][order], ev[first][order]
            if trace:
                acc: list[list[int]] = [[] for _ in range(len(uk))]
                for x, g in zip(prov, inv.tolist()):
                    acc[g].extend(x)
                prov = [acc[g] for g in order.tolist()]
            el = np.clip(1.0 - q, 0.0, 1.0)[order]
            es = s_acc[order]
    keep = np.zeros(total, dtype=bool)
    keep[:nb] = ~local_v
    keep[eu] = True
    keep[ev] = True
    remap = np.cumsum(keep) - 1
    out_edges = np.stack([remap[eu], remap[ev]], axis=1)
    merged = Wireframe(all_pos[keep], all_lab[keep], out_edges, el, es)  # type: ignore[arg-type]
    return merged, [sorted(set(x)) for x in prov]
