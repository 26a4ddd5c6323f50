"""Wireframe scan likelihood ``p(S | W)`` (paper Sec. IV-D).

A scan ``S`` and the predicted scan ``P`` of one particle ``W`` (both in the robot frame, the
robot at the origin, the scan already aligned by ICP) are compared as

``log p(S | W) = sum_vertices log g(d) + sum_edges log b(e_scan, e_predict)``

* ``g`` is the isotropic Gaussian ``N(p_i, sigma^2 I)`` of a vertex about its correspondence.
* ``b`` is the Bernoulli edge model: ``b(1,1) = 1 - p_fn`` (seen and predicted),
  ``b(1,0) = p_fp`` (seen, not predicted), ``b(0,1) = p_fn`` (predicted, not seen).
* Vertices without a correspondence get a **temporary point** in the other wireframe: on the
  vertex itself (no penalty) when it lies in a gap of the other wireframe (unexplored), else
  its projection onto the other wireframe's nearest edge. This is done for both wireframes,
  so every vertex of ``S`` and of ``P`` has exactly one correspondence.
* The **per-edge likelihood** of an edge is the product of its two vertices' Gaussian
  likelihoods and its Bernoulli likelihood; these drive the edge likelihoods that merging
  (Sec. IV-E) and mutation (Sec. IV-F) use.

Choices where the paper is silent
---------------------------------
* ``g`` is the *unnormalised* Gaussian ``exp(-d^2 / 2 sigma^2)`` (1 at a perfect match), so the
  per-edge likelihoods are probabilities in [0, 1] and particles with different numbers of
  vertex terms compare fairly. The constant normalisation is the same for every particle and
  cancels in the weights.
* Robustness: each vertex term is the mixture ``(1 - eps) g + eps`` (``outlier_weight``), so one
  wild vertex costs at most ``-log(eps)`` nats instead of dominating the weights.
* "In a gap" (unexplored): no edge of the other wireframe covers the vertex's bearing from the
  robot. This covers the paper's case (between an occlusion and its frontier with no edge
  behind) and also directions where the other wireframe has no wall at all.
* The ``b(0,0)`` terms (a pair of vertices with no edge in either wireframe) are left out: they
  are about the same for every particle.
* A predicted edge that no scan edge matches is *contradicted* (``b(0,1) = p_fn``) only when the
  scan saw through it: when, along the bearing of the edge's midpoint, the scan has no wall
  nearer than the edge. When the scan has a nearer wall the edge is *occluded* by something
  the particle does not know: no evidence, factor 1. Predicted edges shorter than
  ``min_edge_evidence`` carry no evidence either (slivers of the visibility split).
* Per-edge likelihood of an occluded predicted edge: its Gaussian factors only.
* A predicted edge that lies within ``occlusion_margin`` of the edge of the sensing range, or
  that is seen at a grazing angle (``min_incidence``), carries no evidence either: a small error
  decides whether it was in range, or in front of the robot, at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.icp import Correspondences, correspond, project_onto_segments
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "CONTRADICTED",
    "OBSERVED",
    "OCCLUDED",
    "LikelihoodConfig",
    "ScanLikelihood",
    "in_gap",
    "in_known_free_space",
    "ray_hits",
    "ray_ranges",
    "scan_likelihood",
    "seen_through",
]

#: States of a predicted edge after comparing with the scan.
OBSERVED = 1
CONTRADICTED = 0
OCCLUDED = -1


@dataclass(frozen=True)
class LikelihoodConfig:
    """Parameters of :func:`scan_likelihood`.

    Parameters
    ----------
    sigma : float
        Standard deviation (metres) of the vertex Gaussian, ``Sigma = sigma^2 I`` (default 0.1:
        sensor noise plus map error).
    p_fp, p_fn : float
        Bernoulli false-positive and false-negative probabilities of an edge, in (0, 1).
    gate : float
        Vertex correspondence gate and edge offset gate (metres).
    max_angle : float
        Largest angle (radians) between corresponding edges.
    min_overlap : float
        Least overlap (metres) of corresponding edges (or half the shorter one).
    outlier_weight : float
        ``eps`` of the robust vertex mixture, in (0, 1).
    gap_margin : float
        Angular margin (radians) by which edge bearings are shrunk before the gap test, so a
        vertex exactly on the bearing of an edge's end counts as in the gap.
    occlusion_margin : float
        A scan wall nearer than a predicted edge by more than this (metres) occludes it.
    min_edge_evidence : float
        Predicted edges shorter than this (metres) carry no Bernoulli evidence.
    min_incidence : float
        An unmatched predicted edge seen at a grazing angle, its line of sight meeting it at
        less than this (radians, default 10 degrees), carries no evidence: the robot is close
        to the wall's line, and a small map or pose error decides which side of it the robot
        is on, so whether the wall shows at all.
    """

    sigma: float = 0.1
    p_fp: float = 0.1
    p_fn: float = 0.1
    gate: float = 0.3
    max_angle: float = 0.35
    min_overlap: float = 0.1
    outlier_weight: float = 0.01
    gap_margin: float = 1e-3
    occlusion_margin: float = 0.2
    min_edge_evidence: float = 0.15
    min_incidence: float = math.radians(10.0)

    def __post_init__(self) -> None:
        for name in ("sigma", "gate", "max_angle"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"LikelihoodConfig.{name} must be a positive number, got {v!r}")
        for name in ("p_fp", "p_fn", "outlier_weight"):
            v = getattr(self, name)
            if not (0.0 < v < 1.0):
                raise ValueError(f"LikelihoodConfig.{name} must be in (0, 1), got {v!r}")
        for name in ("min_overlap", "gap_margin", "occlusion_margin", "min_edge_evidence", "min_incidence"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LikelihoodConfig.{name} must be >= 0, got {v!r}")


@dataclass(frozen=True)
class ScanLikelihood:
    """Result of :func:`scan_likelihood`.

    Attributes
    ----------
    log_likelihood : float
        ``log p(S | W)`` (vertex part plus edge part).
    vertex_log, edge_log : float
        The two parts.
    scan_edge_likelihood : (m_s,) float64
        Per-edge likelihood of each scan edge, in [0, 1].
    scan_edge_matched : (m_s,) bool
        Whether each scan edge corresponds to a predicted edge.
    predicted_edge_likelihood : (m_p,) float64
        Per-edge likelihood of each predicted edge, in [0, 1].
    predicted_edge_state : (m_p,) int8
        :data:`OBSERVED`, :data:`CONTRADICTED` or :data:`OCCLUDED`.
    scan_vertex_dist, predicted_vertex_dist : float64 arrays
        Distance of every vertex to its correspondence or temporary point.
    correspondences : Correspondences
    """

    log_likelihood: float
    vertex_log: float
    edge_log: float
    scan_edge_likelihood: FloatArray
    scan_edge_matched: BoolArray
    predicted_edge_likelihood: FloatArray
    predicted_edge_state: NDArray[np.int8]
    scan_vertex_dist: FloatArray
    predicted_vertex_dist: FloatArray
    correspondences: Correspondences


def _bearing_intervals(segments: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Start bearing and counterclockwise angular width of each segment seen from the origin."""
    a, b = segments[:, 0], segments[:, 1]
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    start = np.where(cross >= 0, np.arctan2(a[:, 1], a[:, 0]), np.arctan2(b[:, 1], b[:, 0]))
    dot = np.einsum("ij,ij->i", a, b)
    width = np.abs(np.arctan2(np.abs(cross), dot))
    return start, width


