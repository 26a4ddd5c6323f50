"""Point-to-line matching of a raw lidar scan against the map's walls.

The wireframe ICP (:mod:`mapping.icp`) matches the *extracted* scan -- a handful of corners and
walls -- against the predicted scan. On a real 180-degree lidar that is a few dozen constraints
whose corners carry the extractor's errors (a wall cut short by clutter ends in a frontier that
is not a corner; a corner between two walls fitted through a chair is off by decimetres). Yet a
map of wall segments is exactly what point-to-line matching wants: every beam that hit a wall is
one constraint along that wall's normal. This module matches **every scan point** against the
wall segments in view, in the manner of a point-to-line ICP (Censi's PLICP: the residual is the
distance from the point to the line of its corresponding segment, the cost a robust sum of
those), written for a map whose lines are given rather than interpolated from a previous scan.

Choices
-------
* **Correspondence**: each point goes to the nearest segment (Euclidean distance to the
  segment, not the line) among those within the *gate*, and only if the point's own local
  normal (from its neighbours along the scan) is within ``max_normal_angle`` of the segment's
  normal: a chair leg, a person or a round pillar next to a wall neither has the wall's normal
  nor lies on it. Points more than ``end_margin`` beyond a segment's end do not correspond to
  it (a wall that continues past the mapped part must not drag the scan sideways).
* **Gate** shrinks geometrically from ``gate_start`` (set by the caller from the prior
  covariance) to ``gate_end`` over the first iterations, as in annealed ICP.
* **Robust kernel**: Cauchy weights ``1 / (1 + (r / c)^2)`` with ``c = kernel`` (metres); a
  point in front of a wall (clutter) pulls with a weight that vanishes with its distance.
* **Prior**: the correction has the Gaussian prior ``N(0, prior)`` (the pose's covariance after
  odometry); the estimate is the MAP (Gauss-Newton on the sum of both costs), so directions
  the scan does not constrain (along a corridor) stay at the prediction.
* **Information** of the points is scaled by ``information_scale`` (< 1): the residuals of
  neighbouring beams on one wall are correlated (the wall's own mapping error is common to all
  of them), and a covariance computed as if 150 points were independent would be 150 times too
  confident.
* **Degeneracy**: a direction is *constrained* when the points' information along it is at least
  ``min_information_ratio`` times the prior's (the generalised eigenvalues of the two), as in
  :mod:`mapping.icp`.
* **Acceptance**: at least ``min_inliers`` points and ``min_inlier_fraction`` of the valid
  points within ``inlier_distance`` of their segment, inlier RMS at most ``max_rmse``, and the
  correction's squared Mahalanobis distance under the prior at most ``max_mahalanobis``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mapping.icp import ICPResult
from mapping.se2 import Pose

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["PointMatch", "PointMatchConfig", "assign", "match_points", "point_normals", "refine_match"]


@dataclass(frozen=True)
class PointMatchConfig:
    """Parameters of :func:`match_points` (see the module docstring).

    The ``point_match.*`` settings of :class:`mapping.filter.FilterConfig`.

    Parameters
    ----------
    enabled : bool
        Match the raw points in the filter (:meth:`mapping.filter.WireframeFilter.step` given
        ``points``) and in its loop closer; off by default: the simulator's corner sensor has
        no raw points, and the real-lidar profile (:func:`agents.mapping_run.lidar_profile`)
        turns it on.
    local : bool
        With ``enabled``: also in the step's own scan match (default True); False matches the
        points only in the loop closer's match against the old map.
    max_iterations : int
        Gauss-Newton iterations at most (default 12).
    anneal_iterations : int
        Iterations over which the gate shrinks from ``gate_start`` to ``gate_end`` (default 4).
    gate_end : float
        Final correspondence gate, metres (default 0.3).
    kernel : float
        Cauchy kernel width, metres (default 0.05).
    sigma : float
        Standard deviation of one point's residual (range noise plus map error), metres (0.03).
    information_scale : float
        Factor on the points' information (default 0.05, see the module docstring).
    max_normal_angle : float
        Largest angle between a point's local normal and its segment's, radians (default 30
        degrees).
    normal_window : int
        Neighbours on each side used for a point's normal (default 2).
    end_margin : float
        How far past a segment's end a point may still correspond to it, metres (default 0.1).
    inlier_distance : float
        Residual (metres) under which a point counts as an inlier (default 0.1).
    min_inliers : int
        Fewest inliers for an accepted match (default 20).
    min_inlier_fraction : float
        Least fraction of the scan's points that are inliers (default 0.25).
    max_rmse : float
        Largest inlier RMS residual, metres (default 0.05).
    max_mahalanobis : float
        Largest squared Mahalanobis distance of the correction under the prior (default 16.27,
        chi-square with 3 degrees of freedom at 99.9 %).
    min_information_ratio : float
        See "Degeneracy" (default 0.5).
    tol : float
        Stop when an increment moves less than this (metres, and radians times 1 m).
    """

    enabled: bool = False
    local: bool = True
    max_iterations: int = 12
    anneal_iterations: int = 4
    gate_end: float = 0.3
    kernel: float = 0.05
    sigma: float = 0.03
    information_scale: float = 0.05
    max_normal_angle: float = math.radians(30.0)
    normal_window: int = 2
    end_margin: float = 0.1
    inlier_distance: float = 0.1
    min_inliers: int = 20
    min_inlier_fraction: float = 0.25
    max_rmse: float = 0.05
    max_mahalanobis: float = 16.27
    min_information_ratio: float = 0.5
    tol: float = 1e-4

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.anneal_iterations < 0 or self.normal_window < 1:
            raise ValueError("max_iterations and normal_window must be >= 1, anneal_iterations >= 0")
        for name in ("gate_end", "kernel", "sigma", "information_scale", "max_normal_angle", "inlier_distance",
                     "max_rmse", "max_mahalanobis", "tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"PointMatchConfig.{name} must be a positive number, got {v!r}")
        if self.end_margin < 0 or self.min_inliers < 0 or not 0 <= self.min_inlier_fraction <= 1:
            raise ValueError("end_margin, min_inliers must be >= 0, min_inlier_fraction within [0, 1]")


@dataclass(frozen=True)
class PointMatch:
    """Outcome of :func:`match_points`.

    Attributes
    ----------
    correction : Pose
        Maps the scan's points onto the segments: the corrected pose is
        ``predicted.compose(correction)``.
    accepted : bool
    reason : str
        Why not accepted ("" when accepted).
    inliers : int
        Points within ``inlier_distance`` of their segment at the end.
    valid : int
        Points given (finite).
    rmse : float
        Inlier RMS residual, metres.
    information : (3, 3) float64
        The points' information about the correction (scaled, no prior).
    covariance : (3, 3) float64
        Posterior covariance of the correction (prior and points).
    constrained : int
        Well-constrained directions (0 to 3).
    mahalanobis : float
        Squared Mahalanobis distance of the correction under the prior.
    segment : (n,) int64
        The segment of each point at the end (-1: none).
    """

    correction: Pose
    accepted: bool
    reason: str
    inliers: int
    valid: int
    rmse: float
    information: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    covariance: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    constrained: int = 0
    mahalanobis: float = 0.0
    segment: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def point_normals(points: FloatArray, window: int = 2, max_gap: float = 0.3) -> FloatArray:
    """Unit normal of each point of an ordered scan (sign arbitrary), from the chord between its
    ``window``-th neighbours on each side; NaN where a neighbour is missing or farther than
    ``max_gap`` times the window (a range jump: the point has no wall around it)."""
    n = len(points)
    out = np.full((n, 2), np.nan)
    if n < 2 * window + 1:
        return out
    a = points[: n - 2 * window]
    b = points[2 * window :]
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    ok = np.isfinite(length) & (length > 1e-9) & (length <= 2 * window * max_gap)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.where(ok, length, 1.0)[:, None]
    nrm[~ok] = np.nan
    out[window : n - window] = nrm
    return out


def _segment_distance(points: FloatArray, segs: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Distance (n, m) from each point to each segment and the arc parameter (n, m) of the
    projection onto the segment's line in metres from its start."""
    a = segs[:, 0]
    d = segs[:, 1] - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    u = d / length[:, None]
    rel = points[:, None, :] - a[None, :, :]
    t = rel[..., 0] * u[None, :, 0] + rel[..., 1] * u[None, :, 1]
    tc = np.clip(t, 0.0, length[None, :])
    foot = a[None] + tc[..., None] * u[None]
    dist = np.hypot(points[:, None, 0] - foot[..., 0], points[:, None, 1] - foot[..., 1])
    return dist, t


