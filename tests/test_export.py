"""``wiremap export`` and the occupancy raster behind ``rosmap`` (agents/files/export.py,
agents/commands/export.py), on hand-made maps with known answers."""

from __future__ import annotations

import json
import math
import os
import re
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.cli import main as cli_main
from agents.errors import UserError
from agents.files import export as E
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

REPO = Path(__file__).resolve().parent.parent

# A 6 m x 4 m room (counterclockwise: free inside) with a 1 m x 1 m pillar (clockwise) at
# [2, 3] x [1, 2]. Cell centres sit on multiples of the resolution.
ROOM = [(0.0, 0.0), (6.0, 0.0), (6.0, 4.0), (0.0, 4.0)]
PILLAR = [(2.0, 1.0), (2.0, 2.0), (3.0, 2.0), (3.0, 1.0)]


def room_with_pillar() -> Wireframe:
    return Wireframe.from_polylines([ROOM, PILLAR])


def parse_yaml(text: str) -> dict[str, object]:
    """The flat ``key: value`` YAML map_server reads (numbers, strings, one flow list)."""
    out: dict[str, object] = {}
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        key, sep, value = line.partition(":")
        assert sep, f"not a key: value line: {line!r}"
        value = value.strip()
        if value.startswith("["):
            assert value.endswith("]"), line
            out[key.strip()] = [float(v) for v in value[1:-1].split(",")]
        else:
            try:
                out[key.strip()] = int(value)
            except ValueError:
                try:
                    out[key.strip()] = float(value)
                except ValueError:
                    out[key.strip()] = value.strip('"')
    return out


def parse_pgm_header(data: bytes) -> tuple[int, int, int, int]:
    """``(width, height, maxval, offset of the pixels)`` of a P5 file, written independently of
    :func:`agents.files.export.read_pgm`."""
    m = re.match(rb"P5\s+(?:#[^\n]*\n\s*)*(\d+)\s+(?:#[^\n]*\n\s*)*(\d+)\s+(?:#[^\n]*\n\s*)*(\d+)\s", data)
    assert m is not None, data[:40]
    return int(m.group(1)), int(m.group(2)), int(m.group(3)), m.end()


def pixel(img: np.ndarray, meta: dict[str, object], x: float, y: float) -> int:
    """The PGM value at map point (x, y), from the YAML's origin and resolution alone
    (row 0 of the image is the top of the map)."""
    res = float(meta["resolution"])  # type: ignore[arg-type]
    ox, oy, _ = meta["origin"]  # type: ignore[misc]
    col = math.floor((x - ox) / res)
    row = img.shape[0] - 1 - math.floor((y - oy) / res)
    return int(img[row, col])


def fused_message(wf: Wireframe, seq: int = 7) -> bytes:
    from wire_codec import MapMessage, MessageKind, encode

    return encode(
        MapMessage(
            MessageKind.FUSED_MAP,
            "fusion",
            seq,
            1_700_000_000_000_000_000,
            Pose(),
            "fleet",
            Pose(),
            0.05,
            wf,
            ("r1", "r2"),
            {"stale": ["r2"]},
        )
    )


def run_cli(*args: str) -> int:
    """``wiremap export ARGS`` in this process; argparse's exit becomes the status."""
    try:
        return int(cli_main(["export", *args]))
    except SystemExit as exc:
        return int(exc.code or 0)