def in_gap(view: Wireframe, points: FloatArray, margin: float = 1e-3) -> BoolArray:
    """Whether each point (robot frame) lies in a gap of ``view``: no edge of ``view`` covers
    its bearing from the robot at the origin (each edge's bearing interval shrunk by
    ``margin`` radians at both ends)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if view.n_edges == 0 or len(p) == 0:
        return np.ones(len(p), dtype=bool)
    start, width = _bearing_intervals(view.segments())
    phi = np.arctan2(p[:, 1], p[:, 0])
    rel = np.mod(phi[:, None] - start[None, :] - margin, 2 * math.pi)
    covered = rel <= (width - 2 * margin)[None, :]
    return np.asarray(~covered.any(axis=1))


def ray_ranges(view: Wireframe, bearings: FloatArray) -> FloatArray:
    """Distance from the origin to the nearest edge of ``view`` along each bearing (``inf``
    where no edge is hit)."""
    return ray_hits(view, bearings)[0]


def ray_hits(view: Wireframe, bearings: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
    """Distance from the origin to the nearest edge of ``view`` along each bearing, and that
    edge's index (``inf`` and -1 where no edge is hit)."""
    phi = np.asarray(bearings, dtype=np.float64).reshape(-1)
    if view.n_edges == 0 or len(phi) == 0:
        return np.full(len(phi), np.inf), np.full(len(phi), -1, dtype=np.int64)
    s = view.segments()
    a = s[:, 0]
    d = s[:, 1] - a
    v = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    den = v[:, None, 0] * d[None, :, 1] - v[:, None, 1] * d[None, :, 0]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    t = (a[None, :, 0] * d[None, :, 1] - a[None, :, 1] * d[None, :, 0]) / den
    u = (a[None, :, 0] * v[:, None, 1] - a[None, :, 1] * v[:, None, 0]) / den
    hit = ok & (t > 0) & (u >= -1e-9) & (u <= 1 + 1e-9)
    dist = np.where(hit, t, np.inf)
    idx = np.argmin(dist, axis=1)
    best = dist[np.arange(len(phi)), idx]
    return best, np.where(np.isfinite(best), idx, -1).astype(np.int64)


