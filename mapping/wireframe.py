"""The wireframe: a labelled, directed graph embedded in the plane (paper Sec. III-A).

Vertices are wall corners, edges are walls. Conventions used everywhere in this project:

* **Edge direction.** A directed edge ``(i, j)`` is a wall seen from its *left* side: walking
  from ``p_i`` to ``p_j``, free space is on the left, the solid side on the right. A scan's
  corners sorted counterclockwise around the robot and joined in that order (paper Sec. IV-A)
  produce exactly this direction. The outer wall of a room therefore runs counterclockwise, an
  obstacle inside it clockwise, and a thin interior wall seen from both sides is two edges of
  opposite direction between the same corners. Edges of opposite direction are never merged.
* **Labels** (:class:`Label`): ``NOMINAL`` corners are real corners, ``OCCLUSION`` vertices end a
  visible wall that hides another one, ``FRONTIER`` vertices are where a wall leaves what has
  been seen (behind an occlusion or beyond the sensing range).
* **Likelihood.** Each edge carries the likelihood that it exists (paper Sec. IV-D/E), in [0, 1].
* **Sources.** Each edge carries a bit mask of contributors (bit k = contributor k); the fusion
  service uses it for "which robots saw this wall"; a single robot leaves it 0. Merging ORs
  the masks the way it combines likelihoods. Masks have no width limit (a fleet of any size):
  the array is ``uint64`` while every mask is below ``2**64`` (every fleet of at most 64
  robots, every robot map: the arrays, their bytes and every result are as they always were)
  and an ``object`` array of Python ints once a mask has bit 64 or above (:func:`as_masks`
  makes that canonical choice; :func:`mask_bytes` hashes either kind).

The value type is immutable: its arrays are read-only, and every operation returns a new one.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapping.se2 import Pose

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int32]
LabelArray = NDArray[np.uint8]
MaskArray = NDArray[Any]
"""Contributor masks: ``uint64``, or ``object`` (Python ints) when a mask needs bit 64 or above."""

MASK_WORD = 1 << 64
"""Masks below this live in a ``uint64`` array; an array with any mask at or above it is an
``object`` array of Python ints."""


def as_masks(values: ArrayLike) -> MaskArray:
    """Contributor masks in their canonical array (a fresh, writable copy).

    ``uint64`` when every mask is below ``2**64``, else an ``object`` array of non-negative
    Python ints. A non-object numpy array is cast to ``uint64`` as ``numpy.array(values,
    dtype=numpy.uint64)`` does (the behaviour of 64-bit masks, unchanged); lists and object
    arrays may hold ints of any size.

    Raises
    ------
    ValueError
        A negative mask, or one that is not an integer (only for values that do not fit
        ``uint64``).
    """
    if isinstance(values, np.ndarray) and values.dtype != object:
        return np.array(values, dtype=np.uint64, copy=True)
    try:
        return np.array(values, dtype=np.uint64, copy=True)
    except (OverflowError, TypeError, ValueError):
        pass
    a = np.asarray(values, dtype=object)
    flat: list[int] = []
    for v in a.reshape(-1).tolist():
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"a contributor mask must be an integer, got {v!r}")
        if v < 0:
            raise ValueError(f"a contributor mask must not be negative, got {v}")
        flat.append(int(v))
    if all(v < MASK_WORD for v in flat):
        return np.array(flat, dtype=np.uint64).reshape(a.shape)
    out = np.empty(len(flat), dtype=object)
    out[:] = flat
    return out.reshape(a.shape)


def mask_array(n: int, mask: int) -> MaskArray:
    """``n`` copies of one contributor mask (``uint64`` below ``2**64``, else Python ints)."""
    if mask < MASK_WORD:
        return np.full(n, mask, dtype=np.uint64)
    out = np.empty(n, dtype=object)
    out[:] = [mask] * n
    return out


def mask_bytes(sources: MaskArray) -> bytes:
    """The bytes that identify a mask array, for digests: ``tobytes()`` of a ``uint64`` array
    (so every hash of maps of at most 64 robots is unchanged), and for an ``object`` array a
    marker, then per mask its byte count (4 bytes, little endian) and its bytes (little
    endian)."""
    if sources.dtype != object:
        return np.ascontiguousarray(sources).tobytes()
    parts = [b"wide-masks"]
    for v in sources.reshape(-1).tolist():
        raw = int(v).to_bytes((int(v).bit_length() + 7) // 8, "little")
        parts.append(len(raw).to_bytes(4, "little") + raw)
    return b"".join(parts)


def mask_or(sources: MaskArray) -> int:
    """The OR of every mask (0 for none): the set of contributors of a map."""
    if sources.size == 0:
        return 0
    if sources.dtype != object:
        return int(np.bitwise_or.reduce(sources))
    out = 0
    for v in sources.tolist():
        out |= int(v)
    return out


class Label(IntEnum):
    """Vertex labels of paper Sec. III-A."""

    NOMINAL = 0
    OCCLUSION = 1
    FRONTIER = 2

    @property
    def text(self) -> str:
        return self.name.lower()

    @classmethod
    def from_text(cls, text: str) -> Label:
        try:
            return cls[text.upper()]
        except KeyError:
            raise ValueError(f"unknown vertex label {text!r} (nominal, occlusion or frontier)") from None


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Wireframe:
    """A labelled directed embedded graph ``W = {V, E, phi, lambda}``.

    Parameters
    ----------
    points : (n, 2) float64
        Vertex positions ``phi(i)`` in metres.
    labels : (n,) uint8
        Vertex labels ``lambda(i)``, values of :class:`Label`.
    edges : (m, 2) int32
        Directed edges ``(i, j)``: the wall from ``p_i`` to ``p_j`` with free space on its left.
    likelihood : (m,) float64
        Per-edge existence likelihood in [0, 1].
    sources : (m,) uint64, or object (Python ints)
        Per-edge contributor bit mask (see the module docstring: ``object`` only when a mask
        has bit 64 or above; :func:`as_masks`).

    Raises
    ------
    ValueError
        When shapes disagree, an index is out of range, an edge is a self-loop, a coordinate is
        not finite, a label is unknown or a likelihood is outside [0, 1]. Use :meth:`build`
        for the forgiving constructor that accepts lists and fills defaults.
    """

    points: FloatArray
    labels: LabelArray
    edges: IndexArray
    likelihood: FloatArray
    sources: MaskArray

    def __post_init__(self) -> None:
        pts = _checked_points(self.points)
        n = pts.shape[0]
        labels = _checked_labels(self.labels, n)
        edges = _checked_edges(self.edges, n)
        m = edges.shape[0]
        lik = _checked_likelihood(self.likelihood, m)
        src = _checked_sources(self.sources, m)
        object.__setattr__(self, "points", _readonly(pts))
        object.__setattr__(self, "labels", _readonly(labels))
        object.__setattr__(self, "edges", _readonly(edges))
        object.__setattr__(self, "likelihood", _readonly(lik))
        object.__setattr__(self, "sources", _readonly(src))

    # ------------------------------------------------------------------ construction
    @classmethod
    def checked(
        cls,
        points: FloatArray,
        labels: LabelArray,
        edges: IndexArray,
        likelihood: FloatArray,
        sources: MaskArray,
    ) -> Wireframe:
        """A wireframe from arrays whose values the caller has already checked, without
        :meth:`__post_init__`'s value checks and copies.

        For the wire codec's decoder, which establishes every invariant while it reads the
        bits (finite coordinates on a bounded grid, labels 0..2, edge indices in range and no
        self-loop, likelihoods in fifteenths of [0, 1], non-negative masks): checking them
        again cost a robot map's decode a third of its time (issue 21). Only what is O(1) is
        checked here -- dtypes (float64 points and likelihoods, uint8 labels, int32 edges,
        uint64 or object masks), shapes and C order -- so a caller passing arrays of the
        wrong kind still gets a ``ValueError``; the values are trusted. The arrays are taken
        as they are (made read-only, not copied): the caller must hold no other reference it
        writes through. The result is the wireframe ``Wireframe(points, labels, edges,
        likelihood, sources)`` makes from the same valid arrays, bit for bit.
        """
        def fits(a: Any, dtypes: tuple[Any, ...], shape: tuple[int, ...]) -> bool:
            return (isinstance(a, np.ndarray) and a.dtype in dtypes and a.shape == shape
                    and a.flags.c_contiguous)

        n = points.shape[0] if isinstance(points, np.ndarray) and points.ndim == 2 else -1
        m = edges.shape[0] if isinstance(edges, np.ndarray) and edges.ndim == 2 else -1
        for name, a, dtypes, shape in (
            ("points", points, (np.float64,), (n, 2)),
            ("labels", labels, (np.uint8,), (n,)),
            ("edges", edges, (np.int32,), (m, 2)),
            ("likelihood", likelihood, (np.float64,), (m,)),
            ("sources", sources, (np.uint64, object), (m,)),
        ):
            if not fits(a, dtypes, shape):
                kinds = " or ".join(np.dtype(d).name for d in dtypes)
                raise ValueError(f"Wireframe.checked: {name} must be a C-ordered {kinds} array of shape "
                                 f"({'n' if name in ('points', 'labels') else 'm'}, ...) matching the others")
        return _trusted(points, labels, edges, likelihood, sources)

    @classmethod
    def build(
        cls,
        points: ArrayLike,
        edges: ArrayLike = (),
        labels: ArrayLike | None = None,
        likelihood: ArrayLike | None = None,
        sources: ArrayLike | None = None,
    ) -> Wireframe:
        """Forgiving constructor: lists welcome; labels default to nominal, likelihoods to 1."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.size == 0:
            pts = pts.reshape(0, 2)
        e = np.asarray(edges, dtype=np.int64)
        if e.size == 0:
            e = e.reshape(0, 2)
        n, m = pts.shape[0], e.shape[0]
        lab = np.zeros(n, np.uint8) if labels is None else np.asarray(labels)
        lik = np.ones(m) if likelihood is None else np.asarray(likelihood, dtype=np.float64)
        src = np.zeros(m, np.uint64) if sources is None else as_masks(sources)
        return cls(pts, lab, e, lik, src)  # type: ignore[arg-type]  # validated and cast in __post_init__

    @classmethod
    def empty(cls) -> Wireframe:
        return cls.build(np.zeros((0, 2)))

    @classmethod
    def from_polylines(
        cls, rings: Iterable[ArrayLike], closed: bool = True, likelihood: float = 1.0
    ) -> Wireframe:
        """Chains of corners joined in order (closed rings by default), all nominal."""
        pts: list[FloatArray] = []
        edges: list[tuple[int, int]] = []
        base = 0
        for ring in rings:
            r = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
            if closed and len(r) > 1 and np.allclose(r[0], r[-1]):
                r = r[:-1]
            k = len(r)
            pts.append(r)
            edges.extend((base + a, base + a + 1) for a in range(k - 1))
            if closed and k > 2:
                edges.append((base + k - 1, base))
            base += k
        allp = np.concatenate(pts) if pts else np.zeros((0, 2))
        return cls.build(allp, edges, likelihood=np.full(len(edges), likelihood))

    def replace(self, **changes: Any) -> Wireframe:
        """This wireframe with some arrays replaced (``points``, ``labels``, ``edges``,
        ``likelihood``, ``sources``): ``Wireframe(**fields)`` with the other fields taken from
        ``self``, the same result and the same ``ValueError``s. Only what can have changed is
        checked and copied: the new arrays, and the unchanged ones whose validity depends on a
        count that changed (labels and edges on the vertex count, likelihoods and sources on the
        edge count); the others are this wireframe's own read-only arrays, shared.
        ``replace()`` without changes checks and copies every array (a full re-validation)."""
        if not changes:
            return Wireframe(self.points, self.labels, self.edges, self.likelihood, self.sources)
        unknown = set(changes) - _FIELDS
        if unknown:
            raise TypeError(f"replace() got an unexpected keyword argument {sorted(unknown)[0]!r}")
        def pick(name: str, same_count: bool, check: Callable[[Any, int], Any], count: int) -> Any:
            if name not in changes and same_count:
                return getattr(self, name)  # valid for this count already
            return check(changes.get(name, getattr(self, name)), count)

        pts = _checked_points(changes["points"]) if "points" in changes else self.points
        n = pts.shape[0]
        labels = pick("labels", n == self.n_vertices, _checked_labels, n)
        edges = pick("edges", n == self.n_vertices, _checked_edges, n)
        m = edges.shape[0]
        lik = pick("likelihood", m == self.n_edges, _checked_likelihood, m)
        src = pick("sources", m == self.n_edges, _checked_sources, m)
        return _trusted(pts, labels, edges, lik, src)

    # ------------------------------------------------------------------ queries
    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    def __len__(self) -> int:
        return self.n_vertices

    def __repr__(self) -> str:
        counts = np.bincount(self.labels, minlength=3) if self.n_vertices else np.zeros(3, int)
        return (
            f"Wireframe(vertices={self.n_vertices} [nominal={counts[0]} occlusion={counts[1]} "
            f"frontier={counts[2]}], edges={self.n_edges})"
        )

    def segments(self) -> FloatArray:
        """Edge geometry as ``(m, 2, 2)``: ``[k, 0]`` is the start, ``[k, 1]`` the end."""
        if self.n_edges == 0:
            return np.zeros((0, 2, 2))
        return self.points.take(self.edges, axis=0)  # (take: a row gather, 5x faster than [ ])

    def edge_lengths(self) -> FloatArray:
        s = self.segments()
        return np.asarray(np.hypot(*(s[:, 1] - s[:, 0]).T), dtype=np.float64)

    def total_length(self) -> float:
        return float(self.edge_lengths().sum())

    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)``; raises ``ValueError`` on an empty wireframe."""
        if self.n_vertices == 0:
            raise ValueError("an empty wireframe has no bounds")
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    def degree(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(in_degree, out_degree)`` per vertex."""
        n = self.n_vertices
        return (
            np.bincount(self.edges[:, 1], minlength=n).astype(np.int64),
            np.bincount(self.edges[:, 0], minlength=n).astype(np.int64),
        )

    # ------------------------------------------------------------------ transforms
    def transformed(self, pose: Pose) -> Wireframe:
        """This wireframe moved by ``pose`` (its points mapped from pose's frame to the parent)."""
        return self.moved_to(pose.apply(self.points))

    def moved_to(
        self, points: FloatArray, *, likelihood: FloatArray | None = None, sources: MaskArray | None = None
    ) -> Wireframe:
        """This wireframe's labels and edges with new ``points`` (float64, ``(n, 2)``, C order:
        a transform or a rounding of this wireframe's), and optionally new ``likelihood`` and
        ``sources`` (valid arrays of the stored kinds, :meth:`checked`).

        Only the points are checked (finite; a non-finite one raises the constructor's
        ``ValueError``, naming the vertex): the other arrays are this valid wireframe's,
        shared read-only. The full checks cost a robot map's quarantine a fifth of its time
        and the fold's leaves as much (issue 21)."""
        lik = self.likelihood if likelihood is None else likelihood
        src = self.sources if sources is None else sources
        if not np.isfinite(points).all():
            return Wireframe(points, self.labels, self.edges, lik, src)  # raises
        return Wireframe.checked(points, self.labels, self.edges, lik, src)

    def subgraph_edges(self, keep: NDArray[np.bool_]) -> Wireframe:
        """Keep the edges where ``keep`` is true; vertices left without an edge are dropped."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (self.n_edges,):
            raise ValueError(f"edge mask must have shape ({self.n_edges},), got {keep.shape}")
        if self.sources.dtype == object:  # masks past bit 63: as_masks picks the array kind again
            src = as_masks(self.sources[keep])
        else:
            src = self.sources[keep]
        # A subset of valid arrays is valid: no checks (the arrays are fresh copies).
        return _trusted(self.points, self.labels, self.edges.compress(keep, axis=0), self.likelihood[keep],
                        src).compacted()

    def compacted(self) -> Wireframe:
        """Drop vertices that no edge uses and renumber (order of the rest is kept)."""
        n = self.n_vertices
        used = np.zeros(n, dtype=bool)
        used[self.edges.reshape(-1)] = True
        if used.all():
            return self
        remap = (np.cumsum(used) - 1).astype(np.int32)
        return _trusted(self.points.compress(used, axis=0), self.labels[used], remap[self.edges],
                        self.likelihood, self.sources)

    # ------------------------------------------------------------------ comparison
    def almost_equal(self, other: Wireframe, tol: float = 1e-9, likelihood_tol: float = 1e-9) -> bool:
        """Same graph up to vertex and edge order: a one-to-one vertex matching within ``tol``
        metres with equal labels, and the same directed edges with likelihoods within
        ``likelihood_tol`` and equal sources."""
        if self.n_vertices != other.n_vertices or self.n_edges != other.n_edges:
            return False
        if self.n_vertices == 0:
            return True
        if _surely_differ(self, other, tol, likelihood_tol):
            return False
        perm = _match_vertices(self.points, other.points, tol)
        if perm is None or np.any(self.labels != other.labels[perm]):
            return False
        mine = sorted(
            (int(perm[a]), int(perm[b]), float(lk), int(s))
            for (a, b), lk, s in zip(self.edges, self.likelihood, self.sources)
        )
        theirs = sorted(
            (int(a), int(b), float(lk), int(s))
            for (a, b), lk, s in zip(other.edges, other.likelihood, other.sources)
        )
        return all(
            x[0] == y[0] and x[1] == y[1] and abs(x[2] - y[2]) <= likelihood_tol and x[3] == y[3]
            for x, y in zip(mine, theirs)
        )

    def content_digest(self) -> bytes:
        """A 16-byte digest of the arrays (shape and bytes of points, labels, edges, likelihood,
        sources, in that order).

        Two wireframes have equal digests exactly when their arrays are byte for byte equal
        (up to the BLAKE2b collision odds of 2**-128): the same vertices and edges in the same
        order. It is the identity of a map's content, for caches and for "did it change";
        :meth:`almost_equal` is the comparison up to order and rounding.

        Returns
        -------
        bytes
            ``blake2b(digest_size=16)`` over ``str(a.shape)`` and ``a.tobytes()`` of each array
            (:func:`mask_bytes` for the sources: the same bytes for ``uint64`` masks).

        Notes
        -----
        Computed once per object and kept (the arrays are read-only: the content cannot
        change); the fusion service compares each robot's new map with its last one, which
        recomputed the old map's digest for every arrival.
        """
        cached: bytes | None = self.__dict__.get("_digest")
        if cached is not None:
            return cached
        h = hashlib.blake2b(digest_size=16)
        for a in (self.points, self.labels, self.edges, self.likelihood):
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(str(self.sources.shape).encode())
        h.update(mask_bytes(self.sources))
        digest = h.digest()
        object.__setattr__(self, "_digest", digest)
        return digest

    # ------------------------------------------------------------------ storage
    def paper_storage_bytes(self) -> int:
        """Storage by the paper's accounting (Sec. IV-G): 10 bytes per vertex (two 4-byte
        coordinates, a 2-byte label) plus 10 bytes per edge (two 5-byte indices).
        42 vertices and 42 edges give 840 bytes; 293 and 298 give 5,910."""
        return paper_storage_bytes(self.n_vertices, self.n_edges)

    # ------------------------------------------------------------------ GeoJSON
    def to_geojson(self, properties: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """A GeoJSON FeatureCollection: one ``Point`` per vertex, then one ``LineString`` per
        edge (coordinates in edge direction). Vertices carry ``index``; walls carry ``from`` and
        ``to`` vertex indices, so that :meth:`from_geojson` round-trips exactly even when two
        vertices share a position. ``properties`` go on the collection's ``properties``."""
        feats: list[dict[str, Any]] = []
        for i, ((x, y), lab) in enumerate(zip(self.points.tolist(), self.labels.tolist())):
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "Point", "coordinates": [x, y]},
                    "properties": {"kind": "corner", "label": Label(lab).text, "index": i},
                }
            )
        for (a, b), lk, src in zip(self.edges.tolist(), self.likelihood.tolist(), self.sources.tolist()):
            props: dict[str, Any] = {"kind": "wall", "likelihood": lk, "from": a, "to": b}
            if src:
                props["sources"] = int(src)
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {
                        "type": "LineString",
                        "coordinates": [self.points[a].tolist(), self.points[b].tolist()],
                    },
                    "properties": props,
                }
            )
        fc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
        if properties:
            fc["properties"] = dict(properties)
        return fc

    @classmethod
    def from_geojson(cls, doc: Mapping[str, Any] | str) -> Wireframe:
        """Read what :meth:`to_geojson` writes. Walls without ``from``/``to`` are joined to the
        corner at exactly their end coordinates (a new nominal corner where there is none).
        Raises ``ValueError`` naming the feature that is wrong."""
        if isinstance(doc, str):
            doc = json.loads(doc)
        if not isinstance(doc, Mapping) or doc.get("type") != "FeatureCollection":
            raise ValueError("expected a GeoJSON FeatureCollection")
        feats = doc.get("features")
        if not isinstance(feats, list):
            raise ValueError("FeatureCollection has no 'features' list")
        pts: list[tuple[float, float]] = []
        labels: list[int] = []
        index_of: dict[tuple[float, float], int] = {}
        walls: list[tuple[int, dict[str, Any]]] = []
        for k, f in enumerate(feats):
            geom = (f or {}).get("geometry") or {}
            props = (f or {}).get("properties") or {}
            gtype = geom.get("type")
            if gtype == "Point" and props.get("kind", "corner") == "corner":
                try:
                    x, y = (float(c) for c in geom["coordinates"][:2])
                    lab = Label.from_text(str(props.get("label", "nominal")))
                except (KeyError, TypeError, ValueError) as exc:
                    raise ValueError(f"feature {k}: bad corner: {exc}") from None
                if "index" in props and props["index"] != len(pts):
                    raise ValueError(f"feature {k}: corner index {props['index']} out of order")
                index_of.setdefault((x, y), len(pts))
                pts.append((x, y))
                labels.append(int(lab))
            elif gtype == "LineString" and props.get("kind", "wall") == "wall":
                walls.append((k, f))
            else:
                raise ValueError(f"feature {k}: unsupported {gtype} of kind {props.get('kind')!r}")
        edges: list[tuple[int, int]] = []
        lik: list[float] = []
        src: list[int] = []
        for k, f in walls:
            props = f.get("properties") or {}
            coords = f["geometry"].get("coordinates")
            if not isinstance(coords, list) or len(coords) != 2:
                raise ValueError(f"feature {k}: a wall is a LineString of exactly two points")
            if "from" in props and "to" in props:
                a, b = int(props["from"]), int(props["to"])
            else:
                ends = []
                for c in coords:
                    key = (float(c[0]), float(c[1]))
                    if key not in index_of:
                        index_of[key] = len(pts)
                        pts.append(key)
                        labels.append(int(Label.NOMINAL))
                    ends.append(index_of[key])
                a, b = ends
            edges.append((a, b))
            try:
                lik.append(float(props.get("likelihood", 1.0)))
                src.append(int(props.get("sources", 0)))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"feature {k}: bad wall property: {exc}") from None
        try:
            return cls.build(np.array(pts, dtype=np.float64).reshape(-1, 2), edges, labels, lik, src)
        except ValueError as exc:
            raise ValueError(f"invalid wireframe in GeoJSON: {exc}") from None


