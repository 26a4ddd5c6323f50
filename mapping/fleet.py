"""Fleet-level map algorithms: what the fusion service does with several robots' maps.

Pure functions (no I/O, no clock), used by :mod:`agents.fleet.fusion`:

* :func:`close_frontiers` removes frontiers of one robot that another robot's walls close;
* :func:`align_maps` is the map-to-map alignment: a small rigid correction of one robot's map
  (already placed by its known start pose) onto the maps of the robots fused before it, by the
  wireframe ICP of :mod:`mapping.icp`;
* :func:`fold_split` is where the fusion's fold tree splits a run of robots (see
  ``ARCHITECTURE.md``, "Fusion rules").

The content digest of a map (its identity in caches) is :meth:`Wireframe.content_digest`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapping.icp import icp
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

__all__ = ["align_maps", "close_frontiers", "fold_split"]


# ---------------------------------------------------------------------- frontier closing
def close_frontiers(wf: Wireframe, threshold: float, max_angle: float = math.radians(20.0)) -> Wireframe:
    """Remove frontiers that another wall of the fused map closes.

    A frontier vertex ``v`` (where a wall leaves what its robot saw) is *closed* when it lies
    within ``threshold`` of the interior of an edge ``e`` that does not touch it (more than
    ``threshold`` from both of ``e``'s ends): someone saw the wall go on. Then (choices; the
    paper only says such frontiers should disappear):

    * each wall at ``v`` that runs along ``e`` (within ``max_angle``, same direction) is
      covered by ``e``: it is dropped when its other end ``u`` also lies along ``e``;
      otherwise it is re-attached from ``v`` to ``e``'s nearer end, so that the wall stays one
      connected chain (``u`` -> end of ``e``), keeping its likelihood and sources;
    * if walls at an angle to ``e`` remain at ``v``, ``v`` is where that wall meets ``e``: a
      real corner, relabelled ``NOMINAL``;
    * a vertex left without walls is dropped.

    An edge that runs opposite to one of ``v``'s walls is the back of a thin wall and does not
    close ``v``. When several edges close ``v``, the one of lowest index is used. Decisions are
    made on the input map and applied together.

    Parameters
    ----------
    wf : Wireframe
        The fused map.
    threshold : float
        The merge threshold (metres).
    max_angle : float
        Largest angle (radians) between a wall at ``v`` and ``e`` for the wall to run along ``e``.

    Returns
    -------
    Wireframe
        ``wf`` itself when nothing is closed, else the map with the closed frontiers removed.
    """
    fr = np.flatnonzero(wf.labels == Label.FRONTIER)
    if len(fr) == 0 or wf.n_edges == 0:
        return wf
    geo = EdgeFrame.of(wf)
    A, L, ok, dirs = geo.A, geo.L, geo.ok, geo.dirs
    P, E = wf.points, wf.edges
    # Which edges close each frontier: arc-length along (t) and distance across (d) every edge
    # for a block of frontiers at once (frontier x edge, blocks of at most ~2**18 entries): the
    # same element-wise operations, in the same order, as one frontier at a time, so the same
    # floats and the same candidates, without a dozen numpy calls per frontier.
    closing_of: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # row of fr -> (touches, closing)
    step = max(1, (1 << 18) // max(1, wf.n_edges))
    for b0 in range(0, len(fr), step):
        blk = fr[b0: b0 + step]
        rel = P.take(blk, axis=0)[:, None, :] - A[None, :, :]
        t = rel[..., 0] * dirs[:, 0] + rel[..., 1] * dirs[:, 1]
        d = np.abs(dirs[:, 0] * rel[..., 1] - dirs[:, 1] * rel[..., 0])
        touches = (E[:, 0] == blk[:, None]) | (E[:, 1] == blk[:, None])
        closing = ok & ~touches & (d <= threshold) & (t > threshold) & (t < L - threshold)
        for r in np.flatnonzero(closing.any(axis=1)).tolist():
            closing_of[b0 + r] = (touches[r], np.flatnonzero(closing[r]))
    return apply_closings(wf, geo, [(int(fr[r]), tc[0], tc[1]) for r, tc in closing_of.items()], threshold,
                          max_angle)


@dataclass(frozen=True)
class EdgeFrame:
    """Each edge's start ``A``, length ``L``, whether it has one (``ok``) and unit direction
    ``dirs`` (zero for a zero-length edge): :func:`close_frontiers`' view of the map."""

    A: np.ndarray
    L: np.ndarray
    ok: np.ndarray
    dirs: np.ndarray

    @classmethod
    def of(cls, wf: Wireframe) -> EdgeFrame:
        P, E = wf.points, wf.edges
        A = P[E[:, 0]]
        D = P[E[:, 1]] - A
        L = np.hypot(D[:, 0], D[:, 1])
        ok = L > 1e-12
        dirs = np.zeros_like(D)
        dirs[ok] = D[ok] / L[ok, None]
        return cls(A, L, ok, dirs)


