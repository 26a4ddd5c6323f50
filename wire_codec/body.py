"""The bit-packed body: a wireframe as a few hundred bits (FORMAT.md, section 3).

Layout of the bit stream, in order (everything after ``n`` is absent when ``n == 0``):

1. ``n``, the vertex count (Exp-Golomb order 0);
2. vertex positions on the integer grid ``q = round(p / resolution)``, each coded as its move
   from the previous vertex (the first from the grid origin). Every move has a *major* axis,
   coded relative to the previous move's (a *turn* toggles it); on a rectilinear wall chain
   consecutive corners alternate axes and share the other coordinate, so a corner is a TURN:
   one class bit, one sign bit and an Exp-Golomb magnitude. STRAIGHT moves keep the axis;
   GENERAL moves (both coordinates change, or neither) add a turn bit, a minor sign and a minor
   magnitude;
3. vertex labels (constant, dominant value with exceptions as flags or as gaps, or plain);
4. edges against the vertex order: one bit per consecutive pair ``(k, k+1)``, one bit per chain
   that closes into a ring, optionally one bit per reverse pair ``(k+1, k)``, then the other
   edges sorted, as Exp-Golomb gaps between their first vertices and offsets to the second;
5. edge likelihoods quantised to 4 bits (``round(15 l)``), with the same modes as labels;
6. fused maps only: per-edge contributor masks, as a sorted dictionary of distinct masks of
   ``len(robots)`` bits and a ``ceil(log2 U)``-bit index per edge.

The encoder chooses the vertex order (edges followed as chains, so that most edges cost one bit)
and therefore the decoded vertex and edge order differ from the input's; the graph is the same.
:func:`encode_body` returns the permutations it used. Where the format offers a choice (Exp-Golomb
orders, label and likelihood modes, the reverse section) the encoder takes the cheapest.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mapping.wireframe import MaskArray, Wireframe, as_masks
from wire_codec.bits import I64, MAX_EG_BITS, BitReader, BitWriter, best_eg_orders, ceil_log2
from wire_codec.errors import EncodeError, ExtraDataError, FormatError, LimitError, Limits, TruncatedError

MAX_GRID = 1 << 50
"""Largest ``|q|`` of a grid coordinate (keeps every coded value below ``2**53``)."""

LIKELIHOOD_LEVELS = 15
"""Likelihood ``l`` travels as ``round(15 l)`` in 4 bits and comes back as ``v / 15``."""

MAX_ROBOTS = 4096
"""The most robots a fused map may list (format version 2; masks of ``len(robots)`` bits)."""

MAX_ROBOTS_V1 = 64
"""The most robots of a format version 1 message (its masks were ``uint64``). An encoder writes
version 1 whenever a message fits it, so maps of at most 64 robots travel byte for byte as
before version 2 existed."""

MODE_CONSTANT, MODE_FLAGS, MODE_PLAIN, MODE_GAPS = 0, 1, 2, 3
"""Value-section modes (labels, likelihoods): one value; a dominant value with one exception
flag per item; every value; a dominant value with the exceptions' positions as gaps."""

LABEL_BITS, LIKELIHOOD_BITS = 2, 4


@dataclass(frozen=True)
class EncodedBody:
    """An encoded body and the order the encoder put the graph in.

    Attributes
    ----------
    data : the body bytes.
    vertex_order : decoded vertex ``k`` is input vertex ``vertex_order[k]``.
    edge_order : decoded edge ``e`` is input edge ``edge_order[e]``.
    n_bits : the stream's length before padding.
    """

    data: bytes
    vertex_order: NDArray[np.int64]
    edge_order: NDArray[np.int64]
    n_bits: int


