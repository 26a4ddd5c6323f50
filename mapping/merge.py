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

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from mapping.wireframe import Label, MaskArray, Wireframe, as_masks, mask_bytes

__all__ = ["MergeCache", "MergeConfig", "merge", "merge_all", "merge_traced", "normalize"]

_NOMINAL = int(Label.NOMINAL)
_FRONTIER = int(Label.FRONTIER)
_DENSE_SNAP_MAX = 4096  # candidate vertex pairs from a dense distance matrix up to this many entries
_DENSE_PAIRS_MAX = 160
_COS_45 = math.sqrt(0.5)
_LIST_ASSEMBLY_MAX = 96  # vertices (base + new) up to which step 6 runs on lists (faster there)
# (corner, wall) pairs tested densely up to this many, else via a grid  # all edge pairs are tested
# up to this many local edges, else angle windows
_DENSE_NEAR_MAX = 20000


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
) -> tuple[list[int], list[int]]:
    """One-to-one pairs ``(rows into pb, cols into pn)`` within ``thr`` to combine, as lists.

    ``allowed(rows, cols)`` may veto candidate pairs before the assignment.

    Two frontiers take part in the assignment (so a frontier is not paired with another corner
    when the other wireframe has a frontier right there: merging the same scan twice stays a
    fixed point) but are not returned: frontiers are reconciled along their walls instead.
    """
    if len(pb) == 0 or len(pn) == 0:
        return [], []
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
        return [], []
    r_l, c_l = r.tolist(), c.tolist()
    if len(set(r_l)) < len(r_l) or len(set(c_l)) < len(c_l):  # a corner with several candidates
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
    return r[ok].tolist(), c[ok].tolist()


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
    # (the same element-wise operations as one pair at a time, on stacked arrays)
    ui, uj = u.take(i, axis=0), u.take(j, axis=0)  # (take: row gathers, faster than [ ])
    cos = ui[:, 0] * uj[:, 0] + ui[:, 1] * uj[:, 1]
    li, lj = length[i], length[j]
    shortest = np.minimum(li, lj)
    sin = np.abs(ui[:, 0] * uj[:, 1] - ui[:, 1] * uj[:, 0])
    parallel = cos >= cos_tol
    same = parallel | ((cos >= _COS_45) & (shortest * sin <= thr))
    if not same.all():
        i, j, parallel, li, lj = i[same], j[same], parallel[same], li[same], lj[same]
    if len(i) == 0:
        return i, j
    swap = lj > li
    lg = np.where(swap, j, i)  # the longer edge defines the line
    sh = np.where(swap, i, j)
    ul, al, ll = u.take(lg, axis=0), a.take(lg, axis=0), np.where(swap, lj, li)
    # positions along the longer edge's line (and offsets across it) of the shorter edge's ends,
    # then, as measured, of both edges' ends
    rel = np.stack((a.take(sh, axis=0), b.take(sh, axis=0), a0.take(lg, axis=0), b0.take(lg, axis=0),
                    a0.take(sh, axis=0), b0.take(sh, axis=0))) - al
    ux, uy = ul[:, 0], ul[:, 1]
    t = ux * rel[..., 0] + uy * rel[..., 1]
    off = ux * rel[:2, :, 1] - uy * rel[:2, :, 0]
    ts, te, l0, l1, s0, s1 = t
    gap = np.maximum(ts - ll, -te)
    # the same gap between the ends as measured, along the same line
    gap0 = np.maximum(np.minimum(s0, s1) - np.maximum(l0, l1), np.minimum(l0, l1) - np.maximum(s0, s1))
    on_line = (np.abs(off) <= thr).all(axis=0)
    if parallel.all():
        ok = on_line & (gap <= thr) & (gap0 <= thr)
    else:
        # distance of each end of the short edge to the long edge's segment
        out = np.maximum(np.maximum(-t[:2], t[:2] - ll), 0.0)
        along = (np.hypot(off, out) <= thr).all(axis=0)
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

    Not ``shapely.STRtree``: queried with the boxes' cell ranges (the same pairs) it took 4.5 ms
    against 3.2 ms here (step 3) and 2.4 against 1.2 ms (step 4b) per 600-860-edge merge; queried
    with the boxes themselves it is 10 % faster but drops pairs that share a cell without
    overlapping, which step 3 can relate (boxes grown by ``thr / 2``): not bit-identical.
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


_UPPER: dict[int, NDArray[np.bool_]] = {}


def _upper_mask(k: int) -> NDArray[np.bool_]:
    """``[i, j]`` is ``j > i`` (``k x k``), cached read-only."""
    got = _UPPER.get(k)
    if got is None:
        got = np.triu(np.ones((k, k), dtype=bool), 1)
        got.setflags(write=False)
        if len(_UPPER) > 256:
            _UPPER.clear()
        _UPPER[k] = got
    return got