# ---------------------------------------------------------------------------- occupancy raster
def test_room_with_pillar_cells() -> None:
    g = E.occupancy_grid(room_with_pillar(), resolution=0.1, margin=2)
    # 0..6 m -> cells 0..60 (61 centres) + 2 margin cells each side.
    assert (g.width, g.height) == (65, 45)
    assert g.origin == pytest.approx((-0.25, -0.25))
    assert g.value_at(1.0, 3.0) == E.FREE  # inside the room
    assert g.value_at(5.55, 0.55) == E.FREE
    assert g.value_at(0.0, 2.0) == E.OCCUPIED  # left wall
    assert g.value_at(6.0, 2.0) == E.OCCUPIED  # right wall
    assert g.value_at(3.0, 4.0) == E.OCCUPIED  # top wall
    assert g.value_at(2.5, 1.5) == E.OCCUPIED  # inside the pillar: known solid
    assert g.value_at(2.0, 1.5) == E.OCCUPIED  # the pillar's wall
    assert g.value_at(-0.2, 2.0) == E.UNKNOWN  # outside the room
    assert g.value_at(3.0, 4.2) == E.UNKNOWN
    # Exactly three values are used, and the top row of the image is the top of the map.
    assert set(np.unique(g.data).tolist()) == {E.FREE, E.OCCUPIED, E.UNKNOWN}
    assert np.all(g.data[0] == E.UNKNOWN) and np.all(g.data[-1] == E.UNKNOWN)
    # The pillar is 1 m wide: 11 cell centres 2.0..3.0 are occupied on its middle row.
    r, _ = g.cell_of(0.0, 1.5)
    row = g.data[r]
    c2, c3 = g.cell_of(2.0, 1.5)[1], g.cell_of(3.0, 1.5)[1]
    assert np.all(row[c2 : c3 + 1] == E.OCCUPIED)
    assert row[c2 - 1] == E.FREE and row[c3 + 1] == E.FREE


def test_free_cells_match_free_space() -> None:
    from mapping.metrics import free_space

    wf = room_with_pillar()
    g = E.occupancy_grid(wf, resolution=0.1, margin=1)
    free = free_space(wf)
    rows, cols = np.nonzero(g.data == E.FREE)
    xs = g.origin[0] + (cols + 0.5) * g.resolution
    ys = g.origin[1] + (g.height - 1 - rows + 0.5) * g.resolution
    assert np.all(shapely.contains_xy(free, xs, ys))
    # Every centre strictly inside free space and away from the walls is free.
    gx, gy = np.meshgrid(
        g.origin[0] + (np.arange(g.width) + 0.5) * g.resolution,
        g.origin[1] + (np.arange(g.height)[::-1] + 0.5) * g.resolution,
    )
    deep = shapely.contains_xy(free.buffer(-0.1), gx, gy)
    assert np.all(g.data[deep] == E.FREE)


def test_open_map_and_thin_box_are_unknown() -> None:
    # One wall: no closed face, so everything but the wall is unknown.
    g = E.occupancy_grid(Wireframe.build([(0, 0), (3, 0)], [(0, 1)]), resolution=0.5, margin=1)
    assert set(np.unique(g.data).tolist()) == {E.OCCUPIED, E.UNKNOWN}
    assert g.value_at(1.5, 0.0) == E.OCCUPIED and g.value_at(1.5, 0.5) == E.UNKNOWN
    # A box of thin walls (every wall seen from both sides) gives no evidence: unknown inside.
    box = Wireframe.from_polylines([ROOM])
    both = box.replace(
        edges=np.concatenate([box.edges, box.edges[:, ::-1]]),
        likelihood=np.ones(8),
        sources=np.zeros(8, np.uint64),
    )
    g = E.occupancy_grid(both, resolution=0.5)
    assert g.value_at(3.0, 2.0) == E.UNKNOWN and g.value_at(0.0, 2.0) == E.OCCUPIED


def test_reversed_room_is_solid() -> None:
    # A clockwise room is an obstacle seen from outside: its inside is occupied, not free.
    g = E.occupancy_grid(Wireframe.from_polylines([ROOM[::-1]]), resolution=0.5)
    assert g.value_at(3.0, 2.0) == E.OCCUPIED
    assert not np.any(g.data == E.FREE)


def test_min_likelihood_drops_walls() -> None:
    wf = room_with_pillar()
    lik = np.ones(wf.n_edges)
    lik[4:] = 0.2  # the pillar is unlikely
    wf = wf.replace(likelihood=lik)
    g = E.occupancy_grid(wf, resolution=0.1, min_likelihood=0.5)
    assert g.value_at(2.5, 1.5) == E.FREE
    assert E.occupancy_grid(wf, resolution=0.1).value_at(2.5, 1.5) == E.OCCUPIED


def test_grid_errors() -> None:
    with pytest.raises(ValueError, match="empty"):
        E.occupancy_grid(Wireframe.empty())
    with pytest.raises(ValueError, match="positive"):
        E.occupancy_grid(room_with_pillar(), resolution=0.0)
    with pytest.raises(ValueError, match="too large"):
        E.occupancy_grid(room_with_pillar(), resolution=1e-5)


