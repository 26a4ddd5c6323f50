"""The realistic simulated lidar: what real scans have and the clean ray caster lacks.

:func:`agents.sim.lidar.raycast` returns a wall's exact range plus 1 cm of Gaussian noise. Real
scanners (the CARMEN logs in ``../shared/data/carmen``, looked at in docs/experiments.md,
"A realistic simulated lidar") add, and this module simulates:

* **range noise that grows with range**: ``sigma = a + b * range``, readings rounded to the
  scanner's resolution (the logs hold whole centimetres);
* **beam dropouts**: single beams with no return, independently with probability ``p``;
* **max-range returns**: short bursts of neighbouring beams that report the scanner's maximum
  (no return) although a wall is in range (dark or specular patches);
* **glass**: some walls are panes that return only when a beam strikes them near normal
  incidence; other beams pass through to whatever lies behind (nothing, for a window);
* **clutter**: chairs and tables (their legs), boxes and round pillars or bins standing in the
  free space. The lidar sees them; the truth map (the walls) does not have them;
* **people**: discs about 0.3 m across walking back and forth along straight paths; where they
  are depends on the time of the scan.

Walls at odd angles are a property of the world rather than of the sensor:
``NAME@DEG`` turns any world (:func:`agents.sim.world.rotated_world`).

Two seeds, both explicit: the **scene** (which walls are glass, where the clutter stands, the
people's paths) comes from :func:`build_scene`'s ``seed`` -- a fleet's robots share it, as they
share the building -- and the **per-scan noise** (ranges, dropouts, bursts) from the ``rng``
passed to :func:`realistic_scan`, the robot's sensor generator. The same seeds give the same
scans. Nothing here changes the clean sensor: :func:`agents.sim.lidar.raycast` and its defaults
are untouched.

Geometry that the robot would bump into is left out: clutter within ``route_clearance`` of the
robot's route (:meth:`Scene.clear_of`; the route planner knows only the walls) and people
within ``person_clearance`` of the robot at the time of a scan (they step aside).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import LineString, Point

from agents.sim.lidar import LidarConfig, cast_ranges
from mapping.se2 import Pose

if TYPE_CHECKING:
    from agents.sim.world import World

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

__all__ = [
    "CLUTTER_KINDS",
    "RangeNoise",
    "RealLidarConfig",
    "Scene",
    "SceneConfig",
    "apply_noise",
    "build_scene",
    "realistic_scan",
]

#: Kinds of clutter, drawn with equal odds: chair (four 3 cm legs, 0.45 m apart), table (four
#: 5 cm legs of a 0.8 x 1.4 m top), box (0.3-0.8 m sides) and round (a pillar or a bin, radius
#: 0.1-0.3 m, as a 12-gon).
CLUTTER_KINDS = ("chair", "table", "box", "round")


def _check(name: str, value: float, lo: float, hi: float = math.inf, *, lo_open: bool = False) -> None:
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        bracket = "(" if lo_open else "["
        raise ValueError(f"{name} must be in {bracket}{lo:g}, {hi:g}], got {value!r}")


@dataclass(frozen=True)
class RangeNoise:
    """Per-beam effects of a real scanner, drawn anew for every scan.

    Defaults are a little worse than the CARMEN logs (docs/experiments.md, "A realistic
    simulated lidar": 0.4-0.6 cm within 3 m, 0.8-1.8 cm at 5-12 m; single lost beams 0.02-0.3 %
    of the beams that see a near wall; bursts of 2-8 lost beams on two logs of seven).

    Parameters
    ----------
    sigma0 : float
        Range noise standard deviation at zero range, metres (default 0.005).
    sigma_per_m : float
        Growth of the standard deviation per metre of range (default 0.002: 0.7 cm at 1 m,
        2.1 cm at 8 m).
    resolution : float
        Readings are rounded to this, metres (default 0.01; 0 for no rounding).
    p_dropout : float
        Probability that a beam returns nothing, independently of the others (default 0.005).
    p_burst : float
        Probability that a burst of max-range returns starts at a beam (default 0.002).
    burst_beams : float
        Mean length of a burst in beams, geometric (default 4).

    Raises
    ------
    ValueError
        A value out of its range.
    """

    sigma0: float = 0.005
    sigma_per_m: float = 0.002
    resolution: float = 0.01
    p_dropout: float = 0.005
    p_burst: float = 0.002
    burst_beams: float = 4.0

    def __post_init__(self) -> None:
        _check("sigma0", self.sigma0, 0.0)
        _check("sigma_per_m", self.sigma_per_m, 0.0)
        _check("resolution", self.resolution, 0.0)
        _check("p_dropout", self.p_dropout, 0.0, 1.0)
        _check("p_burst", self.p_burst, 0.0, 1.0)
        _check("burst_beams", self.burst_beams, 1.0)


@dataclass(frozen=True)
class SceneConfig:
    """What stands in the world besides its walls (:func:`build_scene`).

    Parameters
    ----------
    glass_share : float
        Probability that a wall at least ``glass_min_length`` long has a pane (default 0.2):
        a stretch of ``glass_length`` metres (at most the wall) at a random place along it,
        provided nothing lies within ``glass_depth`` behind the pane (a window to the
        outside, or glass between rooms), so that a pane never uncovers the back of a thick
        wall. Panes are in the truth (they are walls), the lidar mostly sees through them.
    glass_min_length, glass_depth : float
        Metres (defaults 1.0 and 1.0).
    glass_length : (float, float)
        Pane lengths drawn between these, metres (default 1-4).
    glass_return_deg : float
        A pane returns a beam that strikes it within this angle of its normal (default 10).
    clutter_per_100m2 : float
        Clutter objects per 100 m^2 of free space (default 2).
    people_per_100m2 : float
        People per 100 m^2 of free space (default 0.5; at least one when positive).
    person_radius : float
        Metres (default 0.15: a disc 0.3 m across).
    person_speed : (float, float)
        Walking speeds drawn between these, m/s (default 0.5-1.3).
    person_path : (float, float)
        Lengths of the straight paths walked back and forth, metres (default 3-10; shortened
        where a wall comes first, never below 1 m).
    route_clearance : float
        Clutter is left out where it comes within this of the robot's route, metres (default
        0.35; the route keeps 0.4 m from the walls).
    person_clearance : float
        A person within this of the robot at a scan is left out of it (default 0.3).

    Raises
    ------
    ValueError
        A value out of its range.
    """

    glass_share: float = 0.2
    glass_min_length: float = 1.0
    glass_depth: float = 1.0
    glass_length: tuple[float, float] = (1.0, 4.0)
    glass_return_deg: float = 10.0
    clutter_per_100m2: float = 2.0
    people_per_100m2: float = 0.5
    person_radius: float = 0.15
    person_speed: tuple[float, float] = (0.5, 1.3)
    person_path: tuple[float, float] = (3.0, 10.0)
    route_clearance: float = 0.35
    person_clearance: float = 0.3

    def __post_init__(self) -> None:
        _check("glass_share", self.glass_share, 0.0, 1.0)
        _check("glass_min_length", self.glass_min_length, 0.0)
        _check("glass_depth", self.glass_depth, 0.0)
        _check("glass_return_deg", self.glass_return_deg, 0.0, 90.0)
        _check("clutter_per_100m2", self.clutter_per_100m2, 0.0, 100.0)
        _check("people_per_100m2", self.people_per_100m2, 0.0, 100.0)
        _check("person_radius", self.person_radius, 0.0, 2.0, lo_open=True)
        _check("route_clearance", self.route_clearance, 0.0)
        _check("person_clearance", self.person_clearance, 0.0)
        pairs = (("person_speed", self.person_speed), ("person_path", self.person_path),
                 ("glass_length", self.glass_length))
        for name, (lo, hi) in pairs:
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
                raise ValueError(f"{name} must be (low, high) with 0 < low <= high, got {(lo, hi)!r}")


@dataclass(frozen=True)
class RealLidarConfig:
    """The realistic lidar: per-scan ``noise`` and the ``scene`` around the walls. Its
    defaults are the ``lidar-real`` sensor (:data:`agents.mapping_run.SENSORS`)."""

    noise: RangeNoise = field(default_factory=RangeNoise)
    scene: SceneConfig = field(default_factory=SceneConfig)


@dataclass(frozen=True, eq=False)
class Scene:
    """The walls and what else a realistic lidar sees in one world.

    Attributes
    ----------
    walls : (m, 2, 2) float
        The world's walls (its truth's segments), each pane cut out as a segment of its own.
    glass : (m,) bool
        Which of ``walls`` are panes.
    glass_min_sin : float
        ``cos(glass_return_deg)``: see :func:`agents.sim.lidar.cast_ranges`.
    clutter : (c, 2, 2) float
        The clutter objects' outlines as segments (not in the truth).
    clutter_object : (c,) int
        Object index of each clutter segment.
    objects : (k, 3) float
        Centre ``x, y`` and enclosing radius of each clutter object.
    kinds : tuple of str
        Each object's kind (:data:`CLUTTER_KINDS`).
    paths : (p, 2, 2) float
        Each person's path, walked from ``[i, 0]`` to ``[i, 1]`` and back.
    speed, phase : (p,) float
        Walking speed (m/s) and the distance along the back-and-forth walked at time 0 (m).
    person_radius, person_clearance : float
        As :class:`SceneConfig`.
    """

    walls: FloatArray
    glass: BoolArray
    glass_min_sin: float
    clutter: FloatArray
    clutter_object: IntArray
    objects: FloatArray
    kinds: tuple[str, ...]
    paths: FloatArray
    speed: FloatArray
    phase: FloatArray
    person_radius: float
    person_clearance: float

    def people_at(self, t: float) -> FloatArray:
        """The people's centres at time ``t`` (seconds), shape ``(p, 2)``."""
        if not len(self.paths):
            return np.zeros((0, 2))
        a, b = self.paths[:, 0], self.paths[:, 1]
        length = np.hypot(*(b - a).T)
        walked = np.mod(self.phase + self.speed * float(t), 2.0 * length)
        along = np.where(walked <= length, walked, 2.0 * length - walked)
        frac = np.where(length > 0, along / np.where(length > 0, length, 1.0), 0.0)
        return np.asarray(a + frac[:, None] * (b - a), dtype=np.float64)

    def people_segments(self, t: float, pose: Pose, reach: float) -> FloatArray:
        """Outlines (12-gons) of the people within ``reach`` of ``pose`` at time ``t`` and not
        within ``person_clearance`` of it, shape ``(12 q, 2, 2)``."""
        centres = self.people_at(t)
        if not len(centres):
            return np.zeros((0, 2, 2))
        dist = np.hypot(centres[:, 0] - pose.x, centres[:, 1] - pose.y)
        keep = (dist <= reach + self.person_radius) & (dist > self.person_radius + self.person_clearance)
        discs = [_circle(c, self.person_radius) for c in centres[keep]]
        return np.concatenate(discs) if discs else np.zeros((0, 2, 2))

    def clear_of(self, route: FloatArray, clearance: float) -> Scene:
        """The scene without the clutter objects that come within ``clearance`` metres of the
        polyline ``route`` (``(k, 2)``; the robot would drive into them)."""
        if not len(self.objects):
            return self
        pts = np.asarray(route, dtype=np.float64).reshape(-1, 2)
        line = LineString(pts) if len(pts) >= 2 else Point(pts[0])
        centres = shapely.points(self.objects[:, :2])
        dist = np.asarray(shapely.distance(line, centres), dtype=np.float64)
        keep = dist > self.objects[:, 2] + clearance
        new_index = np.cumsum(keep) - 1
        seg_keep = keep[self.clutter_object]
        return replace(
            self,
            clutter=self.clutter[seg_keep],
            clutter_object=new_index[self.clutter_object[seg_keep]].astype(np.int64),
            objects=self.objects[keep],
            kinds=tuple(k for k, ok in zip(self.kinds, keep) if ok),
        )


