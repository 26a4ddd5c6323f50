"""Simulated worlds: free space, thin walls, the ground-truth wireframe and an optional route.

A world file is GeoJSON (a ``FeatureCollection``, coordinates in metres):

* ``Polygon`` (or ``MultiPolygon``) features are FREE SPACE: the exterior ring is an outer wall,
  each hole an obstacle. Overlapping or touching polygons are merged (their union is the free
  space), so a wall between two rooms is either a gap between their polygons (a thick wall) or a
  thin wall. Optional property ``"kind": "free_space"``.
* ``LineString`` features without a ``kind`` or with ``"kind": "wall"`` are thin interior walls
  (zero thickness, seen from both sides). A thin wall must lie inside the free space; its ends may
  touch other walls.
* At most one ``LineString`` with ``"kind": "route"`` is the robot route; it must stay in the free
  space and must not touch a thin wall.

Anything else (a ``Point``, an unknown kind, an invalid polygon, bad JSON) raises
:class:`WorldError` naming the feature. The collection's ``properties.name`` names the world
(default: the file's stem).

**Walls at odd angles**: ``NAME@DEG`` (a built-in name or a file, then ``@`` and a number of
degrees) is that world turned by ``DEG`` degrees counterclockwise about the centre of its
bounds and shifted back into the positive quadrant (:func:`rotated_world`), e.g.
``paper-small@23``: every command that takes a world takes it, and its truth turns with it.

Loading normalises the geometry, so that writing a world out with :meth:`World.to_geojson` and
reading it back gives an identical world: straight-through (collinear) ring vertices are
dropped (they are not corners), exteriors run counterclockwise and holes clockwise, every ring
starts at its lexicographically smallest vertex, and polygons and holes are sorted by that vertex.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import shapely.affinity
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from shapely.geometry import LineString, MultiLineString, MultiPolygon, Polygon
from shapely.validation import explain_validity

from agents.errors import UserError
from mapping.wireframe import Wireframe

__all__ = [
    "THIN_WALL_CLEARANCE",
    "World",
    "WorldError",
    "builtin_names",
    "load_world",
    "rotated_world",
    "world_from_geojson",
]

#: Half thickness given to a thin wall by :meth:`World.is_free` (metres): a point closer than
#: this to a thin wall is not free.
THIN_WALL_CLEARANCE = 0.05

# Geometric tolerance (metres) for "the same point" and "on a segment".
_EPS = 1e-7


class WorldError(UserError):
    """A world that cannot be loaded: bad JSON, an unsupported or invalid feature."""


@dataclass(frozen=True, eq=False)
class World:
    """A simulated environment.

    Attributes
    ----------
    name : str
        Built-in name or the file's ``properties.name`` / stem.
    free_space : shapely.MultiPolygon
        Where the robot may be (normalised, see the module docstring).
    thin_walls : tuple of shapely.LineString
        Zero-thickness interior walls.
    truth : Wireframe
        The ground-truth map: every corner nominal, every likelihood 1; edges follow the
        project's direction convention (free space on the left: exteriors counterclockwise,
        holes clockwise); a thin wall is two opposite edges; where a wall's end (or a vertex)
        lies on another wall, that wall is split there so the corner is shared; two thin walls
        that cross are both split at the crossing.
    route : shapely.LineString or None
        The route given in the file, if any.
    """

    name: str
    free_space: MultiPolygon
    thin_walls: tuple[LineString, ...]
    truth: Wireframe
    route: LineString | None = None

    # ------------------------------------------------------------------ queries
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the free space."""
        xmin, ymin, xmax, ymax = self.free_space.bounds
        return (float(xmin), float(ymin), float(xmax), float(ymax))

    @property
    def size(self) -> tuple[float, float]:
        """``(width, height)`` of :meth:`bounds` in metres."""
        xmin, ymin, xmax, ymax = self.bounds()
        return (xmax - xmin, ymax - ymin)

    @cached_property
    def _prepared(self) -> tuple[Any, Any]:
        free = self.free_space
        shapely.prepare(free)
        walls = MultiLineString(list(self.thin_walls)) if self.thin_walls else None
        if walls is not None:
            shapely.prepare(walls)
        return free, walls

    def is_free(self, xy: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each point is free: inside the free space (its boundary counts as not free)
        and farther than :data:`THIN_WALL_CLEARANCE` from every thin wall.

        Parameters
        ----------
        xy : (k, 2) or (2,) array

        Returns
        -------
        (k,) bool array (shape ``()`` for a single point)
        """
        p = np.asarray(xy, dtype=np.float64)
        single = p.ndim == 1
        p = p.reshape(-1, 2)
        free, walls = self._prepared
        inside = np.asarray(shapely.contains_xy(free, p[:, 0], p[:, 1]), dtype=bool)
        if walls is not None and inside.any():
            idx = np.flatnonzero(inside)
            d = shapely.distance(walls, shapely.points(p[idx]))
            inside[idx] = d > THIN_WALL_CLEARANCE
        return inside[0] if single else inside

    def walls(self) -> MultiLineString:
        """Every wall as lines: the free space's boundary and the thin walls."""
        lines: list[LineString] = []
        for poly in self.free_space.geoms:
            lines.append(LineString(poly.exterior.coords))
            lines.extend(LineString(r.coords) for r in poly.interiors)
        lines.extend(self.thin_walls)
        return MultiLineString(lines)

    def summary(self) -> dict[str, Any]:
        """Name, bounds, size, free area and truth counts (for listings and reports)."""
        w, h = self.size
        return {
            "name": self.name,
            "bounds": list(self.bounds()),
            "size_m": [w, h],
            "free_area_m2": float(self.free_space.area),
            "corners": self.truth.n_vertices,
            "walls": self.truth.n_edges,
            "thin_walls": len(self.thin_walls),
            "has_route": self.route is not None,
        }

    # ------------------------------------------------------------------ output
    def to_geojson(self) -> dict[str, Any]:
        """The world as a world file (a GeoJSON FeatureCollection) that :func:`load_world`
        reads back to an identical world."""
        feats: list[dict[str, Any]] = []
        for poly in self.free_space.geoms:
            feats.append(
                {
                    "type": "Feature",
                    "geometry": shapely.geometry.mapping(poly),
                    "properties": {"kind": "free_space"},
                }
            )
        for line in self.thin_walls:
            feats.append(
                {"type": "Feature", "geometry": shapely.geometry.mapping(line),
                 "properties": {"kind": "wall"}}
            )
        if self.route is not None:
            feats.append(
                {"type": "Feature", "geometry": shapely.geometry.mapping(self.route),
                 "properties": {"kind": "route"}}
            )
        doc = {"type": "FeatureCollection", "properties": {"name": self.name}, "features": feats}
        # shapely's mapping() gives tuples; make it plain JSON data.
        return json.loads(json.dumps(doc))

    def same_as(self, other: World, tol: float = 1e-9) -> bool:
        """Equal name, free space, thin walls, route and truth (coordinates within ``tol``)."""
        if self.name != other.name or len(self.thin_walls) != len(other.thin_walls):
            return False
        if not shapely.equals_exact(self.free_space, other.free_space, tolerance=tol):
            return False
        for a, b in zip(self.thin_walls, other.thin_walls):
            if not shapely.equals_exact(a, b, tolerance=tol):
                return False
        if (self.route is None) != (other.route is None):
            return False
        if self.route is not None and other.route is not None:
            if not shapely.equals_exact(self.route, other.route, tolerance=tol):
                return False
        return self.truth.almost_equal(other.truth, tol=tol)


# ---------------------------------------------------------------------- loading
def builtin_names() -> list[str]:
    """Names of the built-in worlds, in listing order."""
    from agents.sim.builtin import BUILTINS

    return list(BUILTINS)


def load_world(spec: str | os.PathLike[str]) -> World:
    """A built-in world by name, or a world file (``.geojson``) by path; ``SPEC@DEG`` is that
    world turned by ``DEG`` degrees (:func:`rotated_world`). A built-in name wins over a file
    of that name in the working directory; built-ins are made once per process.

    Raises
    ------
    WorldError
        Unknown name and no such file, unreadable file, bad JSON, or a bad feature (named).
    """
    from agents.sim.builtin import BUILTINS

    text = os.fspath(spec)
    if text in BUILTINS:
        return _builtin(text)
    path = Path(text)
    base, at, deg = text.rpartition("@")
    if at and base and not path.exists():
        try:
            degrees = float(deg)
        except ValueError:
            raise WorldError(f"world {text!r}: after '@' comes a number of degrees, got {deg!r}") from None
        if not math.isfinite(degrees):
            raise WorldError(f"world {text!r}: the rotation must be a finite number of degrees")
        return rotated_world(load_world(base), degrees)
    if not path.exists():
        raise WorldError(
            f"unknown world {text!r}: not a built-in ({', '.join(BUILTINS)}) and no such file"
        )
    try:
        raw = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise WorldError(f"{path}: cannot read: {exc}") from None
    try:
        doc = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise WorldError(f"{path}: not valid JSON: {exc}") from None
    return world_from_geojson(doc, name=path.stem, where=str(path))


def rotated_world(world: World, degrees: float) -> World:
    """``world`` turned by ``degrees`` counterclockwise about the centre of its bounds, then
    shifted so that its bounds start at the origin again (walls at odd angles for the
    simulator). Named ``NAME@DEG``; free space, thin walls, route and truth all turn.

    Raises
    ------
    WorldError
        The turned geometry does not load (it always should; rounding of a degenerate world).
    """
    xmin, ymin, xmax, ymax = world.bounds()
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    doc = world.to_geojson()
    turned = [shapely.geometry.shape(f["geometry"]) for f in doc["features"]]
    turned = [shapely.affinity.rotate(g, degrees, origin=(cx, cy)) for g in turned]
    bx0 = min(float(g.bounds[0]) for g in turned)
    by0 = min(float(g.bounds[1]) for g in turned)
    for f, g in zip(doc["features"], turned):
        f["geometry"] = json.loads(json.dumps(shapely.geometry.mapping(
            shapely.affinity.translate(g, -bx0, -by0))))
    name = f"{world.name}@{degrees:g}"
    doc["properties"] = {"name": name}
    return world_from_geojson(doc, name=name, where=f"world {name!r}")


@cache
def _builtin(name: str) -> World:
    # Worlds are immutable, so one instance per built-in is shared.
    from agents.sim.builtin import BUILTINS

    return world_from_geojson(BUILTINS[name].generate(), name=name, where=f"built-in world {name!r}")


def world_from_geojson(doc: Any, *, name: str = "world", where: str = "world") -> World:
    """Build a :class:`World` from a parsed world file.

    Parameters
    ----------
    doc : dict
        A GeoJSON FeatureCollection (see the module docstring).
    name : str
        Used when the collection has no ``properties.name``.
    where : str
        Prefix of error messages (a file name).

    Raises
    ------
    WorldError
        Naming the feature that is wrong.
    """
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise WorldError(f"{where}: expected a GeoJSON FeatureCollection")
    feats = doc.get("features")
    if not isinstance(feats, list):
        raise WorldError(f"{where}: the FeatureCollection has no 'features' list")
    props = doc.get("properties") or {}
    if isinstance(props, dict) and isinstance(props.get("name"), str) and props["name"]:
        name = props["name"]

    polys: list[Polygon] = []
    walls: list[LineString] = []
    route: LineString | None = None
    route_label = ""
    for k, f in enumerate(feats):
        label = _feature_label(k, f)
        if not isinstance(f, dict) or f.get("type") != "Feature":
            raise WorldError(f"{where}: {label}: not a GeoJSON Feature")
        geom = f.get("geometry")
        fprops = f.get("properties") or {}
        if not isinstance(fprops, dict):
            raise WorldError(f"{where}: {label}: properties must be an object")
        kind = fprops.get("kind")
        if not isinstance(geom, dict):
            raise WorldError(f"{where}: {label}: has no geometry")
        gtype = geom.get("type")
        if gtype in ("Polygon", "MultiPolygon"):
            if kind not in (None, "free_space"):
                raise WorldError(f"{where}: {label}: a {gtype} must be free space, not kind {kind!r}")
            shape = _shape(geom, where, label)
            parts = list(shape.geoms) if isinstance(shape, MultiPolygon) else [shape]
            for part in parts:
                if not part.is_valid:
                    raise WorldError(f"{where}: {label}: invalid polygon: {explain_validity(part)}")
                if part.is_empty or part.area <= 0.0:
                    raise WorldError(f"{where}: {label}: polygon has no area")
                polys.append(part)
        elif gtype == "LineString":
            line = _shape(geom, where, label)
            assert isinstance(line, LineString)
            line = _dedupe_line(line)
            if line is None:
                raise WorldError(f"{where}: {label}: a LineString needs two distinct points")
            if kind in (None, "wall"):
                walls.append(line)
            elif kind == "route":
                if route is not None:
                    raise WorldError(f"{where}: {label}: a second route (only one is allowed)")
                route, route_label = line, label
            else:
                raise WorldError(f"{where}: {label}: unknown LineString kind {kind!r} (wall or route)")
        else:
            raise WorldError(
                f"{where}: {label}: unsupported geometry {gtype!r} "
                "(Polygon free space, LineString walls and route)"
            )
    if not polys:
        raise WorldError(f"{where}: no free space (no Polygon feature)")

    free = _normalise_free_space(polys)
    if free.is_empty or not free.is_valid:
        raise WorldError(f"{where}: the union of the free-space polygons is not a valid area")
    boundary = free.boundary
    for k, line in enumerate(walls):
        if not free.covers(line):
            raise WorldError(f"{where}: thin wall {k} ({_short(line)}) leaves the free space")
        if line.intersection(boundary).length > _EPS:
            raise WorldError(f"{where}: thin wall {k} ({_short(line)}) runs along the outer walls")
    if route is not None:
        if not free.buffer(1e-9).covers(route):
            raise WorldError(f"{where}: {route_label}: the route leaves the free space")
        for k, line in enumerate(walls):
            if route.intersects(line):
                raise WorldError(f"{where}: {route_label}: the route crosses thin wall {k}")
    thin = tuple(walls)
    return World(name=name, free_space=free, thin_walls=thin, truth=truth_wireframe(free, thin), route=route)


def _feature_label(k: int, f: Any) -> str:
    label = f"feature {k}"
    if isinstance(f, dict):
        props = f.get("properties") or {}
        ident = f.get("id", props.get("name") if isinstance(props, dict) else None)
        if ident is not None:
            label += f" ({ident})"
    return label


def _shape(geom: dict[str, Any], where: str, label: str) -> Any:
    try:
        shape = shapely.geometry.shape(geom)
    except Exception as exc:  # shapely raises several types on malformed coordinates
        raise WorldError(f"{where}: {label}: malformed {geom.get('type')}: {exc}") from None
    coords = shapely.get_coordinates(shape)
    if coords.size == 0 or not np.all(np.isfinite(coords)):
        raise WorldError(f"{where}: {label}: empty or non-finite coordinates")
    return shape


def _short(line: LineString) -> str:
    c = np.asarray(line.coords)
    return f"from ({c[0, 0]:g}, {c[0, 1]:g}) to ({c[-1, 0]:g}, {c[-1, 1]:g})"


def _dedupe_line(line: LineString) -> LineString | None:
    c = np.asarray(line.coords, dtype=np.float64)[:, :2]
    keep = np.ones(len(c), dtype=bool)
    keep[1:] = np.hypot(*(np.diff(c, axis=0).T)) > _EPS
    c = c[keep]
    return LineString(c) if len(c) >= 2 else None


# ---------------------------------------------------------------------- normalisation
def _clean_ring(coords: NDArray[np.float64], ccw: bool) -> NDArray[np.float64]:
    """Open ring (no repeated closing point), straight-through vertices removed, oriented,
    rotated to start at the lexicographically smallest vertex."""
    r = np.asarray(coords, dtype=np.float64)[:, :2]
    if len(r) > 1 and np.allclose(r[0], r[-1]):
        r = r[:-1]
    changed = True
    while changed and len(r) > 3:
        prev = np.roll(r, 1, axis=0)
        nxt = np.roll(r, -1, axis=0)
        a, b = r - prev, nxt - r
        cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        dot = (a * b).sum(axis=1)
        scale = np.hypot(*a.T) * np.hypot(*b.T)
        straight = (np.abs(cross) <= 1e-12 * np.maximum(scale, 1e-300)) & (dot > 0)
        dup = np.hypot(*a.T) <= _EPS
        drop = straight | dup
        changed = bool(drop.any())
        if changed:
            # drop one of each run at a time so neighbours are re-evaluated
            first = int(np.flatnonzero(drop)[0])
            r = np.delete(r, first, axis=0)
    x, y = r[:, 0], r[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    if (area2 > 0) != ccw:
        r = r[::-1]
    start = int(np.lexsort((r[:, 1], r[:, 0]))[0])
    return np.roll(r, -start, axis=0)


def _ring_key(r: NDArray[np.float64]) -> tuple[float, float]:
    return (float(r[0, 0]), float(r[0, 1]))


def _normalise_free_space(polys: list[Polygon]) -> MultiPolygon:
    merged = shapely.unary_union(polys) if len(polys) > 1 else polys[0]
    parts = [g for g in getattr(merged, "geoms", [merged]) if isinstance(g, Polygon) and g.area > 0]
    out: list[Polygon] = []
    for p in parts:
        ext = _clean_ring(np.asarray(p.exterior.coords), ccw=True)
        holes = sorted((_clean_ring(np.asarray(h.coords), ccw=False) for h in p.interiors), key=_ring_key)
        out.append(Polygon(ext, holes))
    out.sort(key=lambda p: (p.exterior.coords[0][0], p.exterior.coords[0][1]))
    return MultiPolygon(out)


# ---------------------------------------------------------------------- ground truth
def truth_wireframe(free: MultiPolygon, thin_walls: tuple[LineString, ...] = ()) -> Wireframe:
    """The ground-truth wireframe of a free space and its thin walls.

    Rings give one edge per side (exteriors counterclockwise, holes clockwise, as they are in a
    normalised free space); each thin-wall segment gives two opposite edges. Every vertex of any
    wall and every crossing of a thin wall with another wall is a node; a directed segment with
    nodes strictly inside it is split at them, so walls that meet share the corner. Nodes closer
    than 1e-7 m are one vertex. All corners are nominal and all likelihoods 1.
    """
    segs: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for poly in free.geoms:
        for ring, ccw in [(poly.exterior, True), *((h, False) for h in poly.interiors)]:
            r = _clean_ring(np.asarray(ring.coords), ccw=ccw)
            # keep the normalised start; orientation is what matters
            for i in range(len(r)):
                segs.append((r[i], r[(i + 1) % len(r)]))
    thin_segs: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for line in thin_walls:
        c = np.asarray(line.coords, dtype=np.float64)[:, :2]
        for i in range(len(c) - 1):
            thin_segs.append((c[i], c[i + 1]))
    nodes = [a for a, _ in segs] + [p for s in thin_segs for p in s]
    # crossings of thin walls with any other wall
    all_segs = segs + thin_segs
    if thin_segs and all_segs:
        a0 = np.array([s[0] for s in thin_segs])
        a1 = np.array([s[1] for s in thin_segs])
        b0 = np.array([s[0] for s in all_segs])
        b1 = np.array([s[1] for s in all_segs])
        nodes.extend(_crossings(a0, a1, b0, b1))
    directed = segs + thin_segs + [(b, a) for a, b in thin_segs]
    if not directed:
        return Wireframe.empty()
    node_arr = np.unique(np.round(np.array(nodes, dtype=np.float64), 12), axis=0)

    # split each directed segment at the nodes strictly inside it
    pieces: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for a, b in directed:
        d = b - a
        length2 = float(d @ d)
        rel = node_arr - a
        t = (rel @ d) / length2
        perp = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / math.sqrt(length2)
        length = math.sqrt(length2)
        inside = (perp <= _EPS) & (t * length > _EPS) & ((1.0 - t) * length > _EPS)
        if inside.any():
            order = np.argsort(t[inside])
            chain = [a, *node_arr[inside][order], b]
        else:
            chain = [a, b]
        pieces.extend(itertools.pairwise(chain))

    pts = np.array([p for seg in pieces for p in seg], dtype=np.float64)
    vid = _cluster(pts, _EPS)
    starts, ends = vid[0::2], vid[1::2]
    edges = {(int(i), int(j)) for i, j in zip(starts, ends) if i != j}
    used = np.unique(vid)
    remap = -np.ones(int(vid.max()) + 1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    first = np.zeros(int(vid.max()) + 1, dtype=np.int64)
    first[vid[::-1]] = np.arange(len(vid))[::-1]
    points = pts[first[used]]
    e = np.array(sorted((int(remap[i]), int(remap[j])) for i, j in edges), dtype=np.int64).reshape(-1, 2)
    return Wireframe.build(points, e)


def _crossings(
    a0: NDArray[np.float64], a1: NDArray[np.float64], b0: NDArray[np.float64], b1: NDArray[np.float64]
) -> list[NDArray[np.float64]]:
    """Proper crossing points of every segment ``a`` with every segment ``b``."""
    da = (a1 - a0)[:, None, :]
    db = (b1 - b0)[None, :, :]
    w = b0[None, :, :] - a0[:, None, :]
    den = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * db[..., 1] - w[..., 1] * db[..., 0]) / den
        u = (w[..., 0] * da[..., 1] - w[..., 1] * da[..., 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (t < 1 - 1e-9) & (u > 1e-9) & (u < 1 - 1e-9)
    return [a0[i] + t[i, j] * (a1[i] - a0[i]) for i, j in zip(*np.nonzero(ok))]


def _cluster(pts: NDArray[np.float64], tol: float) -> NDArray[np.int64]:
    """Cluster label per point: points within ``tol`` (transitively) share the smallest index."""
    n = len(pts)
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    for i, j in cKDTree(pts).query_pairs(tol):
        ri, rj = find(int(i)), find(int(j))
        if ri != rj:
            parent[max(ri, rj)] = min(ri, rj)
    return np.array([find(i) for i in range(n)], dtype=np.int64)