def test_wall_cells_diagonal_is_4_connected() -> None:
    # A 45-degree wall: a supercover marks two cells per column, never a diagonal-only step.
    seg = np.array([[[0.3, 0.2], [4.6, 3.9]]])
    m = E.wall_cells(seg, (0.0, 0.0), 1.0, 6, 5)
    rows, cols = np.nonzero(m)
    cells = set(zip(rows.tolist(), cols.tolist()))
    assert (0, 0) in cells and (3, 4) in cells
    for r, c in cells:
        if (r, c) == (3, 4):
            continue
        assert (r + 1, c) in cells or (r, c + 1) in cells, (r, c)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-3.0, 3.0, allow_nan=False, allow_subnormal=False), min_size=4, max_size=4),
    st.floats(0.05, 1.0),
)
def test_wall_cells_cover_the_segment(coords: list[float], res: float) -> None:
    seg = np.array([[coords[:2], coords[2:]]], dtype=np.float64)
    origin = (-3.5, -3.5)
    n = math.ceil(7.0 / res) + 1
    m = E.wall_cells(seg, origin, res, n, n)
    t = np.linspace(0.0, 1.0, 2001)[:, None]
    pts = seg[0, 0] + t * (seg[0, 1] - seg[0, 0])
    u, v = (pts[:, 0] - origin[0]) / res, (pts[:, 1] - origin[1]) / res
    # A point on a line between cells lies in the cells on both sides (hypothesis found a
    # segment through a lattice corner: the cell touched only at that corner is not marked,
    # the two the segment passes through are).
    covered = np.zeros(len(pts), dtype=bool)
    for c in (np.floor(u).astype(int), np.ceil(u).astype(int) - 1):
        for r in (np.floor(v).astype(int), np.ceil(v).astype(int) - 1):
            covered |= m[r, c]
    assert np.all(covered), "a point of the segment lies in no marked cell"
    # No marked cell is farther from the segment than half a cell diagonal.
    rows, cols = np.nonzero(m)
    centres = np.stack([origin[0] + (cols + 0.5) * res, origin[1] + (rows + 0.5) * res], axis=1)
    # (in numpy: GEOS warns on a segment a few 1e-280 long, which hypothesis does draw)
    a, ab = seg[0, 0], seg[0, 1] - seg[0, 0]
    den = float(ab @ ab)
    t_near = np.clip((centres - a) @ ab / den, 0.0, 1.0) if den > 0 else np.zeros(len(centres))
    d = np.hypot(*(a + t_near[:, None] * ab - centres).T)
    assert np.all(d <= res * math.sqrt(0.5) + 1e-9)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 12))
def test_scanline_fill_matches_shapely(seed: int, k: int) -> None:
    rng = np.random.default_rng(seed)
    # A random star-shaped polygon with a hole of another star around its centre.
    ang = np.sort(rng.uniform(0.0, 2 * np.pi, k))
    rad = rng.uniform(1.0, 3.0, k)
    outer = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=1)
    hole = 0.3 * outer[::-1]
    poly = shapely.Polygon(outer, [hole]).buffer(0)
    res = float(rng.uniform(0.05, 0.4))
    origin, w, h = E.grid_geometry((-3.0, -3.0, 3.0, 3.0), res, 1)
    got = E.fill_polygons(poly, origin, res, w, h)
    gx, gy = np.meshgrid(origin[0] + (np.arange(w) + 0.5) * res, origin[1] + (np.arange(h) + 0.5) * res)
    want = shapely.contains_xy(poly, gx, gy)
    near = shapely.distance(poly.boundary, shapely.points(gx, gy)) < 1e-9
    assert np.array_equal(got[~near], want[~near])


def test_grid_geometry_centres_on_multiples() -> None:
    origin, w, h = E.grid_geometry((0.0, 0.0, 3.0, 2.0), 0.05, 0)
    assert (w, h) == (61, 41)
    assert origin == pytest.approx((-0.025, -0.025))
    origin, w, h = E.grid_geometry((-1.01, 0.3, -0.5, 0.3), 0.5, 2)
    assert origin == pytest.approx((-2.25, -0.75)) and (w, h) == (6, 5)


