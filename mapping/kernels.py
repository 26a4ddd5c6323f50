"""Compiled inner loops (numba): the lidar SLAM's point-to-line match of
:func:`mapping.lidar_slam.match_scan` and its correlative search's scores, the registration's
sample matching (:func:`mapping.registration._match`) and the visibility sweep of
:func:`mapping.visibility.visible_view`.

A real log's SLAM matches a scan's points against a submap ten or more times a scan (the online
match, the loop searches' refinements, the offline refine passes), and each match is a dozen
Gauss-Newton iterations of a nearest-neighbour query and a 3 x 3 normal equation. In NumPy
each iteration is ~20 array operations on ~200 points plus a k-d tree query, and the Python
overhead is most of it; here the whole match is one compiled call (numba), about five times
faster, with the same numbers up to rounding (``tests/test_kernels.py`` holds it to the
NumPy reference on real and random matches).

* :class:`PointGrid`: a point set (a submap, a map's wall samples) bucketed in a uniform grid
  of ``cell`` metres (a counting sort: cell offsets and the points' order). :func:`nearest` is
  the exact nearest point strictly within a gate, as a k-d tree query with
  ``distance_upper_bound`` gives it, and at equal distances the lower index (a k-d tree's
  choice among ties depends on its shape; the registration's samples of two-sided walls tie
  all the time): rings of cells around the query's cell, stopping when the next ring's nearest
  possible point is no nearer than the worst kept so far.
* :func:`gauss_newton`: Censi's point-to-line cost under Cauchy weights with the gate annealed
  geometrically, a prior on the pose, the step by a 3 x 3 solve -- the algorithm and its
  choices are :func:`mapping.lidar_slam.match_scan`'s, documented there.
* :func:`directed_matches`: each query's nearest grid point of a similar direction among its
  three nearest within a gate (the registration's wall-sample match): one pass instead of a
  k-d tree query of one neighbour, then of three for the points whose nearest disagrees.
* :func:`first_crossings`: where each ray (a wall sample's normal) first crosses a map's walls,
  and whether that wall faces back (the registration's free probes across open space,
  :func:`mapping.registration._facing_probes`), the rays in chunks against the walls near each
  chunk, by the same float operations as the NumPy formulation.
* :func:`visibility_sweep`: the predicted scan's sweep (:mod:`mapping.visibility`, steps 2 and
  3: sub-edges, sorted events, the nearest wall of each angular interval, pieces and labels),
  the filter's view of every distinct particle at every step and the simulated corner sensor's
  scene; the same views bit for bit as the Python sweep (``tests/visibility_reference.py``).
* :func:`field_scores`: the correlative loop search's score of a point set under many
  translations, the mean likelihood-field value of the shifted points (Olson 2009); one pass
  over the points per translation instead of a gather of translations x points.

Choices
-------
* The grid's ``cell`` is at least 0.15 m, about the SLAM match's final gate: a late iteration
  looks at the query's cell and its ring (0.10 / 0.15 / 0.25 m measured on captured fhw
  matches: 0.30 / 0.28 / 0.35 ms a match, docs/experiments.md), and at most ``CELLS_PER_POINT``
  cells a point: a sparse set over a wide area gets wider cells (a whole building's 2,000
  registration samples over 220 m x 220 m took 22 ms to bucket in 0.15 m cells, 2.2 million of
  them; a SLAM submap of 640 points over 20 m gets 0.2 m). ``MAX_CELLS`` caps the rest: cells
  double until the grid fits. Same neighbours whatever the cells (ties included); memory and
  build time grow with the number of points.
* The kernels are compiled on first use and cached on disk beside this file (numba's
  ``cache=True``, or the user's cache directory when this file's is read-only, or nowhere when
  neither is writable: then each process compiles them); ``make`` compiles them once after the
  install (:func:`compile_kernels`) so that processes started together do not each compile.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["CELL", "CELLS_PER_POINT", "MAX_CELLS", "PointGrid", "compile_kernels", "directed_matches",
           "field_scores", "first_crossings", "gauss_newton", "nearest", "visibility_sweep"]

#: Grid cell of a :class:`PointGrid`, metres.
CELL = 0.15
#: Most cells a grid may have; a wider point set gets coarser cells.
MAX_CELLS = 4_000_000
#: Most cells per point: a sparse point set gets coarser cells.
CELLS_PER_POINT = 16


@dataclass(frozen=True)
class PointGrid:
    """Points bucketed in a uniform grid: the points of cell ``c`` (row-major, ``ny`` rows of
    ``nx``) are ``order[start[c]:start[c + 1]]``. ``xs``, ``ys``: the points' coordinates."""

    xs: FloatArray
    ys: FloatArray
    origin_x: float
    origin_y: float
    cell: float
    nx: int
    ny: int
    start: IntArray
    order: IntArray

    @classmethod
    def build(cls, points: FloatArray, cell: float = CELL) -> PointGrid:
        """The grid of ``points`` ``(n, 2)``; ValueError when one is not finite."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        xs, ys = np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])
        if len(p) == 0:
            return cls(xs, ys, 0.0, 0.0, float(cell), 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int64))
        if not np.isfinite(p).all():
            raise ValueError("PointGrid.build: points must be finite")
        lo = p.min(axis=0)
        span = p.max(axis=0) - lo
        # A sparse set gets wider cells: at most CELLS_PER_POINT cells a point (a building-wide
        # map's 2,000 samples over 200 m x 200 m would be 1.8 million cells of 0.15 m).
        cell = max(float(cell), math.sqrt(float(span[0] * span[1]) / (CELLS_PER_POINT * len(p))))
        while (span[0] // cell + 1) * (span[1] // cell + 1) > MAX_CELLS:
            cell *= 2.0
        nx = int(span[0] // cell) + 1
        ny = int(span[1] // cell) + 1
        start, order = _bucket(xs, ys, float(lo[0]), float(lo[1]), cell, nx, ny)
        return cls(xs, ys, float(lo[0]), float(lo[1]), cell, nx, ny, start, order)

    @property
    def arrays(self) -> tuple[FloatArray, FloatArray, float, float, float, int, int, IntArray, IntArray]:
        """The grid as the kernels take it: ``xs, ys, origin_x, origin_y, cell, nx, ny, start,
        order`` (:func:`_nearest_k`'s arguments after the query)."""
        return (self.xs, self.ys, self.origin_x, self.origin_y, self.cell, self.nx, self.ny, self.start,
                self.order)


def nearest(grid: PointGrid, queries: FloatArray, gate: float) -> IntArray:
    """Index of each query's nearest grid point at a distance strictly under ``gate`` (finite,
    ValueError otherwise), or -1."""
    q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 2)
    return np.asarray(_nearest_all(q, *grid.arrays, _finite_gate(gate)))


