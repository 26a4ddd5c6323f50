"""``wiremap bench codec``: the wire codec's size and speed against other encodings.

For each map (by default the ground-truth wireframes of the built-in worlds ``paper-small`` at
0.2 m and ``museum`` at 0.4 m; ``--paper-small-map`` / ``--museum-map`` substitute a stored map,
e.g. the best particle of a filter run written as GeoJSON; ``--run-filter WORLD`` runs the
particle filter over that world first (10 particles, corner sensor, ``--filter-seed``,
``--filter-duration``; slow) and measures its best particle; ``--map`` adds one more) it reports:

* ``message_bytes``: the whole payload of :func:`wire_codec.encode` for a robot-map message
  with realistic metadata (sender ``r1``, a 4-digit sequence number, an epoch timestamp in ns,
  a pose and start pose off the origin, frame ``odom/r1``), split into ``body_bytes`` (the
  bit-packed wireframe) and ``envelope_bytes`` (everything else, CRC included);
* ``paper_accounting_bytes``: paper Sec. IV-G, ``10 |V| + 10 |E|``;
* ``msgpack_float_bytes``: the naive alternative, ``msgpack`` of the arrays as nested lists
  (float64 coordinates and likelihoods, int vertex indices and labels);
* ``png_grid_bytes``: the map as an occupancy grid at the same resolution, as an 8-bit
  grayscale PNG (map_server colours: free 254, wall 0, unknown 205; filter type 0 on every
  row; zlib level 9), counting the whole file (signature, IHDR, IDAT, IEND);
* ``ros_grid_bytes``: the same grid as a ROS 1 ``nav_msgs/OccupancyGrid`` message serialised on
  the wire: header (seq 4 + stamp 8 + frame_id ``"map"`` 4+3) + info (map_load_time 8,
  resolution 4, width 4, height 4, origin pose 7x8) + data (length 4 + width*height int8);
* ``encode_us`` / ``decode_us``: median wall time of one call, in microseconds.

The grid: the wireframe's bounds plus one cell on every side; free space is every face of the
wall arrangement (shapely ``polygonize``) that lies on the left of its nearest wall (the
direction convention), walls are rasterised by sampling each edge every quarter cell.

It prints an aligned table, the target checks, then one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import struct
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import shapely
from numpy.typing import NDArray

import wire_codec
from agents.errors import UserError
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.codec import encode_with_plan

HELP = "wire codec size and speed against other encodings"

#: The issue's targets.
TARGETS = {
    "paper_small": {"body_bytes": 96, "message_bytes": 160},
    "museum": {"message_bytes": 700, "codec_us": 1000},
}

FREE, WALL, UNKNOWN = 0, 100, -1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help="(kept for symmetry: the JSON line is always printed last)")
    parser.add_argument("--paper-small-map", metavar="FILE",
                        help="a stored GeoJSON map instead of paper-small's truth")
    parser.add_argument("--museum-map", metavar="FILE", help="a stored GeoJSON map instead of museum's truth")
    parser.add_argument("--map", metavar="FILE", help="one more map to measure (JSON key 'map')")
    parser.add_argument("--resolution", type=float, default=0.2,
                        help="resolution for --map in metres (default 0.2)")
    parser.add_argument("--repeat", type=int, default=300, help="timed calls per measurement (default 300)")
    parser.add_argument("--run-filter", action="append", default=[], choices=("paper-small", "museum"),
                        metavar="WORLD",
                        help="measure the best particle of a filter run over WORLD "
                             "(paper-small or museum; repeatable)")
    parser.add_argument("--filter-seed", type=int, default=1, help="seed of --run-filter (default 1)")
    parser.add_argument("--filter-duration", type=float, default=None,
                        help="simulated seconds of --run-filter (default: the whole route)")


# ---------------------------------------------------------------------------------------- grids
def occupancy_grid(wf: Wireframe, resolution: float) -> NDArray[np.int8]:
    """The wireframe as a ROS-style grid (``-1`` unknown, ``0`` free, ``100`` wall), row 0 at
    the bottom (``ymin``), covering the bounds plus one cell on every side."""
    if wf.n_vertices == 0:
        return np.full((1, 1), UNKNOWN, dtype=np.int8)
    xmin, ymin, xmax, ymax = wf.bounds()
    x0, y0 = xmin - resolution, ymin - resolution
    width = math.ceil((xmax - xmin) / resolution) + 2
    height = math.ceil((ymax - ymin) / resolution) + 2
    grid = np.full((height, width), UNKNOWN, dtype=np.int8)
    free = free_space(wf)
    if free is not None and not free.is_empty:
        shapely.prepare(free)
        cx = x0 + (np.arange(width) + 0.5) * resolution
        cy = y0 + (np.arange(height) + 0.5) * resolution
        gx, gy = np.meshgrid(cx, cy)
        inside = shapely.contains_xy(free, gx.ravel(), gy.ravel()).reshape(height, width)
        grid[inside] = FREE
    seg = wf.segments()
    if len(seg):
        length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
        steps = np.maximum(np.ceil(length / (resolution / 4)).astype(np.int64), 1)
        owner = np.repeat(np.arange(len(seg)), steps + 1)
        t = np.concatenate([np.linspace(0.0, 1.0, s + 1) for s in steps.tolist()])
        pts = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
        ix = np.clip(((pts[:, 0] - x0) / resolution).astype(np.int64), 0, width - 1)
        iy = np.clip(((pts[:, 1] - y0) / resolution).astype(np.int64), 0, height - 1)
        grid[iy, ix] = WALL
    return grid


def free_space(wf: Wireframe) -> Any:
    """Union of the faces of the wall arrangement that lie on the left of their nearest wall
    (a face next to a wall seen from both sides is free on both sides), or ``None``."""
    seg = wf.segments()
    if len(seg) == 0:
        return None
    lines = shapely.linestrings(seg)
    faces = [g for g in shapely.get_parts(shapely.polygonize(lines.tolist())) if g.area > 0]
    if not faces:
        return None
    probe = np.array([[p.x, p.y] for p in (f.representative_point() for f in faces)])
    a, b = seg[:, 0], seg[:, 1]
    ab = b - a
    ap = probe[:, None, :] - a[None, :, :]
    t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    dist = np.hypot(*(probe[:, None, :] - closest).transpose(2, 0, 1))
    cross = ab[None, :, 0] * ap[..., 1] - ab[None, :, 1] * ap[..., 0]
    nearest = dist <= dist.min(axis=1, keepdims=True) + 1e-9
    is_free = np.any(nearest & (cross > 0), axis=1)
    kept = [f for f, ok in zip(faces, is_free.tolist()) if ok]
    return shapely.union_all(kept) if kept else None


def png_bytes(grid: NDArray[np.int8]) -> bytes:
    """A minimal 8-bit grayscale PNG of the grid (top row first), zlib level 9."""
    gray = np.full(grid.shape, 205, dtype=np.uint8)
    gray[grid == FREE] = 254
    gray[grid == WALL] = 0
    rows = gray[::-1]
    raw = np.concatenate((np.zeros((rows.shape[0], 1), np.uint8), rows), axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", rows.shape[1], rows.shape[0], 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 9))
            + chunk(b"IEND", b""))


def ros_grid_bytes(grid: NDArray[np.int8], frame_id: str = "map") -> int:
    """Serialised size of a ROS 1 ``nav_msgs/OccupancyGrid`` holding ``grid``."""
    header = 4 + 8 + 4 + len(frame_id.encode())
    info = 8 + 4 + 4 + 4 + 7 * 8
    return header + info + 4 + int(grid.size)


def msgpack_float_bytes(wf: Wireframe) -> int:
    return len(
        msgpack.packb(
            {
                "points": wf.points.tolist(),
                "labels": wf.labels.tolist(),
                "edges": wf.edges.tolist(),
                "likelihood": wf.likelihood.tolist(),
            }
        )
    )


# ---------------------------------------------------------------------------------------- measure
def bench_message(wf: Wireframe, resolution: float) -> wire_codec.MapMessage:
    """A robot-map message with realistic, non-trivial metadata around ``wf``."""
    return wire_codec.MapMessage(
        kind=wire_codec.MessageKind.ROBOT_MAP,
        sender="r1",
        seq=1234,
        stamp_ns=1_700_000_000_123_456_789,
        pose=Pose(12.345, 6.789, 1.2345),
        frame="odom/r1",
        origin=Pose(2.0, 3.0, math.pi / 2),
        resolution=resolution,
        wireframe=wf,
    )


def median_us(fn: Callable[[], object], repeat: int) -> float:
    fn()
    times = []
    for _ in range(max(repeat, 1)):
        t = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t)
    return statistics.median(times) / 1000.0


def measure(wf: Wireframe, resolution: float, repeat: int = 300) -> dict[str, Any]:
    """Every figure of the benchmark for one map (see the module docstring)."""
    message = bench_message(wf, resolution)
    data, body = encode_with_plan(message)
    back = wire_codec.decode(data)
    if back.wireframe.n_vertices != wf.n_vertices or back.wireframe.n_edges != wf.n_edges:
        raise AssertionError("codec round trip changed the graph")  # a bug, not a user error
    grid = occupancy_grid(wf, resolution)
    return {
        "message_bytes": len(data),
        "body_bytes": len(body.data),
        "envelope_bytes": len(data) - len(body.data),
        "paper_accounting_bytes": wf.paper_storage_bytes(),
        "msgpack_float_bytes": msgpack_float_bytes(wf),
        "png_grid_bytes": len(png_bytes(grid)),
        "ros_grid_bytes": ros_grid_bytes(grid),
        "encode_us": round(median_us(lambda: wire_codec.encode(message), repeat), 1),
        "decode_us": round(median_us(lambda: wire_codec.decode(data), repeat), 1),
        "vertices": wf.n_vertices,
        "edges": wf.n_edges,
    }


def _load_map(path: str) -> Wireframe:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: cannot read a GeoJSON map: {exc}") from None
    try:
        return Wireframe.from_geojson(doc)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None


def _world_truth(name: str) -> Wireframe:
    from agents.sim.world import load_world

    return load_world(name).truth


def filter_best(name: str, resolution: float, seed: int, duration: float | None) -> Wireframe:
    """The best particle after a filter run over world ``name`` (10 particles, merge threshold
    ``resolution``, the corner sensor, the whole coverage route unless ``duration``)."""
    from agents.mapping_run import SimOptions, run_filter, sim_filter
    from agents.sim.world import load_world

    filt, inputs = sim_filter(load_world(name), SimOptions(duration=duration), seed, 10, resolution)
    for _ in run_filter(inputs, filt):
        pass
    return filt.best


COLUMNS = (
    ("vertices", "V"),
    ("edges", "E"),
    ("message_bytes", "message B"),
    ("body_bytes", "body B"),
    ("envelope_bytes", "envelope B"),
    ("paper_accounting_bytes", "paper B"),
    ("msgpack_float_bytes", "msgpack B"),
    ("png_grid_bytes", "PNG grid B"),
    ("ros_grid_bytes", "ROS grid B"),
    ("encode_us", "encode us"),
    ("decode_us", "decode us"),
)


def table(results: dict[str, dict[str, Any]]) -> str:
    head = ["map", *(title for _, title in COLUMNS)]
    rows = [[name, *(str(r[key]) for key, _ in COLUMNS)] for name, r in results.items()]
    widths = [max(len(row[i]) for row in [head, *rows]) for i in range(len(head))]
    fmt = lambda row: "  ".join(  # noqa: E731
        c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))
    )
    return "\n".join([fmt(head), *(fmt(r) for r in rows)])


def target_lines(results: dict[str, dict[str, Any]]) -> list[str]:
    lines = []
    for name, limits in TARGETS.items():
        r = results.get(name)
        if r is None:
            continue
        for key, bound in limits.items():
            value = r["encode_us"] + r["decode_us"] if key == "codec_us" else r[key]
            label = "encode+decode us" if key == "codec_us" else key
            lines.append(f"target {name} {label} <= {bound}: {value} {'ok' if value <= bound else 'MISSED'}")
    return lines


def run(args: argparse.Namespace) -> int:
    if args.repeat < 1:
        raise UserError("--repeat must be at least 1")
    if not (args.resolution > 0 and math.isfinite(args.resolution)):
        raise UserError("--resolution must be a positive number of metres")
    if args.filter_duration is not None and not args.filter_duration > 0:
        raise UserError("--filter-duration must be a positive number of seconds")

    def source(world: str, stored: str | None, res: float) -> Wireframe:
        if stored:
            return _load_map(stored)
        if world in args.run_filter:
            return filter_best(world, res, args.filter_seed, args.filter_duration)
        return _world_truth(world)

    maps = {
        "paper_small": (source("paper-small", args.paper_small_map, 0.2), 0.2),
        "museum": (source("museum", args.museum_map, 0.4), 0.4),
    }
    if args.map:
        maps["map"] = (_load_map(args.map), args.resolution)
    results: dict[str, dict[str, Any]] = {}
    for name, (wf, res) in maps.items():
        try:
            results[name] = measure(wf, res, args.repeat)
        except wire_codec.CodecError as exc:
            raise UserError(f"{name}: cannot encode the map: {exc}") from None
    print(table(results))
    for line in target_lines(results):
        print(line)
    print(json.dumps(results, sort_keys=False))
    return 0