# ---------------------------------------------------------------------------- PGM + YAML
def test_pgm_and_yaml_text() -> None:
    g = E.OccupancyGrid(np.array([[0, 254, 205], [205, 0, 254]], dtype=np.uint8), 0.05, (-1.5, 2.25))
    data = E.pgm_bytes(g, comment="hi\nthere")
    assert data.startswith(b"P5\n# hi\n# there\n3 2\n255\n")
    assert data.endswith(bytes([0, 254, 205, 205, 0, 254]))
    assert np.array_equal(E.read_pgm(data), g.data)
    meta = parse_yaml(E.map_yaml(g, "floor.pgm"))
    assert meta == {
        "image": "floor.pgm",
        "mode": "trinary",
        "resolution": 0.05,
        "origin": [-1.5, 2.25, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    with pytest.raises(ValueError):
        E.read_pgm(b"P2\n1 1\n255\n0")
    with pytest.raises(ValueError, match="truncated"):
        E.read_pgm(b"P5\n4 4\n255\n\x00\x00")


def test_values_mean_what_map_server_reads() -> None:
    """map_server (trinary, negate 0): p = (255 - v) / 255; occupied if p > occupied_thresh,
    free if p < free_thresh, else unknown."""

    def classify(v: int) -> str:
        p = (255 - v) / 255.0
        return "occupied" if p > E.OCCUPIED_THRESH else "free" if p < E.FREE_THRESH else "unknown"

    assert classify(E.FREE) == "free"
    assert classify(E.OCCUPIED) == "occupied"
    assert classify(E.UNKNOWN) == "unknown"


@pytest.mark.parametrize(
    ("out", "pgm", "yaml"),
    [
        ("maps/floor", "maps/floor.pgm", "maps/floor.yaml"),
        ("maps/floor.v2", "maps/floor.v2.pgm", "maps/floor.v2.yaml"),
        ("maps/floor.pgm", "maps/floor.pgm", "maps/floor.yaml"),
        ("maps/floor.yaml", "maps/floor.pgm", "maps/floor.yaml"),
        ("maps/floor.yml", "maps/floor.pgm", "maps/floor.yml"),
    ],
)
def test_rosmap_paths(out: str, pgm: str, yaml: str) -> None:
    assert E.rosmap_paths(out) == (Path(pgm), Path(yaml))


# ---------------------------------------------------------------------------- the command
def test_export_rosmap_from_geojson(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "map.geojson"
    src.write_text(json.dumps(room_with_pillar().to_geojson()))
    assert (
        run_cli(
            str(src), "--format", "rosmap", "--out", str(tmp_path / "out" / "floor"), "--resolution", "0.1"
        )
        == 0
    )
    cap = capsys.readouterr()
    assert "floor.pgm" in cap.out and "no free cell" not in cap.err
    data = (tmp_path / "out" / "floor.pgm").read_bytes()
    w, h, maxval, off = parse_pgm_header(data)
    assert (w, h, maxval) == (65, 45, 255)
    assert len(data) == off + w * h
    img = np.frombuffer(data[off:], dtype=np.uint8).reshape(h, w)
    meta = parse_yaml((tmp_path / "out" / "floor.yaml").read_text())
    assert meta["image"] == "floor.pgm"
    assert meta["resolution"] == 0.1
    assert meta["origin"] == pytest.approx([-0.25, -0.25, 0.0])
    assert (meta["negate"], meta["occupied_thresh"], meta["free_thresh"], meta["mode"]) == (
        0,
        0.65,
        0.196,
        "trinary",
    )
    # Read back through the YAML only: free in the room, walls and pillar occupied, outside unknown.
    assert pixel(img, meta, 1.0, 3.0) == 254
    assert pixel(img, meta, 5.0, 0.5) == 254
    assert pixel(img, meta, 0.0, 2.0) == 0
    assert pixel(img, meta, 3.0, 4.0) == 0
    assert pixel(img, meta, 2.5, 1.5) == 0
    assert pixel(img, meta, -0.2, 1.0) == 205
    # Top-down: the image's first room row is the top wall at y = 4, its last the bottom wall.
    assert pixel(img, meta, 1.0, 4.0) == 0 and img[2, 12] == 0 and img[h - 3, 12] == 0


def test_export_rosmap_of_an_open_map_says_it_has_no_free_cell(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A map that closes no room rasterises to walls and unknown only; the command says so
    (a planner cannot use it), and still writes it."""
    src = tmp_path / "open.geojson"
    src.write_text(json.dumps(Wireframe.build([(0, 0), (3, 0), (3, 2)], [(0, 1), (1, 2)]).to_geojson()))
    assert run_cli(str(src), "--format", "rosmap", "--out", str(tmp_path / "open")) == 0
    assert "no free cell" in capsys.readouterr().err
    assert (tmp_path / "open.pgm").is_file() and (tmp_path / "open.yaml").is_file()


def test_a_track_makes_what_the_robot_saw_free(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An open room (a doorway in its south wall, so no face closes) has no free cell from its
    walls alone; with the robot's track, the room it drove through is free, the space behind
    its walls stays unknown, and what was beyond the sensor's range too."""
    # 6 x 4 room, door from x=2.5 to 3.5 in the south wall, walls drawn with free space on the left
    wf = Wireframe.build([(3.5, 0), (6, 0), (6, 4), (0, 4), (0, 0), (2.5, 0)],
                         [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)])
    assert not np.any(E.occupancy_grid(wf, resolution=0.1).data == E.FREE)
    track = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 2.0]])
    g = E.occupancy_grid(wf, resolution=0.1, margin=15, tracks=[track], sensor_range=8.0)
    assert g.value_at(1.0, 1.0) == E.FREE and g.value_at(5.5, 3.5) == E.FREE
    # through the doorway no wall of the map is in range: free only within --open-range (2 m)
    assert g.value_at(3.0, 0.5) == E.FREE and g.value_at(3.0, -1.0) == E.UNKNOWN
    wide = E.occupancy_grid(wf, resolution=0.1, margin=15, tracks=[track], sensor_range=8.0, open_range=4.0)
    assert wide.value_at(3.0, -1.0) == E.FREE
    assert g.value_at(6.0, 2.0) == E.OCCUPIED  # walls are drawn over what was seen
    assert g.value_at(-0.3, 2.0) == E.UNKNOWN and g.value_at(6.3, 2.0) == E.UNKNOWN  # behind the walls
    assert g.value_at(1.0, -0.3) == E.UNKNOWN  # behind the south wall, beside the door's cone
    short = E.occupancy_grid(wf, resolution=0.1, tracks=[track[:1]], sensor_range=1.0)
    assert short.value_at(1.5, 2.0) == E.FREE and short.value_at(2.5, 2.0) == E.UNKNOWN  # beyond range
    # the command: --trajectory reads wiremap map's trajectory.tsv (t x y theta)
    src = tmp_path / "open.geojson"
    src.write_text(json.dumps(wf.to_geojson()))
    tsv = tmp_path / "trajectory.tsv"
    tsv.write_text("".join(f"{k * 0.5:.6f}\t{x:.6f}\t{y:.6f}\t0.0\n" for k, (x, y) in enumerate(track)))
    assert run_cli(str(src), "--format", "rosmap", "--out", str(tmp_path / "room"),
                   "--trajectory", str(tsv)) == 0
    assert "no free cell" not in capsys.readouterr().err
    assert (E.read_pgm((tmp_path / "room.pgm").read_bytes()) == E.FREE).sum() > 1000
    # misuse: one line, exit 2
    bad = tmp_path / "bad.tsv"
    bad.write_text("1 2 x\n")
    for argv in ([str(src), "--format", "rosmap", "--out", str(tmp_path / "r2"), "--trajectory", str(bad)],
                 [str(src), "--format", "svg", "--out", str(tmp_path / "r.svg"), "--trajectory", str(tsv)],
                 [str(src), "--format", "rosmap", "--out", str(tmp_path / "r3"), "--trajectory",
                  str(tmp_path / "missing.tsv")]):
        assert run_cli(*argv) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(err) == 1 and "--trajectory" in err[0], err
    assert run_cli(str(src), "--format", "rosmap", "--out", str(tmp_path / "r4"), "--sensor-range", "5") == 2
    # a header line is skipped; an empty folder is an error
    tsv.write_text("t\tx\ty\ttheta\n" + tsv.read_text())
    assert len(E.read_track(tsv)) == 3
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert run_cli(str(src), "--format", "rosmap", "--out", str(tmp_path / "r5"),
                   "--trajectory", str(tmp_path / "empty")) == 2
    assert "no .tsv" in capsys.readouterr().err


