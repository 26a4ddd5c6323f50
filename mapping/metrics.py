"""Map-quality metrics: a wireframe map against a ground-truth wireframe (paper Sec. V).

Four measures, all pure functions of two :class:`~mapping.wireframe.Wireframe` values:

* :func:`cell_error` -- the paper's cell-by-cell comparison (Sec. V-A): both wireframes are
  rasterised on the same grid and the share of cells whose free/obstacle value differs is
  reported (the paper reports 1.51 % for its small environment).
* :func:`wall_precision_recall` -- how much of the map's wall length lies on a true wall
  (precision) and how much of the true wall length is covered by the map (recall).
* :func:`distance_to_truth` -- the paper's large-environment measure (Sec. V-B): the map's
  walls are finely discretised into points and each point's distance to the nearest true wall
  is taken; the paper reports a mean of 0.33 m. The 95th percentile is added.
* :func:`align_to_truth` -- the rigid motion that best lays the map onto the truth, to tell a
  map that is off as a whole (an early heading error turns everything after it) from one that
  is off in its parts; :func:`distance_to_truth` of the aligned map is reported beside the
  plain one, never instead of it (the start pose is known: the map's frame *is* the truth's).
* :func:`evaluate` -- all of them in one dictionary.

Free space comes from the edge direction convention (free space on the *left* of every directed
edge, see :mod:`mapping.wireframe`): :func:`free_space` cuts the plane into faces along the walls
and lets every face's bounding walls vote on which side they see.

Every edge counts whatever its likelihood; drop unlikely edges first with
:meth:`Wireframe.subgraph_edges` if that is wanted. Zero-length edges are ignored.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.ops import polygonize, unary_union

from mapping.geometry import point_segment_distance, projection_parameter
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Default angular tolerance of :func:`wall_precision_recall` (radians): a wall only matches a
#: wall within ``tol`` that is also within this angle of parallel.
DEFAULT_MAX_ANGLE = math.radians(30.0)

#: Largest raster :func:`cell_error` agrees to build (cells per map).
MAX_CELLS = 50_000_000

METRIC_KEYS = ("cell_error", "wall_precision", "wall_recall", "mean_dist_m", "p95_dist_m")


# ---------------------------------------------------------------------------- geometry helpers
def _scale(segs: FloatArray) -> float:
    """A length scale of the drawing, for relative tolerances."""
    if len(segs) == 0:
        return 1.0
    return max(1.0, float(np.abs(segs).max()))


def _directed_segments(wf: Wireframe) -> FloatArray:
    """``(m, 2, 2)`` edge segments of positive length, in edge direction."""
    s = wf.segments()
    if len(s) == 0:
        return s
    keep = np.hypot(*(s[:, 1] - s[:, 0]).T) > 0.0
    return np.asarray(s[keep], dtype=np.float64)


def _pieces_of(geom: Any) -> FloatArray:
    """All 2-point pieces ``(k, 2, 2)`` of the line work in ``geom`` (positive length only)."""
    parts = shapely.get_parts(shapely.get_parts(geom))  # unnest collections, then multi-parts
    parts = parts[shapely.get_type_id(parts) == 1]  # LineStrings only
    if len(parts) == 0:
        return np.zeros((0, 2, 2))
    coords, idx = shapely.get_coordinates(parts, return_index=True)
    same = idx[1:] == idx[:-1]
    pieces = np.stack([coords[:-1][same], coords[1:][same]], axis=1)
    keep = np.hypot(*(pieces[:, 1] - pieces[:, 0]).T) > 0.0
    return np.asarray(pieces[keep], dtype=np.float64)


def _noded(segs: FloatArray) -> Any:
    """The undirected line work of ``segs``, noded: crossing and touching segments are split
    where they meet and overlapping (e.g. opposite) segments are dissolved into one."""
    return unary_union(shapely.linestrings(segs))


def wall_pieces(wf: Wireframe) -> FloatArray:
    """The wireframe's walls as undirected, noded, non-overlapping 2-point pieces ``(k, 2, 2)``.

    A thin wall's two opposite edges become one line; crossing walls are split at the crossing.
    The total length is the length of the wall *drawing*, each stretch counted once.
    """
    segs = _directed_segments(wf)
    if len(segs) == 0:
        return np.zeros((0, 2, 2))
    return _pieces_of(_noded(segs))


def classify_faces(wf: Wireframe) -> tuple[list[Polygon], FloatArray]:
    """The faces the walls cut the plane into, each with its free-space vote.

    The undirected edge segments are noded (``shapely.ops.unary_union``) and polygonised
    (``shapely.ops.polygonize``); dangling walls and walls with the same face on both sides
    bound no face and so do not take part. Every face's boundary rings are oriented so that the
    face lies on their left (exterior counterclockwise, holes clockwise); each noded piece of a
    ring then adds ``+length`` for every directed edge that runs along it in the same direction
    (the edge has free space on its left, i.e. inside the face) and ``-length`` for every edge
    running the opposite way (the face is on the edge's solid side).

    Parameters
    ----------
    wf : Wireframe
        The map.

    Returns
    -------
    faces : list of shapely.geometry.Polygon
        The bounded faces, in polygonize order.
    votes : (len(faces),) float64
        Length-weighted vote per face in metres: positive means free, negative obstacle. A thin
        wall (two opposite edges) adds nothing to either side.
    """
    segs = _directed_segments(wf)
    if len(segs) == 0:
        return [], np.zeros(0)
    noded = _noded(segs)
    pieces = _pieces_of(noded)
    eps = 1e-9 * _scale(segs)

    # Net direction of every noded piece: which original directed edges run along it, and how.
    tree = shapely.STRtree(shapely.linestrings(segs))
    mids = 0.5 * (pieces[:, 0] + pieces[:, 1])
    pi, ei = tree.query(shapely.points(mids), predicate="dwithin", distance=eps)
    a, b = segs[ei, 0], segs[ei, 1]
    on_line = (point_segment_distance(pieces[pi, 0], a, b) <= eps) & (
        point_segment_distance(pieces[pi, 1], a, b) <= eps
    )
    pi, ei = pi[on_line], ei[on_line]
    sign = np.sign(np.einsum("ij,ij->i", pieces[pi, 1] - pieces[pi, 0], segs[ei, 1] - segs[ei, 0]))
    net = np.zeros(len(pieces))
    np.add.at(net, pi, sign)
    lengths = np.hypot(*(pieces[:, 1] - pieces[:, 0]).T)
    weight = net * lengths
    # Polygonize copies the noded coordinates, so the ring pieces are found by exact lookup.
    directed: dict[tuple[float, float, float, float], float] = {}
    for (p, q), w in zip(pieces.tolist(), weight.tolist()):
        directed[(p[0], p[1], q[0], q[1])] = w
        directed[(q[0], q[1], p[0], p[1])] = -w

    faces = [f for f in polygonize(shapely.get_parts(noded)) if f.area > 0.0]
    votes = np.zeros(len(faces))
    for k, face in enumerate(faces):
        oriented = shapely.orient_polygons(face, exterior_cw=False)
        total = 0.0
        for ring in (oriented.exterior, *oriented.interiors):
            c = shapely.get_coordinates(ring).tolist()
            for p, q in itertools.pairwise(c):
                total += directed.get((p[0], p[1], q[0], q[1]), 0.0)
        votes[k] = total
    return faces, votes


def free_space(wf: Wireframe) -> Any:
    """The free space of a wireframe as a shapely (multi)polygon.

    The union of the faces of :func:`classify_faces` whose vote is positive. A face whose walls
    give no directed evidence (vote exactly zero: e.g. the inside of a closed thin-walled box,
    whose every wall is seen from both sides) counts as *obstacle*, as does everything outside
    the faces: walls that close no face (an open, incomplete map) contribute no free space, so
    unexplored area counts as obstacle, like the paper's cell comparison where a cell is free
    only if its centre is known to be free.

    Parameters
    ----------
    wf : Wireframe
        The map.

    Returns
    -------
    shapely geometry
        A ``Polygon`` or ``MultiPolygon``; an empty geometry when nothing is free. Walls lie
        on its boundary (a point on a wall is not *contained*).
    """
    faces, votes = classify_faces(wf)
    free = [f for f, v in zip(faces, votes.tolist()) if v > 0.0]
    if not free:
        return Polygon()
    return shapely.union_all(free)


def _grid(truth: Wireframe, resolution: float) -> tuple[FloatArray, FloatArray]:
    """Cell centres ``(xs, ys)`` of the raster over the truth's bounding box."""
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
    if truth.n_edges == 0:
        raise ValueError("the ground truth has no walls")
    xmin, ymin, xmax, ymax = truth.bounds()
    # A tiny slack keeps 10 / 0.2 from becoming 51 cells through rounding.
    nx = max(1, math.ceil((xmax - xmin) / resolution - 1e-9))
    ny = max(1, math.ceil((ymax - ymin) / resolution - 1e-9))
    if nx * ny > MAX_CELLS:
        raise ValueError(
            f"a {nx} x {ny} raster at resolution {resolution} m is too large (more than {MAX_CELLS} cells)"
        )
    xs = xmin + (np.arange(nx, dtype=np.float64) + 0.5) * resolution
    ys = ymin + (np.arange(ny, dtype=np.float64) + 0.5) * resolution
    return np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)


