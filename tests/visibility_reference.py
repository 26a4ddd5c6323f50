"""The visibility sweep in plain Python: :mod:`mapping.visibility`'s steps 2 and 3 as they were
before they were compiled (:func:`mapping.kernels.visibility_sweep`), kept as the reference the
compiled sweep is held to bit for bit (``tests/test_visibility_kernel.py``)."""

from __future__ import annotations

import math
from bisect import insort
from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from mapping.se2 import Pose
from mapping.visibility import (
    _CUT,
    _FRONTIER,
    _NOMINAL,
    _OCCLUSION,
    _WINDOW,
    ANGLE_TOL,
    BACK_BIAS,
    JOIN_TOL,
    TWO_PI,
    View,
    _assemble,
    _empty_view,
    _nearby_edges,
)
from mapping.wireframe import Wireframe

BoolArray = np.ndarray


def reference_view(wf: Wireframe, pose: Pose, max_range: float, fov: float = TWO_PI, *,
                   min_piece: float = 1e-3) -> View:
    """:func:`mapping.visibility.visible_view` with the Python sweep."""
    arrays, fov, full, min_piece = _nearby_edges(wf, pose, max_range, fov, min_piece)
    if arrays is None:
        return _empty_view(wf.n_edges)
    ed = SimpleNamespace(**{k: getattr(arrays, k).tolist() for k in (
        "idx", "p0", "d", "pa", "pb", "ta", "tb", "sa", "sb", "phia", "phib", "back", "good")})
    return _sweep(wf, ed, fov, full, min_piece)


def _cross(a: complex, b: complex) -> float:
    return a.real * b.imag - a.imag * b.real


def _sweep(wf: Wireframe, ed: SimpleNamespace, fov: float, full: bool, min_piece: float) -> View:
    """Steps 2 and 3 (plain Python on the few nearby edges): sub-edges, sweep, pieces, labels."""
    m = wf.n_edges
    sub = _sub_edges(ed, fov)
    if not sub.e:
        return _empty_view(m)
    ev = _events(sub, fov)
    in_view = np.zeros(m, bool)
    if ev.live:
        in_view[[ed.idx[sub.e[s]] for s in ev.live]] = True
    nearest = _nearest(sub, ev, -0.5 * fov)
    pieces = _pieces(sub, ev, nearest, full)
    if not pieces:
        return _empty_view(m, in_view)
    ends = _piece_ends(wf, ed, sub, ev, pieces, -0.5 * fov, full)
    return _view(wf, ed, sub, pieces, ends, in_view, min_piece)


@dataclass
class _Sub:
    """Sub-edges (step 2): each nearby edge's part inside the window ``[0, fov]`` of sweep
    angle, as parallel lists: which nearby edge, the end bearings (sweep angles), end points,
    parameters along the input edge and sources (input vertex, ``_RANGE`` or ``_WINDOW``)."""

    e: list[int]
    phia: list[float]
    phib: list[float]
    pa: list[complex]
    pb: list[complex]
    ta: list[float]
    tb: list[float]
    sa: list[int]
    sb: list[int]
    back: list[bool] = field(default_factory=list)  # seen from behind


def _clip(ed: SimpleNamespace, i: int, u: complex) -> tuple[complex, float]:
    """Point and parameter where the ray ``u`` crosses nearby edge ``i`` (within its part)."""
    den = _cross(ed.d[i], u)
    t = _cross(u, ed.p0[i]) / den if den != 0.0 else ed.ta[i]
    lo, hi = min(ed.ta[i], ed.tb[i]), max(ed.ta[i], ed.tb[i])
    t = min(max(t, lo), hi)
    return ed.p0[i] + t * ed.d[i], t