def test_scan_beams_carve_free_space() -> None:
    """One scan from the origin looking along +x, 90 degrees wide, its beams 3 m long but one
    with no return: free in front nearer than the returns, unknown behind the laser, beyond the
    returns and beyond the open range of the beam that saw nothing."""
    ang = np.radians(np.arange(-45.0, 45.1, 1.0))
    ranges = np.full(len(ang), 3.0)
    ranges[43:48] = np.inf  # straight ahead (-2 to +2 degrees): no return
    origin, res, w, h = (-5.0, -5.0), 0.1, 100, 100
    free = E.scan_free([(0.0, 0.0, 0.0)], [(ranges, ang)], 20.0, origin, res, w, h, open_range=1.0)

    def at(x: float, y: float) -> bool:
        return bool(free[int((y - origin[1]) / res), int((x - origin[0]) / res)])

    assert at(2.0, 1.0) and at(2.5, -1.5)  # inside the fan, nearer than 3 m
    assert not at(-1.0, 0.0) and not at(0.5, 2.0)  # behind the laser, outside the fan
    assert not at(3.5, 1.0)  # beyond the returns
    assert at(0.8, 0.0) and not at(1.5, 0.0)  # the beam without a return: only its open range
    # turned by 90 degrees, the fan looks along +y
    turned = E.scan_free([(0.0, 0.0, math.pi / 2)], [(ranges, ang)], 20.0, origin, res, w, h)
    assert bool(turned[int((2.0 + 5.0) / res), int((0.5 + 5.0) / res)]) and not turned[50, 75]