def seen_through(
    scan: Wireframe,
    segments: FloatArray,
    margin: float = 0.2,
    max_range: float = math.inf,
    samples: tuple[float, ...] = (0.25, 0.5, 0.75),
    min_incidence: float = math.radians(10.0),
) -> BoolArray:
    """Whether the scan saw *through* each segment (robot frame): at every sample point along
    it, the scan has a wall on the same bearing farther than the point by more than ``margin``.

    This is positive evidence that no wall is there, whichever way the segment is directed;
    the filter uses it for map edges that are in view but not reported by the predicted scan
    (back-facing edges, paper Fig. 5). A sample point beyond ``max_range - margin`` or on a
    bearing where the scan has no wall gives no evidence, so the answer is then False; so does a
    segment seen at a grazing angle (its midpoint's line of sight meets it at less than
    ``min_incidence``).
    """
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    if len(s) == 0 or scan.n_edges == 0:
        return np.zeros(len(s), dtype=bool)
    t = np.asarray(samples, dtype=np.float64)
    pts = s[:, None, 0, :] + t[None, :, None] * (s[:, None, 1, :] - s[:, None, 0, :])
    flat = pts.reshape(-1, 2)
    dist = np.hypot(flat[:, 0], flat[:, 1])
    rng_scan = ray_ranges(scan, np.arctan2(flat[:, 1], flat[:, 0]))
    ok = np.isfinite(rng_scan) & (rng_scan > dist + margin) & (dist <= max_range - margin)
    facing = _sin_incidence(s) >= math.sin(min_incidence)
    return np.asarray(ok.reshape(len(s), len(t)).all(axis=1) & facing)