def apply_closings(
    wf: Wireframe, geo: EdgeFrame, closings: list[tuple[int, np.ndarray, np.ndarray]], threshold: float,
    max_angle: float,
) -> Wireframe:
    """:func:`close_frontiers`' decisions and their result, given for each frontier ``v`` that
    some edge closes, in vertex order, ``(v, touches, closing)``: the mask of the edges at
    ``v`` and the indices of the edges that close it."""
    P, E = wf.points, wf.edges
    A, L, ok, dirs = geo.A, geo.L, geo.ok, geo.dirs
    cos_max = math.cos(max_angle)
    drop_edge = np.zeros(wf.n_edges, dtype=bool)
    edges = E.copy()
    relabel: list[int] = []
    for v, touches, closing in closings:  # frontiers in order; the others stay
        inc = np.flatnonzero(touches)
        # an edge running the other way is the back of a thin wall, not a continuation
        usable = [int(k) for k in closing if not np.any(ok[inc] & (dirs[inc] @ dirs[k] <= -cos_max))]
        if not usable:
            continue
        k = usable[0]
        at_angle = 0
        for j in inc.tolist():
            if not ok[j] or float(dirs[j] @ dirs[k]) < cos_max:
                at_angle += 1
                continue
            end_v = 0 if E[j, 0] == v else 1
            u = int(E[j, 1 - end_v])
            tu = float((P[u] - A[k]) @ dirs[k])
            du = abs(float(dirs[k, 0] * (P[u] - A[k])[1] - dirs[k, 1] * (P[u] - A[k])[0]))
            if du <= threshold and -threshold <= tu <= L[k] + threshold:
                drop_edge[j] = True  # entirely along e: covered
                continue
            w = int(E[k, 0]) if tu < 0 else int(E[k, 1])
            if float(np.hypot(*(P[w] - P[u]))) <= threshold:
                drop_edge[j] = True
            else:
                edges[j, end_v] = w
        if at_angle:
            relabel.append(v)
    if not drop_edge.any() and np.array_equal(edges, E) and not relabel:
        return wf
    labels = wf.labels.copy()
    labels[relabel] = Label.NOMINAL
    keep = ~drop_edge & (edges[:, 0] != edges[:, 1])
    out = Wireframe(P, labels, edges[keep], wf.likelihood[keep], wf.sources[keep])
    return out.compacted()


# ---------------------------------------------------------------------- map-to-map alignment
def align_maps(source: Wireframe, target: Wireframe, max_shift: float, max_turn: float) -> Pose | None:
    """A small rigid correction of ``source`` onto ``target`` by :func:`mapping.icp.icp`, or None.

    Both maps are in one frame (the fleet frame: each robot's map already moved by its known
    start pose), so the correction only removes residual odometry drift. ICP rotates about its
    frame's origin, so both maps are first expressed in a frame ``F`` at the centroid of
    ``source``'s vertices and the correction ``C`` is brought back (``F * C * F^-1``).

    Parameters
    ----------
    source : Wireframe
        The map to move.
    target : Wireframe
        The map to move it onto (the fused map of the robots before it).
    max_shift : float
        Largest accepted translation of the correction (metres).
    max_turn : float
        Largest accepted rotation of the correction (radians).

    Returns
    -------
    Pose or None
        The correction in the frame of the inputs (``source.transformed(pose)`` lies on
        ``target``); None when either map is empty, ICP fails or does not accept its result,
        the correction exceeds ``max_shift`` / ``max_turn`` (the start pose alone is trusted
        then), or it is negligible (under 1 um and 1e-7 rad).
    """
    if source.n_vertices == 0 or target.n_vertices == 0:
        return None
    c = source.points.mean(axis=0)
    F = Pose(float(c[0]), float(c[1]), 0.0)
    Finv = F.inverse()
    try:
        res = icp(source.transformed(Finv), target.transformed(Finv))
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not res.accepted:
        return None
    pose = F.compose(res.correction).compose(Finv)
    if math.hypot(pose.x, pose.y) > max_shift or abs(pose.theta) > max_turn:
        return None
    if math.hypot(pose.x, pose.y) < 1e-6 and abs(pose.theta) < 1e-7:
        return None
    return pose


# ---------------------------------------------------------------------- the fold tree
def fold_split(lo: int, hi: int) -> int:
    """Where the fold tree splits the leaves ``[lo, hi)``: after the largest power of two below
    ``hi - lo``.

    So up to three leaves the tree is the left fold ``((a, b), c)``, and with 16 leaves it is
    balanced.

    Parameters
    ----------
    lo, hi : int
        The span, ``hi - lo >= 2``.

    Returns
    -------
    int
        ``mid`` with ``lo < mid < hi``: the node is ``merge(node(lo, mid), node(mid, hi))``.

    Raises
    ------
    ValueError
        When the span holds fewer than two leaves.
    """
    if hi - lo < 2:
        raise ValueError(f"a fold node needs at least two leaves, got [{lo}, {hi})")
    p = 1
    while 2 * p < hi - lo:
        p *= 2
    return lo + p