def test_export_wfm_to_each_format(tmp_path: Path) -> None:
    wf = room_with_pillar().replace(labels=np.array([0, 0, 1, 2, 0, 0, 0, 0], dtype=np.uint8))
    src = tmp_path / "fused.wfm"
    src.write_bytes(fused_message(wf, seq=7))

    assert run_cli(str(src), "--format", "geojson", "--out", str(tmp_path / "m.geojson")) == 0
    doc = json.loads((tmp_path / "m.geojson").read_text())
    back = Wireframe.from_geojson(doc)
    assert back.almost_equal(wf, tol=1e-3)  # the codec quantises to its resolution
    assert doc["properties"]["version"] == 7 and doc["properties"]["robots"] == ["r1", "r2"]
    assert doc["properties"]["kind"] == "fused_map" and doc["properties"]["stale"] == ["r2"]
    walls = [f["properties"] for f in doc["features"] if f["properties"]["kind"] == "wall"]
    assert all(set(w["robots"]) <= {"r1", "r2"} for w in walls)  # as in `wiremap run`'s fused.geojson
    # GeoJSON in, GeoJSON out: the same map and properties again.
    assert run_cli(str(tmp_path / "m.geojson"), "--out", str(tmp_path / "again.json")) == 0
    again = json.loads((tmp_path / "again.json").read_text())
    assert Wireframe.from_geojson(again).almost_equal(back) and again["properties"] == doc["properties"]

    assert run_cli(str(src), "--format", "svg", "--out", str(tmp_path / "m.svg")) == 0
    svg = (tmp_path / "m.svg").read_text()
    assert svg.lstrip().startswith("<svg") and svg.rstrip().endswith("</svg>")
    froms = sorted(
        (int(a), int(b)) for a, b in re.findall(r'class="edge" data-from="(\d+)" data-to="(\d+)"', svg)
    )
    assert froms == sorted(map(tuple, wf.edges.tolist()))
    assert svg.count('class="frontier"') == 1 and svg.count('class="occlusion"') == 1

    assert run_cli(str(src), "--format", "png", "--out", str(tmp_path / "m.png")) == 0
    png = (tmp_path / "m.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, pos = {}, 8
    while pos < len(png):
        (n,) = struct.unpack(">I", png[pos : pos + 4])
        tag = png[pos + 4 : pos + 8]
        chunks.setdefault(tag, b"")
        chunks[tag] += png[pos + 8 : pos + 8 + n]
        pos += 12 + n
    pw, ph, depth, ctype = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, ctype) == (8, 2) and pw > 10 and ph > 10
    raw = zlib.decompress(chunks[b"IDAT"])
    assert len(raw) == ph * (1 + 3 * pw)

    assert run_cli(str(src), "--out", str(tmp_path / "nav" / "floor.yaml")) == 0  # format from the suffix
    meta = parse_yaml((tmp_path / "nav" / "floor.yaml").read_text())
    assert meta["image"] == "floor.pgm" and meta["resolution"] == 0.05
    img = E.read_pgm((tmp_path / "nav" / "floor.pgm").read_bytes())
    assert pixel(img, meta, 1.0, 3.0) == 254 and pixel(img, meta, 6.0, 1.0) == 0


