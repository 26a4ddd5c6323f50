"""A heading measurement from wall directions (not in the paper).

Buildings have few wall directions. Once a map holds a good length of walls along a direction,
a long scan wall that the current heading puts within a few degrees of it most likely *is*
parallel to it: the difference is the heading's error. :func:`compass_heading` turns the
directions of a scan's long walls (in the map frame, at the estimated pose) and of the map's
established walls into one measurement of that error, with a variance, for
:class:`mapping.filter.WireframeFilter` to fuse as a Kalman update of the heading.

Why it is needed: the wireframe ICP (:mod:`mapping.icp`) fixes the heading only against walls
of the map *in view*. A robot turning in a hall wider than its range, or entering new territory
after a turn, sees no mapped wall; the odometry's heading error of the turn (about 2.7 degrees
standard deviation for a 90-degree turn with the filter's noise model) is then written into
every new wall, and only a loop closure, if any, takes part of it out again. A wall direction
is an absolute reference that does not need the wall itself to have been seen before.

Choices
-------
* **Directions modulo 180 degrees.** A wall and the one facing it across a corridor run
  opposite ways; both give the same direction.
* **The reference** is the building's wall directions as the map learnt them
  (:class:`Directions`): the established walls (likelihood at or above the filter's keep
  threshold, at least the compass's ``min_length`` long) of the first metres driven,
  where the map frame is exact, then frozen. Not the walls near the robot, nor the whole map's
  consensus at every step: the drift turns those with the heading (measured alternatives in
  :attr:`CompassConfig.anchor`). A direction frozen within a degree of
  perpendicular to one established before it is frozen at exactly perpendicular (a
  right-angle prior, :attr:`CompassConfig.right_angle`).
* **One scan wall, one residual**: the length-weighted median of the differences to the map
  directions within the gate (three standard deviations of the heading and of the scan wall's
  own direction, at most ``max_gate``), provided those map walls add up to ``min_support``
  metres; a scan wall with less support has a direction the map does not know (a new
  direction, or a wall that is not straight) and gives nothing.
* **Combination**: inverse-variance mean of the residuals, the direction of a wall of length
  ``L`` from two corners of std ``corner_sigma`` having variance ``2 corner_sigma^2 / L^2``;
  residuals more than three standard deviations from the mean are dropped once and the mean
  taken again. The result's variance adds ``model_sigma^2``: walls of one direction are not
  perfectly parallel in the map (its drift) nor in the building, and that error is common to
  every scan wall (it does not average out).
* The assumption fails for a wall that is really a few degrees off a frequent direction. The
  gate keeps "a few" to the heading's own uncertainty (the compass runs at full weight only
  while that is larger than :attr:`CompassConfig.min_sigma`; below, a
  slow pull against young walls, :attr:`CompassConfig.young_weight`,
  within a gate of about a degree), so a wall 10 degrees off is never mistaken for a parallel
  one at a 1-degree uncertainty. Likewise the right-angle
  prior squares a building whose wings really meet at 89.5 degrees (by at most its 1-degree
  tolerance); wings at 45 or 60 degrees (tests/worlds/angled, slanted) are left as mapped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.config import check_number
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

__all__ = ["CompassConfig", "Directions", "Heading", "compass_heading", "direction_clusters",
           "wall_directions"]


@dataclass(frozen=True)
class CompassConfig:
    """When and how :class:`mapping.filter.WireframeFilter` fuses the compass (``compass.*``).

    Evidence for each default is in docs/experiments.md (entries "compass ...").

    Parameters
    ----------
    enabled : bool
        Fuse the measurement: after a turn with no mapped wall in view the odometry's heading
        error would otherwise go into every new wall.
    min_sigma : float
        Full-weight measurement while the heading's standard deviation after the match is
        above this (radians; 0.15 degrees, just above the pose floor: whenever the match did
        not pin the heading).
    min_length : float
        Shortest wall (metres) whose direction counts (2: a corner sigma of 3 cm then tilts
        it by under a degree).
    min_support : float
        Metres of established map wall a direction needs to be a reference (10).
    corner_sigma : float
        Corner noise (metres) in a scan wall's direction variance (the sensor's, 0.03).
    model_sigma : float
        Error common to all walls of a direction (radians; 0.15 degrees: map drift and
        buildings' own non-parallel walls).
    max_gate : float
        Largest gate (radians; 6 degrees: a 90-degree turn's odometry error, with margin).
    anchor : float or None
        Reference directions frozen after this many metres driven (10: the map frame is still
        exact); None uses the whole map at every step, which turned with the drift.
    right_angle : float
        A reference within this angle (radians; 1 degree, 0 off) of perpendicular to an earlier
        one is frozen at exactly perpendicular: it straightened the ring corridor.
    young_weight : float
        Weight (0 off) of the measurement when the match pinned the heading against young walls
        (0.05: a slow pull; at full weight it fought the match and walked a heading 2 degrees off).
    young_travel : float
        Matched walls mapped at most this many metres of driving ago are young (25: they carry
        the present drift).

    Raises
    ------
    ValueError
        On a value out of range (the message names the field).
    """

    enabled: bool = True
    min_sigma: float = 0.0026
    min_length: float = 2.0
    min_support: float = 10.0
    corner_sigma: float = 0.03
    model_sigma: float = math.radians(0.15)
    max_gate: float = math.radians(6.0)
    anchor: float | None = 10.0
    right_angle: float = math.radians(1.0)
    young_weight: float = 0.05
    young_travel: float = 25.0

    def __post_init__(self) -> None:
        for name in ("min_sigma", "min_length", "min_support", "corner_sigma", "model_sigma"):
            check_number(name, getattr(self, name), 0.0)
        check_number("max_gate", self.max_gate, 0.0, math.pi / 4, open_low=True)
        if self.anchor is not None:
            check_number("anchor", self.anchor, 0.0)
        check_number("right_angle", self.right_angle, 0.0, math.pi / 4)
        check_number("young_weight", self.young_weight, 0.0, 1.0)
        check_number("young_travel", self.young_travel, 0.0, finite=False)


@dataclass(frozen=True)
class Heading:
    """A heading measurement: the heading's error is ``offset`` (radians, to be added to the
    estimate) with variance ``variance``; from ``walls`` scan walls, ``length`` metres."""

    offset: float
    variance: float
    walls: int
    length: float


def wall_directions(
    wf: Wireframe, min_length: float, min_likelihood: float = 0.0
) -> tuple[FloatArray, FloatArray]:
    """Directions (radians, in ``[0, pi)``) and lengths of the edges of ``wf`` at least
    ``min_length`` long with likelihood at least ``min_likelihood``."""
    if wf.n_edges == 0:
        return np.zeros(0), np.zeros(0)
    seg = wf.segments()
    d = seg[:, 1] - seg[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    keep = (length >= min_length) & (wf.likelihood >= min_likelihood)
    ang = np.mod(np.arctan2(d[keep, 1], d[keep, 0]), math.pi)
    return np.asarray(ang, dtype=np.float64), np.asarray(length[keep], dtype=np.float64)


def _wrap_half(a: FloatArray) -> FloatArray:
    """Angles wrapped to ``[-pi/2, pi/2)`` (directions modulo 180 degrees)."""
    return np.asarray(np.mod(a + 0.5 * math.pi, math.pi) - 0.5 * math.pi, dtype=np.float64)


def _weighted_median(x: FloatArray, w: FloatArray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][int(np.searchsorted(cw, 0.5 * cw[-1]))])


def direction_clusters(
    dirs: FloatArray, lengths: FloatArray, gap: float
) -> tuple[FloatArray, FloatArray]:
    """Group directions (radians modulo pi) into clusters: sorted around the half circle, a new
    cluster starts wherever two neighbours are more than ``gap`` apart. Returns each cluster's
    length-weighted mean direction (in ``[0, pi)``) and its total length, longest first."""
    dirs = np.mod(np.asarray(dirs, dtype=np.float64).reshape(-1), math.pi)
    lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if len(dirs) == 0:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(dirs)
    d, w = dirs[order], lengths[order]
    gaps = np.diff(np.concatenate([d, d[:1] + math.pi]))  # gaps[k]: from d[k] to the next, around
    cuts = np.flatnonzero(gaps > gap)
    if len(cuts) == 0:  # one chain all around the half circle
        labels = np.zeros(len(d), dtype=np.int64)
    else:
        start = (cuts[-1] + 1) % len(d)  # begin just after a cut, so no cluster wraps
        d = np.roll(d, -start)
        w = np.roll(w, -start)
        d = np.where(np.arange(len(d)) >= len(d) - start, d + math.pi, d) if start else d
        labels = np.concatenate([[0], np.cumsum(np.diff(d) > gap)])
    n = int(labels.max()) + 1
    tot = np.bincount(labels, weights=w, minlength=n)
    mean = np.bincount(labels, weights=w * d, minlength=n) / np.maximum(tot, 1e-12)
    order = np.argsort(-tot, kind="stable")
    return (np.asarray(np.mod(mean[order], math.pi), dtype=np.float64),
            np.asarray(tot[order], dtype=np.float64))


class Directions:
    """The reference directions of the compass: the building's wall directions in the map frame.

    While the robot has driven less than ``anchor`` metres, they are the clusters
    (:func:`direction_clusters`, neighbours more than ``gap`` apart start a new cluster) of the
    map's established walls, recomputed at every update: the
    map frame is the first pose's, and those walls carry the least heading error of any. Then
    every cluster with at least ``min_support`` metres of walls is frozen for good. A direction
    met later (a wing of the building turned against the rest) joins the reference once its
    walls, those more than ``max_gate`` from every frozen direction, add up to ``min_support``,
    with the direction they have then. Frozen directions never follow the map: a map that the
    heading's drift has turned a little cannot turn its own reference with it (tried: the whole
    map as reference, museum seeds 4 and 7 kept a 0.5-degree heading error from their first
    30 m for the whole run).

    **Right angles** (``right_angle``, radians; 0 turns it off): a direction frozen within
    ``right_angle`` of perpendicular to one frozen before it is frozen at exactly
    perpendicular. Most buildings are built square, and the map's first walls of the second
    direction carry the heading error of the turn that brought them into view (often the first
    corner, where the compass had only one direction to hold on to); without the prior the
    compass then holds the rest of the run at that error. The clusters are frozen in the order
    their walls were first established (ties: the longest first), so the direction seen from
    the first pose, the one with no heading error, is the one the others are squared to: a
    robot that starts next to a corner maps the second direction with the turn's error within
    its first 10 m, and that cluster may well be the longer one by then.
    """

    def __init__(
        self,
        anchor: float,
        min_support: float,
        max_gate: float,
        gap: float = math.radians(1.0),
        right_angle: float = 0.0,
    ) -> None:
        self.anchor, self.min_support, self.max_gate, self.gap = anchor, min_support, max_gate, gap
        self.right_angle = right_angle
        self._first: list[float] = []  # directions in the order they were first established
        self.frozen: list[tuple[float, float]] = []  # (direction, support when frozen)
        self.settled = False  # updated once at or past the anchor: the frozen set is taken
        self._live = (np.zeros(0), np.zeros(0))

    def update(self, map_dirs: FloatArray, map_lengths: FloatArray, distance: float) -> None:
        """Update from the map's established walls (:func:`wall_directions`) after ``distance``
        metres driven."""
        md = np.asarray(map_dirs, dtype=np.float64)
        ml = np.asarray(map_lengths, dtype=np.float64)
        if self.frozen:
            f = np.array([x for x, _ in self.frozen])
            far = np.abs(_wrap_half(md[:, None] - f[None, :])).min(axis=1) > self.max_gate
            md, ml = md[far], ml[far]
        dirs, support = direction_clusters(md, ml, self.gap)
        ok = support >= self.min_support
        if not self.settled:
            for x in dirs[ok].tolist():
                if self._rank(x) == len(self._first):  # a direction not established before
                    self._first.append(x)
        if distance < self.anchor:
            self._live = (dirs, support)
            return
        self.settled = True
        order = np.argsort([self._rank(x) for x in dirs[ok].tolist()], kind="stable")
        for x, s in zip(dirs[ok][order].tolist(), support[ok][order].tolist()):
            if (not self.frozen
                    or np.abs(_wrap_half(np.array([x - y for y, _ in self.frozen]))).min() > self.max_gate):
                self.frozen.append((self._square(x), s))
        self._live = (np.zeros(0), np.zeros(0))

    def _rank(self, x: float) -> int:
        """Index of the first-established direction within ``max_gate`` of ``x`` (the nearest),
        or the number of them when none is."""
        if not self._first:
            return 0
        d = np.abs(_wrap_half(np.array(self._first) - x))
        k = int(np.argmin(d))
        return k if d[k] <= self.max_gate else len(self._first)

    def _square(self, x: float) -> float:
        """``x`` moved to exactly perpendicular to the nearest frozen direction when within
        ``right_angle`` of it, else ``x``."""
        if not self.frozen or self.right_angle <= 0.0:
            return x
        perp = np.array([y + 0.5 * math.pi for y, _ in self.frozen])
        d = _wrap_half(perp - x)
        k = int(np.argmin(np.abs(d)))
        if abs(float(d[k])) > self.right_angle:
            return x
        return float(np.mod(x + float(d[k]), math.pi))

    def reference(self) -> tuple[FloatArray, FloatArray]:
        """Directions and their supports (metres) for :func:`compass_heading`."""
        if self.frozen:
            return np.array([x for x, _ in self.frozen]), np.array([s for _, s in self.frozen])
        return self._live


def compass_heading(
    scan_dirs: FloatArray,
    scan_lengths: FloatArray,
    map_dirs: FloatArray,
    map_lengths: FloatArray,
    heading_sigma: float,
    *,
    corner_sigma: float = 0.03,
    model_sigma: float = math.radians(0.15),
    min_support: float = 10.0,
    max_gate: float = math.radians(6.0),
) -> Heading | None:
    """The heading error that makes the scan's walls parallel to the map's (module docstring).

    Parameters
    ----------
    scan_dirs, scan_lengths : array
        The scan's long walls, directions in the map frame at the estimated pose.
    map_dirs, map_lengths : array
        The map's established walls (:func:`wall_directions`).
    heading_sigma : float
        Standard deviation (radians) of the heading estimate: sets the gate.
    corner_sigma, model_sigma, min_support, max_gate : float
        See the module docstring.

    Returns
    -------
    Heading or None
        None when no scan wall has a supported map direction within its gate.
    """
    scan_dirs = np.asarray(scan_dirs, dtype=np.float64).reshape(-1)
    scan_lengths = np.asarray(scan_lengths, dtype=np.float64).reshape(-1)
    map_dirs = np.asarray(map_dirs, dtype=np.float64).reshape(-1)
    map_lengths = np.asarray(map_lengths, dtype=np.float64).reshape(-1)
    if len(scan_dirs) == 0 or len(map_dirs) == 0:
        return None
    var_i = 2.0 * corner_sigma**2 / np.maximum(scan_lengths, 1e-6) ** 2
    gate = np.minimum(max_gate, 3.0 * np.sqrt(heading_sigma**2 + var_i))
    diff = _wrap_half(map_dirs[None, :] - scan_dirs[:, None])  # (scan, map)
    near = np.abs(diff) <= gate[:, None]
    support = (near * map_lengths[None, :]).sum(axis=1)
    res, var, lens = [], [], []
    for i in np.flatnonzero(support >= min_support).tolist():
        res.append(_weighted_median(diff[i, near[i]], map_lengths[near[i]]))
        var.append(float(var_i[i]))
        lens.append(float(scan_lengths[i]))
    if not res:
        return None
    r, v, ln = np.array(res), np.array(var), np.array(lens)
    w = 1.0 / v
    z = float(np.sum(w * r) / np.sum(w))
    ok = np.abs(r - z) <= 3.0 * np.sqrt(v + model_sigma**2)
    if not ok.any():
        return None
    if not ok.all():
        r, w, ln = r[ok], w[ok], ln[ok]
        z = float(np.sum(w * r) / np.sum(w))
    return Heading(offset=z, variance=float(1.0 / np.sum(w)) + model_sigma**2, walls=len(r),
                   length=float(ln.sum()))