def _sub_edges(ed: SimpleNamespace, fov: float) -> _Sub:
    """Step 2, sub-edges: each edge's part inside the window [0, fov] of sweep angle. An edge
    across the seam (sweep angle 2 pi == 0) is split in two; so is one across the back of a
    wide window."""
    phi0 = -0.5 * fov
    u_lo = complex(math.cos(phi0), math.sin(phi0))
    u_hi = complex(math.cos(phi0 + fov), math.sin(phi0 + fov))
    sub = _Sub([], [], [], [], [], [], [], [], [])

    def end_piece(i: int, b: float, cut: bool) -> None:
        """Close the piece of nearby edge ``i`` just opened: at the fov's far boundary when
        ``cut``, else at the edge's own end (bearing ``b``)."""
        if cut:
            q, t = _clip(ed, i, u_hi)
            sub.phib.append(fov)
            sub.pb.append(q)
            sub.tb.append(t)
            sub.sb.append(_WINDOW)
        else:
            sub.phib.append(b)
            sub.pb.append(ed.pb[i])
            sub.tb.append(ed.tb[i])
            sub.sb.append(ed.sb[i])

    for i, ok in enumerate(ed.good):
        if not ok:
            continue
        a, b = ed.phia[i], ed.phib[i]
        if a >= TWO_PI:  # np.mod can round up to 2 pi
            a = 0.0
        if b >= TWO_PI:
            b = 0.0
        wrap = b < a  # the end lies past the seam
        if a < fov:
            sub.e.append(i)
            sub.phia.append(a)
            sub.pa.append(ed.pa[i])
            sub.ta.append(ed.ta[i])
            sub.sa.append(ed.sa[i])
            end_piece(i, b, cut=wrap or b > fov)
        if wrap and b > 0.0:
            q, t = _clip(ed, i, u_lo)
            sub.e.append(i)
            sub.phia.append(0.0)
            sub.pa.append(q)
            sub.ta.append(t)
            sub.sa.append(_WINDOW)
            end_piece(i, b, cut=b > fov)
    sub.back = [ed.back[i] for i in sub.e]
    return sub


@dataclass
class _Events:
    """The sweep's events (step 2): the end bearings sorted, those within ``ANGLE_TOL``
    grouped (``ev``), each sub-edge's start and end event (``ka``, ``kb``), and the sub-edges
    spanning at least one interval (``live``)."""

    ev: list[float]
    ka: list[int]
    kb: list[int]
    live: list[int]


def _events(sub: _Sub, fov: float) -> _Events:
    """Step 2, events: end bearings sorted, those within ANGLE_TOL grouped; window ends are
    events."""
    ns = len(sub.e)
    vals = [*sub.phia, *sub.phib, 0.0, fov]
    order = sorted(range(len(vals)), key=vals.__getitem__)
    gid = [0] * len(vals)
    ev: list[float] = []
    last = -math.inf
    for j in order:
        v = vals[j]
        if v - last > ANGLE_TOL:
            ev.append(v)
            last = v
        gid[j] = len(ev) - 1
    ka = gid[:ns]
    kb = gid[ns : 2 * ns]
    live = [s for s in range(ns) if ka[s] < kb[s]]
    return _Events(ev, ka, kb, live)


def _nearest(sub: _Sub, evs: _Events, phi0: float) -> list[int]:
    """Step 2, the sweep: the nearest sub-edge of each elementary interval (-1: none).

    ``active`` holds the sub-edges crossed by the current ray, nearest first."""
    ev, ka, kb, live = evs.ev, evs.ka, evs.kb, evs.live
    s_dx = [(q - p).real for p, q in zip(sub.pa, sub.pb)]
    s_dy = [(q - p).imag for p, q in zip(sub.pa, sub.pb)]
    s_cab = [_cross(p, q) for p, q in zip(sub.pa, sub.pb)]
    s_bias = [BACK_BIAS if bk else 0.0 for bk in sub.back]
    by_start = sorted(live, key=ka.__getitem__)
    by_end = sorted(live, key=kb.__getitem__)
    n_live = len(live)
    nearest = [-1] * (len(ev) - 1)
    active: list[int] = []
    si = ei = 0
    for k in range(len(ev) - 1):
        while ei < n_live and kb[by_end[ei]] == k:
            active.remove(by_end[ei])
            ei += 1
        if si < n_live and ka[by_start[si]] == k:
            mid = phi0 + 0.5 * (ev[k] + ev[k + 1])
            key = _distance_key(s_cab, s_dx, s_dy, s_bias, math.cos(mid), math.sin(mid))
            while si < n_live and ka[by_start[si]] == k:
                insort(active, by_start[si], key=key)
                si += 1
        if active:
            nearest[k] = active[0]
    return nearest