# ---------------------------------------------------------------------------------------- helpers
def zigzag(v: I64) -> I64:
    """Signed to unsigned: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    return np.asarray((v << 1) ^ (v >> 63), dtype=np.int64)


def unzigzag(u: I64) -> I64:
    return np.asarray((u >> 1) ^ -(u & 1), dtype=np.int64)


def quantise(points: NDArray[np.float64], resolution: float) -> I64:
    """Grid coordinates ``round(p / resolution)`` (``numpy.rint``: ties to even); raises
    :class:`EncodeError` beyond ``MAX_GRID`` steps."""
    g = points / resolution
    if g.size and float(np.abs(g).max()) > MAX_GRID:
        raise EncodeError(
            f"a vertex is {float(np.abs(points).max()):.6g} m from the origin: beyond "
            f"{MAX_GRID} steps of {resolution} m"
        )
    return np.rint(g).astype(np.int64)


def chain_order(n: int, edges: NDArray[np.int32]) -> NDArray[np.int64]:
    """A vertex order that follows edges: ``order[k]`` is the input index of position ``k``.

    Each vertex gets at most one chosen outgoing and one chosen incoming edge (three greedy
    rounds, lowest edge index first); the chosen edges form paths and cycles. Paths are emitted
    from their first vertex in increasing index order, then cycles from their lowest vertex.
    Unconnected vertices are one-vertex paths.
    """
    succ = np.full(n, -1, dtype=np.int64)
    pred = np.full(n, -1, dtype=np.int64)
    if len(edges):
        a = edges[:, 0].astype(np.int64)
        b = edges[:, 1].astype(np.int64)
        first = np.empty(n, dtype=np.int64)
        for _ in range(3):
            cand = np.flatnonzero((succ[a] < 0) & (pred[b] < 0))
            if cand.size == 0:
                break
            for end in (a, b):  # keep the lowest candidate edge per source, then per target
                first.fill(len(edges))
                np.minimum.at(first, end[cand], cand)
                cand = cand[first[end[cand]] == cand]
            succ[a[cand]] = b[cand]
            pred[b[cand]] = a[cand]
    nxt = succ.tolist()
    seen = [False] * n
    order: list[int] = []
    heads = np.flatnonzero(pred < 0).tolist()
    for v in heads + list(range(n)):
        while v >= 0 and not seen[v]:
            seen[v] = True
            order.append(v)
            v = nxt[v]
    return np.asarray(order, dtype=np.int64)


def chains(next_bits: NDArray[np.uint8], n: int) -> tuple[I64, I64]:
    """Start and end positions of the maximal runs joined by ``next_bits`` (length ``n - 1``)."""
    breaks = np.flatnonzero(next_bits == 0)
    starts = np.concatenate(([0], breaks + 1)).astype(np.int64)
    ends = np.concatenate((breaks, [n - 1])).astype(np.int64)
    return starts, ends


def _orders(*runs: tuple[int, int]) -> I64:
    """Per-value Exp-Golomb orders of a block made of runs ``(count, order)``."""
    return np.repeat(np.array([k for _, k in runs], dtype=np.int64), [c for c, _ in runs])


def _gaps(positions: I64) -> I64:
    """Gaps between increasing positions: ``p_0``, ``p_1 - p_0 - 1``, ..."""
    return np.asarray(np.diff(positions, prepend=-1) - 1, dtype=np.int64)


def _explicit_cost(a: I64, b: I64) -> tuple[int, int, int]:
    """``(bits, ke, kd)`` of explicit edges ``a -> b`` sorted by ``(a, b)``."""
    (ke, kd), (cost_e, cost_d) = best_eg_orders(np.concatenate((np.diff(a, prepend=0), zigzag(b - a))),
                                                [a.size] * 2)
    return 8 + cost_e + cost_d, ke, kd


# ---------------------------------------------------------------------------------------- encode
def _write_values(w: BitWriter, values: I64, width: int, exc_width: int) -> None:
    """A value section (labels: ``width`` 2, exception 1 bit; likelihoods: 4 and 4 bits) in the
    cheapest of its four modes (ties: constant, flags, plain, gaps)."""
    counts = np.bincount(values)
    dom = int(np.argmax(counts))
    count = int(values.size)
    exc = values != dom
    n_exc = count - int(counts[dom])
    if n_exc == 0:
        w.scalar(MODE_CONSTANT, 2)
        w.scalar(dom, width)
        return
    gaps = _gaps(np.flatnonzero(exc))
    (kg,), (gap_bits,) = best_eg_orders(gaps, [n_exc])
    costs = {
        MODE_FLAGS: width + count + n_exc * exc_width,
        MODE_PLAIN: count * width,
        MODE_GAPS: width + 2 * (n_exc + 1).bit_length() - 1 + 4 + gap_bits + n_exc * exc_width,
    }
    mode = min(costs, key=lambda k: costs[k])
    w.scalar(mode, 2)
    if mode == MODE_PLAIN:
        w.fixed(values, width)
        return
    w.scalar(dom, width)
    if mode == MODE_FLAGS:
        w.flags(exc)
    else:
        w.eg(n_exc)
        w.scalar(kg, 4)
        w.eg_block(gaps, kg)
    if exc_width == 1:  # labels: which of the two other values
        w.flags(values[exc] == max(x for x in (0, 1, 2) if x != dom))
    else:
        w.fixed(values[exc], exc_width)


def encode_body(wf: Wireframe, resolution: float, n_robots: int | None) -> EncodedBody:
    """Bit-pack ``wf`` on a grid of ``resolution`` metres.

    Parameters
    ----------
    wf : the map.
    resolution : grid step in metres (the envelope's, already rounded to whole millimetres).
    n_robots : ``None`` for a robot map (no sources section; sources must be all zero, which
        the caller checks); for a fused map the number of robots, so masks are that many bits.

    Raises
    ------
    EncodeError
        A vertex too far from the origin, or a contributor bit at or above ``n_robots``.
    """
    w = BitWriter()
    n, m = wf.n_vertices, wf.n_edges
    w.eg(n)
    if n == 0:
        return EncodedBody(w.to_bytes(), np.zeros(0, np.int64), np.zeros(0, np.int64), w.n_bits)

    q = quantise(wf.points, resolution)
    order = chain_order(n, wf.edges)
    inv = np.empty(n, dtype=np.int64)
    inv[order] = np.arange(n, dtype=np.int64)
    _write_vertices(w, q[order])

    # -- labels
    _write_values(w, wf.labels[order].astype(np.int64), LABEL_BITS, 1)

    edge_order = _write_edges(w, inv[wf.edges[:, 0]], inv[wf.edges[:, 1]], n)

    # -- likelihood
    if m:
        lq = np.rint(wf.likelihood[edge_order] * LIKELIHOOD_LEVELS).astype(np.int64)
        _write_values(w, lq, LIKELIHOOD_BITS, LIKELIHOOD_BITS)

    if n_robots is not None and m:
        _write_sources(w, wf.sources[edge_order], n_robots)

    return EncodedBody(w.to_bytes(), order, edge_order, w.n_bits)


def _write_vertices(w: BitWriter, q: I64) -> None:
    """The vertex section (FORMAT.md 3, item 2) of grid points ``q`` in their coded order: the
    major axis of every move is coded relative to the previous one."""
    n = q.shape[0]
    d = np.diff(q, axis=0, prepend=np.zeros((1, 2), dtype=np.int64))
    ad = np.abs(d)
    axis = (ad[:, 1] > ad[:, 0]).astype(np.int64)  # major axis; ties (and zero moves): x
    toggle = axis != np.concatenate(([1], axis[:-1]))  # the axis before the first move is y
    idx = np.arange(n)
    major = d[idx, axis]
    minor = d[idx, 1 - axis]
    single = (minor == 0) & (major != 0)
    general = ~single
    turn = single & toggle
    values = np.concatenate((np.abs(major[single]) - 1, np.abs(major[general]), np.abs(minor[general])))
    n_single, n_general = int(single.sum()), int(general.sum())
    (k1, k2, k3), _ = best_eg_orders(values, [n_single, n_general, n_general])
    w.scalar(k1, 4)
    w.scalar(k2, 4)
    w.scalar(k3, 4)
    w.flags(turn)
    w.flags(single[~turn])  # among non-turns: 1 = straight, 0 = general
    w.flags(toggle[general])
    w.flags(major < 0)
    w.flags(minor[general] < 0)
    w.eg_block(values, _orders((n_single, k1), (n_general, k2), (n_general, k3)))


def _write_edges(w: BitWriter, ea: I64, eb: I64, n: int) -> I64:
    """The edge section (FORMAT.md 3, item 4) of edges ``ea -> eb`` (in the coded vertex order,
    ``n`` vertices): chain bits, ring bits, the reverse section when it is cheaper than those
    edges as explicit ones, then the explicit edges. Returns the edges' decoded order."""
    m = ea.size
    keys = ea * n + eb
    by_key = np.argsort(keys, kind="stable")
    sorted_keys = keys[by_key]
    is_first = np.empty(m, dtype=bool)  # first occurrence of each (i, j); repeats are explicit
    is_first[by_key] = np.concatenate(([True], sorted_keys[1:] != sorted_keys[:-1]))
    is_next = is_first & (eb == ea + 1)
    next_bits = np.zeros(n - 1, dtype=np.uint8)
    next_bits[ea[is_next]] = 1
    starts, ends = chains(next_bits, n)
    chain_of = np.concatenate(([0], np.cumsum(next_bits == 0))).astype(np.int64)
    ca = chain_of[ea]
    is_close = is_first & (ea == ends[ca]) & (eb == starts[ca]) & (ea - eb >= 2)
    closed = np.zeros(starts.size, dtype=bool)
    closed[ca[is_close]] = True
    is_rev = is_first & (eb == ea - 1)
    rest = by_key[~(is_next | is_close)[by_key]]  # sorted by (i, j), repeats in input order
    plan = _explicit_cost(ea[rest], eb[rest]) if rest.size else (0, 0, 0)
    use_rev = False
    if is_rev.any():  # a reverse bit per vertex, if cheaper than those edges as explicit ones
        rest_norev = by_key[~(is_next | is_close | is_rev)[by_key]]
        plan_norev = _explicit_cost(ea[rest_norev], eb[rest_norev]) if rest_norev.size else (0, 0, 0)
        use_rev = (n - 1) + plan_norev[0] < plan[0]
        if use_rev:
            rest, plan = rest_norev, plan_norev
    if not use_rev:
        is_rev = np.zeros(m, dtype=bool)
    w.flags(next_bits)
    w.flags(closed[ends - starts >= 2])
    w.scalar(int(use_rev), 1)
    if use_rev:
        rev_bits = np.zeros(n - 1, dtype=np.uint8)
        rev_bits[eb[is_rev]] = 1
        w.flags(rev_bits)
    w.eg(int(rest.size))
    if rest.size:
        ra, rb = ea[rest], eb[rest]
        _, ke, kd = plan
        w.scalar(ke, 4)
        w.scalar(kd, 4)
        w.eg_block(np.concatenate((np.diff(ra, prepend=0), zigzag(rb - ra))),
                   _orders((rest.size, ke), (rest.size, kd)))

    def by(mask: NDArray[np.bool_], key: I64) -> I64:  # the edges in mask, by distinct key
        sel = np.flatnonzero(mask)
        slot = np.full(n, -1, dtype=np.int64)
        slot[key[sel]] = sel
        return slot[slot >= 0]

    return np.concatenate((by(is_next, ea), by(is_rev, eb), by(is_close, ca), rest)).astype(np.int64)


def _write_sources(w: BitWriter, src: MaskArray, n_robots: int) -> None:
    """A fused map's contributor masks (FORMAT.md 3, item 6), ``src`` in the edges' decoded
    order: the sorted distinct masks of ``n_robots`` bits, then an index per edge.

    Raises
    ------
    EncodeError
        A contributor bit at or above ``n_robots``.
    """
    if n_robots > 64 or src.dtype == object:
        # masks wider than 64 bits (Python ints): the same layout, written from Python ints
        vals = [int(v) for v in src.tolist()]
        if any(v >> n_robots for v in vals):
            raise EncodeError(f"an edge has a contributor bit >= the number of robots ({n_robots})")
        masks = sorted(set(vals))
        slot = {v: i for i, v in enumerate(masks)}
        w.eg(len(masks))
        w.wide(masks, n_robots)
        w.fixed(np.array([slot[v] for v in vals], dtype=np.int64), ceil_log2(len(masks)))
        return
    if n_robots < 64 and np.any(src >> np.uint64(n_robots)):
        raise EncodeError(f"an edge has a contributor bit >= the number of robots ({n_robots})")
    uniq, index = np.unique(src, return_inverse=True)
    w.eg(int(uniq.size))
    w.fixed(uniq, n_robots)
    w.fixed(index.astype(np.int64), ceil_log2(int(uniq.size)))


# ---------------------------------------------------------------------------------------- decode
def _read_values(r: BitReader, count: int, width: int, exc_width: int, what: str) -> I64:
    """Read a value section written by :func:`_write_values`."""
    mode = r.scalar(2, f"the {what} mode")
    if mode == MODE_PLAIN:
        return r.fixed(count, width, f"the {what}").astype(np.int64)
    dom = r.scalar(width, f"the {what} value")
    if width == LABEL_BITS and dom == 3:
        raise FormatError("body: a vertex label is 3 (only 0, 1, 2 exist)")
    out = np.full(count, dom, dtype=np.int64)
    if mode == MODE_CONSTANT:
        return out
    if mode == MODE_FLAGS:
        exc = np.flatnonzero(r.flags(count, f"the {what} exception flags"))
    else:
        n_exc = r.eg(0, f"the {what} exception count")
        if n_exc > count:
            raise FormatError(f"body: {n_exc} {what} exceptions among {count} items")
        kg = r.scalar(4, f"the {what} gap order")
        exc = np.cumsum(r.eg_block(n_exc, kg, f"the {what} gaps") + 1) - 1
        if exc.size and int(exc[-1]) >= count:
            raise FormatError(f"body: a {what} exception lies beyond the last item")
    if exc_width == 1:
        lo, hi = (x for x in (0, 1, 2) if x != dom)
        out[exc] = np.where(r.flags(exc.size, f"the {what} exceptions") == 1, hi, lo)
    else:
        vals = r.fixed(exc.size, exc_width, f"the {what} exceptions").astype(np.int64)
        if np.any(vals == dom):
            raise FormatError(f"body: a {what} exception equals the dominant value")
        out[exc] = vals
    return out


SMALL_BODY_BYTES = 4096
"""Bodies up to this size are first read by :func:`_decode_small`."""


def _decode_small(data: bytes, resolution_mm: int, n_robots: int | None, limits: Limits) -> Wireframe | None:
    """:func:`decode_body` for a well-formed small body, in plain Python (a robot's map is a
    few hundred bits: numpy's per-call cost dominated the vectorised reader there).

    Returns exactly the wireframe the vectorised reader returns, or None at the first sign of
    anything it would reject (or that this reader does not handle: an empty map, moves near the
    grid's limit); :func:`decode_body` then runs the vectorised reader, which says why. So the
    errors are the vectorised reader's, and this reader only has to accept nothing more.

    The sections are read by :func:`_small_vertices`, :func:`_small_edges` and
    :func:`_small_sources` through the bit primitives of :func:`_small_bits` (closures sharing
    one position, as they were before the split). The split costs about 1 % (1 us of 116 us
    for paper-small's truth map, interleaved A/B against the single function), below the run-to-run
    spread of ``wiremap bench codec``."""
    nbits = 8 * len(data)
    if nbits == 0:
        return None
    rd = _small_bits(data)
    try:
        n = rd.eg_block([0])[0]
        if n == 0 or n > limits.max_vertices or n > rd.left():
            return None
        q = _small_vertices(rd, n, resolution_mm, limits)
        if q is None:
            return None
        labels = rd.values(n, LABEL_BITS, 1)
        if 3 in labels:
            return None
        edges = _small_edges(rd, n, limits)
        if edges is None:
            return None
        m = len(edges)
        lq: list[int] = []
        if m:
            lq = rd.values(m, LIKELIHOOD_BITS, LIKELIHOOD_BITS)
            if max(lq) > LIKELIHOOD_LEVELS:
                return None
        sources = [0] * m
        if n_robots is not None and m:
            read = _small_sources(rd, m, n_robots)
            if read is None:
                return None
            sources = read
        if rd.left() >= 8 or "1" in rd.rest():
            return None
        # every value was checked while reading (coordinates on the bounded grid, labels 0..2,
        # edges in range and no self-loop, likelihood codes 0..15): Wireframe.checked skips
        # checking them again, a third of a robot map's decode
        return Wireframe.checked(
            np.array(q, dtype=np.float64) * resolution_mm / 1e3,
            np.array(labels, dtype=np.uint8),
            np.array(edges, dtype=np.int32).reshape(-1, 2),
            np.array(lq, dtype=np.float64) / LIKELIHOOD_LEVELS,
            as_masks(sources),
        )
    except (_Reject, ValueError, IndexError, StopIteration):
        return None


class _SmallBits(NamedTuple):
    """The small reader's primitives over one bit string (see :func:`_small_bits`)."""

    uint: Callable[[int], int]
    flags: Callable[[int], str]
    eg_block: Callable[[list[int]], list[int]]
    values: Callable[[int, int, int], list[int]]
    left: Callable[[], int]
    rest: Callable[[], str]


def _small_bits(data: bytes) -> _SmallBits:
    """Readers of ``data``'s bits (as a ``str`` of ``0``/``1``) sharing one position: ``uint(w)``,
    ``flags(count)`` (the bits as a string), ``eg_block(orders)`` (Exp-Golomb values),
    ``values(count, width, exc_width)`` (a value section, :func:`_read_values`), ``left()`` (bits
    not read yet) and ``rest()`` (those bits). Each raises :class:`_Reject` past the end or on a
    value the vectorised reader rejects."""
    nbits = 8 * len(data)
    bits = format(int.from_bytes(data, "big"), "b").zfill(nbits)
    find = bits.find
    pos = 0

    def uint(w: int) -> int:
        nonlocal pos
        if pos + w > nbits:
            raise _Reject
        v = int(bits[pos : pos + w], 2) if w else 0
        pos += w
        return v

    def flags(count: int) -> str:
        nonlocal pos
        if pos + count > nbits:
            raise _Reject
        out = bits[pos : pos + count]
        pos += count
        return out

    def eg_block(orders: list[int]) -> list[int]:
        nonlocal pos
        zeros = []
        for k in orders:  # the prefixes, each at most MAX_EG_BITS - k zeros
            j = find("1", pos, pos + MAX_EG_BITS - k + 1)
            if j < 0:
                raise _Reject
            zeros.append(j - pos)
            pos = j + 1
        out = []
        for z, k in zip(zeros, orders):  # uint(w), inlined: the mantissas are most of the reads
            w = z + k
            if pos + w > nbits:
                raise _Reject
            v = int(bits[pos : pos + w], 2) if w else 0
            pos += w
            out.append((1 << w) + v - (1 << k))
        return out

    def values(count: int, width: int, exc_width: int) -> list[int]:
        mode = uint(2)
        if mode == MODE_PLAIN:
            return [uint(width) for _ in range(count)]
        dom = uint(width)
        if width == LABEL_BITS and dom == 3:
            raise _Reject
        out = [dom] * count
        if mode == MODE_CONSTANT:
            return out
        if mode == MODE_FLAGS:
            exc = [i for i, c in enumerate(flags(count)) if c == "1"]
        else:
            n_exc = eg_block([0])[0]
            if n_exc > count:
                raise _Reject
            kg = uint(4)
            exc = []
            at = -1
            for g in eg_block([kg] * n_exc):
                at += g + 1
                exc.append(at)
            if exc and exc[-1] >= count:
                raise _Reject
        if exc_width == 1:
            lo, hi = (x for x in (0, 1, 2) if x != dom)
            for i, c in zip(exc, flags(len(exc))):
                out[i] = hi if c == "1" else lo
        else:
            for i in exc:
                v = uint(exc_width)
                if v == dom:
                    raise _Reject
                out[i] = v
        return out

    def left() -> int:
        return nbits - pos

    def rest() -> str:
        return bits[pos:]

    return _SmallBits(uint, flags, eg_block, values, left, rest)


def _small_vertices(rd: _SmallBits, n: int, resolution_mm: int, limits: Limits) -> list[list[int]] | None:
    """The vertex section (FORMAT.md 3, item 2) as grid coordinates; None where the vectorised
    reader must decide (moves near its limit, a vertex beyond ``limits``)."""
    uint, flags, eg_block = rd.uint, rd.flags, rd.eg_block
    k1, k2, k3 = uint(4), uint(4), uint(4)
    turn = flags(n)
    straight = iter(flags(n - turn.count("1")))
    single = [t == "1" or next(straight) == "1" for t in turn]
    n_single = sum(single)
    n_general = n - n_single
    gturn = iter(flags(n_general))
    toggle = [t == "1" if s else next(gturn) == "1" for t, s in zip(turn, single)]
    negative = flags(n)
    minor_negative = flags(n_general)
    moves = eg_block([k1] * n_single + [k2] * n_general + [k3] * n_general)
    q: list[list[int]] = []
    x = y = 0
    axis = 1  # the axis before the first move is y
    total = 0
    ts = tg = 0
    for i in range(n):
        if single[i]:
            major, minor = moves[ts] + 1, 0
            ts += 1
        else:
            major, minor = moves[n_single + tg], moves[n + tg]
            if minor_negative[tg] == "1":
                minor = -minor
            tg += 1
        if negative[i] == "1":
            major = -major
        if toggle[i]:
            axis = 1 - axis
        dx, dy = (major, minor) if axis == 0 else (minor, major)
        total += abs(dx) + abs(dy)
        x += dx
        y += dy
        q.append([x, y])
    if total > 2**59:  # near the vectorised reader's limit (a float sum): let it decide
        return None
    far = float(max(map(abs, itertools.chain.from_iterable(q))))
    if far > MAX_GRID or far * resolution_mm / 1e3 > limits.max_coordinate:
        return None
    return q


def _small_edges(rd: _SmallBits, n: int, limits: Limits) -> list[tuple[int, int]] | None:
    """The edge section (FORMAT.md 3, item 4) in decoded order: chain, reverse, ring closing and
    explicit edges; None where the vectorised reader must decide."""
    uint, flags, eg_block = rd.uint, rd.flags, rd.eg_block
    nxt = flags(n - 1)
    starts = [0] + [k + 1 for k, c in enumerate(nxt) if c == "0"]
    ends = [k for k, c in enumerate(nxt) if c == "0"] + [n - 1]
    rings = [(a, b) for a, b in zip(starts, ends) if b - a >= 2]
    close = flags(len(rings))
    rev = flags(n - 1) if uint(1) else ""
    n_rest = eg_block([0])[0]
    edges = [(k, k + 1) for k, c in enumerate(nxt) if c == "1"]
    edges += [(k + 1, k) for k, c in enumerate(rev) if c == "1"]
    edges += [(b, a) for (a, b), c in zip(rings, close) if c == "1"]
    m = len(edges) + n_rest
    if m > limits.max_edges or 2 * n_rest > rd.left():
        return None
    if n_rest:
        ke, kd = uint(4), uint(4)
        vals = eg_block([ke] * n_rest + [kd] * n_rest)
        if max(vals[:n_rest]) >= n:
            return None
        first = 0
        for t in range(n_rest):
            first += vals[t]
            zz = vals[n_rest + t]
            second = first + ((zz >> 1) ^ -(zz & 1))
            if first >= n or not 0 <= second < n or first == second:
                return None
            edges.append((first, second))
    return edges


def _small_sources(rd: _SmallBits, m: int, n_robots: int) -> list[int] | None:
    """The contributor masks of a fused map's ``m`` edges (FORMAT.md 3, item 6); None where
    the vectorised reader must decide."""
    uint = rd.uint
    n_masks = rd.eg_block([0])[0]
    if not 1 <= n_masks <= m:
        return None
    masks = [uint(n_robots) for _ in range(n_masks)]
    if any(b <= a for a, b in itertools.pairwise(masks)):
        return None
    w = ceil_log2(n_masks)
    index = [uint(w) for _ in range(m)]
    if max(index) >= n_masks:
        return None
    return [masks[i] for i in index]


class _Reject(Exception):
    """The small reader's way out: the vectorised reader will say what is wrong."""


def decode_body(data: bytes, resolution_mm: int, n_robots: int | None, limits: Limits) -> Wireframe:
    """Parse a body written by :func:`encode_body`.

    Parameters
    ----------
    data : the body bytes (already bounded by ``limits.max_bytes``).
    resolution_mm : grid step in millimetres.
    n_robots : ``None`` for a robot map, else the fused map's robot count.
    limits : vertex, edge and coordinate bounds, checked before anything proportional to them
        is allocated.

    Raises
    ------
    TruncatedError, ExtraDataError, LimitError, FormatError
        As their names say; nothing else.
    """
    if len(data) <= SMALL_BODY_BYTES:
        wf = _decode_small(data, resolution_mm, n_robots, limits)
        if wf is not None:
            return wf
    r = BitReader(data, "body")
    n = r.eg(0, "the vertex count")
    if n > limits.max_vertices:
        raise LimitError(f"body declares {n} vertices, the limit is {limits.max_vertices}")
    if n == 0:
        _finish(r)
        return Wireframe.empty()
    if n > r.remaining:  # every vertex costs at least its class bit
        raise TruncatedError(f"body declares {n} vertices but has only {r.remaining} bits left")
    points = _read_vertices(r, n, resolution_mm, limits)

    # -- labels
    labels = _read_values(r, n, LABEL_BITS, 1, "label")
    if np.any(labels == 3):
        raise FormatError("body: a vertex label is 3 (only 0, 1, 2 exist)")

    edges = _read_edges(r, n, limits)
    m = int(edges.shape[0])

    # -- likelihood
    lq = np.zeros(0, dtype=np.int64)
    if m:
        lq = _read_values(r, m, LIKELIHOOD_BITS, LIKELIHOOD_BITS, "likelihood")
        if np.any(lq > LIKELIHOOD_LEVELS):
            raise FormatError("body: a likelihood code is above 15")

    sources = np.zeros(m, dtype=np.uint64)
    if n_robots is not None and m:
        sources = _read_sources(r, m, n_robots)

    _finish(r)
    try:
        return Wireframe(
            points,  # validated and cast in __post_init__
            labels.astype(np.uint8),
            edges.astype(np.int32),
            lq.astype(np.float64) / LIKELIHOOD_LEVELS,
            sources,
        )
    except ValueError as exc:  # pragma: no cover - every case above is checked first
        raise FormatError(f"body: {exc}") from None


def _read_vertices(r: BitReader, n: int, resolution_mm: int, limits: Limits) -> NDArray[np.float64]:
    """The vertex section (FORMAT.md 3, item 2) of ``n`` vertices, as points in metres.

    Raises
    ------
    TruncatedError, FormatError, LimitError
        Too few bits; moves adding up beyond the grid; a vertex beyond ``limits.max_coordinate``.
    """
    k1 = r.scalar(4, "the move code orders")
    k2 = r.scalar(4, "the move code orders")
    k3 = r.scalar(4, "the move code orders")
    turn = r.flags(n, "the turn bits").astype(bool)
    single = turn.copy()
    single[~turn] = r.flags(int(n - turn.sum()), "the straight bits").astype(bool)
    general = ~single
    n_single = int(single.sum())
    n_general = n - n_single
    toggle = turn.copy()
    toggle[general] = r.flags(n_general, "the general turn bits").astype(bool)
    negative = r.flags(n, "the sign bits").astype(bool)
    minor_negative = r.flags(n_general, "the minor sign bits").astype(bool)
    moves = r.eg_block(n + n_general, _orders((n_single, k1), (n_general, k2), (n_general, k3)), "the moves")
    major = np.empty(n, dtype=np.int64)
    major[single] = moves[:n_single] + 1
    major[general] = moves[n_single:n]
    minor = np.zeros(n, dtype=np.int64)
    minor[general] = np.where(minor_negative, -moves[n:], moves[n:])
    major = np.where(negative, -major, major)
    axis = (1 + np.cumsum(toggle, dtype=np.int64)) % 2  # the axis before the first move is y
    d = np.empty((n, 2), dtype=np.int64)
    idx = np.arange(n)
    d[idx, axis] = major
    d[idx, 1 - axis] = minor
    if float(np.abs(d).sum(dtype=np.float64)) > 2.0**60:
        raise FormatError("body: vertex moves add up beyond the grid")
    q = np.cumsum(d, axis=0)
    far = float(np.abs(q).max())
    if far > MAX_GRID or far * resolution_mm / 1e3 > limits.max_coordinate:
        raise LimitError(
            f"body: a vertex lies {far * resolution_mm / 1e3:.6g} m from the origin, "
            f"the limit is {limits.max_coordinate:g} m"
        )
    return np.asarray(q.astype(np.float64) * resolution_mm / 1e3, dtype=np.float64)


def _read_edges(r: BitReader, n: int, limits: Limits) -> I64:
    """The edge section (FORMAT.md 3, item 4) over ``n`` vertices: ``(m, 2)`` vertex pairs,
    chain, reverse, ring closing and explicit edges in that order.

    Raises
    ------
    TruncatedError, LimitError, FormatError
        Too few bits; more than ``limits.max_edges`` edges; an explicit edge that is a
        self-loop or names a vertex that does not exist.
    """
    next_bits = r.flags(n - 1, "the chain bits")
    starts, ends = chains(next_bits, n)
    ring = ends - starts >= 2
    close_bits = r.flags(int(ring.sum()), "the ring bits").astype(bool)
    rev_bits = (r.flags(n - 1, "the reverse bits") if r.scalar(1, "the reverse flag")
                else np.zeros(0, np.uint8))
    n_rest = r.eg(0, "the explicit edge count")
    nk = np.flatnonzero(next_bits)
    rk = np.flatnonzero(rev_bits)
    m = int(nk.size + rk.size + int(close_bits.sum()) + n_rest)
    if m > limits.max_edges:
        raise LimitError(f"body declares {m} edges, the limit is {limits.max_edges}")
    if 2 * n_rest > r.remaining:  # every explicit edge costs at least two bits
        raise TruncatedError(f"body declares {n_rest} explicit edges but has only {r.remaining} bits left")
    pairs = np.zeros((0, 2), dtype=np.int64)
    if n_rest:
        ke = r.scalar(4, "the explicit edge orders")
        kd = r.scalar(4, "the explicit edge orders")
        vals = r.eg_block(2 * n_rest, _orders((n_rest, ke), (n_rest, kd)), "the explicit edges")
        if int(vals[:n_rest].max()) >= n:
            raise FormatError("body: an explicit edge names a vertex that does not exist")
        first = np.cumsum(vals[:n_rest])
        second = first + unzigzag(vals[n_rest:])
        if int(first[-1]) >= n or int(second.min()) < 0 or int(second.max()) >= n or np.any(first == second):
            raise FormatError("body: an explicit edge is a self-loop or names a vertex that does not exist")
        pairs = np.stack((first, second), axis=1)
    return np.concatenate(
        (
            np.stack((nk, nk + 1), axis=1),
            np.stack((rk + 1, rk), axis=1),
            np.stack((ends[ring][close_bits], starts[ring][close_bits]), axis=1),
            pairs,
        )
    )


def _read_sources(r: BitReader, m: int, n_robots: int) -> MaskArray:
    """The contributor masks of a fused map's ``m`` edges (FORMAT.md 3, item 6): ``uint64``
    for at most 64 robots, else :func:`~mapping.wireframe.as_masks` of Python ints.

    Raises
    ------
    TruncatedError, FormatError
        Too few bits; a mask count, mask order or index the encoder never writes.
    """
    n_masks = r.eg(0, "the contributor mask count")
    if not 1 <= n_masks <= m:
        raise FormatError(f"body: {n_masks} distinct contributor masks for {m} edges")
    if n_robots > 64:
        wide = r.wide(n_masks, n_robots, "the contributor masks")
        if any(b <= a for a, b in itertools.pairwise(wide)):
            raise FormatError("body: contributor masks are not strictly increasing")
        idx = r.fixed(m, ceil_log2(n_masks), "the contributor indices").astype(np.int64)
        if np.any(idx >= n_masks):
            raise FormatError("body: a contributor index is out of range")
        return as_masks([wide[i] for i in idx.tolist()])
    masks = r.fixed(n_masks, n_robots, "the contributor masks")
    if np.any(masks[1:] <= masks[:-1]):
        raise FormatError("body: contributor masks are not strictly increasing")
    index = r.fixed(m, ceil_log2(n_masks), "the contributor indices").astype(np.int64)
    if np.any(index >= n_masks):
        raise FormatError("body: a contributor index is out of range")
    return np.asarray(masks[index], dtype=np.uint64)


def _finish(r: BitReader) -> None:
    """The stream must end within the last byte, and the padding must be zero."""
    if r.remaining >= 8:
        raise ExtraDataError(f"body: {r.remaining // 8} bytes follow the end of the map")
    if np.any(r.bits[r.pos :]):
        raise ExtraDataError("body: non-zero padding bits after the end of the map")