def paper_storage_bytes(n_vertices: int, n_edges: int) -> int:
    """The paper's storage accounting (Sec. IV-G): ``10 |V| + 10 |E|`` bytes per wireframe."""
    return 10 * int(n_vertices) + 10 * int(n_edges)


def _surely_differ(a: Wireframe, b: Wireframe, tol: float, likelihood_tol: float | None = None) -> bool:
    """A cheap test that ``a.almost_equal(b, tol, likelihood_tol)`` is false (same sizes
    assumed): a one-to-one matching within ``tol`` leaves the sorted x and the sorted y
    coordinates within ``tol`` of each other, the sorted labels and sources equal and the
    sorted likelihoods within ``likelihood_tol`` (default ``tol``). Maps that changed -- the
    usual case for the fusion service -- are told apart without the matching."""
    lt = tol if likelihood_tol is None else likelihood_tol
    if a.n_vertices and float(np.abs(np.sort(a.points, axis=0) - np.sort(b.points, axis=0)).max()) > tol:
        return True
    if not np.array_equal(np.sort(a.labels), np.sort(b.labels)):
        return True
    if a.n_edges:
        if float(np.abs(np.sort(a.likelihood) - np.sort(b.likelihood)).max()) > lt:
            return True
        if not np.array_equal(np.sort(a.sources), np.sort(b.sources)):
            return True
    return False


