"""Coverage routes through a world's free space.

:func:`plan_route` makes one collision-free polyline that covers the world:

1. **Navigable region.** Points at least ``clearance`` from every wall (the free space's
   boundary and the thin walls), computed with shapely buffers.
2. **Grid graph.** Cell centres of a square grid (resolution ``h``, origin jittered by the rng)
   that lie in the navigable region, 8-connected; a diagonal step needs both of its orthogonal
   neighbours (no corner cutting). The grid's region is shrunk by an extra ``h**2 / (4 c)``: a
   step of length ``L <= h*sqrt(2)`` whose two ends are ``c + L**2 / (8 c)`` from a convex
   obstacle cannot come nearer than ``c`` to it, so every grid step keeps the clearance; and
   ``h < 1.4 c`` so that no step can jump a thin wall.
3. **Waypoints.** The plane is cut into square cells of side ``spacing`` (origin jittered by the
   rng); each cell with navigable nodes gets one waypoint, the node nearest to the centroid of
   its nodes. Waypoints nearer than ``0.6 spacing`` to one of a fuller cell are dropped (a
   corridor straddling two cells gets one row, not two). Then every node farther than
   ``1.09 spacing / sqrt(2)`` (grid-path distance, one multi-source ``dijkstra``) from all
   waypoints gets one too, greedily: rooms behind thin walls are not "covered" through the wall.
4. **Tour.** A greedy nearest-neighbour tour over the waypoints by grid-path distance (bounded
   ``scipy.sparse.csgraph.dijkstra`` from the current node, widened until an unvisited waypoint
   is found) with a little momentum (see :func:`_tour`), the shortest grid paths joining them.
   Waypoints not reachable from the start (e.g. behind a doorway narrower than
   ``2 * clearance``) are left out.
5. **Simplification.** Each leg between consecutive waypoints is string-pulled: from each kept
   vertex, jump to the farthest later vertex of the leg (within 96) that the straight segment
   reaches while staying in the navigable region (exact shapely test). Waypoints are kept, so
   coverage is.

``spacing`` is the distance between neighbouring waypoints (so neighbouring sweeps of a hall
are ``spacing`` apart and every reachable navigable point is within about ``spacing / sqrt(2)``
of a waypoint). The default ``clip(sqrt(free area) / 12, 2.5, 12)`` m gives 2.5 m in rooms and
offices and 12 m in the 200 x 200 m museum, so that with an 8 m sensing range most walls are
seen from nearby.

A world with its own route (``World.route``) uses it instead unless ``use_world_route=False``.
Randomness (grid and cell origins, the start node when none is given) comes only from the
``rng`` argument: the same seed gives the same route.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from agents.sim.world import World

__all__ = ["navigable_region", "plan_route", "plan_routes", "route_clearance", "route_length", "split_route"]

FloatArray = NDArray[np.float64]

# Buffers approximate arcs by chords; with this many segments per quarter circle a chord is
# inside the true arc by at most c * (1 - cos(pi / 64)) = 0.0012 c, which the planner adds.
_QUAD_SEGS = 16
_MAX_GRID_CELLS = 150_000


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
    graph = csr_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))
    return _Grid(xy=np.column_stack([gx[inside], gy[inside]]), graph=graph)


def _default_spacing(world: World) -> float:
    return float(np.clip(math.sqrt(world.free_space.area) / 12.0, 2.5, 12.0))


def _default_resolution(world: World, clearance: float) -> float:
    xmin, ymin, xmax, ymax = world.bounds()
    h = math.sqrt((xmax - xmin) * (ymax - ymin) / _MAX_GRID_CELLS)
    h = max(h, 0.1)
    if clearance > 0:
        h = min(h, 1.4 * clearance)  # a grid step is shorter than 2 * clearance: it cannot cross a wall
    return h


def _waypoints(grid: _Grid, spacing: float, rng_offset: FloatArray) -> NDArray[np.int64]:
    """Node indices of the coverage waypoints (module docstring, step 3), sorted."""
    xy = grid.xy
    org = xy.min(axis=0) - rng_offset
    cell = np.floor((xy - org) / spacing).astype(np.int64)
    cid = cell[:, 0] * (int(cell[:, 1].max()) + 2) + cell[:, 1]
    # the node nearest to the centroid of its cell's nodes (a cell cut by a wall gets its
    # waypoint in the middle of its free part)
    uniq, inv = np.unique(cid, return_inverse=True)
    cnt = np.bincount(inv).astype(np.float64)
    centre = np.column_stack([np.bincount(inv, xy[:, 0]) / cnt, np.bincount(inv, xy[:, 1]) / cnt])[inv]
    d = np.hypot(*(xy - centre).T)
    order = np.lexsort((np.arange(len(xy)), d, cid))
    _, first = np.unique(cid[order], return_index=True)
    way = [int(i) for i in order[first]]
    # thin out: a waypoint nearer than 0.6 spacing to one of a fuller cell goes (a corridor that
    # straddles two cells would otherwise get two waypoints side by side)
    fullness = np.bincount(inv)[np.searchsorted(uniq, cid[way])]
    kept: list[int] = []
    kept_xy = np.zeros((len(way), 2))
    for k in np.argsort(-fullness, kind="stable"):
        p = xy[way[k]]
        if kept and np.min(np.hypot(*(kept_xy[: len(kept)] - p).T)) < 0.6 * spacing:
            continue
        kept_xy[len(kept)] = p
        kept.append(way[k])
    way = kept
    # 8-connected grid paths overestimate straight distances by up to 8.3 % (at 22.5 degrees)
    radius = 1.09 * spacing / math.sqrt(2.0)
    dist = dijkstra(grid.graph, indices=way, limit=radius, min_only=True)
    uncovered = ~np.isfinite(dist)
    while uncovered.any():
        u = int(np.flatnonzero(uncovered)[0])
        way.append(u)
        du = dijkstra(grid.graph, indices=u, limit=radius)
        uncovered &= ~np.isfinite(du)
    return np.array(sorted(set(way)), dtype=np.int64)


def _tour(grid: _Grid, start: int, way: NDArray[np.int64], spacing: float) -> list[NDArray[np.int64]]:
    """Node-index legs of a greedy nearest-neighbour tour over the waypoints (module step 4).

    From the current node, the next waypoint is the unvisited one with the smallest grid-path
    distance minus ``spacing / 4`` times the cosine of the turn it asks for (a little momentum,
    so that rows are swept in order instead of zigzagging); waypoints within ``0.3 spacing`` of
    a path already driven count as visited. Waypoints not reachable from the start are dropped.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(grid.xy[way])
    todo = np.ones(len(way), dtype=bool)
    is_way = -np.ones(grid.xy.shape[0], dtype=np.int64)
    is_way[way] = np.arange(len(way))
    legs: list[NDArray[np.int64]] = []
    cur = start
    heading = np.zeros(2)

    def visit(nodes: NDArray[np.int64]) -> None:
        for hits in tree.query_ball_point(grid.xy[nodes], r=0.3 * spacing):
            todo[hits] = False

    visit(np.array([start]))
    while todo.any():
        limit = 2.5 * spacing
        while True:
            dist, pred = dijkstra(grid.graph, indices=cur, limit=limit, return_predecessors=True)
            cand = way[todo & np.isfinite(dist[way])]
            if len(cand) or np.isinf(limit):
                break
            limit = limit * 4.0 if limit < 1e6 else math.inf
        if not len(cand):
            break
        dcand = dist[cand]
        near = cand[dcand <= dcand.min() + 0.5 * spacing]
        vec = grid.xy[near] - grid.xy[cur]
        norm = np.maximum(np.hypot(*vec.T), 1e-12)
        score = dist[near] - 0.25 * spacing * (vec @ heading) / norm
        target = int(near[np.argmin(score)])
        path = [target]
        while path[-1] != cur:
            path.append(int(pred[path[-1]]))
        leg = np.array(path[::-1], dtype=np.int64)
        visit(leg)
        todo[is_way[target]] = False
        step = grid.xy[target] - grid.xy[leg[max(0, len(leg) - 4)]]
        heading = step / max(float(np.hypot(*step)), 1e-12)
        legs.append(leg)
        cur = target
    return legs


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