def gauss_newton(
    points: FloatArray,
    grid: PointGrid,
    normals: FloatArray,
    guess: FloatArray,
    prior: FloatArray,
    iterations: int,
    gate_start: float,
    gate_end: float,
    sigma: float,
    kernel: float,
    effective_points: float,
    inlier_distance: float,
    point_sides: FloatArray | None = None,
    facing_cos: float = -2.0,
) -> tuple[FloatArray, FloatArray, float, int]:
    """Point-to-line Gauss-Newton of robot-frame ``points`` against the grid's points with unit
    ``normals`` from ``guess`` (see :func:`mapping.lidar_slam.match_scan`). With
    ``point_sides`` (robot frame, one unit vector per point: the side of a wall it was seen
    from, :func:`mapping.lidar_slam.scan_sides`; NaN: paired unchecked) a point is paired with the
    nearest of its three nearest grid points whose normal has a dot product of at least
    ``facing_cos`` with its side turned by the pose (none: unpaired). Returns the pose,
    the data term's Hessian, the inlier share and the points matched in the last iteration.
    Raises ValueError for a non-finite point, guess or prior."""
    if not (np.isfinite(points).all() and np.isfinite(guess).all() and np.isfinite(prior).all()):
        raise ValueError("gauss_newton: points, guess and prior must be finite")
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    qn = (np.zeros((0, 2)) if point_sides is None
          else np.ascontiguousarray(point_sides, dtype=np.float64).reshape(-1, 2))
    if point_sides is not None and len(qn) != len(pts):
        raise ValueError(f"gauss_newton: {len(qn)} point sides for {len(pts)} points")
    pose, hess, inliers, matched = _gauss_newton(
        pts, *grid.arrays,
        np.ascontiguousarray(normals[:, 0], dtype=np.float64),
        np.ascontiguousarray(normals[:, 1], dtype=np.float64),
        np.ascontiguousarray(guess, dtype=np.float64), np.ascontiguousarray(prior, dtype=np.float64),
        int(iterations), float(gate_start), float(gate_end), float(sigma), float(kernel),
        float(effective_points), float(inlier_distance), qn, float(facing_cos))
    return pose, hess, float(inliers), int(matched)


def directed_matches(grid: PointGrid, directions: FloatArray, queries: FloatArray,
                     query_directions: FloatArray, gate: float, cos_min: float, k: int = 3) -> IntArray:
    """For each query, among its ``k`` nearest grid points strictly within ``gate`` (nearest
    first), the first whose unit ``directions`` row has a dot product of at least ``cos_min``
    with the query's direction; -1 when none has."""
    q = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 2)
    qd = np.ascontiguousarray(query_directions, dtype=np.float64).reshape(-1, 2)
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 2)
    return np.asarray(_directed_matches(q, qd, d, *grid.arrays, _finite_gate(gate), float(cos_min), int(k)))


def _finite_gate(gate: float) -> float:
    if not math.isfinite(gate):
        raise ValueError(f"the gate must be finite, got {gate}")
    return float(gate)


def first_crossings(origins: FloatArray, normals: FloatArray, segments: FloatArray,
                    segment_normals: FloatArray, reach: float,
                    chunk: int = 128) -> tuple[FloatArray, NDArray[np.bool_]]:
    """For each ray ``origins + t normals`` (``1e-6 < t <= reach``): the first ``t`` at which
    it crosses one of ``segments`` ``(m, 2, 2)`` (inf: none), and whether that segment's unit
    normal points against the ray. Rays are taken ``chunk`` at a time against the segments whose
    bounding box meets the chunk's (put nearby rays together for speed; the result does not
    depend on it); among equal ``t`` the lower segment index."""
    o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 2)
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 2)
    seg = np.ascontiguousarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    sn = np.ascontiguousarray(segment_normals, dtype=np.float64).reshape(-1, 2)
    first, facing = _first_crossings(o, n, seg, sn, float(reach), int(chunk))
    return np.asarray(first), np.asarray(facing)