def _match_vertices(a: FloatArray, b: FloatArray, tol: float) -> NDArray[np.int64] | None:
    """A permutation ``perm`` with ``|a[i] - b[perm[i]]| <= tol`` for all i, or None."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    tree = cKDTree(b)
    d, j = tree.query(a, k=1)
    if np.all(d <= tol) and len(np.unique(j)) == len(j):
        return np.asarray(j, dtype=np.int64)
    # Ambiguous (several vertices within tol): a perfect matching of within-tol pairs exists iff
    # the assignment minimising the number of pairs farther than tol has none (minimising the
    # summed distance instead could pick a pair beyond tol when a feasible matching exists).
    dist = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    rows, cols = linear_sum_assignment((dist > tol).astype(np.float64) + dist * 1e-12)
    if not np.all(dist[rows, cols] <= tol):
        return None
    perm = np.empty(len(a), dtype=np.int64)
    perm[rows] = cols
    return perm


_FIELDS = frozenset(("points", "labels", "edges", "likelihood", "sources"))


def _trusted(points: Any, labels: Any, edges: Any, likelihood: Any, sources: Any) -> Wireframe:
    """A wireframe from arrays of the right dtypes and shapes whose values are valid (checked
    by the ``_checked_*`` functions, or derived from a wireframe's arrays by an operation that
    keeps them valid), taken as they are and made read-only: each must be a fresh array or a
    wireframe's own read-only one."""
    wf = object.__new__(Wireframe)
    object.__setattr__(wf, "points", _readonly(points))
    object.__setattr__(wf, "labels", _readonly(labels))
    object.__setattr__(wf, "edges", _readonly(edges))
    object.__setattr__(wf, "likelihood", _readonly(likelihood))
    object.__setattr__(wf, "sources", _readonly(sources))
    return wf