def rasterize(wf: Wireframe, xs: FloatArray, ys: FloatArray) -> BoolArray:
    """Free-space raster ``(len(ys), len(xs))``: True where the cell centre ``(xs[i], ys[j])``
    lies strictly inside :func:`free_space` (a centre exactly on a wall is obstacle)."""
    free = free_space(wf)
    if free.is_empty:
        return np.zeros((len(ys), len(xs)), dtype=bool)
    shapely.prepare(free)
    gx, gy = np.meshgrid(xs, ys)
    return np.asarray(shapely.contains_xy(free, gx, gy), dtype=bool)


def cell_error(truth: Wireframe, wf: Wireframe, resolution: float) -> float:
    """Share of raster cells whose free/obstacle value differs from the truth (paper Sec. V-A).

    Both wireframes are rasterised over the truth's bounding box with square cells of side
    ``resolution``, the grid starting at the box's lower-left corner (``ceil(width / r)`` by
    ``ceil(height / r)`` cells, so the grid may overhang the box by less than one cell on the
    upper and right sides). A cell is free when its centre lies in :func:`free_space`, obstacle
    otherwise; open (incomplete) maps therefore count unexplored area as obstacle.

    Parameters
    ----------
    truth : Wireframe
        Ground truth; must have at least one edge.
    wf : Wireframe
        The map to score, in the truth's frame.
    resolution : float
        Cell side in metres (the paper uses the corner-merge threshold).

    Returns
    -------
    float
        Fraction of differing cells, in [0, 1]. The paper's score is this times the cell count.

    Raises
    ------
    ValueError
        When the resolution is not positive, the truth has no walls or the raster would exceed
        :data:`MAX_CELLS` cells.
    """
    xs, ys = _grid(truth, resolution)
    a = rasterize(truth, xs, ys)
    b = rasterize(wf, xs, ys)
    return float(np.count_nonzero(a != b)) / float(a.size)


