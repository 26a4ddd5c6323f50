"""A slow, literal body decoder written from FORMAT.md, one bit at a time.

It exists to check the fast vectorised decoder in :mod:`wire_codec.body` (the test suite runs
both on the same payloads and expects the same map or a rejection from both) and to show that
the format document is enough to write a decoder. Not used on the hot path.
"""

from __future__ import annotations

import itertools

import numpy as np

from mapping.wireframe import Wireframe, as_masks
from wire_codec.errors import ExtraDataError, FormatError, LimitError, Limits, TruncatedError

MAX_EG_BITS = 53
MAX_GRID = 1 << 50


class _Stream:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0
        self.size = 8 * len(data)

    def bit(self) -> int:
        if self.pos >= self.size:
            raise TruncatedError("body ends early")
        b = (self.data[self.pos >> 3] >> (7 - (self.pos & 7))) & 1
        self.pos += 1
        return b

    def uint(self, width: int) -> int:
        v = 0
        for _ in range(width):
            v = (v << 1) | self.bit()
        return v

    def unary(self, max_zeros: int) -> int:
        z = 0
        while self.bit() == 0:
            z += 1
            if z > max_zeros:
                raise FormatError("Exp-Golomb code too long")
        return z

    def eg_block(self, orders: list[int]) -> list[int]:
        """Exp-Golomb values of the given orders: all unary prefixes first, then the mantissas."""
        zeros = [self.unary(MAX_EG_BITS - k) for k in orders]
        return [(1 << (z + k)) + self.uint(z + k) - (1 << k) for z, k in zip(zeros, orders)]


def _bits_for(n: int) -> int:
    return max(n - 1, 0).bit_length()


def _values(s: _Stream, count: int, width: int, exc_width: int) -> list[int]:
    """A value section (FORMAT.md 3.4): labels ``(2, 1)``, likelihoods ``(4, 4)``."""
    mode = s.uint(2)
    if mode == 2:
        return [s.uint(width) for _ in range(count)]
    dom = s.uint(width)
    if exc_width == 1 and dom == 3:
        raise FormatError("label value 3")
    out = [dom] * count
    if mode == 0:
        return out
    if mode == 1:
        positions = [i for i in range(count) if s.bit()]
    else:
        c = s.eg_block([0])[0]
        if c > count:
            raise FormatError("more exceptions than items")
        kg = s.uint(4)
        positions = []
        p = -1
        for gap in s.eg_block([kg] * c):
            p += gap + 1
            if p >= count:
                raise FormatError("exception beyond the last item")
            positions.append(p)
    others = [v for v in (0, 1, 2) if v != dom]
    for p in positions:
        if exc_width == 1:
            out[p] = others[s.bit()]
        else:
            out[p] = s.uint(exc_width)
            if out[p] == dom:
                raise FormatError("exception equals dominant")
    return out


