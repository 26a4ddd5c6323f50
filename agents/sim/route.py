"""Coverage routes that keep the walls in sensing range.

:func:`plan_route` makes one collision-free polyline from which every wall is seen from nearby.
What a mapping robot must cover is the *walls*, not the floor: a floor-covering route sends it
through the middle of large halls where an 8 m sensor sees nothing, its pose drifts, and the
walls it maps next are misplaced. So:

1. **Navigable region.** Points at least ``clearance`` from every wall (the free space's
   boundary and the thin walls), computed with shapely buffers.
2. **Grid graph.** Cell centres of a square grid (resolution ``h``, origin jittered by the rng)
   that lie in the navigable region, 8-connected; a diagonal step needs both of its orthogonal
   neighbours (no corner cutting). The grid's region is shrunk by an extra ``h**2 / (4 c)``: a
   step of length ``L <= h*sqrt(2)`` whose two ends are ``c + L**2 / (8 c)`` from a convex
   obstacle cannot come nearer than ``c`` to it, so every grid step keeps the clearance; and
   ``h < 1.4 c`` so that no step can jump a thin wall. For the tour, a step where no wall is
   within ``0.75 sensor_range`` (blind) costs twice its length, so travel between waypoints
   goes along walls rather than across empty halls when that is not much longer.
3. **Waypoints: a wall cover.** Targets are points every ``min(1, spacing / 3)`` metres along
   every wall face (the truth's directed edges), just inside the free space. Candidates are
   grid nodes, one per cell of side ``max(spacing / 4, h)``. A candidate *sees* a target when
   it is within ``spacing`` (the coverage radius), on the face's free side at 10 degrees or more
   from grazing, and the straight segment between them crosses no wall. A greedy set cover
   picks candidates until every target that some candidate sees is seen (the classic
   ``ln n``-approximation); targets no candidate sees within ``spacing`` get a second pass with
   the full ``sensor_range``.
4. **Tour.** A greedy nearest-neighbour tour over the waypoints by (weighted) grid-path distance
   (bounded ``scipy.sparse.csgraph.dijkstra`` from the current node, widened until an
   unvisited waypoint is found) with a little momentum (see :func:`_tour`), the shortest grid
   paths joining them. Waypoints not reachable from the start (e.g. behind a doorway narrower
   than ``2 * clearance``) are left out.
5. **Smoothing.** The whole tour is string-pulled: from each kept vertex, jump to the farthest
   later vertex (within 96) that a straight segment reaches inside the navigable region and
   within ``0.75 sensor_range`` of a wall, passing within ``spacing / 2`` of every waypoint it
   skips. So the route passes within ``1.5 spacing`` of every wall point it covers, well inside
   the sensing range, and zigzags between waypoints on both sides of a corridor straighten.
6. **Rounded corners.** Each corner becomes a circular arc (radius up to 1.5 m, passing at most
   0.5 m from the corner, inside the navigable region): odometry's heading error grows with the
   angle turned in one step (:class:`agents.sim.motion.OdometryNoise`), so a 90-degree turn
   spread over several steps costs a few times less heading error than one turned at once.

``spacing`` is the coverage radius: ``clip(sqrt(free area) / 12, 2.5, sensor_range / 2)`` by
default, i.e. half the 8 m sensing range in large worlds (walls are seen from 4 m, where a
corner sensor or a lidar sees them well) and 2.5 m in small ones (so that a room is still seen
from several places).

A world with its own route (``World.route``) uses it instead unless ``use_world_route=False``.
Randomness (grid origin, the start node when none is given) comes only from the ``rng``
argument: the same seed gives the same route.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from agents.sim.world import World

__all__ = [
    "navigable_region", "plan_fleet_routes", "plan_route", "plan_routes", "route_clearance", "route_length",
    "split_route",
]

FloatArray = NDArray[np.float64]

# Buffers approximate arcs by chords; with this many segments per quarter circle a chord is
# inside the true arc by at most c * (1 - cos(pi / 64)) = 0.0012 c, which the planner adds.
_QUAD_SEGS = 16
_MAX_GRID_CELLS = 150_000
_TARGET_OFFSET = 0.05  # wall targets sit this far into the free space
_ANCHOR_TOL = 0.5  # the smoothed route passes within this many coverage radii of each waypoint
_BLIND_FRACTION = 0.75  # farther than this times the sensing range from every wall: blind
_BLIND_COST = 1.0  # a blind metre costs this much more than a sighted one
_ROUND_RADIUS = 1.5  # corners are rounded into arcs of at most this radius (metres)
_ROUND_CUT = 0.5  # ... passing at most this far from the corner (metres)
_MIN_SIN = math.sin(math.radians(10.0))  # a wall face is seen at 10 degrees or more


def navigable_region(world: World, clearance: float) -> Any:
    """The points at distance >= ``clearance`` from every wall (a shapely geometry), made a
    little smaller than exact so that its polygonal arcs never come nearer than ``clearance``."""
    if not (clearance >= 0 and math.isfinite(clearance)):
        raise ValueError(f"clearance must be a finite number >= 0, got {clearance}")
    c = clearance / math.cos(math.pi / (4 * _QUAD_SEGS)) + 1e-6
    region = world.free_space.buffer(-c, quad_segs=_QUAD_SEGS) if c > 0 else world.free_space
    if world.thin_walls:
        walls = shapely.MultiLineString(list(world.thin_walls)).buffer(max(c, 1e-6), quad_segs=_QUAD_SEGS)
        region = region.difference(walls)
    shapely.prepare(region)
    return region


def route_length(route: FloatArray) -> float:
    """Length of a polyline ``(k, 2)`` in metres."""
    r = np.asarray(route, dtype=np.float64).reshape(-1, 2)
    return float(np.hypot(*np.diff(r, axis=0).T).sum()) if len(r) > 1 else 0.0


def route_clearance(world: World, route: FloatArray) -> float:
    """Smallest distance from the route to any wall (exact); ``-inf`` if any part of it is
    outside the free space."""
    r = np.asarray(route, dtype=np.float64).reshape(-1, 2)
    geom = shapely.LineString(r) if len(r) > 1 else shapely.Point(r[0])
    if not world.free_space.covers(geom):
        return -math.inf
    return float(shapely.distance(world.walls(), geom))


@dataclass(frozen=True)
class _Grid:
    xy: FloatArray  # (N, 2) node positions
    graph: csr_matrix  # symmetric, weights in metres


def _grid(world: World, clearance: float, h: float, rng: np.random.Generator) -> _Grid:
    """Navigable grid nodes and their 8-connected graph (see the module docstring, step 2)."""
    extra = h * h / (4.0 * clearance) if clearance > 0 else h
    region = navigable_region(world, clearance + extra)
    xmin, ymin, xmax, ymax = world.bounds()
    off = rng.uniform(0.0, h, size=2)
    xs = np.arange(xmin + off[0], xmax, h)
    ys = np.arange(ymin + off[1], ymax, h)
    gx, gy = np.meshgrid(xs, ys)  # (ny, nx)
    inside = np.asarray(shapely.contains_xy(region, gx.ravel(), gy.ravel()), dtype=bool).reshape(gx.shape)
    ny, nx = inside.shape
    ids = -np.ones(inside.shape, dtype=np.int64)
    ids[inside] = np.arange(int(inside.sum()))
    rows: list[NDArray[np.int64]] = []
    cols: list[NDArray[np.int64]] = []
    wts: list[FloatArray] = []

    def link(dy: int, dx: int, w: float, need: NDArray[np.bool_] | None = None) -> None:
        # node (r, c) -> (r + dy, c + dx), dy >= 0
        src = (slice(0, ny - dy), slice(0, nx - dx) if dx >= 0 else slice(-dx, nx))
        dst = (slice(dy, ny), slice(dx, nx) if dx >= 0 else slice(0, nx + dx))
        ok = inside[src] & inside[dst]
        if need is not None:
            ok &= need
        rows.append(ids[src][ok])
        cols.append(ids[dst][ok])
        wts.append(np.full(int(ok.sum()), w))

    link(0, 1, h)
    link(1, 0, h)
    # diagonals: cell (r, c) -> (r+1, c+1) needs (r, c+1) and (r+1, c); (r, c) -> (r+1, c-1)
    # needs (r, c-1) and (r+1, c)
    d = h * math.sqrt(2.0)
    need_pp = inside[:-1, 1:] & inside[1:, :-1]  # aligned with a = inside[:-1, :-1]
    link(1, 1, d, need_pp)
    need_pm = inside[:-1, :-1] & inside[1:, 1:]  # aligned with a = inside[:-1, 1:]
    link(1, -1, d, need_pm)
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    w = np.concatenate(wts)
    n = int(inside.sum())
    graph = csr_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))),
                       shape=(n, n))
    return _Grid(xy=np.column_stack([gx[inside], gy[inside]]), graph=graph)


def _wall_distance(world: World, xy: FloatArray, step: float = 0.25) -> FloatArray:
    """Distance (to within ``step / 2``) from each point to the nearest wall."""
    from scipy.spatial import cKDTree

    seg = world.truth.segments()
    if len(seg) == 0 or len(xy) == 0:
        return np.full(len(xy), math.inf)
    d = seg[:, 1] - seg[:, 0]
    count = np.maximum(1, np.ceil(np.hypot(d[:, 0], d[:, 1]) / step).astype(np.int64)) + 1
    owner = np.repeat(np.arange(len(seg)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    t = k / (count[owner] - 1)
    pts = seg[owner, 0] + t[:, None] * d[owner]
    dist, _ = cKDTree(pts).query(xy)
    return np.asarray(dist, dtype=np.float64)


def _penalise_blind(grid: _Grid, world: World, sensor_range: float) -> _Grid:
    """The grid with the cost of travel where no wall is in sensing range raised (module
    docstring, step 2): a step's cost is its length times ``1 + _BLIND_COST`` per blind end / 2,
    blind meaning farther than ``_BLIND_FRACTION * sensor_range`` from every wall."""
    blind = (_wall_distance(world, grid.xy) > _BLIND_FRACTION * sensor_range).astype(np.float64)
    g = grid.graph.tocoo()
    w = g.data * (1.0 + 0.5 * _BLIND_COST * (blind[g.row] + blind[g.col]))
    return _Grid(xy=grid.xy, graph=csr_matrix((w, (g.row, g.col)), shape=g.shape))


def _default_spacing(world: World, sensor_range: float) -> float:
    return float(np.clip(math.sqrt(world.free_space.area) / 12.0, 2.5, 0.5 * sensor_range))


def _default_resolution(world: World, clearance: float) -> float:
    xmin, ymin, xmax, ymax = world.bounds()
    h = math.sqrt((xmax - xmin) * (ymax - ymin) / _MAX_GRID_CELLS)
    h = max(h, 0.1)
    if clearance > 0:
        h = min(h, 1.4 * clearance)  # a grid step is shorter than 2 * clearance: it cannot cross a wall
    return h


def _wall_targets(world: World, step: float) -> tuple[FloatArray, FloatArray]:
    """Points every ``step`` metres along every wall face (the truth's directed edges), moved
    :data:`_TARGET_OFFSET` into the free space on the face's left, and the faces' left normals."""
    seg = world.truth.segments()
    if len(seg) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    d = seg[:, 1] - seg[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = length > 1e-9
    seg, d, length = seg[ok], d[ok], length[ok]
    u = d / length[:, None]
    normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
    count = np.maximum(1, np.ceil(length / step).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    t = (k + 0.5) / count[owner] * length[owner]  # centres of equal pieces: corners are not targets
    pts = seg[owner, 0] + t[:, None] * u[owner] + _TARGET_OFFSET * normal[owner]
    free = world.is_free(pts)
    return pts[free], normal[owner][free]


def _candidates(grid: _Grid, cell: float) -> NDArray[np.int64]:
    """One grid node per square cell of side ``cell`` (the node nearest to the cell's centre)."""
    xy = grid.xy
    org = xy.min(axis=0)
    c = np.floor((xy - org) / cell).astype(np.int64)
    cid = c[:, 0] * (int(c[:, 1].max()) + 2) + c[:, 1]
    centre = org + (c + 0.5) * cell
    d = np.hypot(*(xy - centre).T)
    order = np.lexsort((np.arange(len(xy)), d, cid))
    _, first = np.unique(cid[order], return_index=True)
    return np.sort(order[first]).astype(np.int64)


def _sight_pairs(
    world: World, targets: FloatArray, normals: FloatArray, cand_xy: FloatArray, radius: float, min_sin: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(target, candidate)`` pairs within ``radius`` where the candidate sees the target: the
    straight segment between them crosses no wall and meets the wall face at an angle whose sine
    is at least ``min_sin`` (a face seen at a grazing angle is barely seen)."""
    from scipy.spatial import cKDTree

    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if len(targets) == 0 or len(cand_xy) == 0:
        return empty
    pairs = cKDTree(targets).query_ball_tree(cKDTree(cand_xy), r=radius)
    cnt = np.fromiter((len(p) for p in pairs), dtype=np.int64, count=len(pairs))
    if cnt.sum() == 0:
        return empty
    ti = np.repeat(np.arange(len(targets), dtype=np.int64), cnt)
    ci = np.fromiter(itertools.chain.from_iterable(pairs), dtype=np.int64, count=int(cnt.sum()))
    v = cand_xy[ci] - targets[ti]
    dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-12)
    facing = np.einsum("ij,ij->i", v, normals[ti]) >= min_sin * dist
    ti, ci = ti[facing], ci[facing]
    if len(ti) == 0:
        return empty
    walls = world.walls()
    shapely.prepare(walls)
    segs = shapely.linestrings(np.stack([targets[ti], cand_xy[ci]], axis=1))
    clear = ~np.asarray(shapely.intersects(walls, segs), dtype=bool)
    return ti[clear], ci[clear]


def _greedy_cover(ti: NDArray[np.int64], ci: NDArray[np.int64], n_targets: int, n_cand: int) -> list[int]:
    """Greedy set cover: candidates (indexes) that together see every target some candidate sees,
    each chosen to see the most targets not yet seen (ties: the lowest index)."""
    if len(ti) == 0:
        return []
    by_cand = csr_matrix((np.ones(len(ti), dtype=np.int8), (ci, ti)), shape=(n_cand, n_targets))
    by_target = by_cand.T.tocsr()
    gain = np.asarray(by_cand.sum(axis=1)).ravel().astype(np.int64)
    covered = np.zeros(n_targets, dtype=bool)
    chosen: list[int] = []
    while True:
        c = int(np.argmax(gain))
        if gain[c] <= 0:
            break
        chosen.append(c)
        new = by_cand.indices[by_cand.indptr[c] : by_cand.indptr[c + 1]]
        new = new[~covered[new]]
        covered[new] = True
        # every candidate that also saw a newly covered target gains one less
        hit = np.concatenate([by_target.indices[by_target.indptr[t] : by_target.indptr[t + 1]]
                              for t in new.tolist()])
        np.subtract.at(gain, hit, 1)
    return chosen


def _wall_waypoints(
    world: World, grid: _Grid, radius: float, sensor_range: float, h: float
) -> NDArray[np.int64]:
    """Node indices of the wall-coverage waypoints (module docstring, step 3), sorted."""
    step = min(1.0, radius / 3.0)
    targets, normals = _wall_targets(world, step)
    cand = _candidates(grid, max(radius / 4.0, h))
    cxy = grid.xy[cand]
    chosen: list[int] = []
    todo = np.ones(len(targets), dtype=bool)
    for r in (radius, sensor_range):
        if not todo.any() or r <= 0:
            continue
        idx = np.flatnonzero(todo)
        ti, ci = _sight_pairs(world, targets[idx], normals[idx], cxy, r, _MIN_SIN)
        pick = _greedy_cover(ti, ci, len(idx), len(cxy))
        chosen += pick
        seen = np.zeros(len(idx), dtype=bool)
        seen[ti[np.isin(ci, pick)]] = True
        todo[idx[seen]] = False
    return np.array(sorted({int(cand[c]) for c in chosen}), dtype=np.int64)


class _Walker:
    """One robot's greedy nearest-neighbour walk over shared waypoints (module step 4).

    From the current node, the next waypoint is the unvisited one with the smallest grid-path
    distance minus ``spacing / 4`` times the cosine of the turn it asks for (a little momentum,
    so that rows are swept in order instead of zigzagging); waypoints within ``0.3 spacing`` of
    a path driven count as visited (in ``todo``, which walkers may share). ``clock`` is the
    grid-path cost driven so far.
    """

    def __init__(self, grid: _Grid, start: int, spacing: float) -> None:
        self.grid = grid
        self.start = start
        self.cur = start
        self.spacing = spacing
        self.heading = np.zeros(2)
        self.clock = 0.0
        self.legs: list[NDArray[np.int64]] = []

    def step(self, way: NDArray[np.int64], todo: NDArray[np.bool_], visit: Callable[..., None]) -> bool:
        """Drive to the next waypoint of ``way`` still in ``todo``; False when none is reachable."""
        grid, sp = self.grid, self.spacing
        limit = 2.5 * sp
        while True:
            dist, pred = dijkstra(grid.graph, indices=self.cur, limit=limit, return_predecessors=True)
            cand = way[todo & np.isfinite(dist[way])]
            if len(cand) or np.isinf(limit):
                break
            limit = limit * 4.0 if limit < 1e6 else math.inf
        if not len(cand):
            return False
        dcand = dist[cand]
        near = cand[dcand <= dcand.min() + 0.5 * sp]
        vec = grid.xy[near] - grid.xy[self.cur]
        norm = np.maximum(np.hypot(*vec.T), 1e-12)
        score = dist[near] - 0.25 * sp * (vec @ self.heading) / norm
        target = int(near[np.argmin(score)])
        path = [target]
        while path[-1] != self.cur:
            path.append(int(pred[path[-1]]))
        leg = np.array(path[::-1], dtype=np.int64)
        visit(leg, target)
        step = grid.xy[target] - grid.xy[leg[max(0, len(leg) - 4)]]
        self.heading = step / max(float(np.hypot(*step)), 1e-12)
        self.clock += float(dist[target])
        self.legs.append(leg)
        self.cur = target
        return True


def _visitor(
    grid: _Grid, way: NDArray[np.int64], todo: NDArray[np.bool_], spacing: float
) -> Callable[..., None]:
    """A function ``visit(nodes, target)`` that marks in ``todo`` the waypoints within ``0.3
    spacing`` of ``nodes`` and the ``target`` itself."""
    from scipy.spatial import cKDTree

    tree = cKDTree(grid.xy[way])
    is_way = -np.ones(grid.xy.shape[0], dtype=np.int64)
    is_way[way] = np.arange(len(way))

    def visit(nodes: NDArray[np.int64], target: int | None = None) -> None:
        for hits in tree.query_ball_point(grid.xy[nodes], r=0.3 * spacing):
            todo[hits] = False
        if target is not None:
            todo[is_way[target]] = False

    return visit


def _tour(grid: _Grid, start: int, way: NDArray[np.int64], spacing: float) -> list[NDArray[np.int64]]:
    """Node-index legs of one robot's greedy tour over the waypoints (:class:`_Walker`).
    Waypoints not reachable from the start are dropped."""
    todo = np.ones(len(way), dtype=bool)
    visit = _visitor(grid, way, todo, spacing)
    walker = _Walker(grid, start, spacing)
    visit(np.array([start]))
    while todo.any() and walker.step(way, todo, visit):
        pass
    return walker.legs


def _fleet_tours(
    grid: _Grid, starts: list[int], way: NDArray[np.int64], spacing: float
) -> list[list[NDArray[np.int64]]]:
    """Node-index legs of one tour per start that share the waypoints out, then go on.

    **Shared phase:** the robot that has driven least so far (grid-path cost, ties by index)
    takes the next waypoint of its greedy walk among those no robot has visited, until every
    reachable waypoint is visited, so the robots cover the world in about a fleet's share of
    the time each, and each sweeps the part nearest to where it is. **Own phase:** each robot
    then walks on over the waypoints it has not passed itself (the others' parts), so that
    routes do not end early and the robots' maps come to share walls.
    """
    todo = np.ones(len(way), dtype=bool)
    visit = _visitor(grid, way, todo, spacing)
    walkers = [_Walker(grid, s, spacing) for s in starts]
    for s in starts:
        visit(np.array([s]))
    active = list(range(len(walkers)))
    while todo.any() and active:
        i = min(active, key=lambda k: (walkers[k].clock, k))
        if not walkers[i].step(way, todo, visit):
            active.remove(i)
    for w in walkers:
        own = np.ones(len(way), dtype=bool)
        mark = _visitor(grid, way, own, spacing)
        for nodes in [np.array([w.start]), *w.legs]:  # what it drove itself
            mark(nodes)
        while own.any() and w.step(way, own, mark):
            pass
    return [w.legs for w in walkers]


def _straight_runs(p: FloatArray) -> FloatArray:
    """Drop interior points where a grid path goes straight on."""
    if len(p) <= 2:
        return p
    d1 = p[1:-1] - p[:-2]
    d2 = p[2:] - p[1:-1]
    cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    keep = np.ones(len(p), dtype=bool)
    keep[1:-1] = np.abs(cross) > 1e-12
    return p[keep]


def _pull(
    p: FloatArray,
    region: Any,
    window: int = 96,
    anchors: NDArray[np.bool_] | None = None,
    tol: float = 0.0,
) -> FloatArray:
    """String-pull a polyline inside ``region`` keeping its end points: from each kept vertex,
    jump to the farthest vertex within ``window`` that a straight segment inside ``region``
    reaches and that passes within ``tol`` of every ``anchors`` vertex it skips."""
    if len(p) <= 2:
        return p
    out = [p[0]]
    i = 0
    anc = np.flatnonzero(anchors) if anchors is not None else np.zeros(0, dtype=np.int64)
    while i < len(p) - 1:
        js = np.arange(i + 1, min(len(p), i + 1 + window))
        segs = np.stack([np.broadcast_to(p[i], (len(js), 2)), p[js]], axis=1)
        ok = np.asarray(shapely.covers(region, shapely.linestrings(segs)), dtype=bool)
        lo = np.searchsorted(anc, i, side="right")
        hi = np.searchsorted(anc, js[-1], side="left")
        for a in anc[lo:hi].tolist():  # segments that skip waypoint a must pass near it
            later = js > a
            if not later.any():
                break
            d = p[js[later]] - p[i]
            w = p[a] - p[i]
            t = np.clip((d @ w) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
            near = np.hypot(*(p[i] + t[:, None] * d - p[a]).T) <= tol
            ok[later] &= near
        ok[0] = True  # a grid step keeps the clearance by construction
        i = int(js[np.flatnonzero(ok)[-1]])
        out.append(p[i])
    return np.array(out)


def _setup(
    world: World,
    rng: np.random.Generator,
    clearance: float,
    spacing: float | None,
    resolution: float | None,
    sensor_range: float,
) -> tuple[_Grid, float, float]:
    """The grid, the coverage radius and the grid's cell size, with the parameters checked."""
    if not (clearance > 0 and math.isfinite(clearance)):
        raise ValueError(f"clearance must be positive, got {clearance}")
    if not (sensor_range > 0 and math.isfinite(sensor_range)):
        raise ValueError(f"sensor_range must be positive, got {sensor_range}")
    sp = _default_spacing(world, sensor_range) if spacing is None else float(spacing)
    if not (sp > 0 and math.isfinite(sp)):
        raise ValueError(f"spacing must be positive, got {spacing}")
    h = _default_resolution(world, clearance) if resolution is None else float(resolution)
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    grid = _grid(world, clearance, h, rng)
    if grid.xy.shape[0] == 0:
        raise ValueError(f"world {world.name!r} has no room for a robot with clearance {clearance} m")
    return grid, sp, h


def _start_of(world: World, grid: _Grid, start: tuple[float, float]) -> int:
    sx, sy = float(start[0]), float(start[1])
    if not bool(world.is_free(np.array([sx, sy]))):
        raise ValueError(f"start ({sx:g}, {sy:g}) is not in the free space of {world.name!r}")
    return _start_node(world, grid, sx, sy)


def _smoothing_regions(world: World, clearance: float, sensor_range: float) -> tuple[Any, Any]:
    """Where smoothing may go: the navigable region, and the part of it within sight of a wall
    (smoothing must not cut through the blind areas that the grid path went around)."""
    nav = navigable_region(world, clearance)
    check = shapely.intersection(nav, world.walls().buffer(_BLIND_FRACTION * sensor_range, quad_segs=4))
    shapely.prepare(check)
    return nav, check


def _smooth(
    grid: _Grid, start: int, node_legs: list[NDArray[np.int64]], regions: tuple[Any, Any], sp: float
) -> list[FloatArray]:
    """Module steps 5 and 6: the legs string-pulled and their corners rounded inside
    ``regions`` (:func:`_smoothing_regions`)."""
    if not node_legs:
        return [grid.xy[[start]]]
    nav, check = regions
    pts = [grid.xy[node_legs[0][:1]]] + [_straight_runs(grid.xy[leg])[1:] for leg in node_legs]
    anchor = [np.ones(1, dtype=bool)] + [np.arange(len(q)) == len(q) - 1 for q in pts[1:]]
    path = np.concatenate(pts)
    path = _pull(path, check, anchors=np.concatenate(anchor), tol=_ANCHOR_TOL * sp)
    return [_round_corners(path, nav, _ROUND_RADIUS)]


def _plan(
    world: World,
    rng: np.random.Generator,
    start: tuple[float, float] | None,
    clearance: float,
    spacing: float | None,
    resolution: float | None,
    sensor_range: float,
) -> list[FloatArray]:
    """Simplified legs ``[(k_i, 2)]`` of the coverage route (consecutive legs share ends)."""
    grid, sp, h = _setup(world, rng, clearance, spacing, resolution, sensor_range)
    s = int(rng.integers(grid.xy.shape[0])) if start is None else _start_of(world, grid, start)
    way = _wall_waypoints(world, grid, sp, max(sp, sensor_range), h)
    node_legs = _tour(_penalise_blind(grid, world, sensor_range), s, way, sp)
    return _smooth(grid, s, node_legs, _smoothing_regions(world, clearance, sensor_range), sp)


def _round_corners(p: FloatArray, region: Any, radius: float) -> FloatArray:
    """Replace each corner of a polyline by a circular arc tangent to its two segments (module
    docstring, step 6): radius ``radius`` or less, so that the arc's tangent points stay within
    the middle of each segment, the arc passes within :data:`_ROUND_CUT` of the corner and stays
    inside ``region`` (else the corner stays sharp)."""
    if len(p) <= 2 or radius <= 0:
        return p
    seg = np.diff(p, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    out = [p[0]]
    for k in range(1, len(p) - 1):
        u1, u2 = seg[k - 1] / length[k - 1], seg[k] / length[k]
        cross = float(u1[0] * u2[1] - u1[1] * u2[0])
        turn = math.atan2(cross, float(u1 @ u2))
        if abs(turn) < math.radians(5.0) or abs(turn) > math.radians(175.0):
            out.append(p[k])
            continue
        half = math.tan(abs(turn) / 2.0)
        # the arc passes the corner at r (1 / cos(turn / 2) - 1): at most _ROUND_CUT from it
        cut = 1.0 / math.cos(abs(turn) / 2.0) - 1.0
        r = min(radius, 0.5 * min(length[k - 1], length[k]) / half, _ROUND_CUT / cut)
        arc = None
        while r >= 0.25:
            d = r * half
            t1 = p[k] - d * u1
            normal = np.array([-u1[1], u1[0]]) * math.copysign(1.0, turn)
            centre = t1 + r * normal
            a0 = math.atan2(t1[1] - centre[1], t1[0] - centre[0])
            n = max(2, math.ceil(abs(turn) * r / 0.2))  # a vertex every 0.2 m at most
            ang = a0 + np.linspace(0.0, turn, n + 1)
            cand = centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
            if bool(shapely.covers(region, shapely.LineString(np.vstack([out[-1], cand])))):
                arc = cand
                break
            r *= 0.5
        if arc is None:
            out.append(p[k])
        else:
            out.extend(arc)
    out.append(p[-1])
    q = np.asarray(out, dtype=np.float64)
    keep = np.ones(len(q), dtype=bool)
    keep[1:] = np.hypot(*np.diff(q, axis=0).T) > 1e-9
    return q[keep]


def _start_node(world: World, grid: _Grid, sx: float, sy: float) -> int:
    d = np.hypot(grid.xy[:, 0] - sx, grid.xy[:, 1] - sy)
    near = np.argsort(d)[:64]
    segs = shapely.linestrings(np.stack([np.broadcast_to([sx, sy], (len(near), 2)), grid.xy[near]], axis=1))
    ok = np.asarray(shapely.covers(world.free_space, segs), dtype=bool)
    if world.thin_walls:
        ok &= ~np.asarray(shapely.intersects(shapely.MultiLineString(list(world.thin_walls)), segs),
                          dtype=bool)
    return int(near[np.flatnonzero(ok)[0]]) if ok.any() else int(near[0])


def _join(legs: list[FloatArray]) -> FloatArray:
    parts = [legs[0]] + [leg[1:] for leg in legs[1:]]
    r = np.concatenate(parts)
    keep = np.ones(len(r), dtype=bool)
    keep[1:] = np.hypot(*np.diff(r, axis=0).T) > 1e-12
    return np.asarray(r[keep], dtype=np.float64)


def plan_route(
    world: World,
    rng: np.random.Generator,
    *,
    start: tuple[float, float] | None = None,
    clearance: float = 0.4,
    spacing: float | None = None,
    resolution: float | None = None,
    use_world_route: bool = True,
    sensor_range: float = 8.0,
) -> FloatArray:
    """A collision-free coverage route (module docstring) as a ``(k, 2)`` polyline.

    Parameters
    ----------
    world : World
    rng : numpy.random.Generator
        Jitters the grid origin and picks the start when ``start`` is None.
    start : (x, y), optional
        Start near this free point: at the nearest navigable grid node that it sees (no wall
        in between), else the nearest one. Ignored when the world's own route is used.
    clearance : float
        Least distance from the route to any wall, metres (> 0).
    spacing : float, optional
        Coverage radius, metres: every wall point is seen from a waypoint at most this far
        (default from the free area and the sensing range, see the module docstring).
    resolution : float, optional
        Grid cell size, metres (default: at most 300,000 cells over the bounds, >= 0.1 m,
        <= 1.4 * clearance).
    use_world_route : bool
        Return the world's own route when it has one.
    sensor_range : float
        The robot's sensing range, metres: bounds the default coverage radius, is the radius of
        the second covering pass and defines blind travel (module docstring).

    Returns
    -------
    (k, 2) float array
        No two consecutive points equal; ``k == 1`` only when the robot cannot move at all.

    Raises
    ------
    ValueError
        Bad parameters, a start outside the free space, or no room for the clearance.
    """
    if use_world_route and world.route is not None:
        return np.asarray(world.route.coords, dtype=np.float64)[:, :2].copy()
    return _join(_plan(world, rng, start, clearance, spacing, resolution, sensor_range))


def plan_fleet_routes(
    world: World,
    starts: list[tuple[float, float]],
    rng: np.random.Generator,
    *,
    clearance: float = 0.4,
    spacing: float | None = None,
    resolution: float | None = None,
    sensor_range: float = 8.0,
) -> list[FloatArray]:
    """One coverage route per start point that share the world's coverage out (:func:`_fleet_tours`):
    the robots first sweep, each from its own start, the waypoints no other robot has reached
    yet (the one that has driven least takes the next), then each goes on over the parts the
    others swept. The grid and waypoints are those of :func:`plan_route`; the routes are
    smoothed the same way. This is how an operator with the floor plan would dispatch robots
    switched on wherever they stand; the robots themselves learn nothing of it."""
    grid, sp, h = _setup(world, rng, clearance, spacing, resolution, sensor_range)
    nodes = [_start_of(world, grid, s) for s in starts]
    way = _wall_waypoints(world, grid, sp, max(sp, sensor_range), h)
    tours = _fleet_tours(_penalise_blind(grid, world, sensor_range), nodes, way, sp)
    regions = _smoothing_regions(world, clearance, sensor_range)  # once for every robot
    return [_join(_smooth(grid, s, legs, regions, sp)) for s, legs in zip(nodes, tours)]


def split_route(route: FloatArray, n: int, overlap: float = 0.0) -> list[FloatArray]:
    """Cut a polyline into ``n`` consecutive pieces of equal length.

    Piece ``i`` runs from arc length ``i L / n`` to ``(i + 1) L / n + overlap * L / n`` (capped
    at the end), so with ``overlap > 0`` each piece also covers the start of the next one.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if overlap < 0:
        raise ValueError(f"overlap must be >= 0, got {overlap}")
    r = np.asarray(route, dtype=np.float64).reshape(-1, 2)
    seg = np.hypot(*np.diff(r, axis=0).T) if len(r) > 1 else np.zeros(0)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(cum[-1])
    if total <= 0:
        return [r.copy() for _ in range(n)]

    def at(s: float) -> FloatArray:
        k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        t = (s - cum[k]) / seg[k] if seg[k] > 0 else 0.0
        return np.asarray(r[k] + min(max(t, 0.0), 1.0) * (r[k + 1] - r[k]), dtype=np.float64)

    out = []
    for i in range(n):
        a = total * i / n
        b = min(total, total * (i + 1 + overlap) / n)
        inner = r[(cum > a + 1e-9) & (cum < b - 1e-9)]
        piece = np.vstack([at(a), inner, at(b)])
        out.append(piece)
    return out


def plan_routes(
    world: World,
    n: int,
    rng: np.random.Generator,
    *,
    clearance: float = 0.4,
    spacing: float | None = None,
    resolution: float | None = None,
    overlap: float = 0.0,
    use_world_route: bool = True,
) -> list[FloatArray]:
    """``n`` routes that share the coverage: one coverage route (:func:`plan_route` from a
    random start) cut into ``n`` consecutive pieces of equal length (:func:`split_route`), so
    each robot sweeps its own part of the world and they start at distinct points, evenly spread
    along the tour. With ``overlap`` each piece runs on into the next by that fraction of a
    piece, which gives the robots' maps common walls."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    full = plan_route(
        world, rng, clearance=clearance, spacing=spacing, resolution=resolution,
        use_world_route=use_world_route
    )
    return split_route(full, n, overlap)
