"""Small vectorised 2-D geometry helpers shared by the mapping algorithms.

Every function takes array-likes whose last axis holds the two coordinates and broadcasts the
rest with numpy's usual rules, so one call can test one point against many segments, many
points against one segment, or an ``(n, 1, 2)`` array against an ``(1, m, 2)`` one for all
pairs. Nothing here allocates more than its result and a few temporaries of the same shape.

Conventions: a segment is given by its start ``a`` and end ``b``; its direction is ``b - a``.
The *left* side of a directed line is where :func:`cross2` of the direction and the offset is
positive (counterclockwise). In a wireframe the left of an edge is free space.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "cross2",
    "dot2",
    "orient2d",
    "pairwise_distances",
    "parallel",
    "point_segment_distance",
    "projection_parameter",
    "segments_intersect",
    "signed_line_offset",
    "unit_vectors",
]


def _f(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=np.float64)


def cross2(u: ArrayLike, v: ArrayLike) -> FloatArray:
    """The z component of the 3-D cross product of 2-D vectors: ``u_x v_y - u_y v_x``.

    Positive when ``v`` points to the left of ``u`` (counterclockwise turn).
    """
    u, v = _f(u), _f(v)
    return np.asarray(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0], dtype=np.float64)


def dot2(u: ArrayLike, v: ArrayLike) -> FloatArray:
    """The dot product of 2-D vectors along the last axis."""
    u, v = _f(u), _f(v)
    return np.asarray(u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1], dtype=np.float64)


def unit_vectors(v: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """``(v / |v|, |v|)``; zero vectors give a zero unit vector (and length 0) instead of NaN."""
    v = _f(v)
    n = np.hypot(v[..., 0], v[..., 1])
    safe = np.where(n > 0.0, n, 1.0)
    return np.asarray(v / safe[..., None], dtype=np.float64), np.asarray(n, dtype=np.float64)


def projection_parameter(p: ArrayLike, a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Parameter ``t`` of the orthogonal projection of ``p`` on the line ``a + t (b - a)``.

    ``t`` is 0 at ``a`` and 1 at ``b`` (not clipped). A zero-length segment gives 0.
    """
    p, a, b = _f(p), _f(a), _f(b)
    d = b - a
    dd = dot2(d, d)
    return np.asarray(dot2(p - a, d) / np.where(dd > 0.0, dd, 1.0), dtype=np.float64)


