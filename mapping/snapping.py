"""Snapping new scan walls onto established map walls before the merge (not in the paper).

The map and the pose are estimated from each other; a wall that grows at its frontier, or a new
wall that continues an old one across a doorway, would take the pose's current error into the
map, and the next match against it could not see that error. :func:`snap_frontiers` moves a
scan frontier onto the line of the longer map wall it continues; :func:`snap_collinear` puts a
new scan wall that continues an established wall past its end onto that wall's line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.config import check_number
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["SnappingConfig", "snap_collinear", "snap_frontiers"]


@dataclass(frozen=True)
class SnappingConfig:
    """Which snapping runs before the merge (``snapping.*`` settings).

    Parameters
    ----------
    frontiers : bool
        :func:`snap_frontiers`, after every consistent match: snapping after accepted matches
        only let the others drag a museum wall's far end 0.4 degrees over 40 m.
    collinear : bool
        :func:`snap_collinear`, after accepted matches: museum seed 1 went from 0.45 to 0.29 m
        mean wall error (recall 0.80 to 0.89).
    collinear_min_support : float
        Metres of established map wall a new wall must continue (2: a door's width of wall).
    collinear_max_offset : float
        Largest offset (metres) of both ends from the wall's line (0.08: a few corner sigmas).
    collinear_max_angle : float
        Largest angle (radians) to the wall's direction (1.5 degrees: above the heading's
        uncertainty after a match, below any real change of direction).

    Raises
    ------
    ValueError
        On a negative value, or an angle above pi/2.
    """

    frontiers: bool = True
    collinear: bool = True
    collinear_min_support: float = 2.0
    collinear_max_offset: float = 0.08
    collinear_max_angle: float = math.radians(1.5)

    def __post_init__(self) -> None:
        check_number("collinear_min_support", self.collinear_min_support, 0.0)
        check_number("collinear_max_offset", self.collinear_max_offset, 0.0)
        check_number("collinear_max_angle", self.collinear_max_angle, 0.0, math.pi / 2)


def snap_frontiers(
    scan_points: FloatArray,
    scan: Wireframe,
    ref: Wireframe,
    edge_pairs: IntArray,
    support: FloatArray,
    max_offset: float,
) -> FloatArray:
    """Frontier vertices of the scan moved onto the line of the map wall they continue.

    A frontier vertex is where sight of a wall ended, not a corner: its position *along* the
    wall says how far the wall was seen, its position *across* it is only as good as the pose.
    When the scan edge that ends in it corresponds (``edge_pairs``: ``(scan edge, ref edge)``)
    to a reference edge whose map wall (``support``: length of the map wall behind each
    reference edge) is longer than the scan edge, the established wall knows its line better:
    the vertex is projected onto that line if that moves it by at most ``max_offset``.
    Otherwise a wall growing scan by scan at its frontier would follow the pose's error (its
    newest end is placed by the newest pose), and matching the next scan against it could not
    see that error: the map and the pose would drift together.

    Parameters
    ----------
    scan_points : (n, 2)
        The scan's vertices, in the reference's frame (moved by the ICP correction).
    scan, ref : Wireframe
        The scan and the reference (predicted scan).
    edge_pairs : (k, 2) int
    support : (ref.n_edges,) float
    max_offset : float

    Returns
    -------
    (n, 2) float64
        The vertices, frontiers snapped where the rule applies.
    """
    out = np.array(scan_points, dtype=np.float64, copy=True)
    if len(edge_pairs) == 0:
        return out
    s_len = np.hypot(*(scan_points[scan.edges[:, 1]] - scan_points[scan.edges[:, 0]]).T)
    best: dict[int, tuple[float, int]] = {}
    for si, rj in edge_pairs.tolist():
        sup = float(support[rj])
        if sup <= s_len[si]:
            continue
        for v in scan.edges[si].tolist():
            if scan.labels[v] == Label.FRONTIER and sup > best.get(v, (-1.0, -1))[0]:
                best[v] = (sup, rj)
    for v, (_, rj) in best.items():
        a, b = ref.points[ref.edges[rj, 0]], ref.points[ref.edges[rj, 1]]
        d = b - a
        ln = float(math.hypot(d[0], d[1]))
        if ln <= 0:
            continue
        n = np.array([-d[1], d[0]]) / ln
        off = float((out[v] - a) @ n)
        if abs(off) <= max_offset:
            out[v] = out[v] - off * n
    return out


def snap_collinear(
    scan_points: FloatArray,
    scan: Wireframe,
    ref: Wireframe,
    edge_pairs: IntArray,
    support: FloatArray,
    min_support: float,
    max_offset: float,
    max_angle: float,
) -> FloatArray:
    """Scan walls that continue an established map wall across a gap put onto its line.

    A wall behind a doorway is new to the map, so nothing pins it: it enters at the pose's
    heading, a tenth of a degree off, and the next wall of the corridor continues *it*; door by
    door the corridor bends. Buildings are built along lines: a new scan wall (no reference edge
    corresponds to it) that runs in the same direction as a map wall at least ``min_support``
    long (within ``max_angle``, same free side) with both ends within ``max_offset`` of that
    wall's line, beyond its extent, is taken to continue it, and its ends are projected onto
    the line. A wall genuinely offset by less than ``max_offset`` is straightened by at most
    that much.

    Parameters
    ----------
    scan_points : (n, 2)
        The scan's vertices in the reference's frame.
    scan, ref : Wireframe
    edge_pairs : (k, 2) int
        ``(scan edge, ref edge)`` correspondences of the match.
    support : (ref.n_edges,) float
        Length of the map wall behind each reference edge (0 where none).
    min_support, max_offset, max_angle : float

    Returns
    -------
    (n, 2) float64
    """
    out = np.array(scan_points, dtype=np.float64, copy=True)
    if scan.n_edges == 0 or ref.n_edges == 0:
        return out
    new = np.ones(scan.n_edges, dtype=bool)
    if len(edge_pairs):
        new[edge_pairs[:, 0]] = False
    cand = np.flatnonzero(support >= min_support)
    if not new.any() or len(cand) == 0:
        return out
    ra, rb = ref.points[ref.edges[cand, 0]], ref.points[ref.edges[cand, 1]]
    rd = rb - ra
    rl = np.hypot(rd[:, 0], rd[:, 1])
    ru = rd / np.maximum(rl, 1e-12)[:, None]
    rn = np.stack([-ru[:, 1], ru[:, 0]], axis=1)
    cos_tol = math.cos(max_angle)
    moved: dict[int, FloatArray] = {}
    for si in np.flatnonzero(new).tolist():
        i, j = scan.edges[si].tolist()
        p, q = out[i], out[j]
        d = q - p
        ln = math.hypot(d[0], d[1])
        if ln <= 0:
            continue
        ok = (ru @ (d / ln)) >= cos_tol
        op = np.einsum("ij,ij->i", p - ra, rn)
        oq = np.einsum("ij,ij->i", q - ra, rn)
        ok &= (np.abs(op) <= max_offset) & (np.abs(oq) <= max_offset)
        tp = np.einsum("ij,ij->i", p - ra, ru)
        tq = np.einsum("ij,ij->i", q - ra, ru)
        ok &= (np.minimum(tp, tq) >= rl - 1e-9) | (np.maximum(tp, tq) <= 1e-9)  # beyond its extent
        if not ok.any():
            continue
        k = int(np.flatnonzero(ok)[np.argmax(rl[ok])])
        for v, off in ((i, op[k]), (j, oq[k])):
            if v not in moved:
                moved[v] = out[v] - off * rn[k]
    for v, pt in moved.items():
        out[v] = pt
    return out