def field_scores(field: FloatArray, origin: FloatArray, res: float, points: FloatArray,
                 offsets: IntArray) -> FloatArray:
    """Mean ``field`` value (rows = y, cols = x; cell ``(0, 0)`` at ``origin``, ``res`` metres)
    of world ``points`` shifted by each of ``offsets`` (cells, ``(k, 2)`` as ``(dx, dy)``),
    over all the points. A point that some offset would take off the grid is dropped for all
    of them (the caller's grid is wider than any window, so it lies off the submap anyway)."""
    return np.asarray(_field_scores(
        np.ascontiguousarray(field, dtype=np.float64), float(origin[0]), float(origin[1]), float(res),
        np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(offsets, dtype=np.int64).reshape(-1, 2)))


def visibility_sweep(ed: Any, labels: NDArray[np.uint8], fov: float, full: bool, min_piece: float,
                     angle_tol: float, back_bias: float, join_tol: float) -> tuple[Any, ...]:
    """:mod:`mapping.visibility`'s steps 2 and 3 over its nearby edges ``ed`` (a
    ``visibility._Edges``): the reported vertices (x, y, label, source), the scan's edges
    (start and end vertex, nearby edge, parameters along it) and the nearby edges with a part
    in view. See that module for the sweep, the pieces and the labels."""
    c = np.ascontiguousarray
    f8, i8 = np.float64, np.int64
    out: tuple[Any, ...] = _sweep(c(ed.p0.real, f8), c(ed.p0.imag, f8), c(ed.d.real, f8), c(ed.d.imag, f8),
                  c(ed.pa.real, f8), c(ed.pa.imag, f8), c(ed.pb.real, f8), c(ed.pb.imag, f8),
                  c(ed.ta, f8), c(ed.tb, f8), c(ed.sa, i8), c(ed.sb, i8), c(ed.phia, f8), c(ed.phib, f8),
                  c(ed.back, np.bool_), c(ed.good, np.bool_), c(labels, np.uint8), float(fov), bool(full),
                  float(min_piece), float(angle_tol), float(back_bias), float(join_tol))
    return out


def compile_kernels() -> None:
    """Compile (or load from the cache) every kernel, on inputs of the types real calls use."""
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    grid = PointGrid.build(pts)
    normals = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    nearest(grid, pts, 0.5)
    directed_matches(grid, normals, pts, normals, 0.5, 0.9)
    gauss_newton(pts, grid, normals, np.zeros(3), np.eye(3), 2, 0.5, 0.15, 0.03, 0.05, 2.0, 0.1)
    field_scores(np.zeros((4, 4)), np.zeros(2), 0.1, pts * 0.1, np.zeros((1, 2), np.int64))
    first_crossings(pts, normals, np.stack([pts, pts[::-1]], axis=1), normals, 2.0)
    from mapping.se2 import Pose
    from mapping.visibility import visible_view
    from mapping.wireframe import Wireframe

    visible_view(Wireframe.from_polylines([pts], closed=True), Pose(0.5, 0.5, 0.0), 8.0)


# ------------------------------------------------------------------------------------- kernels


