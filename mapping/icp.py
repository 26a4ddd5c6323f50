"""Wireframe matching: correspondences and a modified ICP over wireframes (paper Sec. IV-C).

The measured scan and the predicted scan (the best particle seen from the odometry-predicted
pose) do not line up because of odometry error and sensor noise. This module finds

* **vertex correspondences**, one-to-one by distance (:func:`match_vertices`: candidate pairs
  from a :class:`scipy.spatial.cKDTree`, the assignment from
  :func:`scipy.optimize.linear_sum_assignment`);
* **edge correspondences**, many-to-many ("duplicates allowed", :func:`match_edges`): two
  directed edges correspond when their directions agree (edges of opposite direction never
  correspond: the back of a wall is not the wall, paper Fig. 5), their projections overlap and
  the offset between them over the overlap is small; edges whose two end vertices correspond
  always correspond;
* the rigid correction (:func:`icp`) that moves the scan onto the prediction. With the scan
  taken at the predicted pose ``x_pred``, the corrected robot pose is
  ``x_pred.compose(result.correction)``.

Choices where the paper is silent
---------------------------------
* Frontier vertices are artefacts of the view, not corners: they never give a point-to-point
  constraint. Point-to-point constraints come from vertex pairs where neither end is a frontier;
  every edge correspondence adds two point-to-line constraints (the ends of the overlap of the
  scan edge, onto the predicted edge's line). Frontier ends therefore only pin a wall sideways.
* The vertex assignment prefers pairs of the same kind: a frontier paired with a corner costs
  :attr:`ICPConfig.frontier_penalty` metres extra (it is still allowed, within the gate).
* Robustness to outliers: a correspondence gate that shrinks from ``gate_start`` to
  ``gate_end`` over the first iterations, one-to-one vertex pairs, and Huber weights on the
  residuals (iteratively reweighted Gauss-Newton).
* Degenerate geometry (a featureless corridor constrains only one direction): a weak Gaussian
  prior on the correction (``prior_sigma_xy``, ``prior_sigma_theta``) keeps the unobservable
  directions at the odometry prediction instead of letting them drift.
* Acceptance: the correction is marked ``accepted`` only with at least ``min_constraints``
  inlier constraints, at least ``min_matched_fraction`` of the scan's wall length matched, an
  inlier RMS residual of at most ``max_rmse`` and a correction within
  ``max_translation``/``max_rotation`` (a scan step's odometry error is far smaller; a larger
  "correction" is a wrong match). The filter falls back to odometry otherwise.

References
----------
P. J. Besl and N. D. McKay, "A method for registration of 3-D shapes", PAMI 1992 (ICP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_DENSE_MAX = 4096  # vertex pairs up to which a dense distance matrix replaces the k-d trees

__all__ = [
    "Correspondences",
    "ICPConfig",
    "ICPResult",
    "correspond",
    "edge_overlap",
    "icp",
    "match_edges",
    "match_vertices",
    "project_onto_segments",
]


@dataclass(frozen=True)
class ICPConfig:
    """Parameters of :func:`icp` and of the correspondence tests.

    Parameters
    ----------
    max_iterations : int
        Gauss-Newton iterations at most.
    anneal_iterations : int
        Iterations over which the gate shrinks linearly from ``gate_start`` to ``gate_end``.
    gate_start, gate_end : float
        Correspondence gate in metres: vertices farther apart, and edges offset by more, do not
        correspond. Large at first to capture odometry error, small at the end to reject outliers.
    max_angle : float
        Largest angle (radians) between the directions of two corresponding edges.
    min_overlap : float
        Two edges correspond only if their projections overlap by at least this many metres (or
        half the shorter edge, whichever is less).
    frontier_penalty : float
        Extra assignment cost (metres) for pairing a frontier vertex with a non-frontier one.
    huber : float
        Huber threshold (metres) of the residual weights.
    sigma : float
        Standard deviation (metres) of one constraint residual; scales against the prior.
    prior_sigma_xy, prior_sigma_theta : float
        Standard deviations of the Gaussian prior that keeps the correction near zero (the
        odometry prediction), in metres and radians.
    tol : float
        Stop when an increment moves less than this (metres, and radians times 1 m).
    min_constraints : int
        Fewest inlier constraints (rows) for an accepted correction.
    min_matched_fraction : float
        Least fraction of the scan's edges (by length) that must correspond to a reference edge
        for an accepted correction.
    max_rmse : float
        Largest inlier RMS residual (metres) for an accepted correction.
    max_translation, max_rotation : float
        Largest accepted correction (metres, radians).
    """

    max_iterations: int = 20
    anneal_iterations: int = 4
    gate_start: float = 1.0
    gate_end: float = 0.3
    max_angle: float = 0.35
    min_overlap: float = 0.1
    frontier_penalty: float = 0.25
    huber: float = 0.08
    sigma: float = 0.05
    prior_sigma_xy: float = 0.5
    prior_sigma_theta: float = 0.25
    tol: float = 5e-4
    min_constraints: int = 4
    min_matched_fraction: float = 0.3
    max_rmse: float = 0.1
    max_translation: float = 0.5
    max_rotation: float = 0.35

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.anneal_iterations < 0:
            raise ValueError("max_iterations must be >= 1 and anneal_iterations >= 0")
        for name in ("gate_start", "gate_end", "max_angle", "huber", "sigma", "prior_sigma_xy",
                     "prior_sigma_theta", "tol", "max_rmse", "max_translation", "max_rotation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ICPConfig.{name} must be a positive number, got {v!r}")
        if self.gate_end > self.gate_start:
            raise ValueError("ICPConfig.gate_end must not exceed gate_start")
        if self.min_overlap < 0 or self.frontier_penalty < 0 or self.min_constraints < 0:
            raise ValueError("min_overlap, frontier_penalty and min_constraints must be >= 0")
        if not 0.0 <= self.min_matched_fraction <= 1.0:
            raise ValueError("min_matched_fraction must be within [0, 1]")


@dataclass(frozen=True)
class Correspondences:
    """Vertex and edge correspondences between a scan ``S`` and a reference ``P``.

    Attributes
    ----------
    vertex_pairs : (k, 2) int64
        ``(scan vertex, reference vertex)``, one-to-one.
    vertex_dist : (k,) float64
        Distance between the paired vertices.
    edge_pairs : (l, 2) int64
        ``(scan edge, reference edge)``, many-to-many.
    edge_offset : (l,) float64
        Largest perpendicular offset over the overlap of each edge pair.
    edge_lo, edge_hi : (l,) float64
        The overlap as arc-length parameters along the scan edge.
    """

    vertex_pairs: IntArray
    vertex_dist: FloatArray
    edge_pairs: IntArray
    edge_offset: FloatArray
    edge_lo: FloatArray = field(default_factory=lambda: np.zeros(0))
    edge_hi: FloatArray = field(default_factory=lambda: np.zeros(0))

    def scan_vertex_match(self, n_scan: int) -> IntArray:
        """Reference vertex of each scan vertex, -1 where there is none."""
        out = np.full(n_scan, -1, dtype=np.int64)
        out[self.vertex_pairs[:, 0]] = self.vertex_pairs[:, 1]
        return out

    def ref_vertex_match(self, n_ref: int) -> IntArray:
        """Scan vertex of each reference vertex, -1 where there is none."""
        out = np.full(n_ref, -1, dtype=np.int64)
        out[self.vertex_pairs[:, 1]] = self.vertex_pairs[:, 0]
        return out

    def scan_edge_matched(self, m_scan: int) -> BoolArray:
        out = np.zeros(m_scan, dtype=bool)
        out[self.edge_pairs[:, 0]] = True
        return out

    def ref_edge_matched(self, m_ref: int) -> BoolArray:
        out = np.zeros(m_ref, dtype=bool)
        out[self.edge_pairs[:, 1]] = True
        return out


@dataclass(frozen=True)
class ICPResult:
    """Outcome of :func:`icp`.

    Attributes
    ----------
    correction : Pose
        The rigid motion that maps scan points onto the reference (scan frame to reference
        frame). The corrected pose is ``predicted_pose.compose(correction)``.
    accepted : bool
        Whether the correction passed the acceptance tests of :class:`ICPConfig`.
    correspondences : Correspondences
        The correspondences at the final gate, scan moved by ``correction``.
    rmse : float
        Inlier RMS residual (metres) at the end.
    n_constraints : int
        Inlier constraint rows at the end (point-to-point pairs count twice).
    iterations : int
    reason : str
        Why the correction was rejected ("" when accepted).
    """

    correction: Pose
    accepted: bool
    correspondences: Correspondences
    rmse: float
    n_constraints: int
    iterations: int
    reason: str = ""


# ---------------------------------------------------------------------------------- geometry
def project_onto_segments(points: FloatArray, segments: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
    """Closest point on any of ``segments`` for each point.

    Parameters
    ----------
    points : (n, 2)
    segments : (m, 2, 2), m >= 1

    Returns
    -------
    index : (n,) int64
        The nearest segment.
    closest : (n, 2)
        The closest point on it.
    dist : (n,)
        The distance.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    if s.shape[0] == 0:
        raise ValueError("project_onto_segments needs at least one segment")
    a = s[None, :, 0, :]
    d = s[None, :, 1, :] - a
    dd = np.einsum("...i,...i->...", d, d)
    t = np.einsum("...i,...i->...", p[:, None, :] - a, d) / np.where(dd > 0, dd, 1.0)
    t = np.clip(t, 0.0, 1.0)
    c = a + t[..., None] * d
    dist2 = np.einsum("...i,...i->...", p[:, None, :] - c, p[:, None, :] - c)
    idx = np.argmin(dist2, axis=1)
    rows = np.arange(p.shape[0])
    return idx.astype(np.int64), c[rows, idx], np.sqrt(dist2[rows, idx])


