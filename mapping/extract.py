"""Corner extraction from a 2-D lidar scan by split-and-merge (paper Sec. II, ref. [12]; Sec. IV-A).

The paper assumes "a sensor processing layer [that] extracts environment corners from raw
sensor measurements", e.g. split-and-merge line extraction from a 2-D lidar scan. This module is
that layer: :func:`extract_corners` turns one scan's ranges into the same labelled corner scan the
simulated corner sensor produces -- a :class:`~mapping.wireframe.Wireframe` in the robot frame,
vertices in counterclockwise order, one directed edge per visible wall with free space (the
robot's side) on its left.

Pipeline
--------
1. **Points.** Beam ``k`` with range ``r_k`` at bearing ``a_k`` is the point
   ``r_k (cos a_k, sin a_k)``. Non-finite (``NaN``, ``inf``) ranges, ranges ``<= min_range``
   (many scanners report 0 for "no echo") and ranges ``>= max_range`` are *no return*.
2. **Runs.** The returning points are cut into runs of consecutive beams wherever two neighbours
   are more than ``jump`` metres apart or more than ``max_gap`` no-return beams lie between them
   (shorter drop-outs, e.g. a specular spot on a wall, are bridged). A scan that covers a whole
   turn is cyclic: its last and first beams are neighbours.
3. **Split.** Each run is split recursively at the point farthest from the chord joining its
   ends while that distance exceeds ``split_tol`` (iterative end-point fit). Each split point
   is then moved, within a few beams, to where it best separates the two fitted lines.
4. **Merge.** Neighbouring pieces of one run whose fitted lines differ by less than
   ``merge_angle`` and whose union still fits one line within ``split_tol`` are merged.
5. **Fit.** Every piece is fitted by total least squares (the principal axis of its points,
   from prefix sums, so each fit is O(1)). Pieces with fewer than ``min_points`` points or
   shorter than ``min_length`` are dropped (clutter, legs, glass reflections) -- unless they
   are at least ``min_corner_length`` long and meet a kept wall in a corner (step 6): the end
   face of a thick wall or a door jamb is structure.
5a. **Grazing walls.** A wall seen at a grazing angle returns points more than ``jump`` apart,
   so it falls apart into runs too short to keep. Points just beyond a kept piece that lie on
   its line (within ``split_tol``) and further along it are absorbed into it -- a beam crosses
   a line only once, so such a point is where the continued wall was hit -- and chains of
   leftover points on one line become pieces of their own when they pass the tests above.
5b. **Walls between two beams.** Two neighbouring kept pieces (stubs of 5c included, which run
   first) hit by *consecutive* beams and lying on one line (all their returns, and a stub's
   corner, within ``split_tol`` of one line) are one wall: no ray passed between them, and a
   wall seen almost in its own plane (the robot in a doorway, in line with the face) returns
   one beam near each end and none in between.
5c. **Stubs.** A short wall seen end-on -- the end face of a thick wall or a door jamb seen from
   the room -- returns one to ``min_points - 1`` beams next to the end of the wall it meets:
   too few to fit. The corner sensor (and the filter's predicted scan) report it, and a map's
   jamb would look seen-through without it. So the unowned returns just beyond a free end of
   a kept wall, in the same run and off its line, followed by a break (range jump, no-return
   gap, end of the run or another kept piece), become a *stub* wall from the corner (the
   wall's line on the boundary ray) through the farthest of them; the wall ends in a
   ``NOMINAL`` corner there. The chain may cross a range jump only as a wall at a grazing angle
   does: the next return on one line (``split_tol``) with the chain and the corner, further
   along, at most ``5 jump`` from the previous return (a 4 m jump onto a wall behind, along a
   line of sight, is not a grazing wall). With two or more returns the corner is where the
   stub's fitted line meets the wall's. A stub's corner is known to half a beam along its wall
   (like a silhouette corner); its far end gets a label by the rules of step 6. Two collinear
   stubs from two walls hit by consecutive beams become one wall by 5b.
6. **Corners.** Two consecutive kept pieces meet in a ``NOMINAL`` corner at the intersection
   of their lines when fewer than ``min_points`` points and no long no-return gap lie between
   them, the intersection's bearing lies between the two pieces' boundary beams (one beam of
   slack) and it is within ``corner_tol`` plus the larger of the point spacing and half the
   length of each piece of that piece's end. A kept piece next to a dropped piece of three or
   more points meets it in a ``NOMINAL`` corner by the same test (the short wall is not
   reported). Every other end of a piece gets a label from what the scanner saw next to it:

   * **range jump to a farther surface** -> ``OCCLUSION`` (the piece ends on a silhouette),
     unless that farther point lies on the piece's own line further along (the same wall
     continuing at a grazing angle) -> ``FRONTIER``;
   * **range jump to a nearer surface** -> ``FRONTIER`` (the piece continues behind the nearer
     one);
   * the two rules also decide between two neighbouring kept pieces that do not meet in a
     corner (the one nearer along the boundary ray is the occluder);
   * **no return beyond it** -> ``FRONTIER`` on the range circle when the fitted line, extended
     to the next beam, would have been at or beyond ``max_range - range_tol`` (the wall leaves
     the range); otherwise the wall really ends within range and nothing behind it was seen, so
     the end is an ``OCCLUSION`` (a silhouette corner whose background is out of range);
   * **the edge of the field of view** -> ``FRONTIER`` on the first / last beam;
   * **a dropped piece of the same run next to it** -> ``FRONTIER`` (the wall may continue
     behind the clutter).

   Ends at a jump or a gap are placed on the *boundary ray*, the bisector of the last beam on
   the piece and the first beam off it; an ``OCCLUSION`` and the ``FRONTIER`` on the wall behind
   it therefore lie on one ray from the robot, as paper Sec. III-A describes (the frontier is
   the occlusion point projected onto the farther wall along the line of sight). The bisector
   halves the worst-case error of a silhouette corner compared with taking the last point,
   but the extrapolation beyond the last point is capped at the smaller of 0.75 of the piece's
   point spacing at that end and ``max_extrapolation`` (0.1 m): at a grazing angle the bisector
   lies far beyond the last return, and a wall run past its corner stays so in the map (a
   merge is a union), while one that stops short is completed by the next scan. A wall leaving
   the range ends at most ``max_extrapolation`` past its last return towards the range circle
   (on the circle with ``exit_on_circle``); a wall ending against clutter ends at its last
   point.
7. **Budget.** At most ``max_vertices`` vertices are returned: whole walls are kept longest
   first while the vertex count stays within the budget.

Edges get likelihood 1 and sources 0. A gap between runs is never an edge. The function is pure
and deterministic.

Accuracy
--------
Noise-free, a corner between two walls is exact to the fit (sub-millimetre); a silhouette
corner (``OCCLUSION``) is known only to within half a beam, ``r dθ / 2`` across the line of
sight, which grows as ``1 / sin(incidence)`` along a wall seen obliquely (and ends are placed
conservatively, at most ``max_extrapolation`` past the last return); so is the corner at the
foot of a stub. Walls seen at a grazing angle (a few degrees) may be missed: the scanner cannot
tell where they end. A wall whose whole length falls between two beams (a degree or less of
incidence) returns one beam or none: a single return between two walls is not joined to them
(from one scan it cannot be told from a short wall seen along a line of sight).

Stubs, grazing chains, walls between two beams and the extrapolation cap are there because they
raised corner detection and label accuracy on simulated lidar (docs/experiments.md).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ExtractConfig:
    """Tuning of :func:`extract_corners`.

    Parameters
    ----------
    split_tol : float
        A run is split where a point lies more than this many metres from the chord; also the
        largest residual allowed when two pieces are merged.
    merge_angle : float
        Neighbouring pieces whose lines differ by less than this (radians) may be merged.
    min_points : int
        Pieces with fewer returning beams are dropped (>= 2).
    min_length : float
        Pieces shorter than this (metres, along the fitted line) are dropped.
    jump : float
        Two neighbouring points farther apart than this (metres) belong to different runs.
    jump_beams : float
        ... or farther apart than this many times the arc between them at the nearer one's
        range, when that is more (0: ``jump`` alone). A real lidar's beams are 1 degree apart:
        17 cm at 10 m, 35 cm on a wall seen at 30 degrees, so a fixed ``jump`` cuts far walls
        to pieces; ``jump_beams = 3`` keeps walls seen at 20 degrees or more in one run.
    max_vertices : int
        Vertex budget of the returned scan (longest walls are kept).
    corner_tol : float
        How far (metres) the intersection of two neighbouring fitted lines may lie from each
        piece's end, beyond the larger of that piece's point spacing and half its length, to
        make a nominal corner; also the furthest a free end is extrapolated.
    max_gap : int
        Up to this many consecutive no-return beams inside a wall are bridged.
    min_range : float
        Ranges at or below this (metres) are no return.
    range_tol : float
        A wall whose line reaches ``max_range - range_tol`` at the next beam is taken to leave
        the sensing range (frontier) rather than to end (occlusion).
    min_corner_length : float
        A piece shorter than ``min_length`` (but with ``min_points``) is kept after all when it
        is at least this long (metres) and meets a kept wall in a corner: a door jamb or the end
        face of a thick wall, not clutter.
    stubs : bool
        Report short walls seen end-on next to a wall's end (fewer than ``min_points`` returns,
        step 5c of the module notes) as walls from a nominal corner.
    max_extrapolation : float
        The furthest (metres) a free end (occlusion or frontier) is placed beyond the wall's
        last return (step 6). Keep it small: a merge is a union and keeps any overshoot.
    lost_gap : float
        A no-return gap of more than ``max_gap`` beams after which the next return lies on the
        wall's own line, further along and at most this far (metres), is lost beams (a dark
        patch, a burst of max-range returns), not where the wall ends: the ends on both sides
        are ``FRONTIER`` at their last point instead of ``OCCLUSION`` (0: off; doorways are
        wider).
    exit_on_circle : bool
        A wall taken to leave the range ends exactly on the range circle (up to ``corner_tol``
        plus twice the end's extrapolation past its last return) instead of at most
        ``max_extrapolation`` past it. Off by default: from one scan a wall ending just short
        of the range limit looks the same, and extending it puts it past its corner for good.

    Raises
    ------
    ValueError
        With the reason, when a value is out of its range.
    """

    split_tol: float = 0.05
    merge_angle: float = math.radians(3.0)
    min_points: int = 4
    min_length: float = 0.3
    jump: float = 0.3
    max_vertices: int = 200
    corner_tol: float = 0.2
    max_gap: int = 2
    min_range: float = 0.02
    range_tol: float = 0.1
    min_corner_length: float = 0.1
    stubs: bool = True
    max_extrapolation: float = 0.1
    exit_on_circle: bool = False
    jump_beams: float = 0.0
    lost_gap: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.jump_beams) and self.jump_beams >= 0.0):
            raise ValueError(f"jump_beams must be a non-negative number, got {self.jump_beams}")
        if not (math.isfinite(self.lost_gap) and self.lost_gap >= 0.0):
            raise ValueError(f"lost_gap must be a non-negative number of metres, got {self.lost_gap}")
        for name in ("split_tol", "jump", "corner_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be a positive number of metres, got {v}")
        for name in ("min_length", "min_range", "range_tol", "min_corner_length", "max_extrapolation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a non-negative number of metres, got {v}")
        if not (math.isfinite(self.merge_angle) and 0.0 <= self.merge_angle < math.pi / 2):
            raise ValueError(f"merge_angle must be in [0, pi/2) radians, got {self.merge_angle}")
        for name, lo in (("min_points", 2), ("max_vertices", 0), ("max_gap", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")


@dataclass
class _Piece:
    """A run piece: compressed point indices ``[lo, hi]`` inclusive and its TLS line."""

    run: int
    lo: int
    hi: int
    c: FloatArray  # centroid
    u: FloatArray  # unit direction, oriented from the first point towards the last
    t0: float = 0.0  # first point's coordinate along u (relative to c)
    t1: float = 0.0  # last point's coordinate along u
    kept: bool = True
    stub: bool = False  # a short wall of 1..min_points-1 returns hanging off a kept wall's end

    @property
    def count(self) -> int:
        return self.hi - self.lo + 1

    @property
    def length(self) -> float:
        return self.t1 - self.t0


class _Fitter:
    """O(1) total-least-squares line fits over index ranges, from prefix sums."""

    def __init__(self, pts: FloatArray) -> None:
        self.pts = pts
        self.xs: list[float] = pts[:, 0].tolist()
        self.ys: list[float] = pts[:, 1].tolist()
        # Shift to the mean first: keeps the second moments well conditioned far from the robot.
        self.ox, self.oy = (float(v) for v in (pts.mean(axis=0) if len(pts) else (0.0, 0.0)))
        qx, qy = pts[:, 0] - self.ox, pts[:, 1] - self.oy

        def prefix(v: FloatArray) -> list[float]:
            return [0.0, *np.cumsum(v).tolist()]

        # Python floats: scalar arithmetic on them is several times faster than on numpy's.
        self.sx, self.sy = prefix(qx), prefix(qy)
        self.sxx, self.syy, self.sxy = prefix(qx * qx), prefix(qy * qy), prefix(qx * qy)

    def fit(self, lo: int, hi: int) -> tuple[FloatArray, FloatArray]:
        """Centroid and unit direction (first -> last point) of points ``lo..hi`` (>= 2 points)."""
        n = hi - lo + 1
        a, b = lo, hi + 1
        mx = (self.sx[b] - self.sx[a]) / n
        my = (self.sy[b] - self.sy[a]) / n
        cxx = (self.sxx[b] - self.sxx[a]) / n - mx * mx
        cyy = (self.syy[b] - self.syy[a]) / n - my * my
        cxy = (self.sxy[b] - self.sxy[a]) / n - mx * my
        # Principal axis of the 2x2 covariance: angle 0.5 * atan2(2 cxy, cxx - cyy).
        phi = 0.5 * math.atan2(2.0 * cxy, cxx - cyy)
        ux, uy = math.cos(phi), math.sin(phi)
        if (self.xs[hi] - self.xs[lo]) * ux + (self.ys[hi] - self.ys[lo]) * uy < 0.0:
            ux, uy = -ux, -uy
        return np.array([mx + self.ox, my + self.oy]), np.array([ux, uy])

    def refit(self, p: _Piece) -> None:
        p.c, p.u = self.fit(p.lo, p.hi)
        self.extent(p)

    def extent(self, p: _Piece) -> None:
        """Update the piece's first / last point coordinates along its (unchanged) line."""
        cx, cy, ux, uy = float(p.c[0]), float(p.c[1]), float(p.u[0]), float(p.u[1])
        p.t0 = (self.xs[p.lo] - cx) * ux + (self.ys[p.lo] - cy) * uy
        p.t1 = (self.xs[p.hi] - cx) * ux + (self.ys[p.hi] - cy) * uy


def _line_dist(pts: FloatArray, c: FloatArray, u: FloatArray) -> FloatArray:
    """Unsigned distances of ``pts`` to the line through ``c`` with unit direction ``u``."""
    d = pts - c
    return np.asarray(np.abs(d[:, 0] * u[1] - d[:, 1] * u[0]), dtype=np.float64)


def _split_points(pts: FloatArray, lo: int, hi: int, tol: float, ring: bool) -> list[int]:
    """Split indices (inclusive corner points) of run ``lo..hi`` by iterative end-point fit.
    ``ring``: the run closes on itself (its two ends are neighbours)."""
    out: list[int] = []
    stack = [(lo, hi)]
    while stack:
        s, e = stack.pop()
        if e - s < 2:
            continue
        inner = pts[s + 1 : e]
        chord = pts[e] - pts[s]
        clen = math.hypot(chord[0], chord[1])
        if clen < 1e-9 or (ring and (s, e) == (lo, hi)):
            # The run closes on itself (a full-turn scan of a closed room): split where it is
            # farthest from its start instead of from a degenerate chord.
            d = np.hypot(inner[:, 0] - pts[s, 0], inner[:, 1] - pts[s, 1])
            m = int(np.argmax(d))
            if d[m] <= tol:
                continue
        else:
            rel = inner - pts[s]
            d = np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0]) / clen
            m = int(np.argmax(d))
            if d[m] <= tol:
                continue
        k = s + 1 + m
        out.append(k)
        stack.append((s, k))
        stack.append((k, e))
    out.sort()
    return out