def _circle(centre: FloatArray, radius: float, sides: int = 12) -> FloatArray:
    ang = 2.0 * math.pi * np.arange(sides + 1) / sides
    ring = np.stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang)], axis=1)
    return np.stack([ring[:-1], ring[1:]], axis=1)


def _rectangle(centre: FloatArray, w: float, h: float, heading: float) -> FloatArray:
    c, s = math.cos(heading), math.sin(heading)
    corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h], [-w, -h]]) * 0.5
    ring = centre + corners @ np.array([[c, s], [-s, c]])
    return np.asarray(np.stack([ring[:-1], ring[1:]], axis=1), dtype=np.float64)


def _legs(centre: FloatArray, w: float, h: float, heading: float, leg: float) -> FloatArray:
    """Four square legs of side ``leg`` at the corners of a ``w x h`` top."""
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, s], [-s, c]])
    offsets = (np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) * 0.5) @ rot
    return np.concatenate([_rectangle(centre + o, leg, leg, heading) for o in offsets])


def _clutter_object(kind: str, centre: FloatArray, rng: np.random.Generator) -> tuple[FloatArray, float]:
    """Outline segments and enclosing radius of one object of ``kind`` at ``centre``."""
    heading = float(rng.uniform(0.0, math.pi))
    if kind == "chair":
        return _legs(centre, 0.45, 0.45, heading, 0.03), 0.45 / math.sqrt(2.0) + 0.03
    if kind == "table":
        return _legs(centre, 1.4, 0.8, heading, 0.05), math.hypot(0.7, 0.4) + 0.05
    if kind == "box":
        w, h = (float(v) for v in rng.uniform(0.3, 0.8, size=2))
        return _rectangle(centre, w, h, heading), 0.5 * math.hypot(w, h)
    radius = float(rng.uniform(0.1, 0.3))
    return _circle(centre, radius), radius