def edge_overlap(
    scan_segments: FloatArray, ref_segments: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Pairwise geometry of two sets of directed segments.

    Returns ``(cos_angle, lo, hi, offset, ref_len)``, each ``(ms, mr)``: the cosine of the angle
    between the directions; the overlap ``[lo, hi]`` of the reference segment's projection with
    the scan segment, as arc length along the scan segment (empty when ``hi <= lo``); the
    largest distance from the scan segment to the reference line over that overlap; and the
    reference lengths broadcast.
    """
    s = np.asarray(scan_segments, dtype=np.float64).reshape(-1, 2, 2)
    r = np.asarray(ref_segments, dtype=np.float64).reshape(-1, 2, 2)
    ds = s[:, 1] - s[:, 0]
    dr = r[:, 1] - r[:, 0]
    ls = np.hypot(ds[:, 0], ds[:, 1])
    lr = np.hypot(dr[:, 0], dr[:, 1])
    us = ds / np.where(ls > 0, ls, 1.0)[:, None]
    ur = dr / np.where(lr > 0, lr, 1.0)[:, None]
    cos = us @ ur.T
    t1 = np.einsum("smi,si->sm", r[None, :, 0, :] - s[:, None, 0, :], us)
    t2 = np.einsum("smi,si->sm", r[None, :, 1, :] - s[:, None, 0, :], us)
    lo = np.maximum(0.0, np.minimum(t1, t2))
    hi = np.minimum(ls[:, None], np.maximum(t1, t2))
    nr = np.stack([-ur[:, 1], ur[:, 0]], axis=1)  # left normals of the reference edges
    p_lo = s[:, None, 0, :] + lo[..., None] * us[:, None, :]
    p_hi = s[:, None, 0, :] + hi[..., None] * us[:, None, :]
    d_lo = np.einsum("smi,mi->sm", p_lo - r[None, :, 0, :], nr)
    d_hi = np.einsum("smi,mi->sm", p_hi - r[None, :, 0, :], nr)
    offset = np.maximum(np.abs(d_lo), np.abs(d_hi))
    return cos, lo, hi, offset, np.broadcast_to(lr[None, :], cos.shape)


# ---------------------------------------------------------------------------- correspondences
def match_vertices(
    scan_points: FloatArray,
    ref_points: FloatArray,
    gate: float,
    scan_labels: NDArray[np.uint8] | None = None,
    ref_labels: NDArray[np.uint8] | None = None,
    frontier_penalty: float = 0.0,
) -> tuple[IntArray, FloatArray]:
    """One-to-one vertex correspondences by distance (paper Sec. IV-C).

    Candidate pairs within ``gate`` come from a k-d tree (a dense distance matrix for small
    inputs); when they are ambiguous (a vertex with several candidates), the assignment
    minimising the total cost (distance, plus ``frontier_penalty`` where exactly one of the two
    is a frontier) is solved exactly by ``linear_sum_assignment`` on the candidates.

    Returns
    -------
    pairs : (k, 2) int64
        ``(scan index, reference index)`` sorted by scan index.
    dist : (k,) float64
    """
    a = np.asarray(scan_points, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(ref_points, dtype=np.float64).reshape(-1, 2)
    empty = (np.zeros((0, 2), dtype=np.int64), np.zeros(0))
    if len(a) == 0 or len(b) == 0:
        return empty
    if len(a) * len(b) <= _DENSE_MAX:
        # Small scans: one dense distance matrix is cheaper than building two trees.
        dd = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
        ia, ib = np.nonzero(dd <= gate)
        dv = dd[ia, ib]
        ia = ia.astype(np.int64)
        ib = ib.astype(np.int64)
    else:
        sdm = cKDTree(a).sparse_distance_matrix(cKDTree(b), gate, output_type="ndarray")
        ia = sdm["i"].astype(np.int64)
        ib = sdm["j"].astype(np.int64)
        dv = sdm["v"].astype(np.float64)
    if len(ia) == 0:
        return empty
    if len(np.unique(ia)) == len(ia) and len(np.unique(ib)) == len(ib):
        # Unambiguous: every candidate pair is disjoint from the others.
        order = np.argsort(ia, kind="stable")
        return np.stack([ia[order], ib[order]], axis=1), dv[order]
    cost_v = dv.copy()
    if frontier_penalty > 0 and scan_labels is not None and ref_labels is not None:
        fa = np.asarray(scan_labels)[ia] == Label.FRONTIER
        fb = np.asarray(ref_labels)[ib] == Label.FRONTIER
        cost_v = cost_v + frontier_penalty * (fa != fb)
    ra, inv_a = np.unique(ia, return_inverse=True)
    rb, inv_b = np.unique(ib, return_inverse=True)
    big = 10.0 * (gate + frontier_penalty) + 1.0
    cost = np.full((len(ra), len(rb)), big)
    dist = np.full((len(ra), len(rb)), np.inf)
    cost[inv_a, inv_b] = cost_v
    dist[inv_a, inv_b] = dv
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < big
    rows, cols = rows[ok], cols[ok]
    pairs = np.stack([ra[rows], rb[cols]], axis=1).astype(np.int64)
    order = np.argsort(pairs[:, 0], kind="stable")
    return pairs[order], dist[rows, cols][order]


def match_edges(
    scan: Wireframe,
    ref: Wireframe,
    vertex_pairs: IntArray,
    max_offset: float,
    max_angle: float,
    min_overlap: float = 0.1,
    scan_points: FloatArray | None = None,
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """Edge correspondences, duplicates allowed (paper Sec. IV-C).

    A scan edge and a reference edge correspond if (a) both their end vertices correspond, in
    order, or (b) their directions differ by at most ``max_angle`` (directed: opposite edges
    never correspond), their projections overlap by at least ``min(min_overlap, half the
    shorter edge)`` and the perpendicular offset over the overlap is at most ``max_offset``.

    ``scan_points`` replaces the scan's vertex positions (the scan moved by a trial pose).

    Returns
    -------
    pairs : (l, 2) int64
        ``(scan edge, reference edge)``.
    offset, lo, hi : (l,) float64
        Offset over the overlap, and the overlap along the scan edge (arc length).
    """
    empty = (np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros(0))
    if scan.n_edges == 0 or ref.n_edges == 0:
        return empty
    sp = scan.points if scan_points is None else np.asarray(scan_points, dtype=np.float64)
    ss = sp[scan.edges]
    rs = ref.segments()
    cos, lo, hi, offset, lr = edge_overlap(ss, rs)
    ls = np.hypot(*(ss[:, 1] - ss[:, 0]).T)
    need = np.minimum(min_overlap, 0.5 * np.minimum(ls[:, None], lr))
    geo = (cos >= math.cos(max_angle)) & (hi - lo >= need) & (offset <= max_offset)
    if len(vertex_pairs):
        vmap = np.full(scan.n_vertices, -1, dtype=np.int64)
        vmap[vertex_pairs[:, 0]] = vertex_pairs[:, 1]
        ea = vmap[scan.edges[:, 0]]
        eb = vmap[scan.edges[:, 1]]
        both = (ea >= 0) & (eb >= 0)
        if np.any(both):
            # Reference edges keyed by (from, to): a scan edge whose ends map onto one corresponds.
            n_ref = ref.n_vertices
            key_ref = ref.edges[:, 0].astype(np.int64) * n_ref + ref.edges[:, 1]
            key_scan = np.where(both, ea * n_ref + eb, -1)
            hit = key_scan[:, None] == key_ref[None, :]
            hit &= both[:, None]
            geo |= hit
            # An endpoint-matched pair may have an empty overlap test; give it the full edge.
            lo = np.where(hit, 0.0, lo)
            hi = np.where(hit, np.maximum(hi, ls[:, None]), hi)
    si, ri = np.nonzero(geo)
    pairs = np.stack([si, ri], axis=1).astype(np.int64)
    return pairs, offset[si, ri], lo[si, ri], hi[si, ri]


def correspond(
    scan: Wireframe,
    ref: Wireframe,
    gate: float,
    max_angle: float = 0.35,
    min_overlap: float = 0.1,
    frontier_penalty: float = 0.25,
    scan_points: FloatArray | None = None,
) -> Correspondences:
    """Vertex and edge correspondences of ``scan`` (optionally moved: ``scan_points``) against
    ``ref``, with one gate (metres) for vertex distance and edge offset."""
    sp = scan.points if scan_points is None else np.asarray(scan_points, dtype=np.float64)
    vp, vd = match_vertices(sp, ref.points, gate, scan.labels, ref.labels, frontier_penalty)
    ep, eo, elo, ehi = match_edges(scan, ref, vp, gate, max_angle, min_overlap, scan_points=sp)
    return Correspondences(vp, vd, ep, eo, elo, ehi)


# ---------------------------------------------------------------------------------------- ICP
def _constraints(
    scan: Wireframe, ref: Wireframe, sp: FloatArray, corr: Correspondences
) -> tuple[FloatArray, FloatArray]:
    """Stack the linearised constraints at the current scan points ``sp``.

    Returns ``(J, r)``: rows ``J @ delta + r`` ~ 0, ``delta = (dx, dy, dtheta)`` applied as
    ``R(dtheta) p + (dx, dy)`` about the robot (the origin of the scan frame).
    """
    rows_j: list[FloatArray] = []
    rows_r: list[FloatArray] = []
    vp = corr.vertex_pairs
    if len(vp):
        keep = (scan.labels[vp[:, 0]] != Label.FRONTIER) & (ref.labels[vp[:, 1]] != Label.FRONTIER)
        vp = vp[keep]
    if len(vp):
        p = sp[vp[:, 0]]
        q = ref.points[vp[:, 1]]
        k = len(vp)
        jx = np.zeros((k, 3))
        jx[:, 0] = 1.0
        jx[:, 2] = -p[:, 1]
        jy = np.zeros((k, 3))
        jy[:, 1] = 1.0
        jy[:, 2] = p[:, 0]
        rows_j += [jx, jy]
        rows_r += [p[:, 0] - q[:, 0], p[:, 1] - q[:, 1]]
    ep = corr.edge_pairs
    if len(ep):
        a = sp[scan.edges[ep[:, 0], 0]]
        b = sp[scan.edges[ep[:, 0], 1]]
        d = b - a
        ln = np.hypot(d[:, 0], d[:, 1])
        u = d / np.where(ln > 0, ln, 1.0)[:, None]
        ra = ref.points[ref.edges[ep[:, 1], 0]]
        rb = ref.points[ref.edges[ep[:, 1], 1]]
        dr = rb - ra
        lr = np.hypot(dr[:, 0], dr[:, 1])
        ur = dr / np.where(lr > 0, lr, 1.0)[:, None]
        n = np.stack([-ur[:, 1], ur[:, 0]], axis=1)
        for t in (corr.edge_lo, corr.edge_hi):
            p = a + t[:, None] * u
            j = np.empty((len(ep), 3))
            j[:, 0] = n[:, 0]
            j[:, 1] = n[:, 1]
            j[:, 2] = -n[:, 0] * p[:, 1] + n[:, 1] * p[:, 0]
            rows_j.append(j)
            rows_r.append(np.einsum("ij,ij->i", p - ra, n))
    if not rows_j:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(rows_j), np.concatenate(rows_r)


def icp(scan: Wireframe, ref: Wireframe, config: ICPConfig | None = None, initial: Pose | None = None) -> ICPResult:
    """Align ``scan`` onto ``ref`` with a modified ICP over wireframes (paper Sec. IV-C).

    Both wireframes are in the frame of the predicted robot pose (the robot at the origin).
    Each iteration re-computes the vertex and edge correspondences at the current alignment
    and the current gate, builds point-to-point and point-to-line constraints (see the module
    docstring), and takes one iteratively reweighted (Huber) Gauss-Newton step with a weak
    prior on the correction.

    Parameters
    ----------
    scan, ref : Wireframe
        The measured scan and the predicted scan, robot frame.
    config : ICPConfig, optional
    initial : Pose, optional
        Starting correction (identity by default).

    Returns
    -------
    ICPResult
        ``correction`` maps scan points onto the reference.
    """
    cfg = config or ICPConfig()
    T = initial or Pose.identity()
    empty = Correspondences(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, 2), np.int64), np.zeros(0))
    if scan.n_vertices == 0 or ref.n_vertices == 0:
        return ICPResult(T, False, empty, math.inf, 0, 0, "empty scan or reference")
    w_prior = np.array([1.0 / cfg.prior_sigma_xy**2, 1.0 / cfg.prior_sigma_xy**2, 1.0 / cfg.prior_sigma_theta**2])
    inv_s2 = 1.0 / cfg.sigma**2
    it = 0
    for it in range(1, cfg.max_iterations + 1):
        frac = min(1.0, (it - 1) / cfg.anneal_iterations) if cfg.anneal_iterations else 1.0
        gate = cfg.gate_start + (cfg.gate_end - cfg.gate_start) * frac
        sp = T.apply(scan.points)
        corr = correspond(scan, ref, gate, cfg.max_angle, cfg.min_overlap, cfg.frontier_penalty, scan_points=sp)
        J, r = _constraints(scan, ref, sp, corr)
        absr = np.abs(r)
        w = np.where(absr <= cfg.huber, 1.0, cfg.huber / np.maximum(absr, 1e-12)) * inv_s2
        H = (J * w[:, None]).T @ J + np.diag(w_prior)
        tvec = np.array([T.x, T.y, T.theta])
        g = (J * w[:, None]).T @ r + w_prior * tvec
        try:
            delta = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = Pose(float(delta[0]), float(delta[1]), float(delta[2])).compose(T)
        if frac >= 1.0 and math.hypot(delta[0], delta[1]) + abs(delta[2]) < cfg.tol:
            break
    sp = T.apply(scan.points)
    corr = correspond(scan, ref, cfg.gate_end, cfg.max_angle, cfg.min_overlap, cfg.frontier_penalty, scan_points=sp)
    J, r = _constraints(scan, ref, sp, corr)
    inl = np.abs(r) <= cfg.gate_end
    n_c = int(inl.sum())
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if n_c else math.inf
    lengths = scan.edge_lengths()
    total = float(lengths.sum())
    matched = float(lengths[corr.scan_edge_matched(scan.n_edges)].sum())
    frac_matched = matched / total if total > 0 else 0.0
    reason = ""
    if n_c < cfg.min_constraints:
        reason = f"too few constraints ({n_c} < {cfg.min_constraints})"
    elif frac_matched < cfg.min_matched_fraction:
        reason = f"too little of the scan matched ({frac_matched:.0%})"
    elif rmse > cfg.max_rmse:
        reason = f"residual too large ({rmse:.3f} m > {cfg.max_rmse} m)"
    elif math.hypot(T.x, T.y) > cfg.max_translation or abs(T.theta) > cfg.max_rotation:
        reason = "correction too large"
    return ICPResult(T, reason == "", corr, rmse, n_c, it, reason)