def in_known_free_space(
    view: Wireframe,
    segments: FloatArray,
    margin: float = 0.2,
    min_likelihood: float = 0.5,
    samples: tuple[float, ...] = (0.25, 0.5, 0.75),
) -> BoolArray:
    """Whether each segment (robot frame) lies where ``view`` (a predicted scan) is confident
    there is free space: at least half of the sample points along it are *known free* (``view``
    sees past the point by more than ``margin`` onto a wall whose likelihood is at least
    ``min_likelihood``) and none is contradicted (``view`` has a wall at or before the point);
    a sample where ``view`` sees no wall at all is neither."""
    s = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    if len(s) == 0 or view.n_edges == 0:
        return np.zeros(len(s), dtype=bool)
    t = np.asarray(samples, dtype=np.float64)
    pts = (s[:, None, 0, :] + t[None, :, None] * (s[:, None, 1, :] - s[:, None, 0, :])).reshape(-1, 2)
    dist = np.hypot(pts[:, 0], pts[:, 1])
    rng_view, edge = ray_hits(view, np.arctan2(pts[:, 1], pts[:, 0]))
    sure = np.where(edge >= 0, view.likelihood[np.maximum(edge, 0)], 0.0) >= min_likelihood
    hit = np.isfinite(rng_view)
    free = (hit & (rng_view > dist + margin) & sure).reshape(len(s), len(t))
    unknown = (~hit).reshape(len(s), len(t))
    return np.asarray((free | unknown).all(axis=1) & (2 * free.sum(axis=1) >= len(t)))


def _temporary_dist(points: FloatArray, other: Wireframe, margin: float) -> FloatArray:
    """Distance of unmatched ``points`` to their temporary points in ``other`` (paper IV-D)."""
    if len(points) == 0:
        return np.zeros(0)
    if other.n_edges == 0:
        return np.zeros(len(points))
    gap = in_gap(other, points, margin)
    out = np.zeros(len(points))
    if np.any(~gap):
        _, _, dist = project_onto_segments(points.compress(~gap, axis=0), other.segments())
        out[~gap] = dist
    return out


def _sin_incidence(segments: FloatArray) -> FloatArray:
    """Sine of the angle between each segment ``(m, 2, 2)`` and the line of sight from the
    origin to its midpoint (0: seen edge-on)."""
    d = segments[:, 1] - segments[:, 0]
    mid = 0.5 * (segments[:, 0] + segments[:, 1])
    cross = np.abs(d[:, 0] * mid[:, 1] - d[:, 1] * mid[:, 0])
    den = np.hypot(d[:, 0], d[:, 1]) * np.hypot(mid[:, 0], mid[:, 1])
    return np.asarray(np.where(den > 0, cross / np.where(den > 0, den, 1.0), 0.0), dtype=np.float64)