def test_load_map_sniffs_unsuffixed_files(tmp_path: Path) -> None:
    wf = room_with_pillar()
    (tmp_path / "a").write_bytes(fused_message(wf))
    (tmp_path / "b").write_text(json.dumps(wf.to_geojson({"note": "x"})))
    a, b = E.load_map(tmp_path / "a"), E.load_map(tmp_path / "b")
    assert a.wireframe.almost_equal(wf, tol=1e-3) and a.properties["sender"] == "fusion"
    assert b.wireframe.almost_equal(wf) and b.properties == {"note": "x"}
    assert int(a.wireframe.labels[0]) == Label.NOMINAL


@pytest.mark.parametrize(
    ("make", "args", "message"),
    [
        (None, ["--format", "png"], "no such file"),
        (b"\x00garbage that is no message", ["--format", "png"], "not a valid wiremap message"),
        ('{"type": "Feature"}', ["--format", "svg"], "FeatureCollection"),
        ("{broken json", ["--format", "svg"], "not valid JSON"),
        (None, ["--format", "jpeg"], "invalid choice"),
        (None, [], "cannot tell the format"),
        (None, ["--format", "rosmap", "--resolution", "-0.1"], "positive"),
    ],
)
def test_bad_input_is_one_line_exit_2(
    tmp_path: Path,
    make: bytes | str | None,
    args: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    src = tmp_path / ("in.geojson" if isinstance(make, str) else "in.wfm")
    if isinstance(make, bytes):
        src.write_bytes(make)
    elif isinstance(make, str):
        src.write_text(make)
    elif "no such file" not in message:
        src.write_bytes(fused_message(room_with_pillar()))
    assert run_cli(str(src), *args, "--out", str(tmp_path / "out.xyz")) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "out.xyz").exists()


def test_empty_map_rosmap_is_a_user_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "empty.geojson"
    src.write_text(json.dumps(Wireframe.empty().to_geojson()))
    assert run_cli(str(src), "--format", "rosmap", "--out", str(tmp_path / "x")) == 2
    assert "empty" in capsys.readouterr().err
    assert not list(tmp_path.glob("x*"))
    with pytest.raises(UserError, match="no such file"):
        E.load_map(tmp_path / "missing.wfm")


@pytest.mark.fleet
def test_subprocess_errors_have_no_traceback(tmp_path: Path) -> None:
    """The real entry point: one line on stderr, exit status 2, for a bad file and a bad flag."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    bad = tmp_path / "bad.wfm"
    bad.write_bytes(b"\xff" * 40)
    for args, needle in (
        ([str(bad), "--format", "rosmap", "--out", str(tmp_path / "o")], "not a valid wiremap message"),
        ([str(bad), "--format", "bmp", "--out", str(tmp_path / "o")], "invalid choice"),
    ):
        p = subprocess.run(
            [sys.executable, "-m", "agents", "export", *args],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert p.returncode == 2, p.stderr
        assert needle in p.stderr and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1
        assert not list(tmp_path.glob("o*"))