def _checked_points(points: Any) -> FloatArray:
    """``Wireframe.points`` from the argument: a float64 (n, 2) copy, every value finite."""
    pts = np.array(points, dtype=np.float64, copy=True)
    if pts.size == 0:
        pts = pts.reshape(0, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        bad = int(np.argwhere(~np.isfinite(pts))[0, 0])
        raise ValueError(f"vertex {bad} has a non-finite coordinate")
    return pts


def _checked_labels(labels: Any, n: int) -> LabelArray:
    """``Wireframe.labels`` for ``n`` vertices: a uint8 (n,) copy of known labels."""
    labels_in = np.asarray(labels)
    if labels_in.shape != (n,):
        raise ValueError(f"labels must have shape ({n},), got {labels_in.shape}")
    if n and (np.any(labels_in < 0) or np.any(labels_in > max(Label))):
        raise ValueError("labels must be 0 (nominal), 1 (occlusion) or 2 (frontier)")
    return labels_in.astype(np.uint8, copy=True)


def _checked_edges(edges: Any, n: int) -> IndexArray:
    """``Wireframe.edges`` for ``n`` vertices: an int32 (m, 2) copy, indices in range, no
    self-loop."""
    e_in = np.asarray(edges)
    if e_in.size == 0:
        e_in = e_in.reshape(0, 2)
    if e_in.ndim != 2 or e_in.shape[1] != 2:
        raise ValueError(f"edges must have shape (m, 2), got {e_in.shape}")
    if e_in.size and not np.issubdtype(e_in.dtype, np.integer):
        if not np.all(np.equal(np.mod(e_in, 1), 0)):
            raise ValueError("edge indices must be integers")
    m = e_in.shape[0]
    if m and (e_in.min() < 0 or e_in.max() >= n):
        bad = int(np.argwhere((e_in < 0) | (e_in >= n))[0, 0])
        raise ValueError(f"edge {bad} {tuple(int(v) for v in e_in[bad])} has a vertex index "
                         f"outside 0..{n - 1}")
    out = e_in.astype(np.int32, copy=True)
    if m and np.any(out[:, 0] == out[:, 1]):
        bad = int(np.argwhere(out[:, 0] == out[:, 1])[0, 0])
        raise ValueError(f"edge {bad} is a self-loop on vertex {int(out[bad, 0])}")
    return out


def _checked_likelihood(likelihood: Any, m: int) -> FloatArray:
    """``Wireframe.likelihood`` for ``m`` edges: a float64 (m,) copy within [0, 1]."""
    lik = np.array(likelihood, dtype=np.float64, copy=True).reshape(-1)
    if lik.shape != (m,):
        raise ValueError(f"likelihood must have shape ({m},), got {lik.shape}")
    if m and (not np.all(np.isfinite(lik)) or lik.min() < 0.0 or lik.max() > 1.0):
        raise ValueError("edge likelihoods must be finite and within [0, 1]")
    return lik


def _checked_sources(sources: Any, m: int) -> MaskArray:
    """``Wireframe.sources`` for ``m`` edges: the canonical mask array (:func:`as_masks`)."""
    try:
        src = as_masks(sources).reshape(-1)
    except ValueError as exc:
        raise ValueError(f"sources: {exc}") from None
    if src.shape != (m,):
        raise ValueError(f"sources must have shape ({m},), got {src.shape}")
    return src