def _pieces(sub: _Sub, evs: _Events, nearest: list[int], full: bool) -> list[list[int]]:
    """Step 3, pieces: runs of intervals with the same nearest sub-edge (or -1 for nothing),
    each ``[start sub-edge, start event, end event, end sub-edge]``; with ``full``, a wall
    across the seam is one piece, from its part before to its part after it."""
    ka, kb = evs.ka, evs.kb
    pieces: list[list[int]] = []
    for k, s in enumerate(nearest):
        if pieces and pieces[-1][0] == s:
            pieces[-1][2] = k + 1
        else:
            pieces.append([s, k, k + 1, s])
    if full and len(pieces) > 1:
        fs, ls = pieces[0][0], pieces[-1][0]
        if (
            fs >= 0
            and ls >= 0
            and sub.e[fs] == sub.e[ls]
            and sub.sa[fs] == _WINDOW
            and pieces[0][1] == ka[fs]
            and sub.sb[ls] == _WINDOW
            and pieces[-1][2] == kb[ls]
        ):
            pieces = [[ls, pieces[-1][1], pieces[0][2], fs], *pieces[1:-1]]
    return pieces


def _point_at(
    ed: SimpleNamespace, sub: _Sub, evs: _Events, phi0: float, s: int, k: int, start: bool
) -> tuple[complex, float, int]:
    """(point, t, source) of sub-edge ``s`` at event ``k``."""
    if start and k == evs.ka[s]:
        return sub.pa[s], sub.ta[s], sub.sa[s]
    if not start and k == evs.kb[s]:
        return sub.pb[s], sub.tb[s], sub.sb[s]
    bearing = phi0 + evs.ev[k]
    u = complex(math.cos(bearing), math.sin(bearing))
    i = sub.e[s]
    den = _cross(ed.d[i], u)
    t = _cross(u, ed.p0[i]) / den if den != 0.0 else sub.ta[s]
    t = min(max(t, min(sub.ta[s], sub.tb[s])), max(sub.ta[s], sub.tb[s]))
    return ed.p0[i] + t * ed.d[i], t, _CUT


@dataclass
class _Ends:
    """Step 3's vertices: positions, labels and sources of the reported vertices, and per
    piece its start and end vertex (-1: none), parameters along its input edge and whether it
    faces the robot."""

    xy: list[complex]
    lab: list[int]
    src: list[int]
    start_vid: list[int]
    end_vid: list[int]
    start_t: list[float]
    end_t: list[float]
    is_front: list[bool]


