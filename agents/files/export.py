"""Map files in and out: wireframe -> occupancy raster -> ROS ``map_server`` PGM + YAML, and
the loaders/writers behind ``wiremap export`` and ``wiremap watch --save``.

The ROS map (``rosmap``) is what Nav2's ``map_server`` loads: a binary PGM (``P5``, 8 bit) and a
YAML file naming it. Each cell of the raster is one of three values:

* **free (254)**: the cell centre lies inside :func:`mapping.metrics.free_space`, i.e. inside
  a closed face whose walls see it from their free (left) side;
* **occupied (0)**: every cell a wall segment passes through or touches (a conservative
  "supercover" line, so a wall is at least one cell thick and 4-connected: no diagonal gap a
  planner could slip through), plus every cell whose centre lies inside a closed face the walls
  see from their *solid* side (the inside of a pillar, the material between two rooms);
* with a robot's track (``wiremap export --trajectory``), also **free**: what the walls let a
  sensor at the track's positions see within its range (:func:`seen_free`), since a map of a
  real building rarely closes its rooms (a doorway, a wall never seen); with real scans
  (``wiremap map --carmen/--rosbag``), what their beams crossed (:func:`scan_free`);
* **unknown (205)**: everything else: outside every closed face (unexplored space, the outside
  of the building, the open side of an incomplete room) and inside faces whose walls give no
  directed evidence (e.g. a box closed only by thin, two-sided walls).

With the YAML's ``negate: 0``, ``occupied_thresh: 0.65`` and ``free_thresh: 0.196``,
``map_server`` reads 254 as free (``(255 - 254) / 255 < 0.196``), 0 as occupied and 205 as
unknown (``(255 - 205) / 255 = 0.19608``, just above ``free_thresh``); the YAML says
``mode: trinary`` so the three values are kept as such.

Grid placement: cells are squares of side ``resolution`` whose *centres* lie on multiples of
the resolution (so a wall at such a coordinate runs through the middle of its cells, and grids
of maps in one frame line up); the grid spans the wireframe's bounding box plus a margin of
``margin`` unknown cells (default 2) on every side. Row 0 of the image (and of :attr:`OccupancyGrid.data`)
is the *top* of the map (largest y), as PGM and ``map_server`` expect; the YAML ``origin`` is
the pose of the lower-left corner of the lower-left cell, yaw 0.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from agents.errors import UserError
from agents.files.io import is_number, load_wireframe_geojson, write_atomic, write_json
from mapping.wireframe import Wireframe

FREE = 254
OCCUPIED = 0
UNKNOWN = 205

#: ``map_server`` thresholds written to the YAML (the values its documentation uses).
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
#: How far a robot's track saw walls (``wiremap export --sensor-range``): the simulator's range.
DEFAULT_SENSOR_RANGE = 8.0
#: Free space from a beam that met no wall (``--open-range``): a real map lacks walls the
#: scanner saw, and nothing beyond them is known to be free.
DEFAULT_OPEN_RANGE = 2.0

DEFAULT_RESOLUTION = 0.05
DEFAULT_MARGIN = 2

#: Largest raster :func:`occupancy_grid` agrees to build (cells).
MAX_CELLS = 100_000_000

FORMATS = ("geojson", "svg", "png", "rosmap")

Uint8Array = NDArray[np.uint8]
FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------- loading maps
@dataclass(frozen=True)
class LoadedMap:
    """A map file's wireframe and what the file says about it.

    Attributes
    ----------
    wireframe : the map.
    properties : GeoJSON ``properties`` of the collection (for a ``.geojson``) or the message's
        metadata (for a ``.wfm``: ``kind``, ``sender``, ``seq``, ``stamp_ns``, ``frame``,
        ``resolution``, ``robots`` and ``meta``).
    """

    wireframe: Wireframe
    properties: dict[str, Any]


def message_properties(msg: Any, world: str | None = None) -> dict[str, Any]:
    """The JSON-able metadata of a :class:`wire_codec.MapMessage` (everything but the map): the
    one schema of every map GeoJSON wiremap writes (``wiremap run``'s ``fused.geojson``,
    ``wiremap export``, ``wiremap watch --save``).

    Every map: ``kind`` (``fused_map`` / ``robot_map``), ``sender``, ``stamp_ns``, ``frame``,
    ``resolution`` (the quantisation step, m), ``robots``. A fused map adds ``version``,
    ``merge_threshold`` (m), ``stale`` (robots whose token is gone) and, when known,
    ``sim_time_s`` and ``world``; a robot map adds ``seq``. Other metadata goes under ``meta``.
    """
    from wire_codec import MessageKind

    meta = dict(msg.meta) if isinstance(msg.meta, dict) else {}
    props: dict[str, Any] = {
        "kind": getattr(msg.kind, "name", str(msg.kind)).lower(),
        "sender": msg.sender,
    }
    if world is not None:
        props["world"] = world
    if msg.kind == MessageKind.FUSED_MAP:
        from agents.fleet.fusion.state import merge_threshold_of

        props["version"] = int(msg.seq)
        props["merge_threshold"] = merge_threshold_of(msg)
        stale = meta.pop("stale", [])
        props["stale"] = [str(r) for r in stale] if isinstance(stale, (list, tuple)) else []
        t = meta.pop("t", None)
        if isinstance(t, (int, float)) and not isinstance(t, bool):
            props["sim_time_s"] = float(t)
        meta.pop("threshold", None)
        meta.pop("version", None)
    else:
        props["seq"] = int(msg.seq)
    props.update(
        {"stamp_ns": int(msg.stamp_ns), "frame": msg.frame, "resolution": float(msg.resolution),
         "robots": list(msg.robots)}
    )
    if meta:
        props["meta"] = _jsonable(meta)
    return props


def wireframe_geojson(wf: Wireframe, properties: dict[str, Any] | None = None) -> dict[str, Any]:
    """The map GeoJSON: :meth:`Wireframe.to_geojson` with ``properties`` on the collection and,
    when they list the map's ``robots``, each wall's contributing ``robots`` (bit ``k`` of its
    ``sources`` is ``robots[k]``)."""
    doc = wf.to_geojson(properties)
    robots = (properties or {}).get("robots")
    if isinstance(robots, list) and robots:
        for f in doc["features"]:
            p = f["properties"]
            if p.get("kind") == "wall":
                mask = int(p.get("sources", 0))
                p["robots"] = [r for k, r in enumerate(robots) if (mask >> k) & 1]
    return doc


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, bytes):
        return obj.hex()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def load_map(path: str | os.PathLike[str]) -> LoadedMap:
    """Read a map file: a ``.wfm`` (one :mod:`wire_codec` message) or a ``.geojson``/``.json``.

    The suffix decides; a file with another suffix is tried as a ``.wfm`` when it does not
    start with ``{`` and as GeoJSON otherwise.

    Raises
    ------
    UserError
        A missing or unreadable file, or one that is neither format, with the reason on one line.
    """
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such file")
    if p.is_dir():
        raise UserError(f"{p}: is a directory, not a map file")
    suffix = p.suffix.lower()
    if suffix in (".geojson", ".json"):
        loaded = load_wireframe_geojson(p)
        return LoadedMap(loaded, _geojson_properties(p))
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise UserError(f"{p}: {exc.strerror}") from None
    if suffix != ".wfm" and data.lstrip()[:1] == b"{":
        return LoadedMap(load_wireframe_geojson(p), _geojson_properties(p))
    return LoadedMap(*_decode_wfm(p, data))


def _geojson_properties(p: Path) -> dict[str, Any]:
    from agents.files.io import read_json

    doc = read_json(p)
    props = doc.get("properties") if isinstance(doc, dict) else None
    return dict(props) if isinstance(props, dict) else {}


def _decode_wfm(p: Path, data: bytes) -> tuple[Wireframe, dict[str, Any]]:
    try:
        from wire_codec import decode
    except ImportError:  # pragma: no cover - the codec is part of the package
        raise UserError(f"{p}: cannot read .wfm files: wire_codec.decode is not available") from None
    try:
        msg = decode(data)
    except ValueError as exc:  # CodecError derives from ValueError
        raise UserError(f"{p}: not a valid wiremap message (.wfm): {exc}") from None
    return msg.wireframe, message_properties(msg)


# ---------------------------------------------------------------------------- occupancy raster
@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """An 8-bit occupancy raster in ``map_server`` values.

    Attributes
    ----------
    data : (height, width) uint8
        :data:`FREE`, :data:`OCCUPIED` or :data:`UNKNOWN`; row 0 is the top (largest y).
    resolution : float
        Cell side in metres.
    origin : (x, y)
        Map coordinates of the lower-left corner of the lower-left cell (``data[-1, 0]``).
    """

    data: Uint8Array
    resolution: float
    origin: tuple[float, float]

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """``(row, col)`` of the cell containing the map point ``(x, y)`` (row 0 at the top)."""
        col = math.floor((x - self.origin[0]) / self.resolution)
        row_from_bottom = math.floor((y - self.origin[1]) / self.resolution)
        return self.height - 1 - row_from_bottom, col

    def value_at(self, x: float, y: float) -> int:
        """The cell value at map point ``(x, y)``; ``IndexError`` outside the grid."""
        r, c = self.cell_of(x, y)
        if not (0 <= r < self.height and 0 <= c < self.width):
            raise IndexError(f"({x}, {y}) is outside the grid")
        return int(self.data[r, c])


def grid_geometry(
    bounds: tuple[float, float, float, float], resolution: float, margin: int = DEFAULT_MARGIN
) -> tuple[tuple[float, float], int, int]:
    """``(origin, width, height)`` of the grid covering ``bounds = (xmin, ymin, xmax, ymax)``.

    Cell centres sit on integer multiples of ``resolution`` (cell ``k`` spans
    ``[(k - 1/2) r, (k + 1/2) r)``), so a wall at a coordinate that is a multiple of the
    resolution runs through the middle of its cells and the grids of all maps in one frame line
    up. The grid spans the cells containing the bounds plus ``margin`` cells on every side.

    Raises
    ------
    ValueError
        For a non-positive resolution, a negative margin or more than :data:`MAX_CELLS` cells.
    """
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0 cells, got {margin}")
    xmin, ymin, xmax, ymax = bounds
    i0 = math.floor(xmin / resolution + 0.5) - margin
    j0 = math.floor(ymin / resolution + 0.5) - margin
    i1 = math.floor(xmax / resolution + 0.5) + margin
    j1 = math.floor(ymax / resolution + 0.5) + margin
    width, height = i1 - i0 + 1, j1 - j0 + 1
    if width * height > MAX_CELLS:
        raise ValueError(
            f"a {width} x {height} raster at resolution {resolution} m is too large "
            f"(more than {MAX_CELLS:,} cells); use a coarser resolution"
        )
    return ((i0 - 0.5) * resolution, (j0 - 0.5) * resolution), width, height


def fill_polygons(
    geom: Any, origin: tuple[float, float], resolution: float, width: int, height: int
) -> NDArray[np.bool_]:
    """Cells whose centre lies inside the (multi)polygon ``geom``, by scanline (even-odd rule).

    Returns a ``(height, width)`` boolean raster with row 0 at the *bottom* (row ``j`` has
    centre ``y = origin[1] + (j + 0.5) * resolution``). Every ring (exteriors and holes) is
    crossed with each row's centre line; pairs of crossings bound the inside. A centre exactly
    on the boundary may fall either way (callers draw walls over boundaries anyway). Runs in
    time proportional to cells plus crossings, unlike a point-in-polygon test per cell.
    """
    out = np.zeros((height, width), dtype=bool)
    if geom is None or geom.is_empty:
        return out
    polys = [g for g in shapely.get_parts(geom) if g.geom_type == "Polygon"]
    rings = [r for poly in polys for r in (poly.exterior, *poly.interiors)]
    if not rings:
        return out
    segs: list[FloatArray] = []
    for ring in rings:
        c = shapely.get_coordinates(ring)
        if len(c) >= 2:
            segs.append(np.stack([c[:-1], c[1:]], axis=1))
    s = np.concatenate(segs)
    # Grid units: cell j spans [j, j+1); its centre is at j + 0.5.
    p = (s - np.asarray(origin)) / resolution
    x0, y0, x1, y1 = p[:, 0, 0], p[:, 0, 1], p[:, 1, 0], p[:, 1, 1]
    lo, hi = np.minimum(y0, y1), np.maximum(y0, y1)
    # Rows whose centre c satisfies lo <= c < hi (half-open: a vertex is counted once).
    r_start = np.clip(np.ceil(lo - 0.5), 0, height).astype(np.int64)
    r_stop = np.clip(np.ceil(hi - 0.5), 0, height).astype(np.int64)
    counts = np.maximum(r_stop - r_start, 0)
    total = int(counts.sum())
    if total == 0:
        return out
    seg_idx = np.repeat(np.arange(len(s)), counts)
    offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    rows = r_start[seg_idx] + offsets
    yc = rows + 0.5
    t = (yc - y0[seg_idx]) / (y1[seg_idx] - y0[seg_idx])
    xc = x0[seg_idx] + t * (x1[seg_idx] - x0[seg_idx])
    order = np.lexsort((xc, rows))
    rows, xc = rows[order], xc[order]
    # Consecutive crossings on one row pair up (even-odd); every row has an even count.
    a_rows, a_x, b_x = rows[0::2], xc[0::2], xc[1::2]
    # Columns whose centre c satisfies a <= c < b.
    c_start = np.clip(np.ceil(a_x - 0.5), 0, width).astype(np.int64)
    c_stop = np.clip(np.ceil(b_x - 0.5), 0, width).astype(np.int64)
    keep = c_stop > c_start
    diff = np.zeros((height, width + 1), dtype=np.int32)
    np.add.at(diff, (a_rows[keep], c_start[keep]), 1)
    np.add.at(diff, (a_rows[keep], c_stop[keep]), -1)
    out = np.cumsum(diff[:, :width], axis=1) > 0
    return np.asarray(out, dtype=bool)


def wall_cells(
    segments: FloatArray, origin: tuple[float, float], resolution: float, width: int, height: int
) -> NDArray[np.bool_]:
    """Cells any of ``segments`` ``(m, 2, 2)`` passes through or touches (supercover).

    Returns a ``(height, width)`` boolean raster with row 0 at the *bottom*. For every column
    the segment crosses, the cells between the lowest and highest y of the segment within that
    column are marked, so the marked set is 4-connected along each segment (a segment running
    exactly along a line between cells marks the cells on its upper/right side; with the
    centring of :func:`grid_geometry` that only happens off the resolution's multiples). A
    zero-length segment marks its cell.
    """
    out = np.zeros((height, width), dtype=bool)
    if len(segments) == 0:
        return out
    p = (np.asarray(segments, dtype=np.float64) - np.asarray(origin)) / resolution
    # Order each segment left to right.
    swap = p[:, 0, 0] > p[:, 1, 0]
    p[swap] = p[swap][:, ::-1]
    x0, y0, x1, y1 = p[:, 0, 0], p[:, 0, 1], p[:, 1, 0], p[:, 1, 1]
    c0 = np.floor(x0).astype(np.int64)
    c1 = np.floor(x1).astype(np.int64)
    ncol = c1 - c0 + 1
    seg_idx = np.repeat(np.arange(len(p)), ncol)
    cols = c0[seg_idx] + (np.arange(int(ncol.sum())) - np.repeat(np.cumsum(ncol) - ncol, ncol))
    # The segment's x-range inside each column, then its y at both ends of that range.
    xa = np.maximum(x0[seg_idx], cols)
    xb = np.minimum(x1[seg_idx], cols + 1)
    dx = x1 - x0
    slope = np.divide(y1 - y0, dx, out=np.zeros_like(dx), where=dx > 0)[seg_idx]
    vertical = dx[seg_idx] <= 0
    ya = np.where(vertical, y0[seg_idx], y0[seg_idx] + slope * (xa - x0[seg_idx]))
    yb = np.where(vertical, y1[seg_idx], y0[seg_idx] + slope * (xb - x0[seg_idx]))
    r0 = np.floor(np.minimum(ya, yb)).astype(np.int64)
    r1 = np.floor(np.maximum(ya, yb)).astype(np.int64)
    # Clip to the grid (a segment never leaves a grid built from the wireframe's bounds, but
    # callers may pass any segments).
    ok = (cols >= 0) & (cols < width) & (r1 >= 0) & (r0 < height)
    cols, r0, r1 = cols[ok], np.clip(r0[ok], 0, height - 1), np.clip(r1[ok], 0, height - 1)
    nrow = r1 - r0 + 1
    idx = np.repeat(np.arange(len(cols)), nrow)
    rows = r0[idx] + (np.arange(int(nrow.sum())) - np.repeat(np.cumsum(nrow) - nrow, nrow))
    out[rows, cols[idx]] = True
    # The interpolated y at a column edge can round below an endpoint that lies exactly on a cell
    # boundary; the endpoints' own cells are marked outright.
    ends = np.floor(p.reshape(-1, 2)).astype(np.int64)
    inside = (ends[:, 0] >= 0) & (ends[:, 0] < width) & (ends[:, 1] >= 0) & (ends[:, 1] < height)
    out[ends[inside, 1], ends[inside, 0]] = True
    return out


def seen_free(
    wf: Wireframe,
    positions: ArrayLike,
    max_range: float,
    origin: tuple[float, float],
    resolution: float,
    width: int,
    height: int,
    rays: int = 720,
    spacing: float = 0.25,
    open_range: float = DEFAULT_OPEN_RANGE,
) -> NDArray[np.bool_]:
    """Cells (a raster as :func:`fill_polygons` returns, row 0 at the bottom) that the map's
    walls let a sensor see from ``positions`` ``(n, 2)``: from positions at least ``spacing``
    metres apart along the track (the first always), ``rays`` rays all round, each stopped by
    the first wall it meets within ``max_range``; a ray that meets no wall of the map goes
    ``open_range`` only. A cell is seen when its centre is nearer than both rays around its
    bearing (the shorter of the two: a cell behind a wall's end between two rays stays
    unseen).

    A map alone cannot say where free space is unless a room closes (an open map's rooms miss a
    wall or a doorway); the robot's own track can: what it could see past no wall it saw
    free. But a real map lacks walls the scanner did see (too short, too far, glass), and a ray
    through such a gap would call the obstacle behind it free: so free space is only claimed up
    to a wall the map has, or within ``open_range`` of the track where the map has none. All
    round, not the scanner's field of view (the track has no scanner heading)."""
    from agents.sim.lidar import LidarConfig, cast_ranges
    from mapping.se2 import Pose

    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    pos = pos[np.isfinite(pos).all(axis=1)]
    if len(pos) == 0 or not max_range > 0.0:
        return np.zeros((height, width), dtype=bool)
    keep = [0]
    for i in range(1, len(pos)):
        if np.hypot(*(pos[i] - pos[keep[-1]])) >= spacing:
            keep.append(i)
    # The simulator's ray caster, all round; the fan is closed by repeating the first ray a
    # turn later, and filled as a real scan's beams are (no hit = no return).
    lidar = LidarConfig(beams=rays, fov=2.0 * math.pi, max_range=max_range, sigma=0.0)
    bearings = np.append(lidar.angles(), lidar.angles()[0] + 2.0 * math.pi)
    segs = wf.segments()
    fans = []
    for x, y in pos[keep].tolist():
        r = cast_ranges(segs, Pose(x, y, 0.0), lidar)
        fans.append((np.append(r, r[0]), bearings))
    return scan_free([(x, y, 0.0) for x, y in pos[keep].tolist()], fans, max_range, origin, resolution,
                     width, height, open_range=open_range)


def scan_free(
    poses: ArrayLike,
    scans: Sequence[tuple[ArrayLike, ArrayLike]],
    max_range: float,
    origin: tuple[float, float],
    resolution: float,
    width: int,
    height: int,
    open_range: float = DEFAULT_OPEN_RANGE,
) -> NDArray[np.bool_]:
    """Cells (row 0 at the bottom) that real scans saw free: scan ``k`` = ``(ranges, bearings)``
    (radians, evenly spaced, the sensor's frame) taken at ``poses[k]`` = ``(x, y, theta)`` of
    the sensor. A cell is free when its centre lies between two neighbouring beams, nearer than
    both of their returns (a return at or beyond ``max_range``, zero or not finite is no
    return: such a beam counts as ``open_range`` long, as :func:`seen_free` does). The classic
    occupancy grid's free space, from the beams themselves rather than from the map."""
    out = np.zeros((height, width), dtype=bool)
    xs = origin[0] + (np.arange(width) + 0.5) * resolution
    ys = origin[1] + (np.arange(height) + 0.5) * resolution
    ps = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    for (x, y, th), (rr, aa) in zip(ps.tolist(), scans):
        r = np.asarray(rr, dtype=np.float64).reshape(-1)
        a = np.asarray(aa, dtype=np.float64).reshape(-1)
        if len(r) < 2 or len(a) != len(r) or not all(map(math.isfinite, (x, y, th))):
            continue
        if a[-1] < a[0]:
            r, a = r[::-1], a[::-1]
        step = (a[-1] - a[0]) / (len(a) - 1)
        if not step > 0.0:
            continue
        with np.errstate(invalid="ignore"):
            seen = np.isfinite(r) & (r > 0.0) & (r < max_range)
        r = np.where(seen, r, min(open_range, max_range))
        sector = np.minimum(r[:-1], r[1:])  # between beam k and beam k + 1
        if not sector.max(initial=0.0) > 0.0:
            continue
        # the cells the fan can reach: the box of the laser and its beams' ends
        ex = np.append(x + r * np.cos(th + a), x)
        ey = np.append(y + r * np.sin(th + a), y)
        # (plus a cell: a sector's arc bulges past the chord by r * step**2 / 8)
        i0 = max(0, math.floor((ex.min() - origin[0]) / resolution) - 1)
        i1 = min(width, math.floor((ex.max() - origin[0]) / resolution) + 2)
        j0 = max(0, math.floor((ey.min() - origin[1]) / resolution) - 1)
        j1 = min(height, math.floor((ey.max() - origin[1]) / resolution) + 2)
        if i0 >= i1 or j0 >= j1:
            continue
        dx = xs[i0:i1][None, :] - x
        dy = ys[j0:j1][:, None] - y
        rel = np.remainder(np.arctan2(dy, dx) - th - a[0], 2.0 * math.pi)
        k = np.floor(rel / step).astype(np.int64)
        inside = k < len(sector)
        lim = np.where(inside, sector[np.minimum(k, len(sector) - 1)], 0.0)
        out[j0:j1, i0:i1] |= np.hypot(dx, dy) < lim
    return out


def occupancy_grid(
    wf: Wireframe,
    resolution: float = DEFAULT_RESOLUTION,
    margin: int = DEFAULT_MARGIN,
    min_likelihood: float = 0.0,
    bounds: tuple[float, float, float, float] | None = None,
    tracks: Sequence[ArrayLike] = (),
    sensor_range: float = DEFAULT_SENSOR_RANGE,
    open_range: float = DEFAULT_OPEN_RANGE,
    scans: tuple[ArrayLike, Sequence[tuple[ArrayLike, ArrayLike]], float] | None = None,
) -> OccupancyGrid:
    """Rasterise a wireframe into ``map_server`` values (rules in the module docstring).

    Parameters
    ----------
    wf : Wireframe
        The map; must have at least one vertex (or pass ``bounds``).
    resolution : float
        Cell side in metres (default 0.05, Nav2's usual).
    margin : int
        Unknown cells added around the wireframe's bounding box on every side.
    min_likelihood : float
        Edges with a lower likelihood are dropped first (default 0: every edge counts).
    bounds : (xmin, ymin, xmax, ymax), optional
        Area to cover instead of the wireframe's bounding box.
    tracks : sequence of (n, 2) arrays
        Robots' positions: what their sensor could see within ``sensor_range`` metres, up to
        a wall of the map or ``open_range`` where none is in reach (:func:`seen_free`), is free
        too, under the rules above (a closed face's verdict and the walls are drawn over it).
    scans : (poses, scans, max_range), optional
        Real scans and the poses they were mapped at: what their beams crossed is free too
        (:func:`scan_free`), under the same rules.

    Returns
    -------
    OccupancyGrid

    Raises
    ------
    ValueError
        An empty wireframe without ``bounds``, a bad resolution or margin, or a raster over
        :data:`MAX_CELLS` cells.
    """
    from mapping.metrics import classify_faces

    if min_likelihood > 0.0 and wf.n_edges:
        wf = wf.subgraph_edges(wf.likelihood >= min_likelihood)
    if bounds is None:
        if wf.n_vertices == 0:
            raise ValueError("the map is empty: nothing to rasterise")
        bounds = wf.bounds()
    origin, width, height = grid_geometry(bounds, resolution, margin)
    grid = np.full((height, width), UNKNOWN, dtype=np.uint8)
    if scans is not None:
        grid[scan_free(scans[0], scans[1], scans[2], origin, resolution, width, height,
                       open_range=open_range)] = FREE
    for track in tracks:
        seen = seen_free(wf, track, sensor_range, origin, resolution, width, height, open_range=open_range)
        grid[seen] = FREE
    faces, votes = classify_faces(wf)
    free = [f for f, v in zip(faces, votes.tolist()) if v > 0.0]
    solid = [f for f, v in zip(faces, votes.tolist()) if v < 0.0]
    if solid:
        grid[fill_polygons(shapely.union_all(solid), origin, resolution, width, height)] = OCCUPIED
    if free:
        grid[fill_polygons(shapely.union_all(free), origin, resolution, width, height)] = FREE
    grid[wall_cells(wf.segments(), origin, resolution, width, height)] = OCCUPIED
    # Rows were built bottom-up; images run top-down.
    return OccupancyGrid(np.ascontiguousarray(grid[::-1]), float(resolution), origin)


# ---------------------------------------------------------------------------- PGM + YAML
def pgm_bytes(grid: OccupancyGrid, comment: str | None = None) -> bytes:
    """The grid as a binary 8-bit PGM (``P5``, maxval 255), row 0 first (the top of the map)."""
    header = "P5\n"
    if comment:
        header += "".join(f"# {line}\n" for line in comment.splitlines())
    header += f"{grid.width} {grid.height}\n255\n"
    return header.encode("ascii") + np.ascontiguousarray(grid.data, dtype=np.uint8).tobytes()


_PGM_TOKEN = re.compile(rb"(?:\s|#[^\n]*\n)*([0-9]+|P5)")


def read_pgm(data: bytes) -> Uint8Array:
    """Parse a binary 8-bit PGM (``P5``, maxval <= 255) into a ``(height, width)`` array.

    Raises ``ValueError`` for anything else (other magic, 16-bit, truncated data)."""
    pos = 0
    tokens: list[bytes] = []
    for _ in range(4):
        m = _PGM_TOKEN.match(data, pos)
        if m is None:
            raise ValueError("not a binary PGM (P5) header")
        tokens.append(m.group(1))
        pos = m.end()
    if tokens[0] != b"P5":
        raise ValueError(f"not a binary PGM: magic {tokens[0]!r}")
    width, height, maxval = (int(t) for t in tokens[1:])
    if not 0 < maxval < 256:
        raise ValueError(f"only 8-bit PGM is supported, maxval {maxval}")
    if pos >= len(data) or data[pos : pos + 1] not in (b" ", b"\n", b"\r", b"\t"):
        raise ValueError("PGM header must end with one whitespace character")
    pos += 1
    body = data[pos : pos + width * height]
    if len(body) != width * height:
        raise ValueError(f"PGM data truncated: {len(body)} of {width * height} bytes")
    return np.frombuffer(body, dtype=np.uint8).reshape(height, width).copy()


def _num(v: float) -> str:
    text = repr(round(float(v), 9))  # no binary noise: -0.175, not -0.17500000000000002
    return "0.0" if text == "-0.0" else text


def map_yaml(grid: OccupancyGrid, image: str) -> str:
    """The ``map_server`` YAML for ``grid`` whose PGM is ``image`` (a path relative to the
    YAML file's directory; normally just the file name)."""
    if any(ch in image for ch in "\n\r\"'#:") or image != image.strip():
        quoted = '"' + image.replace("\\", "\\\\").replace('"', '\\"') + '"'
    else:
        quoted = image
    return (
        f"image: {quoted}\n"
        "mode: trinary\n"
        f"resolution: {_num(grid.resolution)}\n"
        f"origin: [{_num(grid.origin[0])}, {_num(grid.origin[1])}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )


def rosmap_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``(pgm, yaml)`` paths for ``--out PATH``.

    ``PATH`` ending in ``.pgm``, ``.yaml`` or ``.yml`` names one of the two files and the other
    gets the same stem; any other ``PATH`` (``maps/floor``, ``maps/floor.v2``) is a stem to
    which ``.pgm`` and ``.yaml`` are appended.
    """
    p = Path(out)
    if p.suffix.lower() == ".pgm":
        return p, p.with_suffix(".yaml")
    if p.suffix.lower() in (".yaml", ".yml"):
        return p.with_suffix(".pgm"), p
    return p.with_name(p.name + ".pgm"), p.with_name(p.name + ".yaml")


def write_rosmap(
    wf: Wireframe,
    out: str | os.PathLike[str],
    resolution: float = DEFAULT_RESOLUTION,
    margin: int = DEFAULT_MARGIN,
    min_likelihood: float = 0.0,
    tracks: Sequence[ArrayLike] = (),
    sensor_range: float = DEFAULT_SENSOR_RANGE,
    open_range: float = DEFAULT_OPEN_RANGE,
    scans: tuple[ArrayLike, Sequence[tuple[ArrayLike, ArrayLike]], float] | None = None,
    bounds: tuple[float, float, float, float] | None = None,
) -> tuple[Path, Path, OccupancyGrid]:
    """Write ``map_server`` PGM + YAML for ``wf`` (paths from :func:`rosmap_paths`), each
    atomically, the PGM first. Returns ``(pgm_path, yaml_path, grid)``.

    Raises ``ValueError`` as :func:`occupancy_grid` does."""
    pgm_path, yaml_path = rosmap_paths(out)
    grid = occupancy_grid(wf, resolution, margin, min_likelihood, bounds=bounds, tracks=tracks,
                          sensor_range=sensor_range, open_range=open_range, scans=scans)
    write_atomic(pgm_path, pgm_bytes(grid, comment=f"wiremap occupancy map, {resolution:g} m/cell"))
    write_atomic(yaml_path, map_yaml(grid, pgm_path.name))
    return pgm_path, yaml_path, grid


# ---------------------------------------------------------------------------- other formats
def svg_text(wf: Wireframe) -> str:
    """The map as SVG (drawn by :func:`agents.files.render.wireframe_svg`)."""
    from agents.files import render

    return str(render.wireframe_svg(wf))


def png_bytes(wf: Wireframe, title: str = "map") -> bytes:
    """The map as PNG: the figure every command draws (:func:`agents.files.render.map_figure`)."""
    from agents.files import render

    return bytes(render.map_figure(wf, title=title))


def _title(props: dict[str, Any]) -> str:
    """A picture's title from a map's properties: what map it is and whose."""
    kind = str(props.get("kind", "map")).replace("_", " ")
    version = props.get("version", props.get("seq"))
    robots = props.get("robots") or []
    text = kind + (f" v{version}" if version is not None else "")
    if robots:
        text += " from " + ", ".join(str(r) for r in robots)
    if props.get("world"):
        text = f"{props['world']}: {text}"
    return text


def format_from_suffix(path: str | os.PathLike[str]) -> str | None:
    """The export format a file name implies (``.geojson``/``.json``, ``.svg``, ``.png``,
    ``.pgm``/``.yaml``/``.yml`` for rosmap), or None."""
    suffix = Path(path).suffix.lower()
    return {
        ".geojson": "geojson",
        ".json": "geojson",
        ".svg": "svg",
        ".png": "png",
        ".pgm": "rosmap",
        ".yaml": "rosmap",
        ".yml": "rosmap",
    }.get(suffix)


def export_map(
    loaded: LoadedMap,
    fmt: str,
    out: str | os.PathLike[str],
    resolution: float = DEFAULT_RESOLUTION,
    min_likelihood: float = 0.0,
    tracks: Sequence[ArrayLike] = (),
    sensor_range: float = DEFAULT_SENSOR_RANGE,
    open_range: float = DEFAULT_OPEN_RANGE,
) -> list[Path]:
    """Write ``loaded`` in format ``fmt`` to ``out``; returns the files written.

    ``geojson`` keeps the source's properties; ``svg``/``png`` draw the map with
    :mod:`agents.files.render`; ``rosmap`` writes PGM + YAML (:func:`write_rosmap`).

    Raises
    ------
    ValueError
        For an unknown format, or what the rasteriser rejects.
    """
    wf = loaded.wireframe
    if fmt != "rosmap" and min_likelihood > 0.0 and wf.n_edges:
        wf = wf.subgraph_edges(wf.likelihood >= min_likelihood)
    if fmt == "geojson":

        write_json(out, wireframe_geojson(wf, loaded.properties or None))
        return [Path(out)]
    if fmt == "svg":
        write_atomic(out, svg_text(wf))
        return [Path(out)]
    if fmt == "png":
        write_atomic(out, png_bytes(wf, title=_title(loaded.properties)))
        return [Path(out)]
    if fmt == "rosmap":
        pgm, yaml, _ = write_rosmap(wf, out, resolution, min_likelihood=min_likelihood, tracks=tracks,
                                    sensor_range=sensor_range, open_range=open_range)
        return [pgm, yaml]
    raise ValueError(f"unknown format {fmt!r}: use one of {', '.join(FORMATS)}")


def read_track(path: str | os.PathLike[str]) -> FloatArray:
    """Positions ``(n, 2)`` from a track file: whitespace-separated rows of ``t x y theta``
    (``wiremap map``'s ``trajectory.tsv``), ``x y theta`` (three columns are always read so)
    or ``x y`` (``wiremap run``'s ``tracks/``); ``#`` comments and a header line are skipped.
    A bad file is a one-line :class:`UserError`."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise UserError(f"--trajectory {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise UserError(f"--trajectory {p}: not a text file") from None
    rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if rows and not is_number(rows[0][0]):  # a header line (``t x y theta``)
        rows = rows[1:]
    if not rows:
        raise UserError(f"--trajectory {p}: no positions")
    width = len(rows[0])
    if width not in (2, 3, 4) or any(len(r) != width for r in rows):
        raise UserError(f"--trajectory {p}: expected rows of 't x y theta', 'x y theta' or 'x y'")
    try:
        a = np.array(rows, dtype=np.float64)
    except ValueError:
        raise UserError(f"--trajectory {p}: not numbers") from None
    xy = a[:, 1:3] if width == 4 else a[:, 0:2]
    if not np.isfinite(xy).all():
        raise UserError(f"--trajectory {p}: a position is not finite")
    return np.ascontiguousarray(xy)
