"""Scores of a mapping run on a real lidar log against a true trajectory (no truth map).

A real log has no wireframe truth; what it has is a true pose per scan (a ``TRUEPOS`` track or
a SLAM-corrected trajectory). The map is then judged against the *real scan endpoints placed at
the true poses* -- the closest thing to the building a log holds. All functions are pure; poses
are ``(k, 3)`` arrays of ``x, y, theta`` in one frame, indexed by scan.

* :func:`ate` -- absolute trajectory error: RMSE and maximum of the position error, **without
  alignment** (the run starts at the known true pose, so its frame is the truth's).
* :func:`rpe` -- relative error over a travelled distance: for each scan ``i``, the first scan
  ``j`` at least ``distance`` metres further along the true path; the error is the length of
  the difference between the estimated and the true motion from ``i`` to ``j`` (in ``i``'s
  frame), averaged over the pairs. Drift per metre without the early errors that dominate ATE.
* :func:`scan_endpoints` -- the returns of scans placed at given poses.
* :func:`map_precision` -- the fraction of points sampled every ``spacing`` metres along the
  map's walls that lie within ``tol`` of an endpoint: how much of the map is real.
* :func:`map_coverage` -- the fraction of endpoints within ``tol`` of a map wall: how much of
  what the laser saw is in the map.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from mapping.metrics import rigid_fit, sample_walls, wall_pieces
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

__all__ = ["ate", "map_coverage", "map_precision", "rpe", "scan_endpoints", "score_run"]


def _poses(a: ArrayLike, name: str, cols: int = 3) -> FloatArray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < cols:
        raise ValueError(f"{name} must be a (k, {cols}) array, got shape {p.shape}")
    return p


def ate(estimate: ArrayLike, truth: ArrayLike) -> tuple[float, float]:
    """Absolute trajectory error without alignment.

    Parameters
    ----------
    estimate, truth : (k, >=2) array
        Positions (extra columns such as headings are ignored), row ``i`` of both for scan ``i``.

    Returns
    -------
    rmse, max : float
        Metres; ``nan`` for empty input.

    Raises
    ------
    ValueError
        For arrays of a bad or different shape.
    """
    e, t = _poses(estimate, "estimate", 2), _poses(truth, "truth", 2)
    if len(e) != len(t):
        raise ValueError(f"estimate and truth differ in length ({len(e)} and {len(t)})")
    if len(e) == 0:
        return math.nan, math.nan
    d = np.hypot(e[:, 0] - t[:, 0], e[:, 1] - t[:, 1])
    return float(np.sqrt(np.mean(d * d))), float(d.max())


def _relative(p: FloatArray, i: NDArray[np.int64], j: NDArray[np.int64]) -> FloatArray:
    """Translation of ``p[i]^-1 * p[j]`` per pair, ``(m, 2)``."""
    dx, dy = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1]
    c, s = np.cos(p[i, 2]), np.sin(p[i, 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)


def rpe(estimate: ArrayLike, truth: ArrayLike, distance: float = 1.0) -> float:
    """Mean relative translation error over pose pairs ``distance`` metres apart on the true path.

    Parameters
    ----------
    estimate, truth : (k, 3) array
        Poses ``x, y, theta``, row ``i`` of both for scan ``i``.
    distance : float
        Path length between the poses of a pair (metres): pair ``(i, j)`` takes the first ``j``
        whose true path length from ``i`` is at least ``distance``.

    Returns
    -------
    float
        Metres; ``nan`` when no pair is that far apart.

    Raises
    ------
    ValueError
        For arrays of a bad or different shape, or a non-positive distance.
    """
    e, t = _poses(estimate, "estimate"), _poses(truth, "truth")
    if len(e) != len(t):
        raise ValueError(f"estimate and truth differ in length ({len(e)} and {len(t)})")
    if not (math.isfinite(distance) and distance > 0):
        raise ValueError(f"distance must be a positive number of metres, got {distance}")
    if len(t) < 2:
        return math.nan
    steps = np.hypot(np.diff(t[:, 0]), np.diff(t[:, 1]))
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    i = np.arange(len(t))
    j = np.searchsorted(travelled, travelled + distance - 1e-12, side="left")
    ok = j < len(t)
    if not ok.any():
        return math.nan
    i, j = i[ok], j[ok]
    diff = _relative(e, i, j) - _relative(t, i, j)
    return float(np.mean(np.hypot(diff[:, 0], diff[:, 1])))


def scan_endpoints(
    poses: ArrayLike,
    ranges: Sequence[ArrayLike],
    angles: Sequence[ArrayLike],
    max_range: float = math.inf,
) -> FloatArray:
    """The returns of scans placed at ``poses``, as world points ``(m, 2)``.

    Parameters
    ----------
    poses : (k, 3) array
        The sensor's pose per scan.
    ranges, angles : sequences of k arrays
        Each scan's ranges and bearings (sensor frame); non-finite ranges are no return.
    max_range : float
        Returns at or beyond this range are left out.

    Raises
    ------
    ValueError
        For a pose array of a bad shape or sequences of different lengths.
    """
    p = _poses(poses, "poses")
    if not (len(p) == len(ranges) == len(angles)):
        raise ValueError(f"{len(p)} poses, {len(ranges)} range arrays and {len(angles)} angle arrays")
    out = []
    for (x, y, th), r_, a_ in zip(p, ranges, angles):
        r = np.asarray(r_, dtype=np.float64).reshape(-1)
        a = np.asarray(a_, dtype=np.float64).reshape(-1)
        keep = np.isfinite(r) & (r < max_range)
        r, a = r[keep], a[keep] + th
        out.append(np.stack([x + r * np.cos(a), y + r * np.sin(a)], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def map_precision(wf: Wireframe, endpoints: ArrayLike, tol: float = 0.2, spacing: float = 0.05) -> float:
    """The fraction of points sampled every ``spacing`` metres along the map's walls
    (:func:`mapping.metrics.sample_walls`, each stretch of wall once) within ``tol`` of an endpoint.

    Returns
    -------
    float
        In [0, 1]; ``nan`` for a map without walls.

    Raises
    ------
    ValueError
        For a non-positive ``tol`` or ``spacing`` or endpoints not ``(m, 2)``.
    """
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number of metres, got {tol}")
    pts = _poses(endpoints, "endpoints", 2)[:, :2]
    samples, _, _ = sample_walls(wf, spacing)
    if len(samples) == 0:
        return math.nan
    if len(pts) == 0:
        return 0.0
    d, _ = cKDTree(pts).query(samples, k=1, distance_upper_bound=tol)
    return float(np.mean(d <= tol))


def align_to_points(
    wf: Wireframe, endpoints: ArrayLike, step: float = 0.1, max_dist: float = 1.0, keep: float = 0.8,
    iterations: int = 50,
) -> Pose:
    """The rigid motion that lays the map's walls best onto scan endpoints (a map whose frame
    is arbitrary -- robots that never shared one -- scored after one rigid alignment, as
    :func:`mapping.metrics.align_to_truth` does against true walls).

    Trimmed ICP from the identity: the walls sampled every ``step`` metres, each sample paired
    with its nearest endpoint within ``max_dist``, the ``keep`` share of closest pairs aligned
    in closed form (length-weighted), until it stops moving or ``iterations`` times. A local
    refinement: a map off by more than ``max_dist`` is not found.

    Returns
    -------
    Pose
        ``T`` such that ``wf.transformed(T)`` is the aligned map (identity when fewer than 10
        samples pair up).
    """
    if not (math.isfinite(step) and step > 0 and math.isfinite(max_dist) and max_dist > 0):
        raise ValueError(f"step and max_dist must be positive numbers of metres, got {step}, {max_dist}")
    if not (0.0 < keep <= 1.0):
        raise ValueError(f"keep must be within (0, 1], got {keep}")
    pts = _poses(endpoints, "endpoints", 2)[:, :2]
    mp, mw, _ = sample_walls(wf, step)
    if len(mp) < 10 or len(pts) < 10:
        return Pose.identity()
    tree = cKDTree(pts)
    R, t = np.eye(2), np.zeros(2)
    for _ in range(iterations):
        q = mp @ R.T + t
        d, j = tree.query(q, k=1, distance_upper_bound=max_dist)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        sel = ok & (d <= np.quantile(d[ok], keep))
        R_new, t_new = rigid_fit(mp[sel], pts[j[sel]], mw[sel])
        done = np.abs(R_new - R).max() < 1e-9 and np.abs(t_new - t).max() < 1e-7
        R, t = R_new, t_new
        if done:
            break
    return Pose(float(t[0]), float(t[1]), math.atan2(R[1, 0], R[0, 0]))


def map_coverage(wf: Wireframe, endpoints: ArrayLike, tol: float = 0.2) -> float:
    """The fraction of ``endpoints`` within ``tol`` metres of a map wall (exact point-to-segment
    distance).

    Returns
    -------
    float
        In [0, 1]; ``nan`` without endpoints.

    Raises
    ------
    ValueError
        For a non-positive ``tol`` or endpoints not ``(m, 2)``.
    """
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number of metres, got {tol}")
    pts = _poses(endpoints, "endpoints", 2)[:, :2]
    if len(pts) == 0:
        return math.nan
    pieces = wall_pieces(wf)
    if len(pieces) == 0:
        return 0.0
    tree = shapely.STRtree(shapely.linestrings(pieces))
    hit, _ = tree.query(shapely.points(pts), predicate="dwithin", distance=tol)
    return float(len(np.unique(hit)) / len(pts))


def score_run(
    estimate: ArrayLike, truth: ArrayLike, wf: Wireframe, endpoints: ArrayLike,
    tol: float = 0.2, spacing: float = 0.05, rpe_distance: float = 1.0,
) -> dict[str, float]:
    """The figures of one run against its truth, as ``wiremap map`` and ``wiremap bench lidar``
    report them: ``ate_rmse_m``, ``ate_max_m``, ``rpe_1m_m`` (relative error over
    ``rpe_distance``), ``map_precision`` and ``map_coverage`` (at ``tol`` against ``endpoints``),
    and ``map_precision_aligned`` with ``alignment_m`` and ``alignment_deg``: the precision after
    the one rigid motion that lays the map best onto the endpoints (:func:`align_to_points`) and
    that motion's size. A map turned about its start by a few tenths of a degree loses precision
    at its far end that the aligned figure keeps: the two apart tell a map's shape from its
    placement."""
    rmse, mx = ate(estimate, truth)
    fix = align_to_points(wf, endpoints)
    return {
        "ate_rmse_m": rmse,
        "ate_max_m": mx,
        "rpe_1m_m": rpe(estimate, truth, rpe_distance),
        "map_precision": map_precision(wf, endpoints, tol, spacing),
        "map_coverage": map_coverage(wf, endpoints, tol),
        "map_precision_aligned": map_precision(wf.transformed(fix), endpoints, tol, spacing),
        "alignment_m": math.hypot(fix.x, fix.y),
        "alignment_deg": math.degrees(fix.theta),
    }