def decode_body(data: bytes, resolution_mm: int, n_robots: int | None, limits: Limits) -> Wireframe:
    """Same contract as :func:`wire_codec.body.decode_body`."""
    s = _Stream(data)
    n = s.eg_block([0])[0]
    if n > limits.max_vertices:
        raise LimitError("too many vertices")
    points: list[tuple[int, int]] = []
    labels: list[int] = []
    edges: list[tuple[int, int]] = []
    lik: list[int] = []
    sources: list[int] = []
    if n > 0:
        k1, k2, k3 = s.uint(4), s.uint(4), s.uint(4)
        turn = [s.bit() for _ in range(n)]
        cls = ["turn" if t else "" for t in turn]
        for i in range(n):
            if not cls[i]:
                cls[i] = "straight" if s.bit() else "general"
        toggle = [cls[i] == "turn" for i in range(n)]
        for i in range(n):
            if cls[i] == "general":
                toggle[i] = bool(s.bit())
        sign = [s.bit() for _ in range(n)]
        minor_sign = {i: s.bit() for i in range(n) if cls[i] == "general"}
        singles = [i for i in range(n) if cls[i] != "general"]
        generals = [i for i in range(n) if cls[i] == "general"]
        values = s.eg_block([k1] * len(singles) + [k2] * len(generals) + [k3] * len(generals))
        major: dict[int, int] = {}
        minor: dict[int, int] = {}
        for t, i in enumerate(singles):
            major[i], minor[i] = values[t] + 1, 0
        for t, i in enumerate(generals):
            major[i] = values[len(singles) + t]
            minor[i] = values[len(singles) + len(generals) + t]
            if minor_sign[i]:
                minor[i] = -minor[i]
        x = y = 0
        axis = 1
        total = 0
        for i in range(n):
            if toggle[i]:
                axis = 1 - axis
            big = -major[i] if sign[i] else major[i]
            dx, dy = (big, minor[i]) if axis == 0 else (minor[i], big)
            total += abs(dx) + abs(dy)
            if total > 2**60:
                raise FormatError("moves too large")
            x, y = x + dx, y + dy
            points.append((x, y))
        far = max(max(abs(a), abs(b)) for a, b in points)
        if far > MAX_GRID or far * resolution_mm / 1e3 > limits.max_coordinate:
            raise LimitError("vertex too far")
        labels = _values(s, n, 2, 1)
        if any(v == 3 for v in labels):
            raise FormatError("label 3")
        nxt = [s.bit() for _ in range(n - 1)]
        starts = [0] + [k + 1 for k in range(n - 1) if not nxt[k]]
        ends = [k for k in range(n - 1) if not nxt[k]] + [n - 1]
        rings = [(a, b) for a, b in zip(starts, ends) if b - a >= 2]
        close = [s.bit() for _ in rings]
        rev = [s.bit() for _ in range(n - 1)] if s.bit() else [0] * (n - 1)
        n_rest = s.eg_block([0])[0]
        m = sum(nxt) + sum(close) + sum(rev) + n_rest
        if m > limits.max_edges:
            raise LimitError("too many edges")
        edges += [(k, k + 1) for k in range(n - 1) if nxt[k]]
        edges += [(k + 1, k) for k in range(n - 1) if rev[k]]
        edges += [(b, a) for (a, b), c in zip(rings, close) if c]
        if n_rest:
            if 2 * n_rest > s.size - s.pos:
                raise TruncatedError("explicit edges do not fit")
            ke, kd = s.uint(4), s.uint(4)
            vals = s.eg_block([ke] * n_rest + [kd] * n_rest)
            a = 0
            for t in range(n_rest):
                a += vals[t]
                off = vals[n_rest + t]
                b = a + ((off >> 1) ^ -(off & 1))
                if a >= n or not 0 <= b < n or a == b:
                    raise FormatError("bad explicit edge")
                edges.append((a, b))
        if m:
            lik = _values(s, m, 4, 4)
            if any(v > 15 for v in lik):
                raise FormatError("likelihood above 15")
        if n_robots is not None and m:
            u = s.eg_block([0])[0]
            if not 1 <= u <= m or u * n_robots > s.size - s.pos:
                raise FormatError("bad mask count")
            masks = [s.uint(n_robots) for _ in range(u)]
            if any(b <= a for a, b in itertools.pairwise(masks)):
                raise FormatError("masks not increasing")
            wi = _bits_for(u)
            for _ in range(m):
                i = s.uint(wi)
                if i >= u:
                    raise FormatError("mask index out of range")
                sources.append(masks[i])
        else:
            sources = [0] * m
    if s.size - s.pos >= 8:
        raise ExtraDataError("trailing bytes")
    while s.pos < s.size:
        if s.bit():
            raise ExtraDataError("non-zero padding")
    pts = np.array(points, dtype=np.float64).reshape(-1, 2) * resolution_mm / 1e3
    return Wireframe.build(
        pts,
        np.array(edges, dtype=np.int64).reshape(-1, 2),
        np.array(labels, dtype=np.uint8),
        np.array(lik, dtype=np.float64) / 15.0,
        as_masks(sources),
    )