def _free_points(free: shapely.Geometry, n: int, rng: np.random.Generator) -> FloatArray:
    """``n`` points drawn uniformly inside ``free`` (rejection from its bounds)."""
    if n <= 0 or free.is_empty or free.area <= 0:
        return np.zeros((0, 2))
    x0, y0, x1, y1 = free.bounds
    shapely.prepare(free)
    got: list[FloatArray] = []
    have = 0
    for _ in range(1000):
        batch = max(64, 2 * (n - have))
        pts = np.stack([rng.uniform(x0, x1, batch), rng.uniform(y0, y1, batch)], axis=1)
        pts = pts[np.asarray(shapely.contains_xy(free, pts[:, 0], pts[:, 1]), dtype=bool)]
        got.append(pts)
        have += len(pts)
        if have >= n:
            break
    return np.concatenate(got)[:n] if got else np.zeros((0, 2))


def _panes(
    world: World, walls: FloatArray, config: SceneConfig, rng: np.random.Generator
) -> tuple[FloatArray, BoolArray]:
    """The walls with panes cut out: ``(segments, glass)``. Each wall (a thin wall's two
    opposite edges together) at least ``glass_min_length`` long gets, with probability
    ``glass_share``, one pane of a length drawn from ``glass_length`` (at most the wall's) at
    a random place along it -- provided the ``glass_depth`` behind the pane's middle (right of
    the edge: walls have free space on their left) crosses no other wall and no solid (the
    inside of a thick wall or an obstacle): a window to the outside, or glass between rooms.
    The draws are made for every wall whatever the outcome."""
    free = world.free_space
    building = shapely.unary_union([shapely.Polygon(p.exterior) for p in free.geoms])
    solid = building.difference(free)
    shapely.prepare(solid)
    lines = shapely.linestrings(walls)
    a, b = walls[:, 0], walls[:, 1]
    e = b - a
    length = np.hypot(e[:, 0], e[:, 1])
    panes: dict[tuple[float, ...], tuple[FloatArray, FloatArray]] = {}  # key -> pane ends (p, q)
    drawn: set[tuple[float, ...]] = set()
    for k in range(len(walls)):
        p, q = tuple(np.round(a[k], 6)), tuple(np.round(b[k], 6))
        key = (*min(p, q), *max(p, q))
        if key in drawn:  # the other edge of a thin wall
            continue
        drawn.add(key)
        u, plen, where = rng.random(), rng.uniform(*config.glass_length), rng.random()
        if length[k] < config.glass_min_length or u >= config.glass_share:
            continue
        plen = min(plen, float(length[k]))
        t0 = where * (length[k] - plen) / length[k]
        t1 = t0 + plen / length[k]
        mid = a[k] + 0.5 * (t0 + t1) * e[k]
        normal = np.array([e[k, 1], -e[k, 0]]) / length[k]  # right of the edge: behind the wall
        probe = LineString([mid + 1e-3 * normal, mid + config.glass_depth * normal])
        if solid.intersects(probe) or bool(np.any(shapely.intersects(lines, probe))):
            continue
        panes[key] = (a[k] + t0 * e[k], a[k] + t1 * e[k])
    segs: list[FloatArray] = []
    glass: list[bool] = []
    for k in range(len(walls)):
        p, q = tuple(np.round(a[k], 6)), tuple(np.round(b[k], 6))
        pane = panes.get((*min(p, q), *max(p, q)))
        if pane is None:
            segs.append(walls[k])
            glass.append(False)
            continue
        g0, g1 = pane
        if np.dot(g1 - g0, e[k]) < 0:  # the twin of a thin wall runs the other way
            g0, g1 = g1, g0
        for piece, is_glass in (((a[k], g0), False), ((g0, g1), True), ((g1, b[k]), False)):
            if float(np.hypot(*(piece[1] - piece[0]))) > 1e-9:
                segs.append(np.stack(piece))
                glass.append(is_glass)
    return np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2), np.asarray(glass, dtype=bool)