def assign(
    points: FloatArray, normals: FloatArray, segs: FloatArray, gate: float, max_normal_angle: float, end_margin: float
) -> IntArray:
    """The segment of each point: the nearest one within ``gate`` whose normal is within
    ``max_normal_angle`` of the point's (points without a normal match on distance alone) and
    that the point's projection falls on, ``end_margin`` of slack at the ends; -1 for none."""
    n = len(points)
    if n == 0 or len(segs) == 0:
        return np.full(n, -1, dtype=np.int64)
    dist, t = _segment_distance(points, segs)
    d = segs[:, 1] - segs[:, 0]
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    sn = np.stack([-d[:, 1], d[:, 0]], axis=1) / length[:, None]
    ok = (dist <= gate) & (t >= -end_margin) & (t <= length[None, :] + end_margin)
    has_n = np.isfinite(normals[:, 0])
    cosang = np.abs(normals[:, 0, None] * sn[None, :, 0] + normals[:, 1, None] * sn[None, :, 1])
    ok &= ~has_n[:, None] | (cosang >= math.cos(max_normal_angle))
    dist = np.where(ok, dist, np.inf)
    j = np.argmin(dist, axis=1)
    best = dist[np.arange(n), j]
    return np.where(np.isfinite(best), j, -1).astype(np.int64)