# ---------------------------------------------------------------------------- wall sampling
def sample_walls(wf: Wireframe, spacing: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Points along the wireframe's walls (undirected, each stretch once: :func:`wall_pieces`).

    A piece of length ``L`` is cut into ``n = max(1, ceil(L / spacing))`` equal parts and
    sampled at their midpoints, each sample standing for ``L / n`` metres of wall; samples thus
    never sit on a corner, and length-weighted sums over them are exact for piecewise-constant
    quantities.

    Returns
    -------
    points : (k, 2) float64
    weights : (k,) float64
        Wall length each sample stands for; sums to the drawing's length.
    directions : (k, 2) float64
        Unit direction of the wall at each sample (sign arbitrary).
    """
    if not (math.isfinite(spacing) and spacing > 0.0):
        raise ValueError(f"sample spacing must be a positive number of metres, got {spacing}")
    pieces = wall_pieces(wf)
    if len(pieces) == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2))
    d = pieces[:, 1] - pieces[:, 0]
    lengths = np.hypot(d[:, 0], d[:, 1])
    n = np.maximum(1, np.ceil(lengths / spacing - 1e-9)).astype(np.int64)
    owner = np.repeat(np.arange(len(pieces)), n)
    first = np.cumsum(n) - n
    j = np.arange(int(n.sum())) - np.repeat(first, n)
    t = (j + 0.5) / n[owner]
    points = pieces[owner, 0] + t[:, None] * d[owner]
    weights = lengths[owner] / n[owner]
    directions = d[owner] / lengths[owner, None]
    return points, weights, directions


def _matched(
    points: FloatArray,
    directions: FloatArray,
    target: FloatArray,
    tol: float,
    max_angle: float | None,
) -> BoolArray:
    """For each sample: is a ``target`` piece within ``tol`` (and within ``max_angle`` of
    parallel, when given)?"""
    out = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(target) == 0:
        return out
    tree = shapely.STRtree(shapely.linestrings(target))
    si, ti = tree.query(shapely.points(points), predicate="dwithin", distance=tol)
    if max_angle is not None:
        td = target[ti, 1] - target[ti, 0]
        td /= np.hypot(td[:, 0], td[:, 1])[:, None]
        cos = np.abs(np.einsum("ij,ij->i", directions[si], td))
        ok = cos >= math.cos(max_angle) - 1e-12
        si = si[ok]
    out[si] = True
    return out


def wall_precision_recall(
    truth: Wireframe, wf: Wireframe, tol: float, max_angle: float | None = DEFAULT_MAX_ANGLE
) -> tuple[float, float]:
    """Length-weighted wall precision and recall.

    Precision is the share of the map's wall length lying within ``tol`` of a true wall; recall
    the share of the true wall length lying within ``tol`` of a map wall. Walls are undirected
    and each stretch counts once (a thin wall's two opposite edges are one line). Lengths are
    measured by sampling every ``tol / 4`` (:func:`sample_walls`).

    By default a wall only matches a wall that is also near-parallel (within ``max_angle``,
    undirected): without this, the ends of a missing wall would count as found because they lie
    within ``tol`` of the perpendicular walls at its corners, and a deleted wall would lower the
    recall by less than its share of the length. Pass ``max_angle=None`` for the plain distance
    test.

    Parameters
    ----------
    truth, wf : Wireframe
        Ground truth (at least one wall) and the map, in the same frame.
    tol : float
        Distance tolerance in metres, positive.
    max_angle : float or None
        Angular tolerance in radians, or None for none.

    Returns
    -------
    (precision, recall) : tuple of float
        Both in [0, 1]. An empty map has precision 1.0 (it claims no wall, so claims nothing
        wrong) and recall 0.0.

    Raises
    ------
    ValueError
        When ``tol`` is not positive or the truth has no walls.
    """
    if not (math.isfinite(tol) and tol > 0.0):
        raise ValueError(f"tolerance must be a positive number of metres, got {tol}")
    if max_angle is not None and not (0.0 <= max_angle <= math.pi / 2):
        raise ValueError(f"max_angle must be within [0, pi/2] radians, got {max_angle}")
    t_pieces = wall_pieces(truth)
    if len(t_pieces) == 0:
        raise ValueError("the ground truth has no walls")
    m_pieces = wall_pieces(wf)
    spacing = tol / 4.0
    tp, tw, td = sample_walls(truth, spacing)
    mp, mw, md = sample_walls(wf, spacing)
    if len(mp) == 0:
        return 1.0, 0.0
    precision = float(mw[_matched(mp, md, t_pieces, tol, max_angle)].sum() / mw.sum())
    recall = float(tw[_matched(tp, td, m_pieces, tol, max_angle)].sum() / tw.sum())
    return min(1.0, precision), min(1.0, recall)


def _weighted_quantile(values: FloatArray, weights: FloatArray, q: float) -> float:
    """Smallest value whose cumulative weight share reaches ``q`` (inverted-CDF quantile)."""
    order = np.argsort(values, kind="stable")
    cw = np.cumsum(weights[order])
    k = int(np.searchsorted(cw, q * cw[-1] * (1.0 - 1e-12), side="left"))
    return float(values[order][min(k, len(values) - 1)])


def distance_to_truth(truth: Wireframe, wf: Wireframe, step: float) -> tuple[float, float]:
    """Mean and 95th percentile distance from the map's walls to the nearest true wall
    (paper Sec. V-B, where the mean was 0.33 m for the 200 m museum).

    The map's walls (undirected, each stretch once) are sampled every ``step`` or closer
    (:func:`sample_walls`); both statistics are weighted by the wall length each sample stands
    for, so they do not depend on how the walls are split into edges.

    Returns
    -------
    (mean, p95) : tuple of float
        Metres. ``(nan, nan)`` for an empty map (no wall to measure).

    Raises
    ------
    ValueError
        When ``step`` is not positive or the truth has no walls.
    """
    t_pieces = wall_pieces(truth)
    if len(t_pieces) == 0:
        raise ValueError("the ground truth has no walls")
    points, weights, _ = sample_walls(wf, step)
    if len(points) == 0:
        return math.nan, math.nan
    tree = shapely.STRtree(shapely.linestrings(t_pieces))
    _, dist = tree.query_nearest(shapely.points(points), return_distance=True, all_matches=False)
    dist = np.asarray(dist, dtype=np.float64)
    mean = float(np.dot(dist, weights) / weights.sum())
    return mean, _weighted_quantile(dist, weights, 0.95)


def rigid_fit(a: FloatArray, b: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(R, t)`` minimising the ``w``-weighted squared distances of ``R a + t`` to ``b`` (2D
    Kabsch / Umeyama, no scale, no reflection)."""
    ca = (a * w[:, None]).sum(0) / w.sum()
    cb = (b * w[:, None]).sum(0) / w.sum()
    H = ((a - ca) * w[:, None]).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0)])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def align_to_truth(
    truth: Wireframe, wf: Wireframe, step: float, iterations: int = 100, keep: float = 0.9
) -> Pose:
    """The rigid motion that lays the map's walls best onto the true walls.

    Trimmed ICP: the map's walls sampled every ``step`` (:func:`sample_walls`), each sample
    paired with the closest point of the nearest true wall, the ``keep`` share of closest pairs
    aligned in closed form (Kabsch / Umeyama, length-weighted), repeated from the identity until
    it stops moving or ``iterations`` times.

    Returns
    -------
    Pose
        ``T`` such that ``wf.transformed(T)`` is the aligned map (identity for an empty map).

    Raises
    ------
    ValueError
        When ``step`` is not positive, ``keep`` not in (0, 1] or the truth has no walls.
    """
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"step must be a positive number of metres, got {step}")
    if not (0.0 < keep <= 1.0):
        raise ValueError(f"keep must be within (0, 1], got {keep}")
    pieces = wall_pieces(truth)
    if len(pieces) == 0:
        raise ValueError("the ground truth has no walls")
    mp, mw, _ = sample_walls(wf, step)
    if len(mp) < 2:
        return Pose.identity()
    tree = shapely.STRtree(shapely.linestrings(pieces))
    R, t = np.eye(2), np.zeros(2)
    for _ in range(iterations):
        q = mp @ R.T + t
        idx = tree.query_nearest(shapely.points(q), all_matches=False)
        src, seg = idx[0], idx[1]
        a0, d0 = pieces[seg, 0], pieces[seg, 1] - pieces[seg, 0]
        u = np.clip(projection_parameter(q[src], pieces[seg, 0], pieces[seg, 1]), 0.0, 1.0)
        target = a0 + u[:, None] * d0
        d = np.hypot(*(q[src] - target).T)
        sel = d <= np.quantile(d, keep)
        R_new, t_new = rigid_fit(mp[src[sel]], target[sel], mw[src[sel]])
        done = np.abs(R_new - R).max() < 1e-9 and np.abs(t_new - t).max() < 1e-7
        R, t = R_new, t_new
        if done:
            break
    return Pose(float(t[0]), float(t[1]), math.atan2(R[1, 0], R[0, 0]))


def evaluate(
    truth: Wireframe, wf: Wireframe, resolution: float, tol: float | None = None
) -> dict[str, float]:
    """All metrics of a map against the truth.

    Parameters
    ----------
    truth, wf : Wireframe
        Ground truth (at least one wall) and map, in the same frame.
    resolution : float
        Raster cell side for :func:`cell_error` and sample step for :func:`distance_to_truth`.
    tol : float, optional
        Wall-matching tolerance for :func:`wall_precision_recall`; ``2 * resolution`` if omitted.

    Returns
    -------
    dict
        Exactly the keys of :data:`METRIC_KEYS`: ``cell_error``, ``wall_precision``,
        ``wall_recall``, ``mean_dist_m``, ``p95_dist_m`` (the distances are NaN for an empty map).
    """
    tol_m = 2.0 * resolution if tol is None else tol
    precision, recall = wall_precision_recall(truth, wf, tol_m)
    mean, p95 = distance_to_truth(truth, wf, resolution)
    return {
        "cell_error": cell_error(truth, wf, resolution),
        "wall_precision": precision,
        "wall_recall": recall,
        "mean_dist_m": mean,
        "p95_dist_m": p95,
    }