def _compiled(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit`` with numba's on-disk cache, or without it where numba finds no writable
    place for one (beside this file, or the user's cache directory: a read-only install under
    a read-only home, as in some robot containers), where numba would refuse to import the
    module: then each process compiles the kernels again on first use (~6 s)."""
    try:
        return njit(cache=True)(fn)
    except RuntimeError:
        return njit(fn)


@_compiled
def _bucket(xs, ys, ox, oy, cell, nx, ny):  # type: ignore[no-untyped-def]
    n = xs.shape[0]
    key = np.empty(n, np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    for k in range(n):
        i = min(nx - 1, int((xs[k] - ox) / cell))
        j = min(ny - 1, int((ys[k] - oy) / cell))
        key[k] = j * nx + i
        start[key[k] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for k in range(n):
        order[fill[key[k]]] = k
        fill[key[k]] += 1
    return start, order


@_compiled
def _nearest_k(qx, qy, xs, ys, ox, oy, cell, nx, ny, start, order, gate, idx, dist):  # type: ignore[no-untyped-def]
    """The ``len(idx)`` nearest points strictly within ``gate`` of ``(qx, qy)``, nearest first
    and at equal distances the lower index first, into ``idx`` and ``dist`` (squared
    distances); returns how many were found."""
    if not (math.isfinite(qx) and math.isfinite(qy)):
        return 0
    fx = (qx - ox) / cell
    fy = (qy - oy) / cell
    reach = gate / cell + 2.0
    # A query farther than the gate from the grid's box has no neighbour.
    if fx < -reach or fy < -reach or fx > nx + reach or fy > ny + reach:
        return 0
    ci = math.floor(fx)
    cj = math.floor(fy)
    # The nearest any point of ring r (r >= 1) can be: the way out of the query's own cell,
    # then r - 1 whole cells.
    edge = min(fx - ci, ci + 1 - fx, fy - cj, cj + 1 - fy) * cell
    kk = idx.shape[0]
    found = 0
    gate2 = gate * gate
    bound = gate2
    for r in range(int(gate / cell) + 2):
        if r > 0:
            lb = edge + (r - 1) * cell
            # (a relative slack of 1e-12: the bound is computed in cell units, and a point on a
            # cell border may be that much nearer than it says)
            if lb * lb * (1.0 - 1e-12) >= bound:
                break
        for j in range(max(0, cj - r), min(ny - 1, cj + r) + 1):
            whole_row = j == cj - r or j == cj + r
            step = 1 if whole_row or r == 0 else 2 * r
            i = ci - r
            while i <= ci + r:
                if 0 <= i < nx:
                    c = j * nx + i
                    for k in range(start[c], start[c + 1]):
                        o = order[k]
                        dx = xs[o] - qx
                        dy = ys[o] - qy
                        d2 = dx * dx + dy * dy
                        # Ordered by (distance, index): among points at the same distance the
                        # lower index first, whatever the grid's cells.
                        if found < kk:
                            if not d2 < gate2:
                                continue
                            p = found
                            found += 1
                        elif d2 < dist[kk - 1] or (d2 == dist[kk - 1] and o < idx[kk - 1]):
                            p = kk - 1
                        else:
                            continue
                        while p > 0 and (d2 < dist[p - 1] or (d2 == dist[p - 1] and o < idx[p - 1])):
                            dist[p] = dist[p - 1]
                            idx[p] = idx[p - 1]
                            p -= 1
                        dist[p] = d2
                        idx[p] = o
                        if found == kk:
                            bound = dist[kk - 1]
                i += step
    return found


@_compiled
def _nearest_all(q, xs, ys, ox, oy, cell, nx, ny, start, order, gate):  # type: ignore[no-untyped-def]
    out = np.full(q.shape[0], -1, np.int64)
    one = np.empty(1, np.int64)
    one_d = np.empty(1)
    for k in range(q.shape[0]):
        if _nearest_k(q[k, 0], q[k, 1], xs, ys, ox, oy, cell, nx, ny, start, order, gate, one, one_d):
            out[k] = one[0]
    return out


@_compiled
def _directed_matches(q, qd, d, xs, ys, ox, oy, cell, nx, ny, start, order, gate, cos_min, kk):  # type: ignore[no-untyped-def]
    out = np.full(q.shape[0], -1, np.int64)
    near = np.empty(kk, np.int64)
    near_d = np.empty(kk)
    dx, dy = d[:, 0], d[:, 1]
    for k in range(q.shape[0]):
        out[k] = _nearest_directed(q[k, 0], q[k, 1], qd[k, 0], qd[k, 1], xs, ys, ox, oy, cell, nx, ny, start,
                                   order, gate, dx, dy, cos_min, near, near_d)
    return out


@_compiled
def _nearest_directed(x, y, ux, uy, xs, ys, ox, oy, cell, nx, ny, start, order, gate, dx, dy, cos_min,  # type: ignore[no-untyped-def]
                      near, near_d):
    """Among the ``len(near)`` nearest grid points strictly within ``gate`` of ``(x, y)``
    (nearest first), the first whose direction ``(dx, dy)`` has a dot product of at least
    ``cos_min`` with ``(ux, uy)``; -1 when none has."""
    n = _nearest_k(x, y, xs, ys, ox, oy, cell, nx, ny, start, order, gate, near, near_d)
    for m in range(n):
        o = near[m]
        if dx[o] * ux + dy[o] * uy >= cos_min:
            return o
    return -1


@_compiled
def _first_crossings(o, n, seg, sn, reach, chunk):  # type: ignore[no-untyped-def]
    n_rays = o.shape[0]
    m = seg.shape[0]
    first = np.full(n_rays, np.inf)
    facing = np.zeros(n_rays, np.bool_)
    near = np.empty(m, np.int64)
    for k in range(0, n_rays, chunk):
        end = min(k + chunk, n_rays)
        # The chunk's rays' bounding box, origin to tip.
        lox = loy = np.inf
        hix = hiy = -np.inf
        for r in range(k, end):
            tx = o[r, 0] + reach * n[r, 0]
            ty = o[r, 1] + reach * n[r, 1]
            lox = min(lox, o[r, 0], tx)
            loy = min(loy, o[r, 1], ty)
            hix = max(hix, o[r, 0], tx)
            hiy = max(hiy, o[r, 1], ty)
        n_near = 0
        for j in range(m):
            if (max(seg[j, 0, 0], seg[j, 1, 0]) >= lox and max(seg[j, 0, 1], seg[j, 1, 1]) >= loy
                    and min(seg[j, 0, 0], seg[j, 1, 0]) <= hix and min(seg[j, 0, 1], seg[j, 1, 1]) <= hiy):
                near[n_near] = j
                n_near += 1
        if n_near == 0:
            continue
        for r in range(k, end):
            n0 = n[r, 0]
            n1 = n[r, 1]
            best = np.inf
            pick = near[0]
            for q in range(n_near):
                j = near[q]
                e0 = seg[j, 1, 0] - seg[j, 0, 0]
                e1 = seg[j, 1, 1] - seg[j, 0, 1]
                den = n0 * e1 - n1 * e0  # cross(n, e)
                if not abs(den) > 1e-9:
                    continue
                wx = seg[j, 0, 0] - o[r, 0]
                wy = seg[j, 0, 1] - o[r, 1]
                t = (wx * e1 - wy * e0) / den  # cross(w, e) / cross(n, e)
                s = (wx * n1 - wy * n0) / den  # cross(w, n) / cross(n, e)
                if t > 1e-6 and t <= reach and s >= 0.0 and s <= 1.0 and t < best:
                    best = t
                    pick = j
            first[r] = best
            facing[r] = sn[pick, 0] * n0 + sn[pick, 1] * n1 < 0.0
    return first, facing


@_compiled
def _wrap(a):  # type: ignore[no-untyped-def]
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@_compiled
def _gauss_newton(points, xs, ys, ox, oy, cell, gnx, gny, start, order, nxs, nys, guess, prior,  # type: ignore[no-untyped-def]
                  n_it, gate_start, gate_end, sigma, kernel, effective_points, inlier_distance, qn,
                  facing_cos):
    pose = guess.copy()
    w_sigma = 1.0 / sigma**2
    hess = np.zeros((3, 3))
    matched = 0
    half = max(1, n_it // 2)
    n = points.shape[0]
    idx = np.empty(n, np.int64)
    wx = np.empty(n)
    wy = np.empty(n)
    h = np.empty((3, 3))
    g = np.empty(3)
    jac = np.empty(3)
    for it in range(n_it):
        f = min(1.0, it / half)
        gate = gate_start * (gate_end / gate_start) ** f
        matched = _place_and_pair(points, pose, xs, ys, ox, oy, cell, gnx, gny, start, order, gate,
                                  wx, wy, idx, qn, nxs, nys, facing_cos)
        d0 = pose[0] - guess[0]
        d1 = pose[1] - guess[1]
        d2 = _wrap(pose[2] - guess[2])
        for a in range(3):
            g[a] = prior[a, 0] * d0 + prior[a, 1] * d1 + prior[a, 2] * d2
        hess = np.zeros((3, 3))
        if matched >= 3:
            # Neighbouring returns' errors are correlated: the data term counts as
            # ``effective_points`` independent points at most.
            scale = min(1.0, effective_points / matched)
            for q in range(n):
                k = idx[q]
                if k < 0:
                    continue
                n0 = nxs[k]
                n1 = nys[k]
                r = n0 * (wx[q] - xs[k]) + n1 * (wy[q] - ys[k])
                jac[0] = n0
                jac[1] = n1
                jac[2] = -n0 * (wy[q] - pose[1]) + n1 * (wx[q] - pose[0])
                w = scale * w_sigma / (1.0 + (r / kernel) ** 2)
                for a in range(3):
                    g[a] += w * jac[a] * r
                    for b in range(3):
                        hess[a, b] += w * jac[a] * jac[b]
        for a in range(3):
            for b in range(3):
                h[a, b] = hess[a, b] + prior[a, b]
            h[a, a] += 1e-9
        step = _solve3(h, g)
        pose[0] -= step[0]
        pose[1] -= step[1]
        pose[2] = _wrap(pose[2] - step[2])
        if it >= half and abs(step[0]) + abs(step[1]) < 1e-4 and abs(step[2]) < 1e-5:
            break
    _place_and_pair(points, pose, xs, ys, ox, oy, cell, gnx, gny, start, order,
                    max(gate_end, inlier_distance), wx, wy, idx, qn, nxs, nys, facing_cos)
    inl = 0
    for q in range(n):
        k = idx[q]
        if k >= 0 and abs(nxs[k] * (wx[q] - xs[k]) + nys[k] * (wy[q] - ys[k])) <= inlier_distance:
            inl += 1
    return pose, hess, inl / max(1, n), matched


@_compiled
def _place_and_pair(points, pose, xs, ys, ox, oy, cell, nx, ny, start, order, gate, wx, wy, idx,  # type: ignore[no-untyped-def]
                    qn, gnx, gny, facing_cos):
    """Robot-frame ``points`` placed at ``pose`` into ``wx``, ``wy``, each one's nearest grid
    point strictly within ``gate`` into ``idx`` (-1: none); returns how many have one. With
    point sides ``qn`` (one row per point; an empty array: none), a point with a side takes the
    nearest of its three nearest whose normal (``gnx``, ``gny``) faces its side turned by the
    pose to at least ``facing_cos``."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    one = np.empty(1, np.int64)
    one_d = np.empty(1)
    three = np.empty(3, np.int64)
    three_d = np.empty(3)
    facing = qn.shape[0] == points.shape[0]
    matched = 0
    for q in range(points.shape[0]):
        x = c * points[q, 0] - s * points[q, 1] + pose[0]
        y = s * points[q, 0] + c * points[q, 1] + pose[1]
        wx[q] = x
        wy[q] = y
        idx[q] = -1
        if facing and math.isfinite(qn[q, 0]):
            ux, uy = c * qn[q, 0] - s * qn[q, 1], s * qn[q, 0] + c * qn[q, 1]  # its side, turned by the pose
            o = _nearest_directed(x, y, ux, uy, xs, ys, ox, oy, cell, nx, ny, start, order, gate, gnx, gny,
                                  facing_cos, three, three_d)
            if o >= 0:
                idx[q] = o
                matched += 1
        elif _nearest_k(x, y, xs, ys, ox, oy, cell, nx, ny, start, order, gate, one, one_d):
            idx[q] = one[0]
            matched += 1
    return matched


@_compiled
def _field_scores(field, ox, oy, res, points, offsets):  # type: ignore[no-untyped-def]
    h, w = field.shape
    n = points.shape[0]
    k = offsets.shape[0]
    out = np.zeros(k)
    if k == 0:
        return out
    lo_x = offsets[:, 0].min()
    hi_x = offsets[:, 0].max()
    lo_y = offsets[:, 1].min()
    hi_y = offsets[:, 1].max()
    base = np.empty(n, np.int64)
    m = 0
    for q in range(n):
        if not (math.isfinite(points[q, 0]) and math.isfinite(points[q, 1])):
            continue
        i = math.floor((points[q, 0] - ox) / res)
        j = math.floor((points[q, 1] - oy) / res)
        if i + lo_x >= 0 and i + hi_x < w and j + lo_y >= 0 and j + hi_y < h:
            base[m] = j * w + i
            m += 1
    flat = field.ravel()
    for o in range(k):
        shift = offsets[o, 1] * w + offsets[o, 0]
        acc = 0.0
        for q in range(m):
            acc += flat[base[q] + shift]
        out[o] = acc / max(1, n)
    return out


@_compiled
def _solve3(a, b):  # type: ignore[no-untyped-def]
    """``a^-1 b`` of a 3 x 3 system by Gaussian elimination with partial pivoting (LAPACK's
    ``gesv`` for this size, without the call)."""
    m = a.copy()
    v = b.copy()
    for col in range(3):
        p = col
        for r in range(col + 1, 3):
            if abs(m[r, col]) > abs(m[p, col]):
                p = r
        if p != col:
            for k in range(3):
                m[col, k], m[p, k] = m[p, k], m[col, k]
            v[col], v[p] = v[p], v[col]
        for r in range(col + 1, 3):
            f = m[r, col] / m[col, col]
            for k in range(col, 3):
                m[r, k] -= f * m[col, k]
            v[r] -= f * v[col]
    x = np.empty(3)
    for r in range(2, -1, -1):
        acc = v[r]
        for k in range(r + 1, 3):
            acc -= m[r, k] * x[k]
        x[r] = acc / m[r, r]
    return x


# --------------------------------------------------------------------- the visibility sweep
# mapping.visibility's steps 2 and 3 (sub-edges, events, sweep, pieces, labels), the same float
# operations in the same order as the Python formulation they replaced (tests/visibility_reference.py):
# complex products written out as CPython computes them, ``a * (x + iy)`` for a real ``a`` as
# ``(a x - 0 y, a y + 0 x)``, Python's min / max argument order, a stable sort of the events.

_RANGE = -1
_WINDOW = -2
_CUT = -3
_NOMINAL, _OCCLUSION, _FRONTIER = 0, 1, 2


@_compiled
def _py_max(a, b):  # type: ignore[no-untyped-def]
    """Python's ``max(a, b)``: ``a`` unless ``b > a`` (NaN kept where Python keeps it)."""
    return b if b > a else a


@_compiled
def _py_min(a, b):  # type: ignore[no-untyped-def]
    """Python's ``min(a, b)``: ``a`` unless ``b < a``."""
    return b if b < a else a


@_compiled
def _ray_point(p0r, p0i, dr, di, ur, ui, t_if_parallel, t_lo_a, t_lo_b):  # type: ignore[no-untyped-def]
    """Where the ray ``u`` crosses the line ``p0 + t d``, ``t`` clamped to
    ``[min(a, b), max(a, b)]``: (x, y, t)."""
    den = dr * ui - di * ur  # cross(d, u)
    if den != 0.0:
        t = (ur * p0i - ui * p0r) / den  # cross(u, p0) / den
    else:
        t = t_if_parallel
    t = _py_min(_py_max(t, _py_min(t_lo_a, t_lo_b)), _py_max(t_lo_a, t_lo_b))
    return p0r + (t * dr - 0.0 * di), p0i + (t * di + 0.0 * dr), t


@_compiled
def _pass_label(labels, src):  # type: ignore[no-untyped-def]
    """Label of a piece end that sight passes: ``OCCLUSION`` at a corner of the map, unless the
    map marks it a frontier; ``FRONTIER`` at a point made on a wall."""
    if src >= 0 and labels[src] != _FRONTIER:
        return _OCCLUSION
    return _FRONTIER


@_compiled
def _put_vertex(out_x, out_y, out_lab, out_src, n, x, y, lab, src):  # type: ignore[no-untyped-def]
    """Report vertex ``n`` (its source an input vertex, or -1 for a point made on a wall);
    returns the count after it."""
    out_x[n] = x
    out_y[n] = y
    out_lab[n] = lab
    out_src[n] = src if src > -1 else -1
    return n + 1


@_compiled
def _piece_point(k, k_own, own_x, own_y, own_t, own_src, phi0, ev, i, p0r, p0i, dr, di, ta, tb):  # type: ignore[no-untyped-def]
    """(x, y, t, source) of a sub-edge's piece end at event ``k``: its own end point when that
    is the sub-edge's own end event ``k_own``, else where the event's ray cuts its wall."""
    if k == k_own:
        return own_x, own_y, own_t, own_src
    bearing = phi0 + ev[k]
    x, y, t = _ray_point(p0r[i], p0i[i], dr[i], di[i], math.cos(bearing), math.sin(bearing), ta, ta, tb)
    return x, y, t, _CUT


@_compiled
def _sweep(p0r, p0i, dr, di, par, pai, pbr, pbi, e_ta, e_tb, e_sa, e_sb, e_phia, e_phib, e_back,  # type: ignore[no-untyped-def]
           good, labels, fov, full, min_piece, angle_tol, back_bias, join_tol):
    n = p0r.shape[0]
    two_pi = 2.0 * math.pi
    phi0 = -0.5 * fov
    ulo_r, ulo_i = math.cos(phi0), math.sin(phi0)
    uhi_r, uhi_i = math.cos(phi0 + fov), math.sin(phi0 + fov)
    # ---- sub-edges: each edge's part inside the window [0, fov] of sweep angle
    cap = 2 * n
    s_e = np.empty(cap, np.int64)
    s_phia = np.empty(cap)
    s_phib = np.empty(cap)
    s_par = np.empty(cap)
    s_pai = np.empty(cap)
    s_pbr = np.empty(cap)
    s_pbi = np.empty(cap)
    s_ta = np.empty(cap)
    s_tb = np.empty(cap)
    s_sa = np.empty(cap, np.int64)
    s_sb = np.empty(cap, np.int64)
    ns = 0
    for i in range(n):
        if not good[i]:
            continue
        a = e_phia[i]
        b = e_phib[i]
        if a >= two_pi:  # np.mod can round up to 2 pi
            a = 0.0
        if b >= two_pi:
            b = 0.0
        wrap = b < a
        for part in range(2):
            if part == 0:
                if not a < fov:
                    continue
                s_phia[ns] = a
                s_par[ns] = par[i]
                s_pai[ns] = pai[i]
                s_ta[ns] = e_ta[i]
                s_sa[ns] = e_sa[i]
                cut = wrap or b > fov
            else:
                if not (wrap and b > 0.0):
                    continue
                qx, qy, t = _ray_point(p0r[i], p0i[i], dr[i], di[i], ulo_r, ulo_i, e_ta[i], e_ta[i], e_tb[i])
                s_phia[ns] = 0.0
                s_par[ns] = qx
                s_pai[ns] = qy
                s_ta[ns] = t
                s_sa[ns] = _WINDOW
                cut = b > fov
            s_e[ns] = i
            if cut:
                qx, qy, t = _ray_point(p0r[i], p0i[i], dr[i], di[i], uhi_r, uhi_i, e_ta[i], e_ta[i], e_tb[i])
                s_phib[ns] = fov
                s_pbr[ns] = qx
                s_pbi[ns] = qy
                s_tb[ns] = t
                s_sb[ns] = _WINDOW
            else:
                s_phib[ns] = b
                s_pbr[ns] = pbr[i]
                s_pbi[ns] = pbi[i]
                s_tb[ns] = e_tb[i]
                s_sb[ns] = e_sb[i]
            ns += 1
    empty_i = np.zeros(0, np.int64)
    empty_f = np.zeros(0)
    if ns == 0:
        return empty_f, empty_f, empty_i, empty_i, empty_i, empty_i, empty_i, empty_f, empty_f, empty_i
    # ---- events: the end bearings sorted (stable), those within angle_tol grouped
    nv = 2 * ns + 2
    vals = np.empty(nv)
    vals[:ns] = s_phia[:ns]
    vals[ns:2 * ns] = s_phib[:ns]
    vals[2 * ns] = 0.0
    vals[2 * ns + 1] = fov
    order = np.argsort(vals, kind="mergesort")
    gid = np.empty(nv, np.int64)
    ev = np.empty(nv)
    n_ev = 0
    last = -np.inf
    for j in order:
        v = vals[j]
        if v - last > angle_tol:
            ev[n_ev] = v
            n_ev += 1
            last = v
        gid[j] = n_ev - 1
    ka = gid[:ns]
    kb = gid[ns:2 * ns]
    live = np.empty(ns, np.int64)
    n_live = 0
    for s in range(ns):
        if ka[s] < kb[s]:
            live[n_live] = s
            n_live += 1
    live = live[:n_live]
    # ---- the sweep: the nearest sub-edge of each elementary interval (-1: none)
    s_dx = s_pbr[:ns] - s_par[:ns]
    s_dy = s_pbi[:ns] - s_pai[:ns]
    s_cab = s_par[:ns] * s_pbi[:ns] - s_pai[:ns] * s_pbr[:ns]
    by_start = live[np.argsort(ka[live], kind="mergesort")]
    by_end = live[np.argsort(kb[live], kind="mergesort")]
    n_int = n_ev - 1
    nearest = np.full(max(n_int, 0), -1, np.int64)
    active = np.empty(max(n_live, 1), np.int64)
    n_act = 0
    si = 0
    ei = 0
    for k in range(n_int):
        while ei < n_live and kb[by_end[ei]] == k:
            x = by_end[ei]
            for r in range(n_act):
                if active[r] == x:
                    for q in range(r, n_act - 1):
                        active[q] = active[q + 1]
                    n_act -= 1
                    break
            ei += 1
        if si < n_live and ka[by_start[si]] == k:
            mid = phi0 + 0.5 * (ev[k] + ev[k + 1])
            ux = math.cos(mid)
            uy = math.sin(mid)
            while si < n_live and ka[by_start[si]] == k:
                x = by_start[si]
                den = ux * s_dy[x] - uy * s_dx[x]
                kx = np.inf if den <= 0.0 else s_cab[x] / den + (back_bias if e_back[s_e[x]] else 0.0)
                lo = 0
                hi = n_act
                while lo < hi:  # bisect_right
                    md = (lo + hi) // 2
                    y = active[md]
                    den = ux * s_dy[y] - uy * s_dx[y]
                    ky = np.inf if den <= 0.0 else s_cab[y] / den + (back_bias if e_back[s_e[y]] else 0.0)
                    if kx < ky:
                        hi = md
                    else:
                        lo = md + 1
                for q in range(n_act, lo, -1):
                    active[q] = active[q - 1]
                active[lo] = x
                n_act += 1
                si += 1
        if n_act > 0:
            nearest[k] = active[0]
    # ---- pieces: runs of intervals with the same nearest sub-edge
    pc_s0 = np.empty(max(n_int, 1), np.int64)
    pc_k0 = np.empty(max(n_int, 1), np.int64)
    pc_k1 = np.empty(max(n_int, 1), np.int64)
    pc_s1 = np.empty(max(n_int, 1), np.int64)
    n_p = 0
    for k in range(n_int):
        s = nearest[k]
        if n_p > 0 and pc_s0[n_p - 1] == s:
            pc_k1[n_p - 1] = k + 1
        else:
            pc_s0[n_p] = s
            pc_k0[n_p] = k
            pc_k1[n_p] = k + 1
            pc_s1[n_p] = s
            n_p += 1
    if full and n_p > 1:
        fs = pc_s0[0]
        ls = pc_s0[n_p - 1]
        if (fs >= 0 and ls >= 0 and s_e[fs] == s_e[ls] and s_sa[fs] == _WINDOW and pc_k0[0] == ka[fs]
                and s_sb[ls] == _WINDOW and pc_k1[n_p - 1] == kb[ls]):
            k0 = pc_k0[n_p - 1]
            k1 = pc_k1[0]
            pc_s0[0] = ls
            pc_k0[0] = k0
            pc_k1[0] = k1
            pc_s1[0] = fs
            n_p -= 1
    # ---- labels at every boundary between pieces
    out_x = np.empty(2 * n_p + 2)
    out_y = np.empty(2 * n_p + 2)
    out_lab = np.empty(2 * n_p + 2, np.int64)
    out_src = np.empty(2 * n_p + 2, np.int64)
    n_out = 0
    start_vid = np.full(n_p, -1, np.int64)
    end_vid = np.full(n_p, -1, np.int64)
    start_t = np.zeros(n_p)
    end_t = np.zeros(n_p)
    is_front = np.zeros(n_p, np.bool_)
    for i in range(n_p):
        is_front[i] = pc_s0[i] >= 0 and not e_back[s_e[pc_s0[i]]]
    n_b = n_p if full else n_p + 1
    for bi in range(n_b):
        if full:
            li = bi
            ri = (bi + 1) % n_p
        else:
            li = bi - 1
            ri = bi if bi < n_p else -1
        has_x = li >= 0 and pc_s1[li] >= 0
        has_y = ri >= 0 and pc_s0[ri] >= 0
        xx = xy_ = xt = 0.0
        xs_ = 0
        yx = yy = yt = 0.0
        ys_ = 0
        if has_x:  # the left piece's end
            s = pc_s1[li]
            xx, xy_, xt, xs_ = _piece_point(pc_k1[li], kb[s], s_pbr[s], s_pbi[s], s_tb[s], s_sb[s], phi0, ev,
                                            s_e[s], p0r, p0i, dr, di, s_ta[s], s_tb[s])
        if has_y:  # the right piece's start
            s = pc_s0[ri]
            yx, yy, yt, ys_ = _piece_point(pc_k0[ri], ka[s], s_par[s], s_pai[s], s_ta[s], s_sa[s], phi0, ev,
                                           s_e[s], p0r, p0i, dr, di, s_ta[s], s_tb[s])
        if has_x and has_y:
            dist_x = math.hypot(xx, xy_)
            dist_y = math.hypot(yx, yy)
            if math.hypot(xx - yx, xy_ - yy) <= join_tol * _py_max(1.0, dist_x):  # two walls meet: one corner
                if xs_ >= 0:
                    qx, qy, src = xx, xy_, xs_
                else:
                    qx, qy, src = yx, yy, ys_
                if src >= 0:
                    lab = _FRONTIER if labels[src] == _FRONTIER else _NOMINAL
                else:
                    lab = _FRONTIER
                vid = -1
                if is_front[li] or is_front[ri]:
                    vid = n_out
                    n_out = _put_vertex(out_x, out_y, out_lab, out_src, n_out, qx, qy, lab, src)
                end_vid[li] = vid
                start_vid[ri] = vid
                end_t[li] = xt
                start_t[ri] = yt
                continue
            # the nearer end is passed by sight, the farther one is a frontier
            x_near = dist_x < dist_y
            lab_x = _pass_label(labels, xs_) if x_near else _FRONTIER
            lab_y = _FRONTIER if x_near else _pass_label(labels, ys_)
        else:  # one side is outside the window or empty: a vertex on the window is a frontier
            window = li < 0 or ri < 0
            lab_x = _FRONTIER if (window or not has_x) else _pass_label(labels, xs_)
            lab_y = _FRONTIER if (window or not has_y) else _pass_label(labels, ys_)
        if has_x:
            end_t[li] = xt
            if is_front[li]:
                end_vid[li] = n_out
                n_out = _put_vertex(out_x, out_y, out_lab, out_src, n_out, xx, xy_, lab_x, xs_)
        if has_y:
            start_t[ri] = yt
            if is_front[ri]:
                start_vid[ri] = n_out
                n_out = _put_vertex(out_x, out_y, out_lab, out_src, n_out, yx, yy, lab_y, ys_)
    # ---- the scan's edges: front-facing pieces with two distinct ends min_piece apart
    ea = np.empty(n_p, np.int64)
    eb = np.empty(n_p, np.int64)
    e_src = np.empty(n_p, np.int64)
    et0 = np.empty(n_p)
    et1 = np.empty(n_p)
    n_e = 0
    for i in range(n_p):
        a_v = start_vid[i]
        b_v = end_vid[i]
        if not is_front[i] or a_v < 0 or b_v < 0 or a_v == b_v:
            continue
        if math.hypot(out_x[b_v] - out_x[a_v], out_y[b_v] - out_y[a_v]) < min_piece:
            continue
        ea[n_e] = a_v
        eb[n_e] = b_v
        e_src[n_e] = s_e[pc_s0[i]]
        et0[n_e] = start_t[i]
        et1[n_e] = end_t[i]
        n_e += 1
    live_e = np.empty(n_live, np.int64)
    for r in range(n_live):
        live_e[r] = s_e[live[r]]
    return (out_x[:n_out], out_y[:n_out], out_lab[:n_out], out_src[:n_out], ea[:n_e], eb[:n_e], e_src[:n_e],
            et0[:n_e], et1[:n_e], live_e)