def match_points(
    points: FloatArray,
    segments: FloatArray,
    prior: FloatArray,
    config: PointMatchConfig | None = None,
    *,
    gate_start: float = 1.0,
    initial: Pose | None = None,
) -> PointMatch:
    """Match scan ``points`` (robot frame of the prediction, ordered by bearing) against wall
    ``segments`` (same frame, (m, 2, 2)) with the Gaussian prior ``N(0, prior)`` on the
    correction; start from ``initial`` (identity by default). See the module docstring.

    Returns
    -------
    PointMatch
    """
    cfg = config or PointMatchConfig()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    segs = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    P = np.asarray(prior, dtype=np.float64) + 1e-12 * np.eye(3)
    Pinv = np.linalg.inv(P)
    x = np.array(initial.as_tuple() if initial is not None else (0.0, 0.0, 0.0))
    valid = len(pts)
    if valid == 0 or len(segs) == 0:
        return PointMatch(Pose(*x), False, "nothing to match", 0, valid, math.inf, covariance=P)
    normals = point_normals(pts, cfg.normal_window)
    sd = segs[:, 1] - segs[:, 0]
    slen = np.maximum(np.hypot(sd[:, 0], sd[:, 1]), 1e-12)
    seg_n = np.stack([-sd[:, 1], sd[:, 0]], axis=1) / slen[:, None]
    gate0 = max(gate_start, cfg.gate_end)
    H = np.zeros((3, 3))
    j = np.full(valid, -1, dtype=np.int64)
    r = np.zeros(valid)
    for it in range(cfg.max_iterations):
        if cfg.anneal_iterations and it < cfg.anneal_iterations:
            gate = gate0 * (cfg.gate_end / gate0) ** (it / cfg.anneal_iterations)
        else:
            gate = cfg.gate_end
        c, s = math.cos(x[2]), math.sin(x[2])
        R = np.array([[c, -s], [s, c]])
        q = pts @ R.T + x[:2]
        qn = normals @ R.T
        j = assign(q, qn, segs, gate, cfg.max_normal_angle, cfg.end_margin)
        m = j >= 0
        if m.sum() < 3:
            break
        nj = seg_n[j[m]]
        r = np.einsum("ij,ij->i", q[m] - segs[j[m], 0], nj)
        w = 1.0 / (1.0 + (r / cfg.kernel) ** 2)
        dq = np.stack([-(q[m, 1] - x[1]), q[m, 0] - x[0]], axis=1)  # d q / d theta
        J = np.stack([nj[:, 0], nj[:, 1], np.einsum("ij,ij->i", nj, dq)], axis=1)
        scale = cfg.information_scale / cfg.sigma**2
        H = scale * (J.T * w) @ J
        g = scale * (J.T * w) @ r
        # MAP step: minimise the robust points' cost plus x^T P^-1 x.
        step = np.linalg.solve(H + Pinv, -(g + Pinv @ x))
        x = x + step
        if it >= cfg.anneal_iterations and math.hypot(step[0], step[1]) + abs(step[2]) < cfg.tol:
            break
    # Final correspondences and residuals at the estimate.
    c, s = math.cos(x[2]), math.sin(x[2])
    R = np.array([[c, -s], [s, c]])
    q = pts @ R.T + x[:2]
    j = assign(q, normals @ R.T, segs, cfg.gate_end, cfg.max_normal_angle, cfg.end_margin)
    m = j >= 0
    r = np.full(valid, np.inf)
    r[m] = np.einsum("ij,ij->i", q[m] - segs[j[m], 0], seg_n[j[m]])
    inl = np.abs(r) <= cfg.inlier_distance
    n_in = int(inl.sum())
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if n_in else math.inf
    if n_in >= 3:
        nj = seg_n[j[inl]]
        dq = np.stack([-(q[inl, 1] - x[1]), q[inl, 0] - x[0]], axis=1)
        J = np.stack([nj[:, 0], nj[:, 1], np.einsum("ij,ij->i", nj, dq)], axis=1)
        w = 1.0 / (1.0 + (r[inl] / cfg.kernel) ** 2)
        H = cfg.information_scale / cfg.sigma**2 * (J.T * w) @ J
    else:
        H = np.zeros((3, 3))
    cov = np.linalg.inv(H + Pinv)
    cov = 0.5 * (cov + cov.T)
    # Generalised eigenvalues of (H, P^-1): information along each direction relative to the prior's.
    Lc = np.linalg.cholesky(P)
    ev = np.linalg.eigvalsh(Lc.T @ H @ Lc)
    constrained = int(np.sum(ev >= cfg.min_information_ratio))
    maha = float(x @ Pinv @ x)
    reason = ""
    if n_in < cfg.min_inliers:
        reason = f"{n_in} inliers < {cfg.min_inliers}"
    elif n_in < cfg.min_inlier_fraction * valid:
        reason = f"inlier fraction {n_in / valid:.2f} < {cfg.min_inlier_fraction}"
    elif rmse > cfg.max_rmse:
        reason = f"rmse {rmse:.3f} > {cfg.max_rmse}"
    elif maha > cfg.max_mahalanobis:
        reason = f"mahalanobis {maha:.1f} > {cfg.max_mahalanobis}"
    elif constrained == 0:
        reason = "no direction constrained"
    return PointMatch(
        Pose(float(x[0]), float(x[1]), float(x[2])), reason == "", reason, n_in, valid, rmse, H, cov,
        constrained, maha, np.where(m, j, -1).astype(np.int64),
    )