def _near_pairs(
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    u: NDArray[np.float64],
    length: NDArray[np.float64],
    thr: float,
    cos_tol: float,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The pairs ``i < j`` of a few edges that :func:`_related` may relate, from dense ``k x k``
    tests: directions at most 45 degrees apart (the cosine computed exactly as it does), and
    bounding boxes grown by ``0.75 * thr`` that meet. That is no approximation: a related pair has a point of
    the shorter edge within ``thr * sqrt(2)`` of the longer edge (parallel: within ``thr`` of
    its line and projecting within ``thr`` of its extent; noisy: both ends within ``thr`` of it).
    Testing only these pairs gives the related pairs of all pairs, hence the same groups."""
    ux, uy = u[:, 0], u[:, 1]
    grow = 0.75 * thr + 1e-6
    lo = np.minimum(a, b) - grow
    hi = np.maximum(a, b) + grow
    lx, ly, hx, hy = lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1]
    keep = (lx[:, None] <= hx[None, :]) & (lx[None, :] <= hx[:, None])
    keep &= (ly[:, None] <= hy[None, :]) & (ly[None, :] <= hy[:, None])
    keep &= np.multiply.outer(ux, ux) + np.multiply.outer(uy, uy) >= min(cos_tol, _COS_45)
    i, j = np.nonzero(keep & _upper_mask(len(u)))
    return i.astype(np.intp), j.astype(np.intp)


def _not_other_face(
    edges: NDArray[np.int64],
    raw_a: NDArray[np.float64],
    raw_d: NDArray[np.float64],
    raw_n: NDArray[np.float64],
    mbl: int,
    nlb: int,
    thr: float,
    cos_tol: float,
) -> Callable[[NDArray[np.intp], NDArray[np.intp]], NDArray[np.bool_]]:
    """Veto for :func:`_snap_pairs`: a base corner and a new corner (local ids ``r`` and
    ``nlb + c``) are not combined when a wall at one and a wall at the other point in opposite
    directions (within ``angle_tol``) along lines more than ``thr / 4`` apart: they are the two
    faces of a thick wall (or the two sides of a narrow gap), whose corners may lie within the
    threshold of each other, not two sightings of one corner. Two faces of a *thin* wall lie on
    one line and still share their corners.

    ``edges`` are the local edges (the first ``mbl`` of base, joining base corners ``< nlb``,
    then those of new), ``raw_a``/``raw_d``/``raw_n`` their starts, vectors and lengths."""

    def allowed(r: NDArray[np.intp], c: NDArray[np.intp]) -> NDArray[np.bool_]:
        if mbl == 0 or mbl == len(edges):
            return np.ones(len(r), dtype=bool)
        # Only the walls at a candidate's two corners can veto it, and a candidate has a few:
        # each (base wall, new wall) pair at a candidate is tested in plain floats, by the same
        # operations in the same order as the dense (base wall x new wall) matrices would
        # (unit vectors, dot product, cross product with the offset), so the same vetoes.
        r_l, c_l = r.tolist(), c.tolist()
        # the walls at a candidate corner (base walls join base corners < nlb, new walls new
        # ones), in edge order
        at = np.zeros(max(int(edges.max()), nlb + int(c.max())) + 1, dtype=bool)
        at[r] = True
        at[c + nlb] = True
        sel = np.flatnonzero(at[edges[:, 0]] | at[edges[:, 1]])
        if len(sel) == 0:
            return np.ones(len(r), dtype=bool)
        if len(r) > 8:
            # many candidates (two maps of the same walls): first whether any base wall at a
            # candidate corner and any new wall at one point opposite ways at all (rarely:
            # the two faces of a wall); if none, nothing is vetoed
            sel_b, sel_n = sel[sel < mbl], sel[sel >= mbl]
            if len(sel_b) == 0 or len(sel_n) == 0:
                return np.ones(len(r), dtype=bool)
            nb_, nn_ = raw_n[sel_b], raw_n[sel_n]
            ub = raw_d.take(sel_b, axis=0) / np.where(nb_ > 0.0, nb_, 1.0)[:, None]
            un = raw_d.take(sel_n, axis=0) / np.where(nn_ > 0.0, nn_, 1.0)[:, None]
            if not (np.multiply.outer(ub[:, 0], un[:, 0]) + np.multiply.outer(ub[:, 1], un[:, 1])
                    <= -cos_tol).any():
                return np.ones(len(r), dtype=bool)
        at_l = at.tolist()
        walls: dict[int, list[int]] = {}
        for k, (x, y) in zip(sel.tolist(), edges.take(sel, axis=0).tolist()):
            if at_l[x]:
                walls.setdefault(x, []).append(k)
            if at_l[y]:
                walls.setdefault(y, []).append(k)
        ks = sorted({k for ws in walls.values() for k in ws})
        rd, rn, ra = raw_d[ks].tolist(), raw_n[ks].tolist(), raw_a[ks].tolist()
        unit = {}
        for k, (dx, dy), n, p in zip(ks, rd, rn, ra):
            den = n if n > 0.0 else 1.0
            unit[k] = (dx / den, dy / den, p[0], p[1])
        lim = 0.25 * thr
        out = []
        for x, y in zip(r_l, c_l):
            ok = True
            for kb in walls.get(x, ()):
                bx, by, ax, ay = unit[kb]
                for kn in walls.get(y + nlb, ()):
                    nx, ny, qx, qy = unit[kn]
                    # pointing opposite ways, along lines more than thr / 4 apart
                    if bx * nx + by * ny <= -cos_tol and abs(bx * (qy - ay) - by * (qx - ax)) > lim:
                        ok = False
                        break
                if not ok:
                    break
            out.append(ok)
        return np.array(out, dtype=bool)

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
            if lim > 0.0:
                for ux, uy in units:
                    if ux * dx + uy * dy >= lim:
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
    alike: dict[int, list[int]],
) -> bool:
    """Whether the corners of class ``rv`` may join class ``rt`` (and move to ``pos[rt]``):

    * all the measured positions of the corners of both classes (``pos0[x]``, and ``pos0`` of
      the corner ``mate[x]`` combined with it) lie within ``thr`` of each other, so that
      no chain of combinations moves a corner farther than the threshold;
    * every wall of the moved corners other than ``eds`` (the group being resolved) still
      points within the angle of ``cos_tol`` of its measured direction ``raw`` (or collapses
      to nothing and is removed). An edge ``f`` of another resolved group (``alike[f]``: that
      group's edges) becomes part of that group's wall, which step 5b keeps when it points
      like *one* of the group's edges: the same test here. (Two sightings of a short wall can
      differ in direction by more than ``angle_tol``; judging the wall by each sighting alone
      refused absorptions that the resolved wall allows, and left a corner twice in the map.)
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
            lim = cos_tol * math.hypot(dx, dy)
            if not any(raw[g][0] * dx + raw[g][1] * dy >= lim * math.hypot(*raw[g])
                       for g in alike.get(f, (f,))):
                return False
    return True


def _assemble_lists(
    pos: list[list[float]],
    lab: list[int],
    kept_v: list[bool] | None,
    eu: list[int],
    ev: list[int],
    el: list[float],
    es: list[int],
    prov: list[list[int]],
    trace: bool,
) -> tuple[Wireframe, list[list[int]]]:
    """Step 6 of :func:`_merge` for a small map, in plain lists (global ids: ``pos``, ``lab``;
    ``kept_v``: base vertices kept whether used or not; the edges ``eu -> ev``, untouched base
    edges first): degenerate edges dropped, duplicate directed edges combined (then every
    likelihood is ``clip(1 - (1 - L))``, as the vectorised path computes it), unused vertices
    dropped. The same result as the vectorised path."""
    keep_e = [x != y and pos[x] != pos[y] for x, y in zip(eu, ev)]
    if not all(keep_e):
        eu = [x for x, o in zip(eu, keep_e) if o]
        ev = [x for x, o in zip(ev, keep_e) if o]
        el = [x for x, o in zip(el, keep_e) if o]
        es = [x for x, o in zip(es, keep_e) if o]
        if trace:
            prov = [x for x, o in zip(prov, keep_e) if o]
    total = len(pos)
    if len(eu) > 1:
        key = [x * total + y for x, y in zip(eu, ev)]
        if len(set(key)) < len(key):  # duplicate directed edges: combined like any merge
            slot: dict[int, int] = {}
            q: list[float] = []
            s_acc: list[int] = []
            acc: list[list[int]] = []
            eu2: list[int] = []
            ev2: list[int] = []
            for n, kk in enumerate(key):
                g = slot.get(kk)
                if g is None:
                    g = slot[kk] = len(q)
                    q.append(1.0)
                    s_acc.append(0)
                    acc.append([])
                    eu2.append(eu[n])
                    ev2.append(ev[n])
                q[g] *= 1.0 - el[n]
                s_acc[g] |= es[n]
                if trace:
                    acc[g].extend(prov[n])
            eu, ev, es = eu2, ev2, s_acc
            el = [min(1.0, max(0.0, 1.0 - x)) for x in q]
            if trace:
                prov = acc
    used = [False] * total
    if kept_v is not None:
        used[: len(kept_v)] = kept_v
    for x in eu:
        used[x] = True
    for x in ev:
        used[x] = True
    kept = [x for x, u in enumerate(used) if u]
    if len(kept) == total:  # every vertex stays: the ids do not change
        pairs = list(zip(eu, ev))
    else:
        remap = [0] * total
        for i, x in enumerate(kept):
            remap[x] = i
        pairs = [(remap[x], remap[y]) for x, y in zip(eu, ev)]
    # fresh arrays of the stored dtypes, valid by construction (Wireframe.checked: no copies)
    merged = Wireframe.checked(
        np.array([pos[x] for x in kept], dtype=np.float64).reshape(-1, 2),
        np.array([lab[x] for x in kept], dtype=np.uint8),
        np.array(pairs, dtype=np.int32).reshape(-1, 2),
        np.array(el, dtype=np.float64),
        as_masks(es),
    )
    return merged, [sorted(set(x)) for x in prov]


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


def merge(
    base: Wireframe, new: Wireframe, config: MergeConfig | None = None, cache: MergeCache | None = None
) -> Wireframe:
    """Merge ``new`` into ``base`` (paper Sec. IV-E); both must be in the same (world) frame.

    Parameters
    ----------
    base : Wireframe
        The current map (a particle, or the fused map). Its corners are the stable reference.
    new : Wireframe
        A scan already moved by the estimated pose, or another robot's map.
    config : MergeConfig, optional
        Thresholds; ``MergeConfig()`` when omitted.
    cache : MergeCache, optional
        Reuses the work on the local part (steps 2 to 5) of an earlier merge in the same cache
        whose local part and ``new`` were the same (:class:`MergeCache`); the result is the
        same without it.

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
      combinations) or turn one of its other walls by more than ``angle_tol`` (a wall that
      another group resolves: away from all of that group's edges, as the clean-up judges it).
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
    return _merge(base, new, config if config is not None else MergeConfig(), False, cache)[0]


class MergeCache:
    """The local work of merges (steps 2 to 5 of :func:`merge`), kept by the content of their
    local part, for :func:`merge` calls whose local parts may repeat.

    The particle filter merges one scan into up to ten particles per step; particles that
    differ only away from the scan (an edge dropped there by an old mutation) have the same
    local part, and steps 2 to 5 -- most of a merge's time -- depend on nothing else: the
    local corners (positions, labels, in order), the local edges between them (likelihoods,
    sources), ``new`` and the configuration. Step 6 (:func:`_assemble`) puts the result back
    into each base. The key is a BLAKE2b digest of those arrays' bytes, so a hit is the same
    computation's result, bit for bit (up to the digest's collision odds of 2**-128).

    Entries are dropped when there are more than ``max_entries`` (all at once); :meth:`clear`
    drops them (the filter clears it at every step, whose scan is new).
    """

    def __init__(self, max_entries: int = 256) -> None:
        self.max_entries = int(max_entries)
        self._store: dict[bytes, tuple[_Corners, _Edges, _Walls, list[int], list[int]]] = {}
        self.hits = 0
        self.misses = 0

    def clear(self) -> None:
        self._store.clear()

    def __len__(self) -> int:
        return len(self._store)

    def get(self, key: bytes) -> tuple[_Corners, _Edges, _Walls, list[int], list[int]] | None:
        out = self._store.get(key)
        if out is None:
            self.misses += 1
        else:
            self.hits += 1
        return out

    def put(self, key: bytes, value: tuple[_Corners, _Edges, _Walls, list[int], list[int]]) -> None:
        if len(self._store) >= self.max_entries:
            self._store.clear()
        self._store[key] = value


def _local_key(base: Wireframe, new: Wireframe, loc: _Local, cfg: MergeConfig) -> bytes:
    """What steps 2 to 5 of a merge depend on, as a digest (:class:`MergeCache`): the
    configuration, the local corners' positions and labels (base's local ones, then new's), the
    local base edges in local corner ids with their likelihoods and sources, and new's edges,
    likelihoods and sources."""
    h = hashlib.blake2b(digest_size=16)
    le_l = loc.le if loc.all_v else np.searchsorted(loc.lb, loc.le)
    if loc.all_e:
        lik, src = base.likelihood, base.sources
    else:
        lik, src = base.likelihood[loc.local_e], base.sources[loc.local_e]
    h.update(repr((cfg.threshold, cfg.angle_tol, cfg.snap_to_lines, loc.nlb, loc.nn, loc.mbl,
                   new.n_edges)).encode())
    for a in (loc.pos, loc.lab, le_l.astype(np.int64), lik, new.edges, new.likelihood):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(mask_bytes(src))
    h.update(mask_bytes(new.sources))
    return h.digest()


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
    base: Wireframe, new: Wireframe, cfg: MergeConfig, trace: bool, cache: MergeCache | None = None
) -> tuple[Wireframe, list[list[int]]]:
    """The body of :func:`merge`; with ``trace`` also the provenance of :func:`merge_traced`.

    The steps of the module docstring, one function each (paper Sec. IV-E). Written for small
    inputs (a scan, a robot's map): numpy for what is quadratic in their size, plain lists for
    the per-corner and per-wall bookkeeping (numpy's per-call cost dominates at a few dozen
    elements). Every number is computed by the same operations in the same order either way
    (``np.hypot`` where a length is vectorised, ``math.hypot`` where it is not).

    With a ``cache`` (not when tracing: the provenance holds global edge ids) steps 2 to 5 are
    looked up by the local part's content first (:class:`MergeCache`); step 6 reads their
    results and changes none of them, so one result serves every base it fits."""
    if new.n_edges == 0:
        return base, [[k] for k in range(base.n_edges)] if trace else []
    thr = cfg.threshold
    cos_tol = math.cos(cfg.angle_tol)
    sin_tol = math.sin(cfg.angle_tol)
    new = new.compacted()
    loc = _local_part(base, new, cfg)  # 1
    key = _local_key(base, new, loc, cfg) if cache is not None and not trace else None
    hit = cache.get(key) if cache is not None and key is not None else None
    if hit is not None:
        cs, ed, walls, root_l, lab_out = hit
        return _assemble(base, new, loc, cs, ed, walls, root_l, lab_out, trace)  # 6
    cs, raw = _correspond(base, new, loc, thr, cos_tol)  # 2
    ed = _kept_edges(base, new, loc, cs, raw, thr)
    comp_l, members = _collinear_groups(ed, thr, cos_tol)  # 3
    grp = _group_spans(cs, ed, comp_l, members, thr, cos_tol)  # 4a
    splits = _t_junctions(cs, ed, grp, comp_l, thr, sin_tol)  # 4b
    plan = _plan_walls(cs, ed, grp, splits, cfg.snap_to_lines)  # 4c
    root_l, lab_out = _settle_corners(cs, ed, plan, thr, cos_tol)  # 5
    walls = _emit_walls(cs, ed, plan, root_l, thr, cos_tol, trace)  # 5b
    if cache is not None and key is not None:
        cache.put(key, (cs, ed, walls, root_l, lab_out))
    return _assemble(base, new, loc, cs, ed, walls, root_l, lab_out, trace)  # 6


@dataclass
class _Local:
    """Step 1's result: which part of ``base`` takes part in the merge.

    ``local_e`` / ``local_v`` mark base edges / vertices (``all_e`` / ``all_v``: all of them),
    ``le`` are the local base edges (global ids) and ``lb`` the local base vertices. Local
    corners are numbered base's local ones first (``nlb``), then new's (``nn``), ``nl`` in all;
    ``pos`` and ``lab`` are their positions and labels, ``mbl`` the number of local base edges."""

    local_e: NDArray[np.bool_]
    local_v: NDArray[np.bool_]
    all_e: bool
    all_v: bool
    le: NDArray[np.int32]
    lb: NDArray[np.intp]
    nlb: int
    nn: int
    nl: int
    mbl: int
    pos: NDArray[np.float64]
    lab: NDArray[np.int64]


def _local_part(base: Wireframe, new: Wireframe, cfg: MergeConfig) -> _Local:
    """Step 1 (paper Sec. IV-E applies the merge rules near the new scan only): the base edges
    whose bounding box meets the bounding box of ``new`` grown by ``2 * threshold``, and the
    vertices they use or that lie in that box; with ``cull`` off, all of ``base``."""
    thr = cfg.threshold
    nb, nn = base.n_vertices, new.n_vertices
    mb = base.n_edges
    bpts, bedges = base.points, base.edges
    if cfg.cull and mb:
        grow = 2.0 * thr
        lo = new.points.min(axis=0) - grow
        hi = new.points.max(axis=0) + grow
        (lx, ly), (hx, hy) = lo.tolist(), hi.tolist()
        (bx0, by0), (bx1, by1) = bpts.min(axis=0).tolist(), bpts.max(axis=0).tolist()
        if bx0 >= lx and by0 >= ly and bx1 <= hx and by1 <= hy:  # all of base is near
            local_e = np.ones(mb, dtype=bool)
            local_v = np.ones(nb, dtype=bool)
        elif bx1 < lx or by1 < ly or bx0 > hx or by0 > hy:
            # base's box misses the grown box: so does every edge's box (inside base's) and
            # every vertex, which the tests below would find one by one; nothing is local
            lb = np.zeros(0, dtype=np.intp)
            return _Local(np.zeros(mb, dtype=bool), np.zeros(nb, dtype=bool), False, False, bedges[:0], lb,
                          0, nn, nn, 0, new.points.copy(), new.labels.astype(np.int64))
        else:
            pa, pb = bpts.take(bedges[:, 0], axis=0), bpts.take(bedges[:, 1], axis=0)
            local_e = ((np.maximum(pa, pb) >= lo) & (np.minimum(pa, pb) <= hi)).all(axis=1)
            local_v = ((bpts >= lo) & (bpts <= hi)).all(axis=1)
    else:
        local_e = np.ones(mb, dtype=bool)
        local_v = np.ones(nb, dtype=bool)
    all_e = bool(local_e.all())
    le = bedges if all_e else bedges.compress(local_e, axis=0)
    local_v[le.reshape(-1)] = True
    all_v = bool(local_v.all())
    lb = np.arange(nb) if all_v else np.flatnonzero(local_v)
    nlb = len(lb)
    pos = np.concatenate([bpts if all_v else bpts.take(lb, axis=0), new.points])
    lab = np.concatenate([base.labels if all_v else base.labels[lb], new.labels]).astype(np.int64)
    return _Local(local_e, local_v, all_e, all_v, le, lb, nlb, nn, nlb + nn, len(le), pos, lab)


@dataclass
class _Corners:
    """The local corners during one merge (local ids, see :class:`_Local`), as lists.

    ``pos_l`` are the current positions (moved by steps 2 and 5), ``pos0_l`` the measured ones,
    ``lab_l`` the labels, ``fixed_l`` whether a position comes from ``base``, ``snap_l`` the
    base corner each new corner was combined with (itself otherwise), ``mate_l`` the new corner
    combined with each base corner (-1 otherwise), ``parent`` the absorption of corners into
    wall ends (step 4a, a union-find forest). ``pos`` is ``pos_l`` after step 2 as an array and
    ``edges`` the local edges with combined corners."""

    pos: NDArray[np.float64]
    edges: NDArray[np.int64]
    pos_l: list[list[float]]
    pos0_l: list[list[float]]
    lab_l: list[int]
    is_new_l: list[bool]
    fixed_l: list[bool]
    snap_l: list[int]
    mate_l: list[int]
    parent: list[int]


def _correspond(
    base: Wireframe, new: Wireframe, loc: _Local, thr: float, cos_tol: float
) -> tuple[_Corners, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]]:
    """Step 2 (paper Sec. IV-C, IV-E: corresponding corners within the merge threshold are
    combined): base and new corners within ``thr`` are paired one-to-one (not the two faces of
    a thick wall) and each pair becomes the base corner, at the better-labelled position.

    Also returns the local edges' measured starts and vectors and which are glimpses (shorter
    than ``thr`` with a frontier end: seen for less than the map's resolution, no reliable
    direction, no corner), all as observed, before corners are combined."""
    nlb, nn, nl, pos, lab = loc.nlb, loc.nn, loc.nl, loc.pos, loc.lab
    if loc.all_v:
        le_l = loc.le.astype(np.int64)
    elif loc.mbl == 0:  # no local base edge
        le_l = np.zeros((0, 2), dtype=np.int64)
    else:
        g2l = np.full(base.n_vertices, -1, dtype=np.int64)
        g2l[loc.lb] = np.arange(nlb)
        le_l = g2l[loc.le]
    edges = np.concatenate([le_l, new.edges.astype(np.int64) + nlb])
    e0, e1 = edges[:, 0], edges[:, 1]
    raw_a = pos.take(e0, axis=0)  # edge starts and directions as measured
    raw_d = pos.take(e1, axis=0) - raw_a
    raw_n = np.hypot(raw_d[:, 0], raw_d[:, 1])
    glimpse = ((lab[e0] == _FRONTIER) | (lab[e1] == _FRONTIER)) & (raw_n < thr)

    pos_l = pos.tolist()
    pos0_l = pos.tolist()  # positions as measured, before corners are combined
    lab_l = lab.tolist()
    fixed_l = [True] * nlb + [False] * nn  # position taken from base
    snap_l = list(range(nl))
    mate_l = [-1] * nl  # the new corner each base corner was combined with
    r_l, c_l = _snap_pairs(
        pos[:nlb], pos[nlb:], lab[:nlb], lab[nlb:], thr,
        _not_other_face(edges, raw_a, raw_d, raw_n, loc.mbl, nlb, thr, cos_tol),
    )
    if r_l:
        for rr, cc in zip(r_l, c_l):
            cn = cc + nlb
            if lab_l[cn] < lab_l[rr]:
                pos_l[rr] = pos_l[cn]
                fixed_l[rr] = False
                lab_l[rr] = lab_l[cn]
            snap_l[cn] = rr
            mate_l[rr] = cn
        pos = np.array(pos_l, dtype=np.float64)
        edges = np.array(snap_l, dtype=np.int64)[edges]
    is_new_l = [False] * nlb + [True] * nn
    cs = _Corners(pos, edges, pos_l, pos0_l, lab_l, is_new_l, fixed_l, snap_l, mate_l, list(range(nl)))
    return cs, (raw_a, raw_d, glimpse)


@dataclass
class _Edges:
    """The local edges that take part after step 2 (base's local ones first, then new's), with
    their ends ``a``, ``b`` after corners were combined, lengths, unit directions ``u``, their
    measured vectors ``raw_d`` (and lengths ``raw_nl``), whether from ``new``, likelihoods,
    sources and input edge ids (``orig_l``, the provenance). ``*_l`` are list copies."""

    edges: NDArray[np.int64]
    raw_a: NDArray[np.float64]
    raw_d: NDArray[np.float64]
    a: NDArray[np.float64]
    b: NDArray[np.float64]
    length: NDArray[np.float64]
    u: NDArray[np.float64]
    e_new_l: list[bool]
    lik_l: list[float]
    src_l: list[int]
    orig_l: list[int]
    edges_l: list[list[int]]
    a_l: list[list[float]]
    b_l: list[list[float]]
    len_l: list[float]
    u_l: list[list[float]]
    raw_l: list[list[float]]
    raw_nl: list[float]

    @property
    def k(self) -> int:
        return len(self.edges_l)


def _kept_edges(
    base: Wireframe,
    new: Wireframe,
    loc: _Local,
    cs: _Corners,
    raw: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]],
    thr: float,
) -> _Edges:
    """Step 2, continued: the local edges after combining corners, without those that collapsed
    (both ends combined, zero length) and without glimpses."""
    raw_a, raw_d, glimpse = raw
    local_e, mbl, mb = loc.local_e, loc.mbl, base.n_edges
    if loc.all_e:
        lik_l = base.likelihood.tolist() + new.likelihood.tolist()
        src_l = base.sources.tolist() + new.sources.tolist()
        orig_l = list(range(mb + new.n_edges))  # input edge ids
    elif mbl == 0:  # no local base edge
        lik_l = new.likelihood.tolist()
        src_l = new.sources.tolist()
        orig_l = list(range(mb, mb + new.n_edges))
    else:
        lik_l = base.likelihood[local_e].tolist() + new.likelihood.tolist()
        src_l = base.sources[local_e].tolist() + new.sources.tolist()
        orig_l = np.flatnonzero(local_e).tolist() + list(range(mb, mb + new.n_edges))
    edges, pos = cs.edges, cs.pos
    a = pos.take(edges[:, 0], axis=0)
    b = pos.take(edges[:, 1], axis=0)
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    ok = (edges[:, 0] != edges[:, 1]) & (length > 0.0) & ~glimpse
    e_new_l = [False] * mbl + [True] * new.n_edges
    if not ok.all():
        edges = edges.compress(ok, axis=0)
        raw_a, raw_d = raw_a.compress(ok, axis=0), raw_d.compress(ok, axis=0)
        a, b, d = a.compress(ok, axis=0), b.compress(ok, axis=0), d.compress(ok, axis=0)
        length = length[ok]
        ok_l = ok.tolist()
        e_new_l = [x for x, o in zip(e_new_l, ok_l) if o]
        lik_l = [x for x, o in zip(lik_l, ok_l) if o]
        src_l = [x for x, o in zip(src_l, ok_l) if o]
        orig_l = [x for x, o in zip(orig_l, ok_l) if o]
    u = d / np.where(length > 0.0, length, 1.0)[:, None]
    raw_l = raw_d.tolist()
    return _Edges(
        edges, raw_a, raw_d, a, b, length, u, e_new_l, lik_l, src_l, orig_l,
        edges_l=edges.tolist(),
        a_l=a.tolist(),
        b_l=b.tolist(),
        len_l=length.tolist(),
        u_l=u.tolist(),
        raw_l=raw_l,
        raw_nl=[math.hypot(x, y) for x, y in raw_l],  # = math.hypot(*raw_l[e])
    )


def _collinear_groups(ed: _Edges, thr: float, cos_tol: float) -> tuple[list[int], dict[int, list[int]]]:
    """Step 3 (paper Sec. IV-E: collinear edges are joined): the transitive closure of
    :func:`_related` over all local edges.

    Returns each edge's group id (its smallest member) and the members, in order, of the groups
    of more than one edge, keyed by id in increasing order."""
    a, b, u, length, k = ed.a, ed.b, ed.u, ed.length, ed.k
    # candidate pairs: all of them for a few edges; else roughly the same direction and
    # bounding boxes within thr of each other
    if k <= _DENSE_PAIRS_MAX:
        pi_, pj_ = _near_pairs(a, b, u, length, thr, cos_tol)
    else:  # grid on the boxes grown by thr / 2, then the direction
        half = 0.5 * thr + 1e-12
        cell = max(4.0 * thr, float(np.median(length)))
        pi_, pj_ = _box_pairs(np.minimum(a, b) - half, np.maximum(a, b) + half, None, None, cell)
        same_dir = u[pi_, 0] * u[pj_, 0] + u[pi_, 1] * u[pj_, 1] >= _COS_45
        pi_, pj_ = pi_[same_dir], pj_[same_dir]
    if len(pi_):
        pi_, pj_ = _related(a, b, u, length, pi_, pj_, thr, cos_tol, ed.raw_a, ed.raw_a + ed.raw_d)
    if len(pi_) == 0:  # nothing related (most merges of maps apart): every edge alone
        return list(range(k)), {}
    # Union-find by hand, roots the smallest index: scipy.sparse.csgraph.connected_components
    # gives the same groups (renumbered by their smallest edge) but costs 410 us per filter
    # merge against 12 us (530 vs 700 us on 600-860-edge fusion merges; medians, recorded calls).
    eparent = list(range(k))
    for x, y in zip(pi_.tolist(), pj_.tolist()):
        rx, ry = _find(eparent, x), _find(eparent, y)
        if rx != ry:
            if rx < ry:
                eparent[ry] = rx
            else:
                eparent[rx] = ry
    # a parent always has a smaller index than its child (a root takes the larger root as its
    # child; compression points at the root): in increasing order, each edge's root is known
    # from its parent's (the same roots as _find on each edge)
    comp_l = list(range(k))
    for x in range(k):
        px = eparent[x]
        if px != x:
            comp_l[x] = comp_l[px]
    members: dict[int, list[int]] = {}
    multi = sorted({cx for x, cx in enumerate(comp_l) if cx != x})
    if multi:
        for x in multi:
            members[x] = []
        for x, cx in enumerate(comp_l):
            if cx in members:
                members[cx].append(x)
    return comp_l, members


@dataclass
class _Groups:
    """Step 4a's result: the walls to resolve. The first ``n_multi`` are the resolved groups of
    several edges (``grp_info``: group id, start corner, end corner, base reference?, the
    reference edge's length, the edges), the others the edges passing alone (``single_list``).
    Per wall: direction ``gu_l``, origin ``go_l`` and, for the groups, the extent ``g_t0`` ..
    ``g_t1`` of their corners along that line."""

    grp_info: list[tuple[int, int, int, bool, float, list[int]]]
    single_list: list[int]
    gu_l: list[list[float]]
    go_l: list[list[float]]
    g_t0: list[float]
    g_t1: list[float]

    @property
    def n_multi(self) -> int:
        return len(self.grp_info)


def _group_ends(
    cs: _Corners, ed: _Edges, eds: list[int], thr: float, cos_tol: float
) -> tuple[int, list[int], dict[int, float], float, float, tuple[int, int] | None]:
    """Step 4a for one group (paper Sec. IV-E: neighbour beyond the end, one edge spanning the
    two most distant end points): its reference edge (the longest base edge, else the longest),
    its corners and their positions ``tv`` along the reference line, their extent ``t0, t1``,
    and the (start, end) corners of the resolved wall (None: leave the edges as they are)."""
    e_new_l, len_l, edges_l, pos_l, lab_l, is_new_l = (
        ed.e_new_l, ed.len_l, ed.edges_l, cs.pos_l, cs.lab_l, cs.is_new_l
    )
    ref = eds[0]
    for e in eds[1:]:  # min over (new?, -length, index): base first, then the longest
        if (e_new_l[e], -len_l[e]) < (e_new_l[ref], -len_l[ref]):
            ref = e
    ux, uy = ed.u_l[ref]
    ox, oy = ed.a_l[ref]
    verts = sorted({v for e in eds for v in edges_l[e]})
    tv = {}
    for v in verts:
        pv = pos_l[v]
        tv[v] = ux * (pv[0] - ox) + uy * (pv[1] - oy)
    t0 = min(tv.values())
    t1 = max(tv.values())
    lo_t, hi_t = t0 + thr, t1 - thr
    # best label; real corners: base before new (a stable map), frontiers: farthest out
    starts = [v for v in verts if tv[v] <= lo_t]
    if len(starts) > 1:
        starts.sort(key=lambda v: (lab_l[v], lab_l[v] != _FRONTIER and is_new_l[v], tv[v], is_new_l[v], v))
    ends = [v for v in verts if tv[v] >= hi_t]
    if len(ends) > 1:
        ends.sort(key=lambda v: (lab_l[v], lab_l[v] != _FRONTIER and is_new_l[v], -tv[v], is_new_l[v], v))
    # the first (start, end) in that order whose wall points like one of its edges as
    # measured; none (a short group of noisy pieces): leave the edges as they are
    chosen = _pick_ends(starts, ends, pos_l, [ed.raw_l[e] for e in eds], cos_tol)
    return ref, verts, tv, t0, t1, chosen


def _group_spans(
    cs: _Corners, ed: _Edges, comp_l: list[int], members: dict[int, list[int]], thr: float, cos_tol: float
) -> _Groups:
    """Step 4a (paper Sec. IV-E: a corner falling on an edge is absorbed): each group's wall
    from its farthest start to its farthest end (:func:`_group_ends`); the other corners near
    either end are absorbed into that end (``cs.parent``) when :func:`_may_absorb` allows it.
    Groups without a resolved wall, and singletons, pass as single edges."""
    vparent = cs.parent
    edges_l, len_l, e_new_l = ed.edges_l, ed.len_l, ed.e_new_l
    grp_info: list[tuple[int, int, int, bool, float, list[int]]] = []
    g_u: list[list[float]] = []
    g_o: list[list[float]] = []
    g_t0: list[float] = []
    g_t1: list[float] = []
    vclass: dict[int, list[int]] = {}  # absorbed corners per root (roots absorbing nothing: absent)
    inc_of: dict[int, list[int]] = {}  # local corner -> its edges (only filled for groups' corners)
    if members:
        for f, (x, y) in enumerate(edges_l):
            inc_of.setdefault(x, []).append(f)
            inc_of.setdefault(y, []).append(f)
    # every group's ends first (absorbing corners moves none, so the ends do not depend on the
    # order): a wall of a moved corner that belongs to a resolved group is judged like that
    # group's wall, which may point like any one of its edges (see _may_absorb)
    ends_of = {cid: _group_ends(cs, ed, eds, thr, cos_tol) for cid, eds in members.items()}
    alike = {e: eds for cid, eds in members.items() if ends_of[cid][5] is not None for e in eds}
    for cid, eds in members.items():
        ref, verts, tv, t0, t1, chosen = ends_of[cid]
        if chosen is None:
            continue
        lo_t, hi_t = t0 + thr, t1 - thr
        s, e_ = chosen
        for v in verts:  # corners near an end are absorbed into it; those inside leave the wall
            if v == s or v == e_:
                continue
            near_s = tv[v] <= lo_t
            near_e = tv[v] >= hi_t
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
                rv, rt, eds, vclass, inc_of, edges_l, cs.pos_l, ed.raw_l, vparent, cos_tol, cs.pos0_l,
                cs.mate_l, thr, alike
            ):
                vparent[rv] = rt
                vclass.setdefault(rt, [rt]).extend(vclass.pop(rv, [rv]))
        grp_info.append((cid, s, e_, not e_new_l[ref], len_l[ref], eds))
        g_u.append(ed.u_l[ref])
        g_o.append(ed.a_l[ref])
        g_t0.append(t0)
        g_t1.append(t1)

    # singletons, and the edges of multi-edge groups skipped above, pass as singletons
    handled = {info[0] for info in grp_info}
    if members:
        single_list = [x for x, cx in enumerate(comp_l) if cx == x and x not in members]
    else:  # no groups: every edge passes alone
        single_list = list(range(len(comp_l)))
    skipped = [e for cid, eds in members.items() if cid not in handled for e in eds]
    if skipped:
        single_list = sorted(single_list + skipped)
    gu_l = g_u + [ed.u_l[e] for e in single_list]
    go_l = g_o + [ed.a_l[e] for e in single_list]
    return _Groups(grp_info, single_list, gu_l, go_l, g_t0, g_t1)


def _t_junctions(
    cs: _Corners, ed: _Edges, grp: _Groups, comp_l: list[int], thr: float, sin_tol: float
) -> dict[int, list[int]]:
    """Step 4b (paper Sec. IV-E: a corner falling on an edge, with a neighbour not on it): the
    corners (not frontiers) within ``thr`` of a wall's interior with another wall leaving them
    into the wall's free side (its left); they will split the wall. Keyed by wall index."""
    pos_l, lab_l, snap_l, edges_l, len_l = cs.pos_l, cs.lab_l, cs.snap_l, ed.edges_l, ed.len_l
    single_list, gu_l = grp.single_list, grp.gu_l
    ng = len(gu_l)
    cand_l = [v for v in range(len(snap_l)) if snap_l[v] == v and lab_l[v] != _FRONTIER]
    splits: dict[int, list[int]] = {}
    if not (ng and cand_l):
        return splits
    cand_v = np.array(cand_l, dtype=np.intp)
    if grp.n_multi == 0 and len(single_list) == ed.k:
        # no group: the walls are the edges in order, their lines the edges' own (the same
        # floats as the lists hold: u_l, a_l and len_l are these arrays' tolist())
        gu, go, gt1 = ed.u, ed.a, ed.length
        gt0 = np.zeros(ng, dtype=np.float64)
    else:
        gu = np.array(gu_l, dtype=np.float64)
        go = np.array(grp.go_l, dtype=np.float64)
        gt0 = np.array(grp.g_t0 + [0.0] * len(single_list), dtype=np.float64)
        gt1 = np.array(grp.g_t1 + [len_l[e] for e in single_list], dtype=np.float64)
    if ng * len(cand_l) <= _DENSE_NEAR_MAX:
        rel = cs.pos.take(cand_v, axis=0)[:, None, :] - go[None, :, :]
        off = gu[None, :, 0] * rel[..., 1] - gu[None, :, 1] * rel[..., 0]
        tt = gu[None, :, 0] * rel[..., 0] + gu[None, :, 1] * rel[..., 1]
        near = (np.abs(off) <= thr) & (tt > gt0[None, :] + thr) & (tt < gt1[None, :] - thr)
        vi, gi = np.nonzero(near)
    else:  # many: candidate (corner, wall) pairs from a grid first
        ends0 = go + gt0[:, None] * gu
        ends1 = go + gt1[:, None] * gu
        pv_ = cs.pos.take(cand_v, axis=0)
        cell = max(4.0 * thr, float(np.median(gt1 - gt0)))
        vi, gi = _box_pairs(pv_, pv_, np.minimum(ends0, ends1) - thr, np.maximum(ends0, ends1) + thr, cell)
        rel = pv_[vi] - go[gi]
        ug = gu[gi]
        off = ug[:, 0] * rel[:, 1] - ug[:, 1] * rel[:, 0]
        tt = ug[:, 0] * rel[:, 0] + ug[:, 1] * rel[:, 1]
        near = (np.abs(off) <= thr) & (tt > gt0[gi] + thr) & (tt < gt1[gi] - thr)
        vi, gi = vi[near], gi[near]
    if len(vi):
        gcomp = [info[0] for info in grp.grp_info] + [comp_l[e] for e in single_list]
        vs_l = cand_v[vi].tolist()
        wanted = set(vs_l)
        incident: dict[int, list[int]] = {}  # the walls at those corners, in edge order
        for f, (x, y) in enumerate(edges_l):
            if x in wanted:
                incident.setdefault(x, []).append(f)
            if y in wanted:
                incident.setdefault(y, []).append(f)
        for v, g in zip(vs_l, gi.tolist()):
            gx, gy = gu_l[g]
            own = gcomp[g]
            px, py = pos_l[v]
            for f in incident.get(v, ()):
                if comp_l[f] == own:
                    continue
                w = edges_l[f][1] if edges_l[f][0] == v else edges_l[f][0]
                dx, dy = pos_l[w][0] - px, pos_l[w][1] - py
                if gx * dy - gy * dx > sin_tol * math.hypot(dx, dy):
                    splits.setdefault(g, []).append(v)
                    break
    return splits


_Todo = tuple[list[int], list[float], list[int], float, float, float, float]


@dataclass
class _Plan:
    """Step 4c's result. ``todo``: per resolved wall, its corners in order along it (start,
    split corners, end), their positions along its line, its edges and the line (unit
    direction, origin). ``pass_l``: the edges left as they are. ``nominal``: the split corners.
    ``constraints``: per split corner, the base walls' lines it may be snapped onto."""

    todo: list[_Todo]
    pass_l: list[bool]
    nominal: set[int]
    constraints: dict[int, list[tuple[float, float, float, float]]]


def _plan_walls(
    cs: _Corners, ed: _Edges, grp: _Groups, splits: dict[int, list[int]], snap_lines: bool
) -> _Plan:
    """Step 4c: the resolved walls, split at their T-junctions (which become nominal)."""
    pos_l = cs.pos_l
    nominal: set[int] = set()
    constraints: dict[int, list[tuple[float, float, float, float]]] = {}
    pass_l = [False] * ed.k
    todo: list[_Todo] = []
    n_multi = grp.n_multi
    for g in range(len(grp.gu_l)):
        spl = splits.get(g)
        if g >= n_multi:
            e = grp.single_list[g - n_multi]
            if not spl:
                pass_l[e] = True
                continue
            s, e_ = ed.edges_l[e]
            eds, base_ref, ref_len = [e], not ed.e_new_l[e], ed.len_l[e]
        else:
            _, s, e_, base_ref, ref_len, eds = grp.grp_info[g]
        ux, uy = grp.gu_l[g]
        ox, oy = grp.go_l[g]
        if spl:
            spl_sorted = sorted(set(spl),
                                key=lambda v: (ux * (pos_l[v][0] - ox) + uy * (pos_l[v][1] - oy), v))
            nominal.update(spl_sorted)
            nodes = [s, *spl_sorted, e_]
        else:
            nodes = [s, e_]
        tn = [ux * (pos_l[v][0] - ox) + uy * (pos_l[v][1] - oy) for v in nodes]
        todo.append((nodes, tn, eds, ux, uy, ox, oy))
        if snap_lines and base_ref and spl:
            for v, tv_ in zip(nodes[1:-1], tn[1:-1]):
                if 0.0 <= tv_ <= ref_len:  # inside the base wall: interpolation, never beyond
                    constraints.setdefault(v, []).append((ux, uy, ox, oy))
    return _Plan(todo, pass_l, nominal, constraints)


def _pieces(
    nodes: list[int],
    tn: list[float],
    eds: list[int],
    ux: float,
    uy: float,
    ox: float,
    oy: float,
    ed: _Edges,
    thr: float,
) -> list[tuple[int, int, list[int], list[int]]]:
    """The walls between consecutive ``nodes`` of one resolved wall (see :class:`_Plan`), each
    with the edges that cover it (that count for its likelihood, paper Sec. IV-E) and all the
    edges overlapping it (its provenance)."""
    npieces = len(nodes) - 1
    if npieces == 1:
        return [(nodes[0], nodes[1], eds, eds)]
    a_l, b_l = ed.a_l, ed.b_l
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


def _settle_corners(
    cs: _Corners, ed: _Edges, plan: _Plan, thr: float, cos_tol: float
) -> tuple[list[int], list[int]]:
    """Step 5: the final corners. Each absorbed corner's class is represented by its root,
    which takes the best label in the class (paper Sec. IV-E's label order: nominal, occlusion,
    frontier) and that member's position; split corners are nominal; then
    :func:`_snap_to_lines`. Returns each local corner's root and the labels (by local id)."""
    parent = cs.parent
    nl = len(parent)
    root_l = list(parent)  # each corner's root (the forest is not read after this step)
    for x in range(nl):
        rx = root_l[x]
        if rx != x:
            while parent[rx] != rx:
                rx = parent[rx]
            root_l[x] = rx
    pos_l, fixed_l = cs.pos_l, cs.fixed_l
    lab_out = cs.lab_l  # (cs.lab_l is not used after this step)
    for v in plan.nominal:
        lab_out[v] = _NOMINAL
    absorbed = [v for v in range(nl) if root_l[v] != v]
    if absorbed:
        best_lab = list(lab_out)
        for x in range(nl):
            rx = root_l[x]
            if lab_out[x] < best_lab[rx]:
                best_lab[rx] = lab_out[x]
        for v in absorbed:  # a root worse-labelled than its class takes a best member's place
            rv = root_l[v]
            if lab_out[rv] > best_lab[rv] and lab_out[v] == best_lab[rv]:
                pos_l[rv] = pos_l[v]
                fixed_l[rv] = fixed_l[v]
                lab_out[rv] = lab_out[v]
        lab_out = best_lab
    if plan.constraints:
        _snap_to_lines(cs, ed, plan, root_l, thr, cos_tol)
    return root_l, lab_out


def _snap_to_lines(
    cs: _Corners, ed: _Edges, plan: _Plan, root_l: list[int], thr: float, cos_tol: float
) -> None:
    """Step 5, ``MergeConfig.snap_to_lines``: a split corner whose position comes from ``new``
    moves onto the base walls' lines it splits (their least-squares intersection, or the
    projection on one line) unless that moves it more than ``thr`` from where any corner
    combined into it was measured or turns a wall ending there by more than ``angle_tol``."""
    pos_l, pos0_l, mate_l, edges_l = cs.pos_l, cs.pos0_l, cs.mate_l, ed.edges_l
    walls_at: dict[int, list[tuple[int, bool, list[int]]]] = {}  # root -> (other end, starts?, edges)
    ends_l = [(x, y, cov) for item in plan.todo for x, y, cov, _ in _pieces(*item, ed, thr)]
    ends_l += [(edges_l[e][0], edges_l[e][1], [e]) for e in range(ed.k) if plan.pass_l[e]]
    for x, y, cov in ends_l:
        walls_at.setdefault(root_l[x], []).append((root_l[y], True, cov))
        walls_at.setdefault(root_l[y], []).append((root_l[x], False, cov))

    for v, lines in plan.constraints.items():
        rv = root_l[v]
        if cs.fixed_l[rv]:
            continue
        px, py = pos_l[rv]
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
        near_c = [rv, v] + [mate_l[x] for x in (rv, v) if mate_l[x] >= 0]
        # and never turning a wall that ends there away from the edges it comes from
        if all(math.hypot(qx - pos0_l[x][0], qy - pos0_l[x][1]) <= thr for x in near_c) and not _turns_a_wall(
            walls_at, rv, qx, qy, pos_l, ed, cos_tol
        ):
            pos_l[rv] = [qx, qy]


def _turns_a_wall(
    walls_at: dict[int, list[tuple[int, bool, list[int]]]],
    rv: int,
    qx: float,
    qy: float,
    pos_l: list[list[float]],
    ed: _Edges,
    cos_tol: float,
) -> bool:
    """Whether moving corner ``rv`` to ``(qx, qy)`` turns one of its walls (``walls_at``: other
    end, whether it starts there, covering edges) away from all of the edges it covers."""
    raw_l, raw_nl = ed.raw_l, ed.raw_nl
    for w, starts, cov in walls_at.get(rv, ()):
        if w == rv:
            continue
        dx, dy = pos_l[w][0] - qx, pos_l[w][1] - qy
        if not starts:
            dx, dy = -dx, -dy
        dd = math.hypot(dx, dy)
        if not any(raw_l[e][0] * dx + raw_l[e][1] * dy >= cos_tol * dd * raw_nl[e] for e in cov):
            return True
    return False


def _points_like(
    x: int, y: int, cov: list[int], fpos: list[list[float]], rx_l: list[int], ed: _Edges, cos_tol: float
) -> bool:
    """Whether the wall from the final corner of ``x`` to that of ``y`` points within the angle
    of ``cos_tol`` of one of the edges ``cov`` as measured."""
    px, py = fpos[rx_l[x]]
    qx, qy = fpos[rx_l[y]]
    dx, dy = qx - px, qy - py
    dd = math.hypot(dx, dy)
    if dd > 0.0:
        lim = cos_tol * dd
        for e in cov:
            rd = ed.raw_l[e]
            if rd[0] * dx + rd[1] * dy >= lim * ed.raw_nl[e]:
                return True
    return False


@dataclass
class _Walls:
    """Step 5b's result: the resolved walls ``out_u -> out_v`` (local corners) with likelihoods,
    sources and provenance (input edge ids; empty unless traced), and ``pass_idx``, the local
    edges passed through as they are."""

    out_u: list[int]
    out_v: list[int]
    out_l: list[float]
    out_s: list[int]
    out_p: list[list[int]]
    pass_idx: list[int]


def _emit_walls(
    cs: _Corners, ed: _Edges, plan: _Plan, rx_l: list[int], thr: float, cos_tol: float, trace: bool
) -> _Walls:
    """Step 5b: the resolved walls, each pointing like one of the edges it covers, with
    likelihoods ``1 - prod(1 - L)`` and OR-ed sources (paper Sec. IV-E).

    With the final corner positions, a split corner off the line, or a corner absorbed
    elsewhere, can turn a short piece; then the split is undone (at the split corner farther
    off the line), and a wall that still does not point like its edges leaves them as they
    were. An edge left as it was but turned around by combining corners (its ends were within
    the threshold of each other and moved past each other) is removed like a degenerate one."""
    fpos, pass_l, lik_l, src_l, orig_l = cs.pos_l, plan.pass_l, ed.lik_l, ed.src_l, ed.orig_l
    w = _Walls([], [], [], [], [], [])
    for nodes, tn, eds, ux, uy, ox, oy in plan.todo:
        while True:
            walls = _pieces(nodes, tn, eds, ux, uy, ox, oy, ed, thr)
            bad = [p for p, (x, y, cov, _) in enumerate(walls)
                   if not _points_like(x, y, cov, fpos, rx_l, ed, cos_tol)]
            if not bad:
                for x, y, cov, prov_xy in walls:
                    w.out_u.append(x)
                    w.out_v.append(y)
                    if len(cov) == 1:
                        w.out_l.append(_combine([lik_l[cov[0]]]))
                        w.out_s.append(src_l[cov[0]])
                    else:
                        w.out_l.append(_combine([lik_l[e] for e in cov]))
                        sv = 0
                        for e in cov:
                            sv |= src_l[e]
                        w.out_s.append(sv)
                    if trace:
                        w.out_p.append([orig_l[e] for e in prov_xy])
                break
            if len(nodes) == 2:
                for e in eds:
                    pass_l[e] = True
                break
            inner = [i for i in (bad[0], bad[0] + 1) if 0 < i < len(nodes) - 1]
            offs = [abs(ux * (fpos[rx_l[nodes[i]]][1] - oy) - uy * (fpos[rx_l[nodes[i]]][0] - ox))
                    for i in inner]
            drop = inner[int(np.argmax(offs))]  # the split corner farther off the line
            del nodes[drop]
            del tn[drop]

    edges_l, raw_l = ed.edges_l, ed.raw_l
    for e in range(ed.k):
        if pass_l[e]:
            x, y = edges_l[e]
            px, py = fpos[rx_l[x]]
            qx, qy = fpos[rx_l[y]]
            if raw_l[e][0] * (qx - px) + raw_l[e][1] * (qy - py) > 0.0:
                w.pass_idx.append(e)
    return w


def _assemble(
    base: Wireframe,
    new: Wireframe,
    loc: _Local,
    cs: _Corners,
    ed: _Edges,
    w: _Walls,
    rx_l: list[int],
    lab_out: list[int],
    trace: bool,
) -> tuple[Wireframe, list[list[int]]]:
    """Step 6 (global ids: base vertices, then new ones): the untouched base edges (their
    corners following the combinations of step 2), the resolved walls and the edges passed
    through; then degenerate edges dropped, duplicates combined, unused local corners dropped
    (:func:`_assemble_lists` for a small map, :func:`_assemble_arrays` otherwise)."""
    nb, nn = base.n_vertices, new.n_vertices
    bpts, bedges = base.points, base.edges
    fpos, snap_l, edges_l, orig_l, pass_idx = cs.pos_l, cs.snap_l, ed.edges_l, ed.orig_l, w.pass_idx
    total = nb + nn
    lb_l = loc.lb.tolist()
    gid_l = lb_l + list(range(nb, total))
    # the surviving edges: untouched base edges, resolved walls, edges passed through
    eu_l = [gid_l[rx_l[x]] for x in w.out_u] + [gid_l[rx_l[edges_l[e][0]]] for e in pass_idx]
    ev_l = [gid_l[rx_l[y]] for y in w.out_v] + [gid_l[rx_l[edges_l[e][1]]] for e in pass_idx]
    el_l = w.out_l + [ed.lik_l[e] for e in pass_idx]
    es_l = w.out_s + [ed.src_l[e] for e in pass_idx]
    if total <= _LIST_ASSEMBLY_MAX:  # a small map: the rest in plain lists
        all_pos_l = bpts.tolist() + new.points.tolist()
        all_lab_l = base.labels.tolist() + new.labels.tolist()
        for x, g in enumerate(gid_l):
            all_pos_l[g] = fpos[x]
            all_lab_l[g] = lab_out[x]
        prov_l = w.out_p + [[orig_l[e]] for e in pass_idx] if trace else []
        if not loc.all_e:
            gmap_l = list(range(total))
            for x, g in enumerate(gid_l):
                gmap_l[g] = gid_l[rx_l[snap_l[x]]]
            far = ~loc.local_e
            be_l = bedges.compress(far, axis=0).tolist()
            eu_l = [gmap_l[x] for x, _ in be_l] + eu_l
            ev_l = [gmap_l[y] for _, y in be_l] + ev_l
            el_l = base.likelihood.compress(far).tolist() + el_l
            es_l = base.sources.compress(far).tolist() + es_l
            if trace:
                prov_l = [[x] for x in np.flatnonzero(far).tolist()] + prov_l
        kept_v = None if loc.all_v else (~loc.local_v).tolist()
        return _assemble_lists(all_pos_l, all_lab_l, kept_v, eu_l, ev_l, el_l, es_l, prov_l, trace)
    gid = np.concatenate([loc.lb, np.arange(nb, total)]) if nn else loc.lb
    all_pos = np.concatenate([bpts, new.points])
    all_pos[gid] = np.array(fpos, dtype=np.float64).reshape(-1, 2)
    all_lab = np.concatenate([base.labels, new.labels])
    all_lab[gid] = np.array(lab_out, dtype=np.uint8)
    prov: list[list[int]] = []
    local_edges = np.ascontiguousarray(np.array([eu_l, ev_l], dtype=np.int64).reshape(2, -1).T)
    if loc.all_e:
        edges = local_edges
        el = np.array(el_l, dtype=np.float64)
        es = as_masks(es_l)
        if trace:
            prov = w.out_p + [[orig_l[e]] for e in pass_idx]
    else:
        gmap = np.arange(total)
        gmap[gid] = gid[np.array(rx_l, dtype=np.intp)[snap_l]]
        far = ~loc.local_e
        edges = np.concatenate([gmap[bedges.compress(far, axis=0)], local_edges])
        el = np.concatenate([base.likelihood[far], np.array(el_l, dtype=np.float64)])
        es = as_masks(es_l)
        if base.sources.dtype == object or es.dtype == object:  # masks past bit 63: Python ints
            es = as_masks(base.sources[far].tolist() + es_l)
        else:
            es = np.concatenate([base.sources[far], es])
        if trace:
            prov = [[x] for x in np.flatnonzero(far).tolist()] + w.out_p + [[orig_l[e]] for e in pass_idx]
    return _assemble_arrays(all_pos, all_lab, ~loc.local_v, edges, el, es, prov, trace)


def _assemble_arrays(
    all_pos: NDArray[np.float64],
    all_lab: NDArray[np.uint8],
    kept_b: NDArray[np.bool_],
    edges: NDArray[np.int64],
    el: NDArray[np.float64],
    es: MaskArray,
    prov: list[list[int]],
    trace: bool,
) -> tuple[Wireframe, list[list[int]]]:
    """Step 6 of :func:`_merge` for a large map, vectorised (global ids; ``kept_b``: base
    vertices kept whether used or not; ``edges`` (k, 2) int64, untouched base edges first):
    degenerate edges dropped, duplicate directed edges combined like any merge, unused
    vertices dropped. The same result as :func:`_assemble_lists`. The arrays are fresh ones,
    the result is built of them (:meth:`Wireframe.checked`: valid by construction)."""
    total = len(all_pos)
    ends = all_pos.take(edges, axis=0)
    ok = (edges[:, 0] != edges[:, 1]) & (ends[:, 0] != ends[:, 1]).any(axis=1)
    if not ok.all():
        edges, el, es = edges.compress(ok, axis=0), el[ok], es[ok]
        if trace:
            prov = [x for x, o in zip(prov, ok.tolist()) if o]
    if len(edges) > 1:
        key = edges[:, 0] * total + edges[:, 1]
        ks = np.sort(key)
        if (ks[1:] == ks[:-1]).any():  # duplicate directed edges: combined like any merge
            uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
            order = np.argsort(first, kind="stable")  # keep first-occurrence order
            q = np.ones(len(uk))
            np.multiply.at(q, inv, 1.0 - el)
            s_acc = np.zeros(len(uk), dtype=es.dtype)  # object: masks past bit 63, OR-ed as ints
            np.bitwise_or.at(s_acc, inv, es)
            edges = edges.take(first, axis=0).take(order, axis=0)
            if trace:
                acc: list[list[int]] = [[] for _ in range(len(uk))]
                for x, g in zip(prov, inv.tolist()):
                    acc[g].extend(x)
                prov = [acc[g] for g in order.tolist()]
            el = np.clip(1.0 - q, 0.0, 1.0)[order]
            es = s_acc[order]
    keep = np.zeros(total, dtype=bool)
    keep[: len(kept_b)] = kept_b
    keep[edges.reshape(-1)] = True
    remap = np.cumsum(keep, dtype=np.int32) - 1
    if es.dtype == object:  # the canonical mask array (uint64 if every mask left fits)
        es = as_masks(es)
    merged = Wireframe.checked(all_pos.compress(keep, axis=0), all_lab[keep], remap[edges],
                               np.ascontiguousarray(el), es)
    return merged, [sorted(set(x)) for x in prov]