def _distance_to_origin(segments: FloatArray) -> FloatArray:
    """Distance from the origin (the robot) to each segment ``(m, 2, 2)``."""
    a = segments[:, 0]
    d = segments[:, 1] - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(-np.einsum("ij,ij->i", a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    c = a + t[:, None] * d
    return np.asarray(np.hypot(c[:, 0], c[:, 1]), dtype=np.float64)


def scan_likelihood(
    scan: Wireframe,
    predicted: Wireframe,
    config: LikelihoodConfig | None = None,
    correspondences: Correspondences | None = None,
    max_range: float = math.inf,
) -> ScanLikelihood:
    """The likelihood ``p(S | W)`` of a scan given one particle's predicted scan (Sec. IV-D).

    Parameters
    ----------
    scan : Wireframe
        The measured scan ``S``, robot frame, aligned (after ICP).
    predicted : Wireframe
        The particle's predicted scan ``P`` at the same pose, robot frame.
    config : LikelihoodConfig, optional
    correspondences : Correspondences, optional
        Reuse correspondences already computed (scan to predicted); computed with
        :func:`mapping.icp.correspond` at ``config.gate`` otherwise.
    max_range : float, optional
        The sensing range: an unmatched predicted edge no part of which is nearer than
        ``max_range - occlusion_margin`` carries no evidence (whether it was in range at all
        depends on small pose and map errors there).

    Returns
    -------
    ScanLikelihood
    """
    cfg = config or LikelihoodConfig()
    corr = correspondences or correspond(scan, predicted, cfg.gate, cfg.max_angle, cfg.min_overlap)
    ns, np_ = scan.n_vertices, predicted.n_vertices
    s_match = corr.scan_vertex_match(ns)
    p_match = corr.ref_vertex_match(np_)
    d_s = np.zeros(ns)
    d_p = np.zeros(np_)
    if len(corr.vertex_pairs):
        d_s[corr.vertex_pairs[:, 0]] = corr.vertex_dist
        d_p[corr.vertex_pairs[:, 1]] = corr.vertex_dist
    um_s = s_match < 0
    um_p = p_match < 0
    # (take / compress: row gathers, faster than [ ] on 2-D arrays at these sizes)
    d_s[um_s] = _temporary_dist(scan.points.compress(um_s, axis=0), predicted, cfg.gap_margin)
    d_p[um_p] = _temporary_dist(predicted.points.compress(um_p, axis=0), scan, cfg.gap_margin)

    inv = 0.5 / cfg.sigma**2
    g_s = np.exp(-inv * d_s**2)
    g_p = np.exp(-inv * d_p**2)
    eps = cfg.outlier_weight
    # Matched pairs are counted once (from the scan side); unmatched predicted vertices add theirs.
    vertex_log = float(np.log((1 - eps) * g_s + eps).sum() + np.log((1 - eps) * g_p[um_p] + eps).sum())

    ms, mp = scan.n_edges, predicted.n_edges
    s_edge = corr.scan_edge_matched(ms)
    p_edge = corr.ref_edge_matched(mp)
    state = np.full(mp, OBSERVED, dtype=np.int8)
    unm = np.flatnonzero(~p_edge)
    if len(unm):
        seg = predicted.segments().take(unm, axis=0)
        mid = 0.5 * (seg[:, 0] + seg[:, 1])
        rng_mid = np.hypot(mid[:, 0], mid[:, 1])
        rng_scan = ray_ranges(scan, np.arctan2(mid[:, 1], mid[:, 0]))
        occluded = rng_scan < rng_mid - cfg.occlusion_margin
        short = np.hypot(*(seg[:, 1] - seg[:, 0]).T) < cfg.min_edge_evidence
        # Near the edge of the sensing range a small pose or map error decides whether the
        # wall was in range at all: no evidence unless some of it is clearly within range.
        edge_of_range = _distance_to_origin(seg) > max_range - cfg.occlusion_margin
        grazing = _sin_incidence(seg) < math.sin(cfg.min_incidence)
        state[unm] = np.where(occluded | short | edge_of_range | grazing, OCCLUDED, CONTRADICTED)
    b_s = np.where(s_edge, 1.0 - cfg.p_fn, cfg.p_fp)
    # Each predicted edge's factor by its state, gathered from a table indexed by the state
    # (OCCLUDED is -1, the table's last entry): the floats np.select would pick, at a fifth of
    # its cost (its per-call cost dominates at a dozen edges).
    by_state = np.empty(3)
    by_state[OBSERVED], by_state[CONTRADICTED], by_state[OCCLUDED] = 1.0 - cfg.p_fn, cfg.p_fn, 1.0
    b_p = by_state[state]
    edge_log = float(np.log(b_s).sum() + np.log(cfg.p_fn) * np.count_nonzero(state == CONTRADICTED))

    if ms:
        lik_s = g_s[scan.edges[:, 0]] * g_s[scan.edges[:, 1]] * b_s
    else:
        lik_s = np.zeros(0)
    if mp:
        lik_p = g_p[predicted.edges[:, 0]] * g_p[predicted.edges[:, 1]] * b_p
    else:
        lik_p = np.zeros(0)
    return ScanLikelihood(
        log_likelihood=vertex_log + edge_log,
        vertex_log=vertex_log,
        edge_log=edge_log,
        scan_edge_likelihood=np.clip(lik_s, 0.0, 1.0),
        scan_edge_matched=s_edge,
        predicted_edge_likelihood=np.clip(lik_p, 0.0, 1.0),
        predicted_edge_state=state,
        scan_vertex_dist=d_s,
        predicted_vertex_dist=d_p,
        correspondences=corr,
    )