def _walkable(walk: shapely.Geometry, a: FloatArray, b: FloatArray, least: float = 1.0) -> FloatArray | None:
    """The end of the longest straight walk from ``a`` towards ``b`` inside ``walk`` (at least
    ``least`` metres), or None."""
    piece = LineString([a, b]).intersection(walk)
    parts = getattr(piece, "geoms", [piece])
    for part in parts:
        if isinstance(part, LineString) and not part.is_empty and part.distance(Point(a)) < 1e-9:
            coords = np.asarray(part.coords, dtype=np.float64)
            end = coords[np.argmax(np.hypot(*(coords - a).T))]
            if float(np.hypot(*(end - a))) >= least:
                return end
    return None


def build_scene(world: World, config: SceneConfig, seed: int) -> Scene:
    """Glass, clutter and people for ``world`` (an :class:`agents.sim.world.World`), drawn from
    ``seed`` alone: the same world, configuration and seed give the same scene.

    Raises
    ------
    ValueError
        ``world`` has no walls.
    """
    from agents.sim.world import World

    if not isinstance(world, World):  # (a caller without type checking)
        raise ValueError(f"world must be an agents.sim.world.World, got {type(world).__name__}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE4E]))
    walls = np.asarray(world.truth.segments(), dtype=np.float64).reshape(-1, 2, 2)
    if not len(walls):
        raise ValueError(f"world {world.name!r} has no walls")

    segments, glass = _panes(world, walls, config, rng)

    free = world.free_space
    area = float(free.area)

    # clutter: objects whose enclosing disc stays 5 cm off the walls and off each other
    n_clutter = round(config.clutter_per_100m2 * area / 100.0)
    kinds_drawn = rng.integers(0, len(CLUTTER_KINDS), size=n_clutter)
    centres = _free_points(free.buffer(-0.1), 4 * n_clutter, rng)
    segs: list[FloatArray] = []
    owner: list[IntArray] = []
    objects: list[tuple[float, float, float]] = []
    kinds: list[str] = []
    walls_geom = world.walls()
    for k, kind_i in enumerate(kinds_drawn):
        kind = CLUTTER_KINDS[int(kind_i)]
        for c in centres[k::max(1, n_clutter)][:4]:  # up to four tries per object
            outline, radius = _clutter_object(kind, c, rng)
            if walls_geom.distance(Point(c)) < radius + 0.05:
                continue
            if any(math.hypot(c[0] - ox, c[1] - oy) < radius + orad + 0.1 for ox, oy, orad in objects):
                continue
            owner.append(np.full(len(outline), len(objects), dtype=np.int64))
            segs.append(outline)
            objects.append((float(c[0]), float(c[1]), radius))
            kinds.append(kind)
            break

    # people: straight paths with 0.3 m to spare from the walls, walked back and forth
    n_people = 0
    if config.people_per_100m2 > 0:
        n_people = max(1, round(config.people_per_100m2 * area / 100.0))
    walk = free.buffer(-(config.person_radius + 0.15))
    for thin in world.thin_walls:
        walk = walk.difference(thin.buffer(config.person_radius + 0.15))
    shapely.prepare(walk)
    starts = _free_points(walk, 20 * n_people, rng)
    paths: list[FloatArray] = []
    for k in range(n_people):
        for a in starts[k::max(1, n_people)][:20]:
            length = float(rng.uniform(*config.person_path))
            ang = float(rng.uniform(0.0, 2.0 * math.pi))
            b = _walkable(walk, a, a + length * np.array([math.cos(ang), math.sin(ang)]))
            if b is not None:
                paths.append(np.stack([a, b]))
                break
    n_walking = len(paths)
    speed = rng.uniform(*config.person_speed, size=n_walking)
    lengths = np.array([float(np.hypot(*(p[1] - p[0]))) for p in paths])
    phase = rng.uniform(0.0, 1.0, size=n_walking) * 2.0 * lengths

    return Scene(
        walls=segments,
        glass=glass,
        glass_min_sin=math.cos(math.radians(config.glass_return_deg)),
        clutter=np.concatenate(segs) if segs else np.zeros((0, 2, 2)),
        clutter_object=np.concatenate(owner) if owner else np.zeros(0, dtype=np.int64),
        objects=np.asarray(objects, dtype=np.float64).reshape(-1, 3),
        kinds=tuple(kinds),
        paths=np.asarray(paths, dtype=np.float64).reshape(-1, 2, 2),
        speed=np.asarray(speed, dtype=np.float64),
        phase=np.asarray(phase, dtype=np.float64),
        person_radius=config.person_radius,
        person_clearance=config.person_clearance,
    )


def apply_noise(
    exact: FloatArray, noise: RangeNoise, max_range: float, rng: np.random.Generator
) -> FloatArray:
    """A real scanner's readings of the ``exact`` ranges (``inf``: no return).

    In this order: Gaussian range noise of ``sigma0 + sigma_per_m * range`` (never below 0),
    rounding to ``resolution``, dropouts, bursts of max-range returns; a reading at or beyond
    ``max_range`` is no return (``inf``), as in :func:`agents.sim.lidar.raycast`. The draws
    depend only on the number of beams and of returns, so the same ``rng`` state and ranges
    give the same readings.
    """
    out = np.array(exact, dtype=np.float64).reshape(-1)
    n = len(out)
    seen = np.isfinite(out)
    r = out[seen]
    noisy = r + rng.normal(0.0, 1.0, size=len(r)) * (noise.sigma0 + noise.sigma_per_m * r)
    noisy = np.maximum(noisy, 0.0)
    if noise.resolution > 0:
        noisy = np.round(noisy / noise.resolution) * noise.resolution
    out[seen] = noisy
    out[rng.random(n) < noise.p_dropout] = np.inf
    starts = np.flatnonzero(rng.random(n) < noise.p_burst)
    if len(starts):
        lengths = rng.geometric(1.0 / noise.burst_beams, size=len(starts))
        for k, m in zip(starts, lengths):
            out[k:k + int(m)] = np.inf
    out[out >= max_range] = np.inf
    return out


def realistic_scan(
    scene: Scene, pose: Pose, t: float, config: LidarConfig, noise: RangeNoise, rng: np.random.Generator
) -> FloatArray:
    """Readings of a realistic lidar at ``pose`` and time ``t`` in ``scene``.

    Exact ranges against the walls (glass returning near normal incidence only), the clutter
    and the people at ``t`` (:func:`agents.sim.lidar.cast_ranges`), then :func:`apply_noise`
    with ``rng``. ``config`` gives the beams, field of view and maximum range (its ``sigma`` is
    replaced by ``noise``).

    Returns
    -------
    (beams,) float64
        Range per beam in metres, ``np.inf`` for no return.
    """
    people = scene.people_segments(t, pose, config.max_range)
    segments = np.concatenate([scene.walls, scene.clutter, people])
    glass = np.zeros(len(segments), dtype=bool)
    glass[: len(scene.walls)] = scene.glass
    exact = cast_ranges(segments, pose, config, glass=glass, glass_min_sin=scene.glass_min_sin)
    return apply_noise(exact, noise, config.max_range, rng)