def _pair_dist(q: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise distance of ``q[i]`` from the line through ``a[i]`` and ``b[i]`` (inf if a == b)."""
    d = b - a
    norm = np.hypot(d[:, 0], d[:, 1])
    rel = q - a
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.abs(rel[:, 0] * d[:, 1] - rel[:, 1] * d[:, 0]) / norm
    return np.asarray(np.where(norm > 1e-12, out, np.inf), dtype=np.float64)


def _ray_hit(theta: float, c: FloatArray, u: FloatArray) -> float | None:
    """Distance along the ray from the origin at bearing ``theta`` to the line (c, u), or None."""
    dx, dy = math.cos(theta), math.sin(theta)
    den = dx * u[1] - dy * u[0]
    if abs(den) < 1e-12:
        return None
    t = (c[0] * u[1] - c[1] * u[0]) / den
    return t if t > 0.0 else None


def _intersect(p: _Piece, q: _Piece) -> FloatArray | None:
    """Intersection of the two pieces' lines, or None when (nearly) parallel."""
    den = p.u[0] * q.u[1] - p.u[1] * q.u[0]
    if abs(den) < math.sin(math.radians(1.0)):
        return None
    w = q.c - p.c
    s = (w[0] * q.u[1] - w[1] * q.u[0]) / den
    return np.asarray(p.c + s * p.u, dtype=np.float64)


def _tls(xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centroid and unit direction (first -> last point) of the total-least-squares line."""
    mean = xy.mean(axis=0)
    d = xy - mean
    cxx, cyy, cxy = float(d[:, 0] @ d[:, 0]), float(d[:, 1] @ d[:, 1]), float(d[:, 0] @ d[:, 1])
    phi = 0.5 * math.atan2(2.0 * cxy, cxx - cyy)  # principal axis of the 2 x 2 scatter
    u = np.array([math.cos(phi), math.sin(phi)])
    if float(np.dot(xy[-1] - xy[0], u)) < 0.0:
        u = -u
    return np.asarray(mean, dtype=np.float64), u


def _line_cross(c1: FloatArray, u1: FloatArray, c2: FloatArray, u2: FloatArray) -> FloatArray | None:
    """Intersection of two lines (point, unit direction), or None when nearly parallel."""
    den = float(u1[0] * u2[1] - u1[1] * u2[0])
    if abs(den) < math.sin(math.radians(5.0)):
        return None
    w = c2 - c1
    s = float(w[0] * u2[1] - w[1] * u2[0]) / den
    return np.asarray(c1 + s * u1, dtype=np.float64)


def _grazing_next(
    pts: FloatArray, chain: list[int], cn: int, corner: FloatArray, wall_end: FloatArray, tol: float
) -> bool:
    """Whether return ``cn``, across a range jump, continues the stub ``chain`` (returns beyond
    a wall's end) as a wall seen at a grazing angle: the chain and ``cn`` fit one line within
    ``tol``, ``cn`` lies further along it, and the line passes the estimated ``corner`` within
    ``tol`` plus the corner's own uncertainty (its distance from the wall's last return)."""
    if not chain:
        return False
    xy = pts[[*chain, cn]]
    c, u = _tls(xy)
    if float(_line_dist(xy, c, u).max()) > tol:
        return False
    if float(np.dot(pts[cn] - pts[chain[-1]], u)) <= 0.0 or float(np.dot(pts[chain[0]] - corner, u)) <= 0.0:
        return False
    slack = tol + float(np.hypot(*(corner - wall_end)))
    return float(_line_dist(corner[None, :], c, u)[0]) <= slack


def _foot(p: _Piece, point: FloatArray) -> FloatArray:
    return np.asarray(p.c + float(np.dot(point - p.c, p.u)) * p.u, dtype=np.float64)


def extract_corners(
    ranges: FloatArray,
    angles: FloatArray,
    max_range: float,
    config: ExtractConfig | None = None,
) -> Wireframe:
    """Labelled corner scan of one lidar scan by split-and-merge (see the module notes).

    Parameters
    ----------
    ranges : (n,) float
        Range per beam in metres; ``NaN``, ``inf``, ``<= config.min_range`` and
        ``>= max_range`` mean no return.
    angles : (n,) float
        Beam bearings in the robot frame, strictly increasing, spanning at most one turn. When
        they cover a whole turn (last bearing + one step reaches the first + 2 pi) the scan is
        treated as cyclic.
    max_range : float
        The scanner's maximum range in metres (positive).
    config : ExtractConfig, optional
        Tuning; the defaults suit a 361-beam, 180-degree, 10 m scanner with 1 cm noise.

    Returns
    -------
    Wireframe
        Robot-frame corners in counterclockwise order, labelled nominal / occlusion / frontier,
        one edge per visible wall with the robot on its left, likelihood 1, sources 0.

    Raises
    ------
    ValueError
        When the shapes differ, the bearings are not finite and strictly increasing or span
        more than a turn, or ``max_range`` is not positive. Bad *ranges* never raise.
    """
    cfg = config if config is not None else ExtractConfig()
    beams = _beams(ranges, angles, max_range, cfg)  # 1
    if beams is None:
        return Wireframe.empty()
    sc = _runs(beams, cfg)  # 2
    pieces = _split_and_merge(sc)  # 3, 4, 5
    kept = [p for p in pieces if p.kept]
    if not kept:
        return Wireframe.empty()
    owner = _absorb_continuations(sc, pieces, kept)  # 5a
    kept = _add_sparse_walls(sc, kept, owner)
    kept = _keep_corner_pieces(sc, pieces, kept, owner)  # 6, short walls in a corner
    if cfg.stubs:
        kept = _add_stubs(sc, kept, owner)  # 5c
    _join_between_beams(sc, kept, owner)  # 5b
    nk = len(kept)
    corner_at: list[FloatArray | None] = [None] * nk  # corner between kept[i] and kept[i + 1]
    pairs = range(nk) if beams.cyclic and nk > 1 else range(nk - 1)
    for i in pairs:
        corner_at[i] = _corner(sc, kept[i], kept[(i + 1) % nk])
    verts, labs, start_v, end_v = _vertices(sc, pieces, kept, owner, corner_at)  # 6
    return _scan_wireframe(sc, kept, verts, labs, start_v, end_v)  # 7


@dataclass(frozen=True)
class _Beams:
    """A validated scan (step 1): ranges, bearings and which beams return; ``step`` is the mean
    bearing step, ``cyclic`` whether the scan covers a whole turn."""

    r_all: FloatArray
    a_all: FloatArray
    valid: NDArray[np.bool_]
    max_range: float
    step: float
    cyclic: bool

    @property
    def n(self) -> int:
        return int(self.r_all.shape[0])

    def bearing(self, k: float) -> float:
        """Bearing of (possibly fractional, possibly unwrapped) beam index ``k``."""
        n, a_all = self.n, self.a_all
        base = math.floor(k)
        frac = k - base
        wraps, b = divmod(int(base), n)
        lo_a = a_all[b] + wraps * TWO_PI
        if frac == 0.0:
            return float(lo_a)
        nb = b + 1
        hi_a = a_all[nb] + wraps * TWO_PI if nb < n else a_all[0] + (wraps + 1) * TWO_PI
        return float(lo_a + frac * (hi_a - lo_a))

    def raw_range(self, k: int) -> float:
        return float(self.r_all[k % self.n])

    def raw_valid(self, k: int) -> bool:
        return bool(self.valid[k % self.n])


def _beams(ranges: FloatArray, angles: FloatArray, max_range: float, cfg: ExtractConfig) -> _Beams | None:
    """Step 1 (points): the validated scan, or None when fewer than ``min_points`` beams return.

    Raises
    ------
    ValueError
        As :func:`extract_corners`.
    """
    r_all = np.asarray(ranges, dtype=np.float64).reshape(-1)
    a_all = np.asarray(angles, dtype=np.float64).reshape(-1)
    if r_all.shape != a_all.shape:
        raise ValueError(f"ranges and angles must have the same length, got {r_all.shape} and {a_all.shape}")
    if not (math.isfinite(max_range) and max_range > 0.0):
        raise ValueError(f"max_range must be a positive number of metres, got {max_range}")
    n = r_all.shape[0]
    if n and not np.all(np.isfinite(a_all)):
        raise ValueError("beam angles must be finite")
    if n > 1 and np.any(np.diff(a_all) <= 0.0):
        raise ValueError("beam angles must be strictly increasing")
    if n > 1 and a_all[-1] - a_all[0] > TWO_PI + 1e-9:
        raise ValueError("beam angles span more than a full turn")
    if n < 2:
        return None

    step = (a_all[-1] - a_all[0]) / (n - 1)
    cyclic = n >= 3 and a_all[-1] - a_all[0] + step >= TWO_PI - 0.5 * step

    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r_all) & (r_all > cfg.min_range) & (r_all < max_range)
    if np.count_nonzero(valid) < cfg.min_points:
        return None
    return _Beams(r_all, a_all, valid, max_range, step, bool(cyclic))


@dataclass(frozen=True)
class _Scan:
    """The returning points cut into runs (step 2): ``pts`` in beam order starting at the
    seam's cut, their (unwrapped) beam indices, ``brk[k]`` whether a run ends between points
    ``k`` and ``k + 1``, whether the cyclic seam is a break, and the line fitter over ``pts``."""

    beams: _Beams
    cfg: ExtractConfig
    pts: FloatArray
    beam_idx: NDArray[np.intp]
    brk: NDArray[np.bool_]
    seam_break: bool
    fitter: _Fitter

    @property
    def m(self) -> int:
        return len(self.beam_idx)


def _far(p: FloatArray, q: FloatArray, cfg: ExtractConfig) -> NDArray[np.bool_]:
    """Whether neighbouring points ``p[i]``, ``q[i]`` (sensor frame) are too far apart for one
    run: more than ``jump``, or with ``jump_beams`` more than that many times the arc between
    them at the nearer one's range."""
    step = np.hypot(*(q - p).T)
    if cfg.jump_beams <= 0.0:
        return np.asarray(step > cfg.jump)
    rmin = np.minimum(np.hypot(*p.T), np.hypot(*q.T))
    ang = np.abs(np.arctan2(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0], np.einsum("ij,ij->i", p, q)))
    return np.asarray(step > np.maximum(cfg.jump, cfg.jump_beams * rmin * ang))


def _runs(beams: _Beams, cfg: ExtractConfig) -> _Scan:
    """Step 2 (runs): cut the returning points wherever neighbours are more than ``jump`` apart
    or more than ``max_gap`` no-return beams lie between them; a cyclic scan is cut at its
    clearest break so that the seam splits no wall."""
    r_all, a_all, n = beams.r_all, beams.a_all, beams.n
    beam_idx = np.flatnonzero(beams.valid)
    r_ok, a_ok = r_all[beam_idx], a_all[beam_idx]
    pts = np.stack([r_ok * np.cos(a_ok), r_ok * np.sin(a_ok)], axis=1)
    gaps = np.diff(beam_idx)
    far = _far(pts[:-1], pts[1:], cfg)
    brk = far | (gaps > cfg.max_gap + 1)
    seam_break = True  # is the cyclic seam (last -> first compressed point) a break?
    if beams.cyclic and len(beam_idx) >= 4:
        # Cut the ring at its clearest break so that the seam splits no wall: a no-return gap
        # first, else the widest jump that is not a grazing wall's sparse continuation.
        nxt = np.roll(pts, -1, axis=0)
        step_c = np.hypot(*(nxt - pts).T)
        gap_c = np.diff(np.concatenate([beam_idx, [beam_idx[0] + n]]))
        brk_c = _far(pts, nxt, cfg) | (gap_c > cfg.max_gap + 1)
        if brk_c.any():
            prv, nxt2 = np.roll(pts, 1, axis=0), np.roll(pts, -2, axis=0)
            cont = (_pair_dist(nxt, prv, pts) <= cfg.split_tol) & (
                _pair_dist(pts, nxt2, nxt) <= cfg.split_tol
            )
            score = np.where(gap_c > cfg.max_gap + 1, np.inf, np.where(cont, 1e-3 * step_c, step_c))
            score = np.where(brk_c, score, -1.0)
            k0 = (int(np.argmax(score)) + 1) % len(beam_idx)
        else:
            # One run all the way round: start at the farthest point (a corner); the ends of
            # the run are neighbours.
            k0 = int(np.argmax(r_all[beam_idx]))
            seam_break = False
        if k0:
            order = np.concatenate([np.arange(k0, len(beam_idx)), np.arange(0, k0)])
            # Unwrap the beam indices so they keep increasing across the seam.
            beam_idx = np.concatenate([beam_idx[k0:], beam_idx[:k0] + n])
            pts = pts[order]
            gaps = np.diff(beam_idx)
            far = _far(pts[:-1], pts[1:], cfg)
            brk = far | (gaps > cfg.max_gap + 1)
    return _Scan(beams, cfg, pts, beam_idx, brk, seam_break, _Fitter(pts))


def _split_and_merge(sc: _Scan) -> list[_Piece]:
    """Steps 3 to 5 (split, merge, fit): every run's pieces in order; those with fewer than
    ``min_points`` points or shorter than ``min_length`` are marked not kept."""
    cfg, pts, fitter, seam_break = sc.cfg, sc.pts, sc.fitter, sc.seam_break
    m = sc.m
    run_start = np.concatenate([[0], np.flatnonzero(sc.brk) + 1])
    run_end = np.concatenate([np.flatnonzero(sc.brk), [m - 1]])
    pieces: list[_Piece] = []
    for run_id, (s, e) in enumerate(zip(run_start.tolist(), run_end.tolist())):
        if not seam_break:
            # A closed ring starts at its farthest point, a corner: the beam there may have hit
            # either wall, so it belongs to neither piece (the seam refines no split).
            s += 1
        if e - s + 1 < cfg.min_points:
            continue
        cuts = _split_points(pts, s, e, cfg.split_tol, ring=not seam_break)
        # Half-open piece bounds: the corner point k first goes to the left piece.
        bounds = [s, *[k + 1 for k in cuts], e + 1]
        bounds = _refine_cuts(pts, fitter, bounds)
        run_pieces: list[_Piece] = []
        for lo, hi_x in itertools.pairwise(bounds):
            piece = _Piece(run_id, lo, hi_x - 1, np.zeros(2), np.zeros(2))
            if piece.count >= 2:
                fitter.refit(piece)
            else:
                piece.kept = False
            run_pieces.append(piece)
        run_pieces = _merge(run_pieces, pts, fitter, cfg)
        pieces.extend(run_pieces)

    for p in pieces:
        if p.kept and (p.count < cfg.min_points or p.length < cfg.min_length):
            p.kept = False
    return pieces


def _absorb_continuations(sc: _Scan, pieces: list[_Piece], kept: list[_Piece]) -> NDArray[np.int64]:
    """Step 5a (grazing walls), first part: grow each kept piece by the points just beyond it
    that lie on its line and further along it (a stray point at a time, or a whole dropped
    piece of ``min_points`` or more at once when all of it fits), across short drop-outs,
    never across the seam. Returns the owner (index into ``kept``, -1 none) of each point."""
    cfg, pts, beam_idx, m = sc.cfg, sc.pts, sc.beam_idx, sc.m
    # A wall seen at a grazing angle returns points far apart (spacing ~ r dθ / sin α), so it
    # breaks into runs too short to keep. Whatever lies just beyond a kept piece on the piece's
    # line (within split_tol) and further along it is where the continued wall would be hit -- a
    # beam crosses the line only once -- so it is absorbed into the piece (so a short wall at a
    # corner keeps its points).
    owner = np.full(m, -1, dtype=np.int64)
    for i, p in enumerate(kept):
        owner[p.lo : p.hi + 1] = i
    if not sc.seam_break:
        owner[0] = -2  # the corner beam at the seam of a closed ring belongs to no piece
    unit_hi = np.arange(m)  # compressed index range [unit_lo, unit_hi] absorbed as one unit
    unit_lo = np.arange(m)
    for d in pieces:
        if not d.kept and d.count >= cfg.min_points:
            unit_lo[d.lo : d.hi + 1] = d.lo
            unit_hi[d.lo : d.hi + 1] = d.hi
    for i, p in enumerate(kept):
        grown = False
        for side in (1, -1):
            while True:
                ci = p.hi if side > 0 else p.lo
                cn = ci + side
                if not 0 <= cn < m or owner[cn] != -1:
                    break
                if abs(int(beam_idx[cn]) - int(beam_idx[ci])) - 1 > cfg.max_gap:
                    break
                lo_u, hi_u = int(unit_lo[cn]), int(unit_hi[cn])
                if np.any(owner[lo_u : hi_u + 1] != -1):
                    break
                cand = pts[lo_u : hi_u + 1]
                if _line_dist(cand, p.c, p.u).max() > cfg.split_tol:
                    break
                if side * float(np.dot(pts[cn] - pts[ci], p.u)) <= 0.0:
                    break
                owner[lo_u : hi_u + 1] = i
                if side > 0:
                    p.hi = hi_u
                else:
                    p.lo = lo_u
                grown = True
        if grown:
            # Extend the piece but keep its line: the dense part fixes the line best, and a
            # point absorbed next to a corner may belong to the other wall.
            sc.fitter.extent(p)
    return owner


def _renumber(kept: list[_Piece], owner: NDArray[np.int64]) -> None:
    """Point each kept piece's points at its index in ``kept``."""
    for i, p in enumerate(kept):
        owner[p.lo : p.hi + 1] = i


def _add_sparse_walls(sc: _Scan, kept: list[_Piece], owner: NDArray[np.int64]) -> list[_Piece]:
    """Step 5a, second part: what is left may hold a wall seen so obliquely that no two of its
    points are within ``jump``: chains of leftover points, each on the line through the chain's
    ends, become pieces (:func:`_sparse_pieces`) when they pass the same tests as any other
    piece. Returns the kept pieces in scan order (``owner`` updated)."""
    for piece in _sparse_pieces(sc.pts, sc.beam_idx, owner == -1, sc.fitter, sc.cfg):
        kept.append(piece)
        owner[piece.lo : piece.hi + 1] = len(kept) - 1
    if len(kept) > 1:
        order_k = sorted(range(len(kept)), key=lambda i: kept[i].lo)
        kept = [kept[i] for i in order_k]
        _renumber(kept, owner)
    return kept


def _corner(sc: _Scan, p: _Piece, q: _Piece) -> FloatArray | None:
    """Step 6: the intersection of the lines of ``p`` and the next piece ``q`` when they meet
    there in a corner (few points and no long no-return gap between them, the intersection
    between their boundary beams and near both pieces' ends), else None."""
    cfg, pts, beam_idx, m, n = sc.cfg, sc.pts, sc.beam_idx, sc.m, sc.beams.n
    between = (q.lo - p.hi - 1) % m
    if between >= cfg.min_points:
        return None
    k_end, k_start = int(beam_idx[p.hi]), int(beam_idx[q.lo])
    if k_start < k_end:
        k_start += n  # across the seam of a cyclic scan
    if k_start - k_end - 1 > cfg.max_gap + between:
        return None  # a no-return gap between them: not a corner
    x = _intersect(p, q)
    if x is None:
        return None
    # The corner must lie between the two pieces' boundary beams, with one beam of slack
    # and, close to the robot, the angle split_tol subtends (range noise moves the split).
    slack = max(sc.beams.step, cfg.split_tol / max(float(np.hypot(x[0], x[1])), 1e-9))
    b_lo, b_hi = sc.beams.bearing(k_end) - slack, sc.beams.bearing(k_start) + slack
    bx = b_lo + (math.atan2(x[1], x[0]) - b_lo) % TWO_PI
    if bx > b_hi:
        return None
    # ... and near both pieces' ends: within corner_tol plus the larger of the piece's own
    # point spacing at that end (sparse at a grazing angle) and half its length, so that a
    # short wall seen end-on is not stretched across the room.
    sp_p = float(np.hypot(*(pts[p.hi] - pts[p.hi - 1]))) if p.count >= 2 else 0.0
    sp_q = float(np.hypot(*(pts[q.lo + 1] - pts[q.lo]))) if q.count >= 2 else 0.0
    reach_p = cfg.corner_tol + max(sp_p, 0.5 * p.length)
    reach_q = cfg.corner_tol + max(sp_q, 0.5 * q.length)
    near_p = _within_extent(sc, p, x) if p.stub else np.hypot(*(x - pts[p.hi])) <= reach_p
    near_q = _within_extent(sc, q, x) if q.stub else np.hypot(*(x - pts[q.lo])) <= reach_q
    if near_p and near_q:
        return x
    return None


def _within_extent(sc: _Scan, p: _Piece, x: FloatArray) -> bool:
    """A stub's extent runs from its corner through its returns: another corner must lie
    on its line within corner_tol plus its point spacing at that end beyond it."""
    cfg, pts = sc.cfg, sc.pts
    t = float(np.dot(x - p.c, p.u))
    sp_lo = float(np.hypot(*(pts[p.lo + 1] - pts[p.lo]))) if p.count >= 2 else 0.0
    sp_hi = float(np.hypot(*(pts[p.hi] - pts[p.hi - 1]))) if p.count >= 2 else 0.0
    return (
        p.t0 - cfg.corner_tol - sp_lo <= t <= p.t1 + cfg.corner_tol + sp_hi
        and float(_line_dist(x[None, :], p.c, p.u)[0]) <= cfg.corner_tol
    )


def _keep_corner_pieces(
    sc: _Scan, pieces: list[_Piece], kept: list[_Piece], owner: NDArray[np.int64]
) -> list[_Piece]:
    """Step 5 exception: a short wall that meets a kept wall in a corner is structure (a door
    jamb, the end face of a thick wall), not clutter: keep it when it is at least
    ``min_corner_length`` long. Returns the kept pieces in scan order (``owner`` updated)."""
    cfg, m = sc.cfg, sc.m
    grown_kept = False
    for d in pieces:
        if d.kept or d.count < cfg.min_points or d.length < cfg.min_corner_length:
            continue
        if np.any(owner[d.lo : d.hi + 1] != -1):
            continue
        before = int(owner[d.lo - 1]) if d.lo > 0 else -1
        after = int(owner[d.hi + 1]) if d.hi + 1 < m else -1
        if (before >= 0 and _corner(sc, kept[before], d) is not None) or (
            after >= 0 and _corner(sc, d, kept[after]) is not None
        ):
            d.kept = True
            kept.append(d)
            owner[d.lo : d.hi + 1] = len(kept) - 1
            grown_kept = True
    if grown_kept:
        kept.sort(key=lambda piece: piece.lo)
        _renumber(kept, owner)
    return kept


def _add_stubs(sc: _Scan, kept: list[_Piece], owner: NDArray[np.int64]) -> list[_Piece]:
    """Step 5c (stubs): short walls seen end-on next to a kept wall's free end become walls
    from a nominal corner. Returns the kept pieces in scan order (``owner`` updated).

    A short wall seen end-on -- the end face of a thick wall or a door jamb, viewed from the
    room at a grazing angle -- returns only one to min_points - 1 beams next to the end of the
    wall it meets, too few to fit or keep. The corner sensor (and the predicted scan of the
    filter) report it: the wall ends in a NOMINAL corner and the short wall runs on to its own
    end. Without it the wall would end in a FRONTIER or OCCLUSION on the boundary ray and a
    map's jamb would look seen-through. So: the unowned returns just beyond a free end of a
    kept wall, in the same run, off its line, followed by a break (a range jump, a no-return
    gap or the end of the run), become a stub wall from the corner (the wall's line on the
    boundary ray between the wall's last beam and the stub's first) through the stub's
    farthest return."""
    cfg, pts, beam_idx, brk, m = sc.cfg, sc.pts, sc.beam_idx, sc.brk, sc.m
    stubs: list[_Piece] = []
    for p in kept:
        if p.stub:
            continue
        for side in (1, -1):
            ci = p.hi if side > 0 else p.lo
            cn = ci + side
            if not (0 <= cn < m and owner[cn] == -1):
                continue  # (most ends: a corner with the next kept wall, or nothing)
            k = int(beam_idx[ci])
            ext = (
                min(0.75 * float(np.hypot(*(pts[ci] - pts[ci - side]))), cfg.max_extrapolation)
                if p.count >= 2
                else 0.0
            )
            cpt = _on_ray(sc.beams.bearing(k + 0.5 * side), p, pts[ci], side, ext, cfg)
            chain: list[int] = []
            while 0 <= cn < m and owner[cn] == -1 and len(chain) < cfg.min_points:
                if abs(int(beam_idx[cn]) - int(beam_idx[cn - side])) - 1 > cfg.max_gap:
                    break
                if brk[min(cn, cn - side)] and not (
                    float(np.hypot(*(pts[cn] - pts[cn - side]))) <= 5.0 * cfg.jump
                    and _grazing_next(pts, chain, cn, cpt, pts[ci], cfg.split_tol)
                ):
                    break
                chain.append(cn)
                cn += side
            if not chain or len(chain) >= cfg.min_points:
                continue
            # followed by a break: a jump, a no-return gap, the run's end, or a kept wall
            after = chain[-1] + side
            if 0 <= after < m and owner[after] == -1 and not brk[min(after, after - side)] and (
                abs(int(beam_idx[after]) - int(beam_idx[after - side])) - 1 <= cfg.max_gap
            ):
                continue
            if (_line_dist(pts[chain], p.c, p.u) <= cfg.split_tol).any():
                continue  # (the wall itself going on: left to the sparse continuation)
            q = _stub(sc, p, side, chain, cpt)
            if q is None:
                continue
            owner[q.lo : q.hi + 1] = -3  # taken (renumbered below)
            stubs.append(q)
    if stubs:
        kept.extend(stubs)
        kept.sort(key=lambda piece: piece.lo)
        owner[owner == -3] = -1
        _renumber(kept, owner)
    return kept


def _stub(sc: _Scan, p: _Piece, side: int, chain: list[int], cpt: FloatArray) -> _Piece | None:
    """The stub wall of returns ``chain`` beyond kept piece ``p``'s end (``side``) from its
    corner (``cpt`` on the boundary ray, or where the stub's fitted line meets the wall's)
    through its farthest return; None when it is degenerate or does not meet ``p`` there."""
    cfg, pts = sc.cfg, sc.pts
    if len(chain) >= 2:  # the corner: where the stub's line meets the wall's
        stub_c, stub_u = _tls(pts[chain])
        x = _line_cross(p.c, p.u, stub_c, stub_u)
        if x is not None and float(np.hypot(*(x - cpt))) <= cfg.corner_tol:
            cpt = x
    far_pt = pts[chain[-1]]
    d = far_pt - cpt
    dn = float(np.hypot(d[0], d[1]))
    if dn <= 1e-6:
        return None
    lo, hi = (chain[0], chain[-1]) if side > 0 else (chain[-1], chain[0])
    u = d / dn if side > 0 else -d / dn  # oriented from the first point to the last
    q = _Piece(-1, lo, hi, np.asarray(cpt, dtype=np.float64), np.asarray(u, dtype=np.float64), stub=True)
    sc.fitter.extent(q)
    if side > 0:  # its extent starts at its corner
        q.t0 = min(q.t0, 0.0)
    else:
        q.t1 = max(q.t1, 0.0)
    if (_corner(sc, p, q) if side > 0 else _corner(sc, q, p)) is None:
        return None
    return q


def _join_between_beams(sc: _Scan, kept: list[_Piece], owner: NDArray[np.int64]) -> None:
    """Step 5b (walls between two beams), in place: two neighbouring kept pieces hit by
    *consecutive* beams (no ray passed between them) that lie on one line are one wall seen at
    a grazing angle.

    The range jumps between the two beams, but nothing was seen through the wall (a ray
    between them would have crossed it). Seen from a doorway almost in the plane of a wall,
    that wall returns a beam at each end and none in between; reporting it as two walls with a
    gap would tell the filter that the scan saw through it."""
    cfg, pts, beam_idx = sc.cfg, sc.pts, sc.beam_idx
    j = 0
    while j + 1 < len(kept):
        p, q = kept[j], kept[j + 1]
        if q.lo != p.hi + 1 or int(beam_idx[q.lo]) - int(beam_idx[p.hi]) != 1:
            j += 1
            continue
        if abs(float(np.dot(p.u, q.u))) < math.cos(
            max(cfg.merge_angle, math.atan(cfg.split_tol / max(min(p.length, q.length), 1e-9)))
        ):
            j += 1
            continue
        cloud = [pts[p.lo : p.hi + 1], pts[q.lo : q.hi + 1]]
        cloud += [p.c[None, :]] if p.stub else []
        cloud += [q.c[None, :]] if q.stub else []
        xy = np.concatenate(cloud)
        mean, u = _tls(xy)
        if float(_line_dist(xy, mean, u).max()) > cfg.split_tol:
            j += 1
            continue
        if float(np.dot(pts[q.hi] - pts[p.lo], u)) < 0.0 or (p.lo == q.hi and float(np.dot(p.u, u)) < 0.0):
            u = -u
        joined = _Piece(p.run, p.lo, q.hi, mean, u)
        sc.fitter.extent(joined)
        # the extent includes a stub's corner
        for r_ in (p, q):
            if r_.stub:
                tc = float(np.dot(r_.c - mean, u))
                joined.t0, joined.t1 = min(joined.t0, tc), max(joined.t1, tc)
        kept[j : j + 2] = [joined]
        owner[joined.lo : joined.hi + 1] = j
        _renumber(kept, owner)


def _vertices(
    sc: _Scan,
    pieces: list[_Piece],
    kept: list[_Piece],
    owner: NDArray[np.int64],
    corner_at: list[FloatArray | None],
) -> tuple[list[FloatArray], list[int], list[int], list[int]]:
    """Step 6 (corners): the vertices in scan order, the corners between kept pieces
    (``corner_at``) and each other end labelled by :func:`_end_vertex`. Returns positions,
    labels and each kept piece's start and end vertex."""
    dropped_of = np.full(sc.m, -1, dtype=np.int64)  # dropped piece of >= 3 points per point
    for k, d in enumerate(pieces):
        if not d.kept and d.count >= 3:
            dropped_of[d.lo : d.hi + 1] = k
    nk = len(kept)
    verts: list[FloatArray] = []
    labs: list[int] = []
    start_v = [-1] * nk
    end_v = [-1] * nk
    for i in range(nk):
        prev_corner = corner_at[i - 1]  # (index -1 closes a cyclic scan; None otherwise)
        if prev_corner is not None:
            j = (i - 1) % nk
            if end_v[j] < 0:
                end_v[j] = len(verts)
                verts.append(prev_corner)
                labs.append(int(Label.NOMINAL))
            start_v[i] = end_v[j]
        else:
            pos, lab = _end_vertex(sc, pieces, kept, owner, dropped_of, i, -1)
            start_v[i] = len(verts)
            verts.append(pos)
            labs.append(lab)
        here = corner_at[i]
        if here is not None:
            if end_v[i] < 0:  # (the closing corner of a ring was made with the first piece)
                end_v[i] = len(verts)
                verts.append(here)
                labs.append(int(Label.NOMINAL))
        else:
            pos, lab = _end_vertex(sc, pieces, kept, owner, dropped_of, i, +1)
            end_v[i] = len(verts)
            verts.append(pos)
            labs.append(lab)
    return verts, labs, start_v, end_v


def _end_vertex(
    sc: _Scan,
    pieces: list[_Piece],
    kept: list[_Piece],
    owner: NDArray[np.int64],
    dropped_of: NDArray[np.int64],
    i: int,
    side: int,
) -> tuple[FloatArray, int]:
    """Step 6: position and label of kept[i]'s free end (side +1 = last point, -1 = first
    point) from what the scanner saw next to it (the rules of the module notes)."""
    cfg, pts, beam_idx, brk, m = sc.cfg, sc.pts, sc.beam_idx, sc.brk, sc.m
    beams = sc.beams
    n, cyclic = beams.n, beams.cyclic
    p = kept[i]
    ci = p.hi if side > 0 else p.lo  # compressed index of the extreme point
    k = int(beam_idx[ci])  # its (unwrapped) beam index
    last = pts[ci]
    kn = k + side  # the raw beam just beyond it
    if (not cyclic) and (kn < 0 or kn >= n):
        # Edge of the field of view: the wall continues outside it.
        b = beams.bearing(k)
        t = _ray_hit(b, p.c, p.u)
        pos = t * np.array([math.cos(b), math.sin(b)]) if t else _foot(p, last)
        return _checked(pos, p, last, cfg.corner_tol), int(Label.FRONTIER)
    beta = beams.bearing(k + 0.5 * side)
    # The boundary ray is half a beam beyond the last point: on the line that is about half
    # the piece's own point spacing at this end. Cap the extrapolation there (a grazing
    # line would otherwise run far past a corner hidden between the beams).
    if p.count >= 2 or (p.stub and 0 <= ci - side < m):
        cap = min(0.75 * float(np.hypot(*(pts[ci] - pts[ci - side]))), cfg.max_extrapolation)
    else:
        cap = 0.0
    cn = ci + side
    if cyclic:
        cn %= m
    if 0 <= cn < m and cn != ci:
        k_other = int(beam_idx[cn])
        if side > 0 and k_other < k:
            k_other += n  # unwrap across the seam
        if side < 0 and k_other > k:
            k_other -= n
        if abs(k_other - k) - 1 <= cfg.max_gap:
            j = int(owner[cn])
            if j >= 0:
                # Two kept pieces side by side that do not meet: nearer along the ray occludes.
                q = kept[j]
                t_me, t_other = _ray_hit(beta, p.c, p.u), _ray_hit(beta, q.c, q.u)
                if t_me is not None and t_other is not None:
                    near = t_me <= t_other
                else:
                    near = beams.raw_range(k) <= beams.raw_range(k_other)
                label = Label.OCCLUSION if near else Label.FRONTIER
            elif (x := _dropped_corner(sc, pieces, dropped_of, p, cn, side)) is not None:
                # A short wall (dropped) meets this one in a corner: a real corner, nominal.
                return x, int(Label.NOMINAL)
            elif brk[min(ci, cn)] if abs(cn - ci) == 1 else sc.seam_break:
                # A range jump: to a farther surface -> silhouette, to a nearer one -> hidden;
                # but a farther point on this wall's own line, further along, is the wall
                # itself continuing at a grazing angle -> frontier.
                farther = beams.raw_range(k_other) > beams.raw_range(k)
                on_line = (
                    _line_dist(pts[cn][None, :], p.c, p.u)[0] <= cfg.split_tol
                    and side * float(np.dot(pts[cn] - last, p.u)) > 0.0
                )
                label = Label.OCCLUSION if farther and not on_line else Label.FRONTIER
            else:
                # Clutter against the wall: it may continue behind. Nothing occludes along
                # the boundary ray, so stop at the last point seen rather than guess.
                return _on_ray(beams.bearing(k), p, last, side, cap, cfg), int(Label.FRONTIER)
            return _on_ray(beta, p, last, side, cap, cfg), int(label)
    # No return beyond this end: does the wall leave the range, or end here?
    if not beams.raw_valid(kn):
        if cfg.lost_gap > 0.0 and 0 <= cn < m and cn != ci:
            q = pts[cn]
            if (
                float(np.hypot(*(q - last))) <= cfg.lost_gap
                and _line_dist(q[None, :], p.c, p.u)[0] <= cfg.split_tol
                and side * float(np.dot(q - last, p.u)) > 0.0
            ):
                # The wall goes on past the lost beams: it may continue there; stop at the
                # last point seen.
                return _on_ray(beams.bearing(k), p, last, side, cap, cfg), int(Label.FRONTIER)
        return _range_exit(sc, p, last, side, kn, beta, cap)
    return _on_ray(beta, p, last, side, cap, cfg), int(Label.OCCLUSION)


def _range_exit(
    sc: _Scan, p: _Piece, last: FloatArray, side: int, kn: int, beta: float, cap: float
) -> tuple[FloatArray, int]:
    """Step 6, no return beyond an end (raw beam ``kn``): a ``FRONTIER`` towards the range
    circle when the wall's line reaches ``max_range - range_tol`` at that beam (at most
    ``max_extrapolation`` past the last return, or on the circle with ``exit_on_circle``), else
    an ``OCCLUSION`` on the boundary ray (the wall ends within range)."""
    cfg, max_range = sc.cfg, sc.beams.max_range
    t_next = _ray_hit(sc.beams.bearing(kn), p.c, p.u)
    if t_next is None or t_next >= max_range - cfg.range_tol:
        exit_pt = _circle_exit(p, last, side, max_range)
        if exit_pt is not None:
            # The exit lies between the last beam and the next: about one spacing on.
            if cfg.exit_on_circle:
                return _checked(exit_pt, p, last, cfg.corner_tol + 2.0 * cap), int(Label.FRONTIER)
            # ... or the wall ends just short of the range limit: no further than
            # max_extrapolation beyond the last return
            foot = _foot(p, last)
            along = float(np.dot(exit_pt - foot, side * p.u))
            along = min(max(along, 0.0), cfg.max_extrapolation, cfg.corner_tol + 2.0 * cap)
            return np.asarray(foot + along * side * p.u, dtype=np.float64), int(Label.FRONTIER)
        return _on_ray(beta, p, last, side, cap, cfg), int(Label.FRONTIER)
    return _on_ray(beta, p, last, side, cap, cfg), int(Label.OCCLUSION)


def _dropped_corner(
    sc: _Scan, pieces: list[_Piece], dropped_of: NDArray[np.int64], p: _Piece, cn: int, side: int
) -> FloatArray | None:
    """Corner of ``p`` with the dropped piece holding compressed point ``cn``, if any."""
    k = int(dropped_of[cn])
    if k < 0:
        return None
    q = pieces[k]
    return _corner(sc, p, q) if side > 0 else _corner(sc, q, p)


def _scan_wireframe(
    sc: _Scan,
    kept: list[_Piece],
    verts: list[FloatArray],
    labs: list[int],
    start_v: list[int],
    end_v: list[int],
) -> Wireframe:
    """Step 7 (budget): one edge per kept piece that still points along its line, at most
    ``max_vertices`` vertices (longest walls first), a cyclic scan's vertices rotated to start
    at the smallest bearing."""
    vp = np.asarray(verts, dtype=np.float64).reshape(-1, 2)
    lab_arr = np.asarray(labs, dtype=np.uint8)
    edges: list[tuple[int, int]] = []
    lengths: list[float] = []
    for i, p in enumerate(kept):
        a, b = start_v[i], end_v[i]
        if a == b:
            continue
        along = float(np.dot(vp[b] - vp[a], p.u))
        if along <= 1e-6:
            continue  # a piece turned inside out by its corners: not a wall
        edges.append((a, b))
        lengths.append(along)

    if edges:
        keep_edges = _budget(edges, lengths, sc.cfg.max_vertices)
        edges = [edges[k] for k in keep_edges]
    if not edges:
        return Wireframe.empty()
    wf = Wireframe.build(vp, edges, lab_arr).compacted()
    if sc.beams.cyclic and wf.n_vertices:
        # Rotate the (already counterclockwise) cyclic order to start at the smallest bearing.
        shift = int(np.argmin(np.arctan2(wf.points[:, 1], wf.points[:, 0])))
        if shift:
            perm = np.roll(np.arange(wf.n_vertices), -shift)
            inv = np.empty_like(perm)
            inv[perm] = np.arange(wf.n_vertices)
            wf = Wireframe.build(wf.points[perm], inv[wf.edges], wf.labels[perm])
    return wf


def _checked(pos: FloatArray, p: _Piece, last: FloatArray, tol: float) -> FloatArray:
    """``pos`` unless it lies more than ``tol`` from the piece's extreme point (then its foot)."""
    if not np.all(np.isfinite(pos)) or math.hypot(*(pos - last)) > tol:
        return _foot(p, last)
    return np.asarray(pos, dtype=np.float64)


def _on_ray(
    beta: float, p: _Piece, last: FloatArray, side: int, cap: float, cfg: ExtractConfig
) -> FloatArray:
    """The piece's line where the ray at bearing ``beta`` meets it, at most ``cap`` metres
    beyond the foot of ``last`` (outwards, ``side * u``) and never behind it; the foot of
    ``last`` when the ray misses the line."""
    foot = _foot(p, last)
    t = _ray_hit(beta, p.c, p.u)
    if t is None:
        return foot
    pos = _checked(t * np.array([math.cos(beta), math.sin(beta)]), p, last, cfg.corner_tol)
    d = side * p.u
    along = float(np.dot(pos - foot, d))
    if along > cap:
        return np.asarray(foot + cap * d, dtype=np.float64)
    if along < 0.0:
        return foot
    return pos


def _circle_exit(p: _Piece, last: FloatArray, side: int, radius: float) -> FloatArray | None:
    """Where the piece's line, continued beyond ``last`` (direction ``side * u``), leaves the
    disc of the given radius."""
    d = side * p.u
    f = _foot(p, last)
    # |f + s d|^2 = R^2 with f . d = (last - c) . u-ish; solve the quadratic for s >= 0.
    b = float(np.dot(f, d))
    cc = float(np.dot(f, f)) - radius * radius
    disc = b * b - cc
    if disc < 0.0:
        return None
    s = -b + math.sqrt(disc)
    if s < 0.0:
        return None
    return np.asarray(f + s * d, dtype=np.float64)


def _refine_cuts(pts: FloatArray, fitter: _Fitter, bounds: list[int], window: int = 3) -> list[int]:
    """Move each interior cut of half-open ``bounds`` by up to ``window`` points to where the
    two neighbouring fitted lines separate the points best (least total squared residual)."""
    out = list(bounds)
    for j in range(1, len(out) - 1):
        lo, cut, hi = out[j - 1], out[j], out[j + 1]
        # Fit each side without the points nearest the cut (they may belong to either line).
        l_hi = cut - 2
        r_lo = cut + 1
        if l_hi - lo + 1 < 2 or hi - 1 - r_lo + 1 < 2:
            continue
        cl, ul = fitter.fit(lo, l_hi)
        cr, ur = fitter.fit(r_lo, hi - 1)
        w_lo = max(lo + 1, cut - window)
        w_hi = min(hi - 1, cut + window)  # candidate cuts in [w_lo, w_hi]
        if w_hi < w_lo:
            continue
        seg = pts[w_lo - 1 : w_hi + 1]  # points that can change side: indices w_lo-1 .. w_hi
        dl = _line_dist(seg, cl, ul) ** 2
        dr = _line_dist(seg, cr, ur) ** 2
        # cut c: points < c go left. Cost over the window: sum(dl[:c-w_lo+1]) + sum(dr[c-w_lo+1:]).
        cdl = np.concatenate([[0.0], np.cumsum(dl)])
        cdr = np.concatenate([[0.0], np.cumsum(dr)])
        cands = np.arange(w_lo, w_hi + 1)
        split = cands - (w_lo - 1)
        cost = cdl[split] + (cdr[-1] - cdr[split])
        out[j] = int(cands[int(np.argmin(cost))])
    return out


def _merge(run_pieces: list[_Piece], pts: FloatArray, fitter: _Fitter, cfg: ExtractConfig) -> list[_Piece]:
    """Merge neighbouring nearly collinear pieces of one run (smallest angle first): their
    lines differ by less than ``merge_angle`` (or, for a short piece, than the angle
    ``split_tol`` subtends over its length) and all their points lie within ``split_tol`` of
    the line fitted to their union."""
    pieces = list(run_pieces)
    while True:
        best: tuple[float, int] | None = None
        for j in range(len(pieces) - 1):
            p, q = pieces[j], pieces[j + 1]
            if not (p.kept and q.kept):
                continue
            ang = math.acos(min(1.0, abs(float(np.dot(p.u, q.u)))))
            # A short piece's direction is uncertain: allow split_tol over its length.
            shorter = max(min(p.length, q.length), 1e-9)
            allowed = max(cfg.merge_angle, math.atan(cfg.split_tol / shorter))
            if ang < allowed and (best is None or ang < best[0]):
                c, u = fitter.fit(p.lo, q.hi)
                if float(_line_dist(pts[p.lo : q.hi + 1], c, u).max()) <= cfg.split_tol:
                    best = (ang, j)
        if best is None:
            return pieces
        j = best[1]
        merged = _Piece(pieces[j].run, pieces[j].lo, pieces[j + 1].hi, np.zeros(2), np.zeros(2))
        fitter.refit(merged)
        pieces[j : j + 2] = [merged]


def _sparse_pieces(
    pts: FloatArray, beam_idx: NDArray[np.int64], free: NDArray[np.bool_], fitter: _Fitter, cfg: ExtractConfig
) -> list[_Piece]:
    """Pieces made of consecutive unowned points (``free``) that lie on one line: each new
    point within ``split_tol`` of the line through the chain's first and last points, moving
    on along it, its spacing per beam within a factor 3 of the previous one, across at most
    ``max_gap`` no-return beams. A chain becomes a piece when it
    has ``min_points`` points, is ``min_length`` long and fits its TLS line within
    ``split_tol``."""
    out: list[_Piece] = []
    chain: list[int] = []

    def close() -> None:
        if len(chain) < cfg.min_points:
            return
        piece = _Piece(-1, chain[0], chain[-1], np.zeros(2), np.zeros(2))
        fitter.refit(piece)
        if piece.length < cfg.min_length:
            return
        if float(_line_dist(pts[piece.lo : piece.hi + 1], piece.c, piece.u).max()) > cfg.split_tol:
            return
        out.append(piece)

    xs, ys = fitter.xs, fitter.ys
    beams: list[int] = beam_idx.tolist()
    tol = cfg.split_tol
    for i in np.flatnonzero(free).tolist():
        if chain and (i != chain[-1] + 1 or beams[i] - beams[chain[-1]] - 1 > cfg.max_gap):
            close()
            chain = []
        if len(chain) >= 2:
            a, b, b0 = chain[0], chain[-1], chain[-2]
            dx, dy = xs[b] - xs[a], ys[b] - ys[a]
            norm = math.hypot(dx, dy)
            off = abs((xs[i] - xs[a]) * dy - (ys[i] - ys[a]) * dx) / norm if norm > 1e-12 else math.inf
            ahead = (xs[i] - xs[b]) * dx + (ys[i] - ys[b]) * dy > 0.0
            # Along a wall the spacing per beam changes smoothly (it grows with r^2 / sin α).
            g_prev = math.hypot(xs[b] - xs[b0], ys[b] - ys[b0]) / (beams[b] - beams[b0])
            g_new = math.hypot(xs[i] - xs[b], ys[i] - ys[b]) / (beams[i] - beams[b])
            smooth = g_prev > 0.0 and 1.0 / 3.0 <= g_new / g_prev <= 3.0
            if off > tol or not ahead or not smooth:
                close()
                chain = [] if len(chain) >= cfg.min_points else chain[-1:]
        chain.append(i)
    close()
    return out


def _budget(edges: list[tuple[int, int]], lengths: list[float], max_vertices: int) -> list[int]:
    """Indices of the edges kept, longest first, while their vertices fit the budget."""
    used: set[int] = set()
    for a, b in edges:
        used.update((a, b))
    if len(used) <= max_vertices:
        return list(range(len(edges)))
    chosen: list[int] = []
    have: set[int] = set()
    for k in sorted(range(len(edges)), key=lambda k: (-lengths[k], k)):
        a, b = edges[k]
        extra = (a not in have) + (b not in have)
        if len(have) + extra <= max_vertices:
            chosen.append(k)
            have.update((a, b))
    chosen.sort()
    return chosen
