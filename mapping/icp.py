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

The correction is a *maximum a posteriori* estimate: the odometry prediction is a Gaussian prior
on it (``prior_covariance``, the filter's pose uncertainty), and the scan only corrects the
directions it actually constrains.

Choices where the paper is silent
---------------------------------
* **What constrains what.** A wall only tells where its *line* is: every edge correspondence
  gives two *point-to-line* constraints (the two ends of the overlap of the scan edge, residual
  perpendicular to the predicted edge's line), never a constraint along the wall. A
  *point-to-point* constraint comes only from a real corner matched to a real corner (labels in
  :attr:`ICPConfig.corner_labels`, nominal and occlusion by default: an occlusion vertex is a
  real corner seen as a silhouette). Frontier vertices are where sight of a wall ended, not
  corners: they never pin a wall along its length.
* **Degeneracy-aware update** (after Zhang, Kaess and Singh, "On degeneracy of optimization-based
  state estimation problems", ICRA 2016). The Gauss-Newton information ``H = J^T W J /
  sigma^2`` of the constraints is compared with the prior's information ``P^-1`` by the
  generalised eigen-decomposition ``H v = lambda P^-1 v`` (the eigenvalues of ``L^T H L`` with
  ``P = L L^T``). A direction whose ``lambda`` is below :attr:`ICPConfig.min_information_ratio`
  is *degenerate*: the scan knows less about it than the odometry does (a corridor along its
  axis, a single wall along itself, the rotation when only a few nearby points match). The
  solution is confined to the well-constrained directions (the degenerate ones keep the
  odometry prediction); along a constrained direction the MAP estimate weighs scan and prior.
  The result carries the posterior covariance (the prior where degenerate).
* **Gates** (each a reason for ``accepted = False``; the filter then keeps the prediction):
  too few inlier constraints or too little of the scan matched; a large inlier RMS residual;
  no well-constrained direction; constraints whose own optimum is too far from the prediction
  (squared Mahalanobis distance with the innovation covariance ``P + H^-1``, over every
  direction the constraints inform, degenerate ones included: a scan that insists on a rotation
  the prior rules out is not matched) beyond :attr:`ICPConfig.max_mahalanobis`; a
  rotation beyond :attr:`ICPConfig.max_rotation_sigmas` prior standard deviations; a robust
  cost over the final correspondences that does not drop from the prediction to the correction
  ("the residual does not drop": the correction is not supported by the constraints that chose
  it); and the absolute limits ``max_translation``/``max_rotation``.
* The vertex assignment prefers pairs of the same kind: a frontier paired with a corner costs
  :attr:`ICPConfig.frontier_penalty` metres extra (it is still allowed, within the gate; such a
  pair only serves to make edges correspond through their end points).
* Robustness to outliers: a correspondence gate that shrinks from ``gate_start`` to
  ``gate_end`` over the first iterations, one-to-one vertex pairs, and Huber weights on the
  residuals (iteratively reweighted Gauss-Newton).
* The correction is parametrised as ``(x, y, theta)`` and increments are added: corrections are
  small (centimetres, a degree or two), where this equals composition to second order.

References
----------
P. J. Besl and N. D. McKay, "A method for registration of 3-D shapes", PAMI 1992 (ICP).
J. Zhang, M. Kaess and S. Singh, "On degeneracy of optimization-based state estimation
problems", ICRA 2016 (degenerate directions, solution remapping).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_DENSE_MAX = 4096  # vertex pairs up to which a dense distance matrix replaces the k-d trees
_DENSE_EDGE_MAX = 4096  # edge pairs up to which match_edges tests every pair, else a k-d tree of samples
_MAX_EDGE_SAMPLES = 200_000  # points sampled along the segments of one match_edges call, at most

__all__ = [
    "Correspondences",
    "ICPConfig",
    "ICPResult",
    "constraints",
    "correspond",
    "edge_overlap",
    "edge_overlap_pairs",
    "icp",
    "information_split",
    "match_edges",
    "match_vertices",
    "near_segment_pairs",
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
        Iterations over which the gate shrinks linearly from ``gate_start`` to ``gate_end``
        (none when they are equal).
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
    corner_labels : tuple of int
        Labels of *real corners*: only a scan vertex and a reference vertex both with one of
        these labels give a point-to-point constraint (default nominal and occlusion).
    huber : float
        Huber threshold (metres) of the residual weights.
    sigma : float
        Standard deviation (metres) of one constraint residual (scan noise plus map error).
    information_scale : float
        Factor on the constraints' information (< 1 when the residuals are correlated, e.g. a
        corner and the two walls that end in it share its noise; the map's own error is shared by
        every scan that matches it).
    prior_sigma_xy, prior_sigma_theta : float
        Standard deviations (metres, radians) of the prior on the correction when :func:`icp`
        is given no ``prior_covariance``.
    min_information_ratio : float
        A direction is well constrained when the scan's information along it is at least this
        times the prior's (generalised eigenvalue, see the module docstring).
    max_mahalanobis : float
        Largest accepted squared Mahalanobis distance between the prediction and the
        constraints' own optimum (module docstring; default: the 99.9 % point of chi-square with
        3 degrees of freedom).
    max_rotation_sigmas : float
        Largest accepted rotation, in prior standard deviations of the heading.
    tol : float
        Stop when an increment moves less than this (metres, and radians times 1 m).
    min_constraints : int
        Fewest inlier constraints (rows) for an accepted correction (default 2: one wall seen
        frontier to frontier gives two point-to-line rows, which fix the heading and the offset
        across it; the degeneracy test keeps the direction along it at the prior. With four, a
        robot seeing one wall of a long hall ran on odometry and bent the wall it extended).
    min_matched_fraction : float
        Least fraction of the scan's edges (by length) that must correspond to a reference edge
        for an accepted correction.
    max_rmse : float
        Largest inlier RMS residual (metres) for an accepted correction.
    max_translation, max_rotation : float
        Largest accepted correction (metres, radians), whatever the prior.

    Raises
    ------
    ValueError
        On a value out of range.
    """

    max_iterations: int = 20
    anneal_iterations: int = 4
    gate_start: float = 2.0
    gate_end: float = 0.3
    max_angle: float = 0.35
    min_overlap: float = 0.1
    frontier_penalty: float = 0.25
    corner_labels: tuple[int, ...] = (int(Label.NOMINAL), int(Label.OCCLUSION))
    huber: float = 0.08
    sigma: float = 0.05
    information_scale: float = 1.0
    prior_sigma_xy: float = 0.5
    prior_sigma_theta: float = 0.25
    min_information_ratio: float = 0.5
    max_mahalanobis: float = 16.27
    max_rotation_sigmas: float = 3.0
    tol: float = 5e-4
    min_constraints: int = 2
    min_matched_fraction: float = 0.3
    max_rmse: float = 0.1
    max_translation: float = 2.0
    max_rotation: float = 0.35

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.anneal_iterations < 0:
            raise ValueError("max_iterations must be >= 1 and anneal_iterations >= 0")
        for name in ("gate_start", "gate_end", "max_angle", "huber", "sigma", "information_scale",
                     "prior_sigma_xy", "prior_sigma_theta", "tol", "max_rmse", "max_translation",
                     "max_rotation", "max_mahalanobis", "max_rotation_sigmas"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ICPConfig.{name} must be a positive number, got {v!r}")
        if self.gate_end > self.gate_start:
            raise ValueError("ICPConfig.gate_end must not exceed gate_start")
        if self.min_overlap < 0 or self.frontier_penalty < 0 or self.min_constraints < 0:
            raise ValueError("min_overlap, frontier_penalty and min_constraints must be >= 0")
        if not 0.0 <= self.min_matched_fraction <= 1.0:
            raise ValueError("min_matched_fraction must be within [0, 1]")
        if not (math.isfinite(self.min_information_ratio) and self.min_information_ratio >= 0):
            raise ValueError("min_information_ratio must be >= 0")
        if any(int(v) not in (int(x) for x in Label) for v in self.corner_labels):
            raise ValueError(f"corner_labels must be vertex labels, got {self.corner_labels!r}")


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
        frame). The corrected pose is ``predicted_pose.compose(correction)``. It is the MAP
        estimate confined to the well-constrained directions, also when not accepted.
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
    information : (3, 3) float64
        Information of the final constraints about ``(x, y, theta)`` of the correction
        (robust weights, ``information_scale`` applied; no prior).
    covariance : (3, 3) float64
        Posterior covariance of the corrected pose's error (robot frame of the prediction):
        the prior's on the degenerate directions, prior and scan combined on the others.
    constrained : int
        Number of well-constrained directions (0 to 3).
    mahalanobis : float
        Squared Mahalanobis distance between the prediction and the constraints' optimum.
    consistent : bool
        The scan agrees with the prediction: accepted, or rejected only because no direction is
        constrained better than the prior (a corridor scan right after an accepted match) while
        the residual, the matched fraction and the Mahalanobis test pass. Such a scan confirms
        the prediction (its correction is the identity) without sharpening it.
    """

    correction: Pose
    accepted: bool
    correspondences: Correspondences
    rmse: float
    n_constraints: int
    iterations: int
    reason: str = ""
    information: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    covariance: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    constrained: int = 0
    mahalanobis: float = 0.0
    consistent: bool = False


# ---------------------------------------------------------------------------------- geometry
def project_onto_segments(
    points: FloatArray, segments: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray]:
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


@dataclass(frozen=True)
class _RefGeometry:
    """What :func:`edge_overlap` computes of the reference segments alone: the segments
    ``r`` (m, 2, 2), their lengths, unit directions and left normals. An ICP's reference is
    the same at every iteration: :func:`icp` computes this once."""

    r: FloatArray
    lr: FloatArray
    ur: FloatArray
    nr: FloatArray

    @classmethod
    def of(cls, ref_segments: FloatArray) -> _RefGeometry:
        r = np.asarray(ref_segments, dtype=np.float64).reshape(-1, 2, 2)
        dr = r[:, 1] - r[:, 0]
        lr = np.hypot(dr[:, 0], dr[:, 1])
        ur = dr / np.where(lr > 0, lr, 1.0)[:, None]
        return cls(r, lr, ur, _left_normals(ur))


def _left_normals(u: FloatArray) -> FloatArray:
    """The left normals ``(-u_y, u_x)`` of unit directions ``u`` (m, 2)."""
    n = np.empty_like(u)
    n[:, 0] = -u[:, 1]
    n[:, 1] = u[:, 0]
    return n


def edge_overlap(
    scan_segments: FloatArray, ref_segments: FloatArray, *, _ref: _RefGeometry | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Pairwise geometry of two sets of directed segments.

    Returns ``(cos_angle, lo, hi, offset, ref_len)``, each ``(ms, mr)``: the cosine of the angle
    between the directions; the overlap ``[lo, hi]`` of the reference segment's projection with
    the scan segment, as arc length along the scan segment (empty when ``hi <= lo``); the
    largest distance from the scan segment to the reference line over that overlap; and the
    reference lengths broadcast. ``_ref``: :class:`_RefGeometry` of ``ref_segments``, when the
    caller has it.
    """
    s = np.asarray(scan_segments, dtype=np.float64).reshape(-1, 2, 2)
    rg = _ref if _ref is not None else _RefGeometry.of(ref_segments)
    r, lr, ur, nr = rg.r, rg.lr, rg.ur, rg.nr
    ds = s[:, 1] - s[:, 0]
    ls = np.hypot(ds[:, 0], ds[:, 1])
    us = ds / np.where(ls > 0, ls, 1.0)[:, None]
    cos = us @ ur.T
    t1 = np.einsum("smi,si->sm", r[None, :, 0, :] - s[:, None, 0, :], us)
    t2 = np.einsum("smi,si->sm", r[None, :, 1, :] - s[:, None, 0, :], us)
    lo = np.maximum(0.0, np.minimum(t1, t2))
    hi = np.minimum(ls[:, None], np.maximum(t1, t2))
    p_lo = s[:, None, 0, :] + lo[..., None] * us[:, None, :]
    p_hi = s[:, None, 0, :] + hi[..., None] * us[:, None, :]
    d_lo = np.einsum("smi,mi->sm", p_lo - r[None, :, 0, :], nr)
    d_hi = np.einsum("smi,mi->sm", p_hi - r[None, :, 0, :], nr)
    offset = np.maximum(np.abs(d_lo), np.abs(d_hi))
    return cos, lo, hi, offset, np.broadcast_to(lr[None, :], cos.shape)


def edge_overlap_pairs(
    scan_segments: FloatArray, ref_segments: FloatArray, si: IntArray, ri: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`edge_overlap` of the pairs ``(scan_segments[si], ref_segments[ri])`` only, each
    output ``(len(si),)``: the same arithmetic, element by element, as the dense matrices'
    entries ``[si, ri]`` (the cosine is a sum of two products here, a matrix product there; it
    only meets a threshold)."""
    s = np.asarray(scan_segments, dtype=np.float64).reshape(-1, 2, 2)
    r = np.asarray(ref_segments, dtype=np.float64).reshape(-1, 2, 2)
    ds = s[:, 1] - s[:, 0]
    dr = r[:, 1] - r[:, 0]
    ls = np.hypot(ds[:, 0], ds[:, 1])
    lr = np.hypot(dr[:, 0], dr[:, 1])
    us = (ds / np.where(ls > 0, ls, 1.0)[:, None])[si]
    ur = (dr / np.where(lr > 0, lr, 1.0)[:, None])[ri]
    s0 = s[si, 0]
    r0 = r[ri, 0]
    cos = us[:, 0] * ur[:, 0] + us[:, 1] * ur[:, 1]
    t1 = np.einsum("pi,pi->p", r0 - s0, us)
    t2 = np.einsum("pi,pi->p", r[ri, 1] - s0, us)
    lo = np.maximum(0.0, np.minimum(t1, t2))
    hi = np.minimum(ls[si], np.maximum(t1, t2))
    nr = _left_normals(ur)
    p_lo = s0 + lo[:, None] * us
    p_hi = s0 + hi[:, None] * us
    d_lo = np.einsum("pi,pi->p", p_lo - r0, nr)
    d_hi = np.einsum("pi,pi->p", p_hi - r0, nr)
    offset = np.maximum(np.abs(d_lo), np.abs(d_hi))
    return cos, lo, hi, offset, lr[ri]


def _sample_segments(seg: FloatArray, step: float) -> tuple[FloatArray, IntArray]:
    """Points every ``step`` (at most) along each segment, both ends included, and the index of
    the segment of each point."""
    length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
    k = np.ceil(length / step).astype(np.int64) + 1  # points per segment
    owner = np.repeat(np.arange(len(seg), dtype=np.int64), k)
    first = np.cumsum(k) - k
    t = (np.arange(int(k.sum()), dtype=np.int64) - first[owner]) / np.maximum(k - 1, 1)[owner]
    pts = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
    return pts, owner


def near_segment_pairs(a: FloatArray, b: FloatArray, reach: float) -> tuple[IntArray, IntArray]:
    """Every pair ``(i, j)`` of segments ``a[i]``, ``b[j]`` that come within ``reach`` of each
    other (and some a little further), in row-major order, without testing all pairs.

    Both sets are sampled every ``step`` along their length (:func:`_sample_segments`); two
    segments within ``reach`` have samples within ``reach + step`` (each closest point is within
    ``step / 2`` of a sample), found by a k-d tree. ``step`` is ``reach`` unless that would make
    more than ``_MAX_EDGE_SAMPLES`` samples (kilometres of walls at a small reach).
    """
    la = float(np.hypot(*(a[:, 1] - a[:, 0]).T).sum())
    lb = float(np.hypot(*(b[:, 1] - b[:, 0]).T).sum())
    step = max(reach, (la + lb) / _MAX_EDGE_SAMPLES, 1e-6)
    pa, oa = _sample_segments(a, step)
    pb, ob = _sample_segments(b, step)
    sdm = cKDTree(pa).sparse_distance_matrix(cKDTree(pb), reach + step, output_type="ndarray")
    code = np.unique(oa[sdm["i"]] * len(b) + ob[sdm["j"]])
    return code // len(b), code % len(b)


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
    if len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib):
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
    *,
    _ref: _RefGeometry | None = None,
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
    ss = sp.take(scan.edges, axis=0)
    rs = ref.segments() if _ref is None else _ref.r
    cos_max = math.cos(max_angle)
    if scan.n_edges * ref.n_edges > _DENSE_EDGE_MAX and cos_max > 0.01:
        return _match_edges_near(scan, ref, vertex_pairs, ss, rs, max_offset, cos_max, min_overlap)
    cos, lo, hi, offset, lr = edge_overlap(ss, rs, _ref=_ref)
    ls = np.hypot(*(ss[:, 1] - ss[:, 0]).T)
    need = np.minimum(min_overlap, 0.5 * np.minimum(ls[:, None], lr))
    geo = (cos >= cos_max) & (hi - lo >= need) & (offset <= max_offset)
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
    pairs = np.empty((len(si), 2), dtype=np.int64)
    pairs[:, 0] = si
    pairs[:, 1] = ri
    return pairs, offset[si, ri], lo[si, ri], hi[si, ri]


def _endpoint_keys(scan: Wireframe, ref: Wireframe, vertex_pairs: IntArray) -> tuple[IntArray, IntArray]:
    """The ``(scan edge, reference edge)`` pairs whose end vertices correspond, in order."""
    none = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if len(vertex_pairs) == 0:
        return none
    vmap = np.full(scan.n_vertices, -1, dtype=np.int64)
    vmap[vertex_pairs[:, 0]] = vertex_pairs[:, 1]
    ea = vmap[scan.edges[:, 0]]
    eb = vmap[scan.edges[:, 1]]
    both = np.nonzero((ea >= 0) & (eb >= 0))[0]
    if len(both) == 0:
        return none
    n_ref = ref.n_vertices
    key_ref = ref.edges[:, 0].astype(np.int64) * n_ref + ref.edges[:, 1]
    order = np.argsort(key_ref, kind="stable")
    key_scan = ea[both] * n_ref + eb[both]
    lo = np.searchsorted(key_ref[order], key_scan, side="left")
    hi = np.searchsorted(key_ref[order], key_scan, side="right")
    count = hi - lo
    si = np.repeat(both, count)
    start = np.repeat(lo, count)
    within = np.arange(len(si)) - np.repeat(np.cumsum(count) - count, count)
    return si.astype(np.int64), order[start + within].astype(np.int64)


def _match_edges_near(
    scan: Wireframe,
    ref: Wireframe,
    vertex_pairs: IntArray,
    ss: FloatArray,
    rs: FloatArray,
    max_offset: float,
    cos_max: float,
    min_overlap: float,
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """:func:`match_edges` for many edges: only pairs that can pass its geometric test.

    A pair passes only if some point of the scan edge within the overlap lies within
    ``max_offset`` of the reference line and has the same projection as a point of the
    reference edge; the two points differ along the scan edge's normal only, by at most
    ``max_offset / cos(angle)``. So the segments come within ``max_offset / cos_max`` of each
    other (:func:`near_segment_pairs`, with a margin for rounding); pairs whose end vertices
    correspond are added (they need no geometry). The result is the dense test's, pair for pair,
    in the same (row-major) order.
    """
    reach = max_offset / cos_max * (1.0 + 1e-6) + 1e-9
    gi, gr = near_segment_pairs(ss, rs, reach)
    ki, kr = _endpoint_keys(scan, ref, vertex_pairs)
    n_ref = len(rs)
    code = np.unique(np.concatenate([gi * n_ref + gr, ki * n_ref + kr]))
    si, ri = code // n_ref, code % n_ref
    cos, lo, hi, offset, lr = edge_overlap_pairs(ss, rs, si, ri)
    ls = np.hypot(*(ss[:, 1] - ss[:, 0]).T)[si]
    need = np.minimum(min_overlap, 0.5 * np.minimum(ls, lr))
    geo = (cos >= cos_max) & (hi - lo >= need) & (offset <= max_offset)
    hit = np.isin(code, ki * n_ref + kr)
    geo |= hit
    lo = np.where(hit, 0.0, lo)
    hi = np.where(hit, np.maximum(hi, ls), hi)
    keep = np.nonzero(geo)[0]
    pairs = np.stack([si[keep], ri[keep]], axis=1).astype(np.int64)
    return pairs, offset[keep], lo[keep], hi[keep]


def correspond(
    scan: Wireframe,
    ref: Wireframe,
    gate: float,
    max_angle: float = 0.35,
    min_overlap: float = 0.1,
    frontier_penalty: float = 0.25,
    scan_points: FloatArray | None = None,
    *,
    _ref: _RefGeometry | None = None,
) -> Correspondences:
    """Vertex and edge correspondences of ``scan`` (optionally moved: ``scan_points``) against
    ``ref``, with one gate (metres) for vertex distance and edge offset."""
    sp = scan.points if scan_points is None else np.asarray(scan_points, dtype=np.float64)
    vp, vd = match_vertices(sp, ref.points, gate, scan.labels, ref.labels, frontier_penalty)
    ep, eo, elo, ehi = match_edges(scan, ref, vp, gate, max_angle, min_overlap, scan_points=sp, _ref=_ref)
    return Correspondences(vp, vd, ep, eo, elo, ehi)


# ---------------------------------------------------------------------------------------- ICP
def constraints(
    scan: Wireframe,
    ref: Wireframe,
    scan_points: FloatArray,
    corr: Correspondences,
    corner_labels: tuple[int, ...] = (int(Label.NOMINAL), int(Label.OCCLUSION)),
) -> tuple[FloatArray, FloatArray]:
    """Linearised constraints of a correction, at the current scan points ``scan_points``.

    Point-to-point rows (two per pair) come from vertex pairs whose two labels are both in
    ``corner_labels``; point-to-line rows (two per edge pair: the ends of the overlap along the
    scan edge) measure the distance to the reference edge's line along its left normal.

    Returns
    -------
    J : (k, 3) float64
    r : (k,) float64
        Rows ``J @ delta + r ~ 0`` for a small motion ``delta = (dx, dy, dtheta)`` applied to the
        scan as ``R(dtheta) p + (dx, dy)`` about the origin (the robot).
    """
    sp = scan_points
    rows_j: list[FloatArray] = []
    rows_r: list[FloatArray] = []
    vp = corr.vertex_pairs
    if len(vp):
        real = np.zeros(len(Label), dtype=bool)
        real[list(corner_labels)] = True
        keep = real[scan.labels[vp[:, 0]]] & real[ref.labels[vp[:, 1]]]
        vp = vp.compress(keep, axis=0)
    if len(vp):
        p = sp.take(vp[:, 0], axis=0)
        q = ref.points.take(vp[:, 1], axis=0)
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
        se = scan.edges.take(ep[:, 0], axis=0)  # (take: row gathers, faster than [ ] here)
        a = sp.take(se[:, 0], axis=0)
        b = sp.take(se[:, 1], axis=0)
        d = b - a
        ln = np.hypot(d[:, 0], d[:, 1])
        u = d / np.where(ln > 0, ln, 1.0)[:, None]
        re = ref.edges.take(ep[:, 1], axis=0)
        ra = ref.points.take(re[:, 0], axis=0)
        rb = ref.points.take(re[:, 1], axis=0)
        dr = rb - ra
        lr = np.hypot(dr[:, 0], dr[:, 1])
        ur = dr / np.where(lr > 0, lr, 1.0)[:, None]
        n = _left_normals(ur)
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


def information_split(
    information: FloatArray, prior_covariance: FloatArray, min_ratio: float
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Generalised eigen-decomposition of a constraint information against a prior.

    With ``P = L L^T`` (Cholesky), the eigenvalues ``lambda`` of ``L^T H L`` are the ratios of the
    constraints' information to the prior's along the directions ``L v``.

    Parameters
    ----------
    information : (3, 3)
        ``H``, the constraints' information.
    prior_covariance : (3, 3)
        ``P``, symmetric positive definite.
    min_ratio : float
        Directions with ``lambda >= min_ratio`` are well constrained.

    Returns
    -------
    L : (3, 3)
        The Cholesky factor of ``P``.
    lam : (3,)
        The ratios, ascending.
    V : (3, 3)
        Orthonormal eigenvectors (columns), in whitened coordinates ``z = L^-1 delta``.
    good : (3,) bool
        Well-constrained directions.
    """
    L = np.linalg.cholesky(np.asarray(prior_covariance, dtype=np.float64))
    M = L.T @ np.asarray(information, dtype=np.float64) @ L
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    lam = np.maximum(lam, 0.0)
    return L, lam, V, lam >= min_ratio


def _huber_weights(r: FloatArray, huber: float) -> FloatArray:
    absr = np.abs(r)
    return np.asarray(np.where(absr <= huber, 1.0, huber / np.maximum(absr, 1e-12)), dtype=np.float64)


def _huber_cost(r: FloatArray, huber: float) -> float:
    absr = np.abs(r)
    return float(np.sum(np.where(absr <= huber, 0.5 * r * r, huber * (absr - 0.5 * huber))))


def icp(
    scan: Wireframe,
    ref: Wireframe,
    config: ICPConfig | None = None,
    initial: Pose | None = None,
    prior_covariance: ArrayLike | None = None,
) -> ICPResult:
    """Align ``scan`` onto ``ref`` with a modified, degeneracy-aware ICP (paper Sec. IV-C).

    Both wireframes are in the frame of the predicted robot pose (the robot at the origin).
    Each iteration re-computes the vertex and edge correspondences at the current alignment and
    gate, builds point-to-point and point-to-line constraints (see the module docstring), weighs
    them (Huber), splits the directions into well-constrained and degenerate ones against the
    prior, and takes the MAP Gauss-Newton step on the well-constrained ones
    (:func:`_map_iterations`). At the correction found, the constraints are linearised once more
    at the final gate for the posterior (:func:`_posterior_covariance`), the consistency with
    the prior (:func:`_prior_mahalanobis`), the fit (:func:`_fit_quality`) and the acceptance
    tests (:func:`_rejection_reason`).

    Parameters
    ----------
    scan, ref : Wireframe
        The measured scan and the predicted scan, robot frame.
    config : ICPConfig, optional
    initial : Pose, optional
        Starting correction (identity by default).
    prior_covariance : (3, 3) array_like, optional
        Covariance of the prediction's error ``(x, y, theta)`` in the robot frame (the
        correction's prior, centred on zero). Default: diagonal from
        ``config.prior_sigma_xy`` and ``config.prior_sigma_theta``.

    Returns
    -------
    ICPResult
        ``correction`` maps scan points onto the reference.

    Raises
    ------
    ValueError
        When ``prior_covariance`` is not a symmetric positive definite 3 x 3 matrix.
    """
    cfg = config or ICPConfig()
    P = _checked_prior(cfg, prior_covariance)
    T = initial or Pose.identity()
    t = np.array([T.x, T.y, T.theta])
    empty = Correspondences(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, 2), np.int64), np.zeros(0))
    if scan.n_vertices == 0 or ref.n_vertices == 0:
        return ICPResult(T, False, empty, math.inf, 0, 0, "empty scan or reference", covariance=P.copy())
    scale = cfg.information_scale / cfg.sigma**2
    rg = _RefGeometry.of(ref.segments())  # the same at every iteration
    t, it = _map_iterations(scan, ref, cfg, P, scale, t, rg)
    T = Pose(float(t[0]), float(t[1]), float(t[2]))
    t = np.array([T.x, T.y, T.theta])
    corr, r, H, g, L, lam, V, good = _linearise(scan, ref, cfg, P, scale, T, cfg.gate_end, rg)
    cov = _posterior_covariance(L, lam, V, good)
    maha = _prior_mahalanobis(t, g, L, lam, V)
    n_c, rmse, frac_matched, cost0, cost1 = _fit_quality(scan, ref, cfg, corr, r)
    reason = _rejection_reason(cfg, P, T, good, maha, n_c, rmse, frac_matched, cost0, cost1)
    consistent = reason == "" or (reason.startswith("degenerate") and maha <= cfg.max_mahalanobis)
    if reason:
        cov = P.copy()
    return ICPResult(
        T, reason == "", corr, rmse, n_c, it, reason,
        information=H, covariance=cov, constrained=int(good.sum()), mahalanobis=maha,
        consistent=consistent,
    )


def _checked_prior(cfg: ICPConfig, prior_covariance: ArrayLike | None) -> FloatArray:
    """The prior covariance of the correction (paper Sec. IV-C: the odometry prediction).

    Parameters
    ----------
    cfg : ICPConfig
    prior_covariance : (3, 3) array_like or None
        As given to :func:`icp`; ``None`` for the diagonal from ``cfg.prior_sigma_xy`` and
        ``cfg.prior_sigma_theta``.

    Returns
    -------
    P : (3, 3)
        The covariance of ``(x, y, theta)``.

    Raises
    ------
    ValueError
        When ``prior_covariance`` is not a finite, symmetric, positive definite 3 x 3 matrix.
    """
    if prior_covariance is None:
        return np.diag([cfg.prior_sigma_xy**2, cfg.prior_sigma_xy**2, cfg.prior_sigma_theta**2])
    P = np.asarray(prior_covariance, dtype=np.float64)
    if P.shape != (3, 3) or not np.all(np.isfinite(P)) or not np.allclose(P, P.T, atol=1e-12):
        raise ValueError("prior_covariance must be a finite symmetric 3 x 3 matrix")
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ValueError("prior_covariance must be positive definite") from None
    return P


def _linearise(
    scan: Wireframe,
    ref: Wireframe,
    cfg: ICPConfig,
    P: FloatArray,
    scale: float,
    at: Pose,
    gate: float,
    rg: _RefGeometry | None = None,
) -> tuple[
    Correspondences, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, BoolArray
]:
    """Linearise the constraints with the scan moved by ``at`` (paper Sec. IV-C).

    Parameters
    ----------
    scan, ref : Wireframe
        The measured and the predicted scan, robot frame.
    cfg : ICPConfig
    P : (3, 3)
        The prior covariance of the correction.
    scale : float
        ``cfg.information_scale / cfg.sigma**2``.
    at : Pose
        The current correction.
    gate : float
        The correspondence gate in metres.

    Returns
    -------
    corr : Correspondences
        Correspondences within ``gate``.
    r : (m,)
        Constraint residuals.
    H : (3, 3)
        Huber-weighted information ``J^T W J * scale``.
    g : (3,)
        Gradient ``J^T W r * scale``.
    L, lam, V, good
        The split against the prior (:func:`information_split`).
    """
    sp = at.apply(scan.points)
    corr = correspond(scan, ref, gate, cfg.max_angle, cfg.min_overlap, cfg.frontier_penalty, scan_points=sp,
                      _ref=rg)
    J, r = constraints(scan, ref, sp, corr, cfg.corner_labels)
    Jw = J * (_huber_weights(r, cfg.huber) * scale)[:, None]
    H, g = Jw.T @ J, Jw.T @ r
    L, lam, V, good = information_split(H, P, cfg.min_information_ratio)
    return corr, r, H, g, L, lam, V, good


def _map_iterations(
    scan: Wireframe, ref: Wireframe, cfg: ICPConfig, P: FloatArray, scale: float, t: FloatArray,
    rg: _RefGeometry | None = None,
) -> tuple[FloatArray, int]:
    """Iteratively reweighted MAP Gauss-Newton with a shrinking gate (paper Sec. IV-C).

    The gate shrinks linearly from ``cfg.gate_start`` to ``cfg.gate_end`` over
    ``cfg.anneal_iterations``; each step solves, in whitened coordinates on the constrained
    directions, ``(I + diag(lam)) a = diag(lam) a0 - Vg^T L^T g`` (module docstring), the
    degenerate directions going back to zero. It stops when a step at the final gate is
    shorter than ``cfg.tol`` or after ``cfg.max_iterations``.

    Parameters
    ----------
    scan, ref : Wireframe
        The measured and the predicted scan, robot frame.
    cfg : ICPConfig
    P : (3, 3)
        The prior covariance of the correction.
    scale : float
        ``cfg.information_scale / cfg.sigma**2``.
    t : (3,)
        The starting correction ``(x, y, theta)``.

    Returns
    -------
    t : (3,)
        The correction reached.
    it : int
        Iterations taken (0 when ``cfg.max_iterations`` is 0).
    """
    it = 0
    anneal = cfg.anneal_iterations if cfg.gate_start > cfg.gate_end else 0
    for it in range(1, cfg.max_iterations + 1):
        frac = min(1.0, (it - 1) / anneal) if anneal else 1.0
        gate = cfg.gate_start + (cfg.gate_end - cfg.gate_start) * frac
        _, _, _, g, L, lam, V, good = _linearise(scan, ref, cfg, P, scale, Pose(*t), gate, rg)
        Vg = V[:, good]
        z0 = np.linalg.solve(L, t)
        a0 = Vg.T @ z0
        # MAP step in whitened coordinates on the constrained directions (module docstring):
        # (I + diag(lam)) a = diag(lam) a0 - Vg^T L^T g; degenerate directions go back to zero.
        a = (lam[good] * a0 - Vg.T @ (L.T @ g)) / (1.0 + lam[good])
        t_new = L @ (Vg @ a)
        step = t_new - t
        t = t_new
        if frac >= 1.0 and math.hypot(step[0], step[1]) + abs(step[2]) < cfg.tol:
            break
    return t, it


def _posterior_covariance(L: FloatArray, lam: FloatArray, V: FloatArray, good: BoolArray) -> FloatArray:
    """Posterior covariance of the correction (paper Sec. IV-C; the prior where degenerate).

    Parameters
    ----------
    L, lam, V, good
        The split of the final information against the prior (:func:`information_split`).

    Returns
    -------
    (3, 3)
        ``L V diag(post) V^T L^T``, symmetrised, with ``post = 1 / (1 + lam)`` on the
        well-constrained directions and 1 on the degenerate ones.
    """
    post = np.ones(3)
    post[good] = 1.0 / (1.0 + lam[good])
    cov = L @ (V * post[None, :]) @ V.T @ L.T
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def _prior_mahalanobis(t: FloatArray, g: FloatArray, L: FloatArray, lam: FloatArray, V: FloatArray) -> float:
    """Squared Mahalanobis distance of the constraints' own optimum from the prediction.

    Consistency with the prior (paper Sec. IV-C, the gate ``max_mahalanobis``), over every
    direction the constraints say anything about (also the degenerate ones, held at the
    prediction): the constraints-only optimum along direction i is
    ``m_i = a_i - v_i^T L^T g / lambda_i`` (whitened), its innovation variance
    ``1 + 1/lambda_i``.

    Parameters
    ----------
    t : (3,)
        The correction.
    g : (3,)
        The gradient at ``t``.
    L, lam, V
        The split of the information at ``t`` against the prior (:func:`information_split`).

    Returns
    -------
    float
        ``sum_i m_i^2 lambda_i / (1 + lambda_i)`` over the informed directions.
    """
    informed = lam > 1e-6
    a_all = V.T @ np.linalg.solve(L, t)
    m = a_all[informed] - (V[:, informed].T @ (L.T @ g)) / lam[informed]
    return float(np.sum(m**2 * lam[informed] / (1.0 + lam[informed])))


def _fit_quality(
    scan: Wireframe, ref: Wireframe, cfg: ICPConfig, corr: Correspondences, r: FloatArray,
) -> tuple[int, float, float, float, float]:
    """How well the final correspondences fit (the quantities of the gates, paper Sec. IV-C).

    Parameters
    ----------
    scan, ref : Wireframe
        The measured and the predicted scan, robot frame.
    cfg : ICPConfig
    corr : Correspondences
        The correspondences at the final gate.
    r : (m,)
        Their residuals at the correction.

    Returns
    -------
    n_c : int
        Inlier constraint rows (``|r| <= cfg.gate_end``).
    rmse : float
        Inlier RMS residual (``inf`` without inliers).
    frac_matched : float
        Fraction of the scan's edge length that has a correspondence.
    cost0, cost1 : float
        Huber cost of the same correspondences at the prediction and at the correction.
    """
    inl = np.abs(r) <= cfg.gate_end
    n_c = int(inl.sum())
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if n_c else math.inf
    lengths = scan.edge_lengths()
    total = float(lengths.sum())
    matched = float(lengths[corr.scan_edge_matched(scan.n_edges)].sum())
    frac_matched = matched / total if total > 0 else 0.0
    # The same correspondences, evaluated at the prediction (no correction).
    _, r0 = constraints(scan, ref, scan.points, corr, cfg.corner_labels)
    cost0 = _huber_cost(r0, cfg.huber)
    cost1 = _huber_cost(r, cfg.huber)
    return n_c, rmse, frac_matched, cost0, cost1


def _rejection_reason(
    cfg: ICPConfig, P: FloatArray, T: Pose, good: BoolArray, maha: float,
    n_c: int, rmse: float, frac_matched: float, cost0: float, cost1: float,
) -> str:
    """The first acceptance gate the correction fails (module docstring, "Gates").

    Parameters
    ----------
    cfg : ICPConfig
    P : (3, 3)
        The prior covariance of the correction.
    T : Pose
        The correction.
    good : (3,) bool
        Well-constrained directions.
    maha : float
        :func:`_prior_mahalanobis`.
    n_c, rmse, frac_matched, cost0, cost1
        :func:`_fit_quality`.

    Returns
    -------
    str
        ``""`` when every gate passes, else why the correction is rejected.
    """
    moved = math.hypot(T.x, T.y) > 1e-4 or abs(T.theta) > 1e-5
    reason = ""
    if n_c < cfg.min_constraints:
        reason = f"too few constraints ({n_c} < {cfg.min_constraints})"
    elif frac_matched < cfg.min_matched_fraction:
        reason = f"too little of the scan matched ({frac_matched:.0%})"
    elif rmse > cfg.max_rmse:
        reason = f"residual too large ({rmse:.3f} m > {cfg.max_rmse} m)"
    elif not good.any():
        reason = "degenerate: no direction constrained better than the prior"
    elif maha > cfg.max_mahalanobis:
        reason = f"correction too unlikely (Mahalanobis^2 {maha:.1f} > {cfg.max_mahalanobis})"
    elif abs(T.theta) > cfg.max_rotation_sigmas * math.sqrt(P[2, 2]):
        reason = f"rotation beyond {cfg.max_rotation_sigmas:g} sigma of the prior"
    elif moved and cost1 >= cost0:
        reason = "residual does not drop"
    elif math.hypot(T.x, T.y) > cfg.max_translation or abs(T.theta) > cfg.max_rotation:
        reason = "correction too large"
    return reason