def point_segment_distance(p: ArrayLike, a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Euclidean distance from ``p`` to the closed segment ``[a, b]``."""
    p, a, b = _f(p), _f(a), _f(b)
    t = np.clip(projection_parameter(p, a, b), 0.0, 1.0)
    foot = a + t[..., None] * (b - a)
    q = p - foot
    return np.asarray(np.hypot(q[..., 0], q[..., 1]), dtype=np.float64)


def signed_line_offset(p: ArrayLike, a: ArrayLike, u: ArrayLike) -> FloatArray:
    """Signed distance of ``p`` from the line through ``a`` with *unit* direction ``u``.

    Positive on the left of the direction (free side of a wireframe edge).
    """
    return cross2(u, _f(p) - _f(a))


def parallel(u: ArrayLike, v: ArrayLike, angle_tol: float, same_direction: bool = True) -> BoolArray:
    """Whether directions ``u`` and ``v`` (any length, non-zero) are within ``angle_tol`` radians.

    With ``same_direction=False`` opposite directions count as parallel too (lines, not rays).
    Zero vectors are never parallel to anything.
    """
    u, v = _f(u), _f(v)
    nu = np.hypot(u[..., 0], u[..., 1])
    nv = np.hypot(v[..., 0], v[..., 1])
    c = dot2(u, v)
    lim = math.cos(angle_tol) * nu * nv
    ok = (nu > 0.0) & (nv > 0.0)
    if same_direction:
        return np.asarray(ok & (c >= lim), dtype=np.bool_)
    return np.asarray(ok & (np.abs(c) >= lim), dtype=np.bool_)


# Shewchuk's error bound for the floating-point orientation determinant ("ccwerrboundA",
# (3 + 16 eps) eps): when |det| exceeds it times the magnitude of its two products, its sign is right.
_ORIENT_BOUND = (3.0 + 16.0 * np.finfo(np.float64).eps) * np.finfo(np.float64).eps


def orient2d(a: ArrayLike, b: ArrayLike, c: ArrayLike) -> FloatArray:
    """Twice the signed area of the triangle ``(a, b, c)``: positive when ``c`` lies to the
    left of the directed line ``a -> b`` (counterclockwise), zero when collinear.

    The *sign* is exact (adaptive: the floating-point value is used when Shewchuk's error bound
    proves its sign, the rest are recomputed in exact rational arithmetic), so the answer does
    not depend on which of the three points the determinant is taken relative to. Values that
    needed the exact path are returned rounded from the exact result.
    """
    a, b, c = np.broadcast_arrays(_f(a), _f(b), _f(c))
    left = (a[..., 0] - c[..., 0]) * (b[..., 1] - c[..., 1])
    right = (a[..., 1] - c[..., 1]) * (b[..., 0] - c[..., 0])
    det = np.asarray(left - right, dtype=np.float64)
    unsure = np.abs(det) <= _ORIENT_BOUND * (np.abs(left) + np.abs(right))
    if np.any(unsure):
        det = det.copy() if det.ndim else np.array(det)
        for idx in zip(*np.nonzero(unsure)) if det.ndim else [()]:
            ax, ay = (Fraction(float(v)) for v in a[idx])
            bx, by = (Fraction(float(v)) for v in b[idx])
            cx, cy = (Fraction(float(v)) for v in c[idx])
            det[idx] = float((ax - cx) * (by - cy) - (ay - cy) * (bx - cx))
    return np.asarray(det, dtype=np.float64)


def segments_intersect(
    a1: ArrayLike, b1: ArrayLike, a2: ArrayLike, b2: ArrayLike, proper: bool = False
) -> BoolArray:
    """Whether segments ``[a1, b1]`` and ``[a2, b2]`` intersect.

    With ``proper=True`` only crossings in both interiors count (touching at an end point or
    overlapping collinearly does not). Otherwise any common point counts, collinear overlaps and
    shared end points included. Exact orientation tests (:func:`orient2d`), no tolerance, so
    the answer is the same whichever way round the segments and their ends are given.
    """
    a1, b1, a2, b2 = _f(a1), _f(b1), _f(a2), _f(b2)
    d1 = orient2d(a2, b2, a1)
    d2 = orient2d(a2, b2, b1)
    d3 = orient2d(a1, b1, a2)
    d4 = orient2d(a1, b1, b2)
    crossing = (np.sign(d1) * np.sign(d2) < 0.0) & (np.sign(d3) * np.sign(d4) < 0.0)  # (no underflow)
    if proper:
        return np.asarray(crossing, dtype=np.bool_)

    def on_seg(p: FloatArray, a: FloatArray, b: FloatArray, d: FloatArray) -> BoolArray:
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        inside = np.all((p >= lo) & (p <= hi), axis=-1)
        return np.asarray((d == 0.0) & inside, dtype=np.bool_)

    touch = on_seg(a1, a2, b2, d1) | on_seg(b1, a2, b2, d2) | on_seg(a2, a1, b1, d3) | on_seg(b2, a1, b1, d4)
    return np.asarray(crossing | touch, dtype=np.bool_)


def pairwise_distances(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """``(n, m)`` Euclidean distances between points ``p`` (n, 2) and ``q`` (m, 2)."""
    p, q = _f(p).reshape(-1, 2), _f(q).reshape(-1, 2)
    return np.asarray(
        np.hypot(p[:, None, 0] - q[None, :, 0], p[:, None, 1] - q[None, :, 1]), dtype=np.float64
    )