def _piece_ends(
    wf: Wireframe, ed: SimpleNamespace, sub: _Sub, evs: _Events, pieces: list[list[int]], phi0: float,
    full: bool,
) -> _Ends:
    """Step 3, labels (paper Sec. IV-A, IV-B): at every boundary between pieces, in sweep
    order, the two sides are compared: one shared ``NOMINAL`` corner where two walls meet,
    else the nearer end is passed by sight (``OCCLUSION`` at a real corner) and the farther
    one is a ``FRONTIER``; window edges are frontiers."""
    in_labels = wf.labels

    def pass_label(src: int) -> int:
        """Label of a piece end that sight passes (nothing, or something farther, behind it)."""
        if src >= 0:
            return _FRONTIER if int(in_labels[src]) == _FRONTIER else _OCCLUSION
        return _FRONTIER

    n_p = len(pieces)
    back = sub.back
    out = _Ends([], [], [], [-1] * n_p, [-1] * n_p, [0.0] * n_p, [0.0] * n_p,
                [p[0] >= 0 and not back[p[0]] for p in pieces])
    is_front = out.is_front

    # Boundaries in sweep order: (left piece, right piece); -1 is outside the window.
    if full:
        # Cyclic. With a merged seam piece first, its end boundary comes first and its start
        # boundary last, so vertices still come out in increasing bearing.
        bounds = [(i, (i + 1) % n_p) for i in range(n_p)]
    else:
        bounds = [(-1, 0), *((i, i + 1) for i in range(n_p - 1)), (n_p - 1, -1)]
    for li, ri in bounds:
        left = pieces[li] if li >= 0 and pieces[li][3] >= 0 else None
        right = pieces[ri] if ri >= 0 and pieces[ri][0] >= 0 else None
        x = _point_at(ed, sub, evs, phi0, left[3], left[2], False) if left is not None else None
        y = _point_at(ed, sub, evs, phi0, right[0], right[1], True) if right is not None else None
        if x is not None and y is not None:
            dist_x, dist_y = abs(x[0]), abs(y[0])
            if abs(x[0] - y[0]) <= JOIN_TOL * max(1.0, dist_x):
                # Two walls meet: one corner.
                q, src = (x[0], x[2]) if x[2] >= 0 else (y[0], y[2])
                if src >= 0:
                    lab = _FRONTIER if int(in_labels[src]) == _FRONTIER else _NOMINAL
                else:
                    lab = _FRONTIER
                vid = -1
                if is_front[li] or is_front[ri]:
                    out.xy.append(q)
                    out.lab.append(lab)
                    out.src.append(max(src, -1))
                    vid = len(out.xy) - 1
                out.end_vid[li], out.start_vid[ri] = vid, vid
                out.end_t[li], out.start_t[ri] = x[1], y[1]
                continue
            x_near = dist_x < dist_y
            lab_x = pass_label(x[2]) if x_near else _FRONTIER
            lab_y = _FRONTIER if x_near else pass_label(y[2])
        else:
            window = li < 0 or ri < 0  # a vertex right on the window edge is a frontier too
            lab_x = _FRONTIER if (window or x is None) else pass_label(x[2])
            lab_y = _FRONTIER if (window or y is None) else pass_label(y[2])
        if x is not None:
            out.end_t[li] = x[1]
            if is_front[li]:
                out.xy.append(x[0])
                out.lab.append(lab_x)
                out.src.append(max(x[2], -1))
                out.end_vid[li] = len(out.xy) - 1
        if y is not None:
            out.start_t[ri] = y[1]
            if is_front[ri]:
                out.xy.append(y[0])
                out.lab.append(lab_y)
                out.src.append(max(y[2], -1))
                out.start_vid[ri] = len(out.xy) - 1
    return out


def _view(
    wf: Wireframe,
    ed: SimpleNamespace,
    sub: _Sub,
    pieces: list[list[int]],
    ends: _Ends,
    in_view: BoolArray,
    min_piece: float,
) -> View:
    """Step 3, assemble the scan: one edge per front-facing piece with two distinct vertices at
    least ``min_piece`` apart, its likelihood and sources those of its input edge."""
    out_xy = ends.xy
    edges: list[tuple[int, int]] = []
    e_src: list[int] = []
    e_t: list[tuple[float, float]] = []
    for i in range(len(pieces)):
        a_v, b_v = ends.start_vid[i], ends.end_vid[i]
        if not ends.is_front[i] or a_v < 0 or b_v < 0 or a_v == b_v:
            continue
        if abs(out_xy[b_v] - out_xy[a_v]) < min_piece:
            continue
        edges.append((a_v, b_v))
        e_src.append(ed.idx[sub.e[pieces[i][0]]])
        e_t.append((ends.start_t[i], ends.end_t[i]))
    xy = np.array(out_xy, dtype=np.complex128).reshape(-1)
    return _assemble(wf, xy.real.copy(), xy.imag.copy(), np.array(ends.lab, dtype=np.int64),
                     np.array(ends.src, dtype=np.int64), np.array(edges, dtype=np.int64).reshape(-1, 2),
                     np.array(e_src, dtype=np.int64), np.array(e_t, dtype=np.float64), in_view)


def _distance_key(
    cab: list[float], dxs: list[float], dys: list[float], bias: list[float], ux: float, uy: float
) -> Callable[[int], float]:
    """Distance along the ray ``u`` to the line of sub-edge ``i`` (plus the back-face bias).

    The ray ``rho u`` meets the line through ``A`` and ``B`` where
    ``rho cross(u, B - A) = cross(A, B)``.
    """

    def key(i: int) -> float:
        den = ux * dys[i] - uy * dxs[i]
        if den <= 0.0:  # only for degenerate or crossing input: treat as very far
            return math.inf
        return cab[i] / den + bias[i]

    return key