def _pull(p: FloatArray, region: Any, window: int = 96) -> FloatArray:
    """String-pull a polyline inside ``region`` keeping its end points."""
    if len(p) <= 2:
        return p
    out = [p[0]]
    i = 0
    while i < len(p) - 1:
        js = np.arange(i + 1, min(len(p), i + 1 + window))
        segs = np.stack([np.broadcast_to(p[i], (len(js), 2)), p[js]], axis=1)
        ok = np.asarray(shapely.covers(region, shapely.linestrings(segs)), dtype=bool)
        ok[0] = True  # a grid step keeps the clearance by construction
        i = int(js[np.flatnonzero(ok)[-1]])
        out.append(p[i])
    return np.array(out)


def _plan(
    world: World,
    rng: np.random.Generator,
    start: tuple[float, float] | None,
    clearance: float,
    spacing: float | None,
    resolution: float | None,
) -> list[FloatArray]:
    """Simplified legs ``[(k_i, 2)]`` of the coverage route (consecutive legs share ends)."""
    if not (clearance > 0 and math.isfinite(clearance)):
        raise ValueError(f"clearance must be positive, got {clearance}")
    sp = _default_spacing(world) if spacing is None else float(spacing)
    if not (sp > 0 and math.isfinite(sp)):
        raise ValueError(f"spacing must be positive, got {spacing}")
    h = _default_resolution(world, clearance) if resolution is None else float(resolution)
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    grid = _grid(world, clearance, h, rng)
    if grid.xy.shape[0] == 0:
        raise ValueError(f"world {world.name!r} has no room for a robot with clearance {clearance} m")
    if start is None:
        s = int(rng.integers(grid.xy.shape[0]))
    else:
        sx, sy = float(start[0]), float(start[1])
        if not bool(world.is_free(np.array([sx, sy]))):
            raise ValueError(f"start ({sx:g}, {sy:g}) is not in the free space of {world.name!r}")
        s = _start_node(world, grid, sx, sy)
    way = _waypoints(grid, sp, rng.uniform(0.0, sp, size=2))
    node_legs = _tour(grid, s, way, sp)
    if not node_legs:
        return [grid.xy[[s]]]
    check = navigable_region(world, clearance)
    return [_pull(_straight_runs(grid.xy[leg]), check) for leg in node_legs]


def _start_node(world: World, grid: _Grid, sx: float, sy: float) -> int:
    d = np.hypot(grid.xy[:, 0] - sx, grid.xy[:, 1] - sy)
    near = np.argsort(d)[:64]
    segs = shapely.linestrings(np.stack([np.broadcast_to([sx, sy], (len(near), 2)), grid.xy[near]], axis=1))
    ok = np.asarray(shapely.covers(world.free_space, segs), dtype=bool)
    if world.thin_walls:
        ok &= ~np.asarray(shapely.intersects(shapely.MultiLineString(list(world.thin_walls)), segs), dtype=bool)
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
        Coverage radius, metres (default from the free area, see the module docstring).
    resolution : float, optional
        Grid cell size, metres (default: at most 300,000 cells over the bounds, >= 0.1 m,
        <= 1.4 * clearance).
    use_world_route : bool
        Return the world's own route when it has one.

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
    return _join(_plan(world, rng, start, clearance, spacing, resolution))


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
        world, rng, clearance=clearance, spacing=spacing, resolution=resolution, use_world_route=use_world_route
    )
    return split_route(full, n, overlap)
