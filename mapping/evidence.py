"""Negative evidence: what a scan says about the map edges it sees through (Sec. IV-D, IV-F).

A scan that sees through a map edge contradicts it. :func:`edge_states` sorts the map edges in
sight into observed and contradicted ones; :func:`contradiction_update` is the Bayes update of a
contradicted edge's existence likelihood, weighted by the part of the edge in view
(:func:`seen_fraction`) so that a 200 m wall seen through along 8 m is not taken down whole.
:func:`seen_through_spans` finds stretches of a partly observed wall that the scan saw through
and :func:`carve` cuts them out (a false-positive edge that the merge joined to a real collinear
wall cannot be dropped by mutation, whose unit is the edge). :func:`edge_log_odds` scores an
edge set's plausibility (the filter's tie-break between equally weighted particles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapping.likelihood import CONTRADICTED, OBSERVED, ray_ranges
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["MAX_LIKELIHOOD", "EvidenceConfig", "carve", "contradiction_update", "edge_log_odds",
           "edge_states", "seen_fraction", "seen_through_spans"]


@dataclass(frozen=True)
class EvidenceConfig:
    """How a scan's evidence changes a particle's map (``evidence.*`` settings).

    Parameters
    ----------
    partial_contradiction : bool
        Weight a contradiction by the part of the wall in view: whole updates took long outer
        walls, mapped a few tenths of a degree off, out of every particle.
    carve : bool
        Cut out of a partly observed wall the stretches two consecutive scans saw through: a
        wall extended too far by the merge keeps the real wall's likelihood and is never mutated.
    reject_in_free_space : bool
        Do not merge a new scan edge where the particle's prediction sees past it onto
        confirmed walls: in a static world (the paper's) it is a false positive or a passer-by.
    """

    partial_contradiction: bool = True
    carve: bool = True
    reject_in_free_space: bool = True


def edge_log_odds(wf: Wireframe, floor: float = 1e-3) -> float:
    """``sum_e log(L_e / (1 - L_e))`` over the edges of ``wf`` (likelihoods clipped to
    ``[floor, 1 - floor]``): how plausible its edge set is under independent edge likelihoods.
    Adding an edge with likelihood below 1/2 lowers it."""
    if wf.n_edges == 0:
        return 0.0
    L = np.clip(wf.likelihood, floor, 1.0 - floor)
    return float(np.sum(np.log(L) - np.log1p(-L)))


#: Edge likelihoods are capped here before a contradiction update: merging combines them as
#: ``1 - (1 - L1)(1 - L2)``, which rounds to exactly 1.0 after a few dozen sightings, and a
#: likelihood of exactly 1 could never be lowered again. At 0.999, four contradicting scans
#: take a wall below a keep threshold of 0.5.
MAX_LIKELIHOOD = 0.999


def contradiction_update(
    likelihood: FloatArray, p_fp: float, p_fn: float, weight: float | FloatArray = 1.0
) -> FloatArray:
    """Bayes update of an edge's existence likelihood after a scan that saw through it:
    ``L p_fn / (L p_fn + (1 - L)(1 - p_fp))``, with ``L`` first capped at
    :data:`MAX_LIKELIHOOD`. With ``weight`` ``w`` (per edge, in [0, 1]) the update counts for
    that fraction of a whole one: the odds are multiplied by ``(p_fn / (1 - p_fp)) ** w``
    (``w = 1`` is the formula above, ``w = 0`` leaves ``L``)."""
    L = np.minimum(np.asarray(likelihood, dtype=np.float64), MAX_LIKELIHOOD)
    ratio = np.power(p_fn / (1.0 - p_fp), np.asarray(weight, dtype=np.float64))
    num = L * ratio
    den = num + (1.0 - L)
    return np.asarray(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), dtype=np.float64)


def seen_fraction(wf: Wireframe, view: Wireframe, edge_source: IntArray) -> FloatArray:
    """Per edge of ``wf``: the length of its pieces in the predicted scan ``view``
    (``edge_source``: the map edge of each view edge) over its own length, in [0, 1]; 1 for an
    edge with no piece in the view (hidden or back-facing: see the filter's step 4)."""
    src = np.asarray(edge_source, dtype=np.int64)
    ok = src >= 0
    seen = np.bincount(src[ok], weights=view.edge_lengths()[ok], minlength=wf.n_edges)
    frac = np.clip(seen / np.maximum(wf.edge_lengths(), 1e-12), 0.0, 1.0)
    return np.asarray(np.where(seen > 0, frac, 1.0), dtype=np.float64)


def edge_states(
    n_edges: int, edge_source: IntArray, state: NDArray[np.int8]
) -> tuple[BoolArray, BoolArray, BoolArray]:
    """Per source edge: in sight, observed (any piece), contradicted (some piece, none observed)."""
    in_sight = np.zeros(n_edges, dtype=bool)
    observed = np.zeros(n_edges, dtype=bool)
    contra = np.zeros(n_edges, dtype=bool)
    src = np.asarray(edge_source, dtype=np.int64)
    ok = src >= 0
    in_sight[src[ok]] = True
    observed[src[ok & (state == OBSERVED)]] = True
    contra[src[ok & (state == CONTRADICTED)]] = True
    return in_sight, observed, contra & ~observed


def seen_through_spans(
    wf: Wireframe,
    pose: Pose,
    view: Wireframe,
    edge_source: IntArray,
    edge_pairs: IntArray,
    evidence: Wireframe,
    min_span: float,
    cover_margin: float,
    margin: float,
    max_range: float,
    memo: dict[Any, list[tuple[float, float, bool]]] | None = None,
) -> dict[int, list[tuple[float, float]]]:
    """Parts of map edges that this scan observed in part and saw through elsewhere.

    For every predicted edge (a visible piece of map edge ``e``) that some scan edges match
    (``edge_pairs``: ``(scan edge, predicted edge)``), the matched scan edges are projected on
    ``e``'s line and their union, grown by ``cover_margin`` at both ends, is *covered*. Each
    uncovered stretch of the visible piece at least ``min_span`` long whose three sample points
    (a quarter, half and three quarters along) the scan saw through -- its ray at that bearing
    meets no scan wall before the point plus ``margin``, and the point is within ``max_range``
    minus ``margin`` (no wall within range is seen-through too: a corner sensor reports every
    wall in range) -- is returned, as arc-length intervals along ``e`` from its start.

    This is the evidence that carves a wall that was extended too far (a false-positive edge
    joined to a real collinear wall by the merge, e.g. across a doorway or between aligned
    pillars): the scan sees the real part and sees through the rest.

    Parameters
    ----------
    wf : Wireframe
        The particle's map (world frame).
    pose : Pose
        Where the scan was taken.
    view : Wireframe
        The predicted scan (robot frame) and ``edge_source``, the map edge of each of its edges.
    edge_pairs : (k, 2) int
        Edge correspondences between ``evidence`` and ``view``.
    evidence : Wireframe
        The scan (robot frame).
    memo : dict, optional
        Answers kept between calls with the same ``evidence``, ``min_span``, ``cover_margin``,
        ``margin`` and ``max_range`` (the caller clears it when one changes): each matched
        predicted edge's stretches and verdicts depend only on its map edge and view piece
        (robot frame) and on the scan edges matching it, so particles that share them (most
        of a filter step's) share the work. The same answers as without it.

    Returns
    -------
    dict
        Map edge index -> list of ``(t0, t1)`` intervals (metres along the edge), disjoint.
    """
    out: dict[int, list[tuple[float, float]]] = {}
    if len(edge_pairs) == 0 or view.n_edges == 0:
        return out
    src = np.asarray(edge_source, dtype=np.int64)
    vseg = view.segments()
    sseg = evidence.segments()
    by_pred: dict[int, list[int]] = {}
    for si, pj in edge_pairs.tolist():
        by_pred.setdefault(int(pj), []).append(int(si))
    # The robot-frame ends of the matched map edges only (a point's transform does not depend
    # on the others': the same numbers as transforming every edge of the map).
    used = sorted({e for e in src.take(list(by_pred)).tolist() if e >= 0})
    row = {e: k for k, e in enumerate(used)}
    corners = wf.points.take(wf.edges.take(used, axis=0).reshape(-1), axis=0)
    ends = pose.apply_inverse(corners).reshape(-1, 2, 2)
    samples: list[FloatArray] = []
    # Per matched predicted edge, in order: its map edge and its stretches with their verdicts
    # (None until the ray test below), and where its memo entry goes.
    items: list[tuple[int, list[tuple[float, float, bool]] | None, Any, list[tuple[float, float]]]] = []
    for pj, scan_edges in by_pred.items():
        e = int(src[pj])
        if e < 0:
            continue
        a, b = ends[row[e]]
        key = None
        if memo is not None:
            key = (a.tobytes(), b.tobytes(), vseg[pj].tobytes(), tuple(scan_edges))
            kept = memo.get(key)
            if kept is not None:
                items.append((e, kept, None, []))
                continue
        gaps = _uncovered(a, b, vseg[pj], sseg, scan_edges, min_span, cover_margin, samples)
        items.append((e, None, key, gaps))
    if samples:
        pts = np.concatenate(samples)
        dist = np.hypot(pts[:, 0], pts[:, 1])
        rng_scan = ray_ranges(evidence, np.arctan2(pts[:, 1], pts[:, 0]))
        seen = np.asarray((rng_scan > dist + margin) & (dist <= max_range - margin), dtype=bool)
        all_seen: list[bool] = np.asarray(seen.reshape(-1, 3).all(axis=1), dtype=bool).tolist()
    else:
        all_seen = []
    k = 0
    for e, kept, key, gaps in items:
        if kept is None:
            kept = [(g0, g1, good) for (g0, g1), good in zip(gaps, all_seen[k : k + len(gaps)])]
            k += len(gaps)
            if memo is not None:
                memo[key] = kept
        for g0, g1, good in kept:
            if good:
                out.setdefault(e, []).append((g0, g1))
    for e in out:
        out[e].sort()
    return out


def _uncovered(
    a: FloatArray,
    b: FloatArray,
    piece: FloatArray,
    sseg: FloatArray,
    scan_edges: list[int],
    min_span: float,
    cover_margin: float,
    samples: list[FloatArray],
) -> list[tuple[float, float]]:
    """:func:`seen_through_spans` for one predicted edge: the stretches of map edge ``a -> b``
    (robot frame) within its view ``piece`` that the matched scan edges do not cover and that
    are at least ``min_span`` long, as arc-length intervals; each one's three sample points are
    appended to ``samples``."""
    d = b - a
    length = float(math.hypot(d[0], d[1]))
    if length < min_span:
        return []
    u = d / length
    v0, v1 = sorted(float((q - a) @ u) for q in piece)
    v0, v1 = max(v0, 0.0), min(v1, length)
    if v1 - v0 < min_span:
        return []
    cov = sorted(
        (min(t0, t1) - cover_margin, max(t0, t1) + cover_margin)
        for t0, t1 in (((sseg[i, 0] - a) @ u, (sseg[i, 1] - a) @ u) for i in scan_edges)
    )
    gaps: list[tuple[float, float]] = []
    cur = v0
    for c0, c1 in cov:
        if c0 > cur:
            gaps.append((cur, min(c0, v1)))
        cur = max(cur, c1)
        if cur >= v1:
            break
    if cur < v1:
        gaps.append((cur, v1))
    out: list[tuple[float, float]] = []
    for g0, g1 in gaps:
        if g1 - g0 >= min_span:
            t = g0 + (g1 - g0) * np.array([0.25, 0.5, 0.75])
            samples.append(a + t[:, None] * u)
            out.append((float(g0), float(g1)))
    return out


def carve(wf: Wireframe, spans: dict[int, list[tuple[float, float]]]) -> tuple[Wireframe, IntArray]:
    """Remove the ``spans`` (arc-length intervals along edges, see :func:`seen_through_spans`)
    from the edges of ``wf``. The remaining pieces keep the edge's direction, likelihood and
    sources; a cut point is a new ``FRONTIER`` vertex (sight of the wall ends there).

    Returns
    -------
    Wireframe
        The kept edges of ``wf`` in order, then the new pieces.
    origin : (m',) int64
        For each edge of the result, the edge of ``wf`` it comes from.
    """
    if not spans:
        return wf, np.arange(wf.n_edges, dtype=np.int64)
    pts = [wf.points]
    labels = [wf.labels]
    n = wf.n_vertices
    new_edges: list[tuple[int, int]] = []
    origin_new: list[int] = []
    for e, ivs in sorted(spans.items()):
        i, j = (int(v) for v in wf.edges[e])
        a, b = wf.points[i], wf.points[j]
        d = b - a
        length = float(math.hypot(d[0], d[1]))
        u = d / length
        cur_v, cur_t = i, 0.0
        for t0, t1 in ivs:
            if t0 > cur_t + 1e-9:
                if t0 >= length - 1e-9:
                    end_v = j
                else:
                    pts.append((a + t0 * u)[None, :])
                    labels.append(np.array([Label.FRONTIER], dtype=np.uint8))
                    end_v = n
                    n += 1
                new_edges.append((cur_v, end_v))
                origin_new.append(e)
            if t1 >= length - 1e-9:
                cur_v, cur_t = -1, length
                break
            pts.append((a + t1 * u)[None, :])
            labels.append(np.array([Label.FRONTIER], dtype=np.uint8))
            cur_v, cur_t = n, t1
            n += 1
        if cur_v >= 0 and cur_t < length - 1e-9:
            new_edges.append((cur_v, j))
            origin_new.append(e)
    keep = np.ones(wf.n_edges, dtype=bool)
    keep[list(spans)] = False
    kept = np.flatnonzero(keep)
    org = np.asarray(origin_new, dtype=np.int64)
    edges = np.concatenate([wf.edges[kept], np.asarray(new_edges, dtype=np.int64).reshape(-1, 2)])
    out = Wireframe(
        np.concatenate(pts),
        np.concatenate(labels),
        edges,
        np.concatenate([wf.likelihood[kept], wf.likelihood[org]]),
        np.concatenate([wf.sources[kept], wf.sources[org]]),
    ).compacted()
    return out, np.concatenate([kept, org]).astype(np.int64)