def refine_match(
    res: ICPResult,
    points: FloatArray,
    ref: FloatArray,
    prior: FloatArray,
    drift: FloatArray | None,
    config: PointMatchConfig,
    max_range: float,
) -> ICPResult:
    """The filter's hook (:attr:`mapping.filter.FilterConfig.point_match`): replace the pose
    correction of the wireframe ICP's result ``res`` by a point-to-line match of the raw scan
    ``points`` against the predicted scan's walls ``ref`` (both robot frame of the prediction).

    The match starts from the wireframe ICP's correction when that was accepted, else from the
    prediction, with the pose covariance ``prior`` as prior; its first gate is three standard
    deviations (the rotation's at half the range), as the filter gives the wireframe ICP. When
    it fails and ``drift`` is given (the map's own drift since it was built, see
    :attr:`mapping.filter.FilterConfig.reanchor`), it is tried once more from the prediction with
    ``prior + drift`` and kept only with all three directions constrained and half the RMS
    residual. The result keeps ``res``'s correspondences (the filter's frontier snapping uses
    them) and takes the point match's correction, covariance, information, residual,
    constrained directions and verdict; a point match that fails leaves ``res`` as it was.
    """
    def gate(P: FloatArray) -> float:
        return float(min(2.0, 3.0 * (math.sqrt(max(P[0, 0], P[1, 1])) + math.sqrt(P[2, 2]) * 0.5 * max_range)))

    start = res.correction if res.accepted else None
    pm = match_points(points, ref, prior, config, gate_start=gate(prior), initial=start)
    if not pm.accepted and start is not None:
        pm = match_points(points, ref, prior, config, gate_start=gate(prior))
    if not pm.accepted and drift is not None:
        wide = prior + drift
        again = match_points(points, ref, wide, config, gate_start=gate(wide))
        if again.accepted and again.constrained == 3 and again.rmse <= 0.5 * config.max_rmse:
            pm = again
    if not pm.accepted:
        return res
    return dataclasses.replace(
        res, correction=pm.correction, accepted=True, reason="", rmse=pm.rmse, n_constraints=pm.inliers,
        information=pm.information, covariance=pm.covariance, constrained=pm.constrained,
        mahalanobis=pm.mahalanobis, consistent=True,
    )
