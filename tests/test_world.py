"""Worlds: loading, errors, the ground-truth wireframe, built-ins, round trips, CLI commands."""

import json

import numpy as np
import pytest
import shapely
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.cli import main as cli_main
from agents.errors import UserError
from agents.sim.world import (
    THIN_WALL_CLEARANCE,
    WorldError,
    builtin_names,
    load_world,
    truth_wireframe,
    world_from_geojson,
)
from mapping import Label


def poly_feature(exterior, holes=(), **props):
    ring = [list(map(float, p)) for p in exterior] + [list(map(float, exterior[0]))]
    rings = [ring] + [[list(map(float, p)) for p in h] + [list(map(float, h[0]))] for h in holes]
    return {"type": "Feature", "properties": props, "geometry": {"type": "Polygon", "coordinates": rings}}


def line_feature(coords, **props):
    return {"type": "Feature", "properties": props, "geometry": {"type": "LineString", "coordinates": coords}}


def collection(*features, name=None):
    doc = {"type": "FeatureCollection", "features": list(features)}
    if name:
        doc["properties"] = {"name": name}
    return doc


SQUARE = [(0, 0), (10, 0), (10, 10), (0, 10)]


def cycles(wf):
    """Vertex cycles of a wireframe whose every vertex has in = out = 1."""
    nxt = {int(a): int(b) for a, b in wf.edges}
    seen, out = set(), []
    for s in nxt:
        if s in seen:
            continue
        cyc, v = [], s
        while v not in seen:
            seen.add(v)
            cyc.append(v)
            v = nxt[v]
        out.append(cyc)
    return out


def signed_area(pts):
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def edge_sides_ok(world, eps=1e-3):
    """Every edge has free space just left of its midpoint; ring edges have solid on the right."""
    seg = world.truth.segments()
    mid = seg.mean(axis=1)
    d = seg[:, 1] - seg[:, 0]
    n = np.column_stack([-d[:, 1], d[:, 0]]) / np.hypot(d[:, 0], d[:, 1])[:, None]
    left = mid + n * (THIN_WALL_CLEARANCE + eps)
    right = mid - n * eps
    free_left = world.is_free(left)
    inside_right = shapely.contains_xy(world.free_space, right[:, 0], right[:, 1])
    return free_left, inside_right


# ---------------------------------------------------------------------- hand-made worlds
def test_square_room_truth_is_ccw_ring():
    w = world_from_geojson(collection(poly_feature(SQUARE)), name="sq")
    assert w.name == "sq"
    assert w.truth.n_vertices == 4 and w.truth.n_edges == 4
    (cyc,) = cycles(w.truth)
    assert signed_area(w.truth.points[cyc]) == pytest.approx(100.0)
    assert np.all(w.truth.labels == Label.NOMINAL) and np.all(w.truth.likelihood == 1.0)


def test_clockwise_input_and_hole_are_normalised():
    hole = [(4, 4), (6, 4), (6, 6), (4, 6)]  # given CCW: must become CW
    w = world_from_geojson(collection(poly_feature(SQUARE[::-1], [hole])))
    areas = sorted(signed_area(w.truth.points[c]) for c in cycles(w.truth))
    assert areas == pytest.approx([-4.0, 100.0])
    free_left, inside_right = edge_sides_ok(w)
    assert free_left.all() and not inside_right.any()


def test_collinear_vertices_are_not_corners():
    ext = [(0, 0), (5, 0), (10, 0), (10, 10), (0, 10), (0, 5)]
    w = world_from_geojson(collection(poly_feature(ext)))
    assert w.truth.n_vertices == 4
    assert len(w.free_space.geoms[0].exterior.coords) == 5


def test_thin_wall_splits_the_wall_it_touches():
    w = world_from_geojson(collection(poly_feature(SQUARE), line_feature([[5, 0], [5, 6]])))
    t = w.truth
    # 4 ring corners + the foot (5, 0) shared by the ring and the wall + the free end (5, 6)
    assert t.n_vertices == 6
    assert t.n_edges == 5 + 2
    idx = {tuple(np.round(p, 9)): i for i, p in enumerate(t.points)}
    foot, top = idx[(5.0, 0.0)], idx[(5.0, 6.0)]
    edges = {tuple(e) for e in t.edges.tolist()}
    assert (foot, top) in edges and (top, foot) in edges
    assert (idx[(0.0, 0.0)], foot) in edges and (foot, idx[(10.0, 0.0)]) in edges
    assert (idx[(0.0, 0.0)], idx[(10.0, 0.0)]) not in edges
    indeg, outdeg = t.degree()
    assert indeg[foot] == 2 and outdeg[foot] == 2


def test_thin_wall_t_junction_and_crossing():
    walls = [
        line_feature([[0, 5], [10, 5]]),  # splits the room
        line_feature([[3, 5], [3, 8]]),  # T on the first thin wall
        line_feature([[6, 2], [8, 4]]),
        line_feature([[6, 4], [8, 2]]),  # crosses the previous one at (7, 3)
    ]
    w = world_from_geojson(collection(poly_feature(SQUARE), *walls))
    pts = {tuple(np.round(p, 9)) for p in w.truth.points}
    for p in [(0, 5), (10, 5), (3, 5), (3, 8), (7, 3)]:
        assert tuple(float(v) for v in p) in pts
    # ring: 4 corners + 2 feet = 6 edges; the long wall split at the T: 2 pieces x 2 directions;
    # the T: 2; the crossing walls split at (7, 3): 4 pieces x 2 directions
    assert w.truth.n_edges == 6 + 4 + 2 + 8
    free_left, _ = edge_sides_ok(w)
    assert free_left.all()


def test_overlapping_polygons_are_merged():
    a = poly_feature([(0, 0), (6, 0), (6, 4), (0, 4)])
    b = poly_feature([(4, 0), (10, 0), (10, 4), (4, 4)])
    c = poly_feature([(20, 0), (22, 0), (22, 2), (20, 2)])  # separate room
    w = world_from_geojson(collection(a, b, c))
    assert len(w.free_space.geoms) == 2
    assert w.free_space.area == pytest.approx(40 + 4)
    assert w.truth.n_vertices == 8


def test_is_free():
    hole = [(4, 4), (4, 6), (6, 6), (6, 4)]
    w = world_from_geojson(collection(poly_feature(SQUARE, [hole]), line_feature([[1, 1], [1, 3]])))
    pts = np.array([[2, 2], [5, 5], [-1, 2], [1.0 + THIN_WALL_CLEARANCE / 2, 2], [1.2, 2], [10, 5]])
    assert w.is_free(pts).tolist() == [True, False, False, False, True, False]
    assert bool(w.is_free(np.array([2.0, 2.0])))
    assert w.bounds() == (0.0, 0.0, 10.0, 10.0)


def test_route_feature():
    doc = collection(poly_feature(SQUARE), line_feature([[1, 1], [9, 1], [9, 9]], kind="route"))
    w = world_from_geojson(doc)
    assert w.route is not None and list(w.route.coords) == [(1, 1), (9, 1), (9, 9)]
    assert w.truth.n_edges == 4  # the route is no wall


# ---------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "features, match",
    [
        ([poly_feature(SQUARE),
          {"type": "Feature", "properties": {}, "geometry": {"type": "Point", "coordinates": [1, 1]}}],
         r"feature 1: unsupported geometry 'Point'"),
        ([poly_feature([(0, 0), (10, 10), (10, 0), (0, 10)])],
         r"feature 0: invalid polygon: Self-intersection"),
        ([poly_feature(SQUARE), line_feature([[5, 5], [15, 5]])], r"thin wall 0 .* leaves the free space"),
        ([poly_feature(SQUARE), line_feature([[0, 2], [0, 8]])],
         r"thin wall 0 .* runs along the outer walls"),
        ([poly_feature(SQUARE), line_feature([[1, 1], [2, 2]], kind="door")],
         r"feature 1: unknown LineString kind 'door'"),
        ([poly_feature(SQUARE, kind="obstacle")], r"feature 0: a Polygon must be free space"),
        ([poly_feature(SQUARE), line_feature([[1, 1], [1, 1]])],
         r"feature 1: a LineString needs two distinct points"),
        ([poly_feature(SQUARE), line_feature([[1, 1], [20, 1]], kind="route")],
         r"feature 1: the route leaves"),
        ([poly_feature(SQUARE), line_feature([[5, 2], [5, 8]]), line_feature([[1, 5], [9, 5]], kind="route")],
         r"feature 2: the route crosses thin wall 0"),
        ([line_feature([[1, 1], [2, 2]])], r"no free space"),
        ([{"type": "Feature", "properties": {"name": "lobby"}, "geometry": None}],
         r"feature 0 \(lobby\): has no geometry"),
    ],
)
def test_bad_features_raise_world_error_naming_them(features, match):
    with pytest.raises(WorldError, match=match):
        world_from_geojson(collection(*features))


def test_world_error_is_a_user_error():
    assert issubclass(WorldError, UserError)


def test_bad_files(tmp_path):
    bad = tmp_path / "bad.geojson"
    bad.write_text("{ not json")
    with pytest.raises(WorldError, match=r"bad\.geojson: not valid JSON"):
        load_world(str(bad))
    point = tmp_path / "point.geojson"
    point.write_text(
        json.dumps(
            collection(
                poly_feature(SQUARE),
                {"type": "Feature", "id": "lamp", "properties": {},
                 "geometry": {"type": "Point", "coordinates": [1, 2]}},
            )
        )
    )
    with pytest.raises(WorldError, match=r"point\.geojson: feature 1 \(lamp\): unsupported geometry 'Point'"):
        load_world(str(point))
    with pytest.raises(WorldError, match=r"unknown world 'no-such-world'.*paper-small"):
        load_world("no-such-world")
    notfc = tmp_path / "list.geojson"
    notfc.write_text("[]")
    with pytest.raises(WorldError, match="FeatureCollection"):
        load_world(notfc)


def test_file_name_is_the_default_world_name(tmp_path):
    p = tmp_path / "my-floor.geojson"
    p.write_text(json.dumps(collection(poly_feature(SQUARE))))
    assert load_world(str(p)).name == "my-floor"
    p.write_text(json.dumps(collection(poly_feature(SQUARE), name="named")))
    assert load_world(p).name == "named"


# ---------------------------------------------------------------------- built-ins
BUILTIN_EXPECT = {
    # name: (width, height, corners range, walls range)
    "paper-small": (15, 15, (42, 42), (42, 42)),
    "museum": (200, 200, (270, 330), (270, 340)),
    "office": (40, 20, (50, 120), (80, 160)),
    "warehouse": (64, 40, (100, 200), (100, 200)),
}


def test_builtin_names():
    assert builtin_names() == list(BUILTIN_EXPECT)


@pytest.mark.parametrize("name", list(BUILTIN_EXPECT))
def test_builtin_counts_and_directions(name):
    w = load_world(name)
    width, height, (vlo, vhi), (elo, ehi) = BUILTIN_EXPECT[name]
    assert w.name == name
    assert w.size == pytest.approx((width, height))
    assert vlo <= w.truth.n_vertices <= vhi
    assert elo <= w.truth.n_edges <= ehi
    assert np.all(w.truth.labels == Label.NOMINAL)
    free_left, inside_right = edge_sides_ok(w)
    assert free_left.all()
    # ring edges have the solid side on the right; thin-wall edges have free space there
    on_thin = np.zeros(w.truth.n_edges, dtype=bool)
    if w.thin_walls:
        mids = w.truth.segments().mean(axis=1)
        walls = shapely.MultiLineString(list(w.thin_walls))
        on_thin = shapely.distance(walls, shapely.points(mids)) < 1e-9
    assert not inside_right[~on_thin].any()
    assert inside_right[on_thin].all()
    # every edge's reverse exists exactly for thin walls
    edges = {tuple(e) for e in w.truth.edges.tolist()}
    rev = np.array([(b, a) in edges for a, b in w.truth.edges.tolist()])
    assert np.array_equal(rev, on_thin)


def test_paper_small_rings_are_exterior_ccw_holes_cw():
    w = load_world("paper-small")
    indeg, outdeg = w.truth.degree()
    assert np.all(indeg == 1) and np.all(outdeg == 1)
    areas = sorted(signed_area(w.truth.points[c]) for c in cycles(w.truth))
    assert areas[-1] > 0 and all(a < 0 for a in areas[:-1])
    assert len(areas) == 4  # the outer wall, the wall island, the box and the counter
    assert sum(areas) == pytest.approx(w.free_space.area)
    assert w.truth.paper_storage_bytes() == 840


@pytest.mark.parametrize("name", list(BUILTIN_EXPECT))
def test_builtin_geojson_round_trip(name, tmp_path):
    w = load_world(name)
    doc = w.to_geojson()
    again = world_from_geojson(json.loads(json.dumps(doc)))
    assert again.same_as(w, tol=0.0)
    path = tmp_path / f"{name}.geojson"
    path.write_text(json.dumps(doc))
    assert load_world(str(path)).same_as(w, tol=0.0)


def test_builtin_doorways_are_wide_enough():
    """The free space stays connected after shrinking it by 0.5 m (doors >= 1.0 m)."""
    for name in builtin_names():
        w = load_world(name)
        region = w.free_space.buffer(-0.5)
        if w.thin_walls:
            region = region.difference(shapely.MultiLineString(list(w.thin_walls)).buffer(0.5))
        parts = getattr(region, "geoms", [region])
        big = [p for p in parts if p.area > 1.0]
        assert len(big) == 1, name


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.tuples(st.integers(0, 8), st.integers(0, 8), st.integers(1, 5), st.integers(1, 5)),
        min_size=1, max_size=5
    ),
    st.lists(st.tuples(st.integers(1, 10), st.integers(1, 10)), max_size=3),
)
def test_union_of_boxes_truth_has_free_space_on_the_left(boxes, pillars):
    rects = [shapely.box(x, y, x + w, y + h) for x, y, w, h in boxes]
    free = shapely.unary_union(rects)
    holes = [shapely.box(px - 0.25, py - 0.25, px + 0.25, py + 0.25) for px, py in pillars]
    free = free.difference(shapely.unary_union(holes)) if holes else free
    polys = [g for g in getattr(free, "geoms", [free]) if g.area > 0]
    feats = [{"type": "Feature", "properties": {}, "geometry": shapely.geometry.mapping(p)} for p in polys]
    w = world_from_geojson(json.loads(json.dumps(collection(*feats))))
    assert w.free_space.area == pytest.approx(free.area)
    free_left, inside_right = edge_sides_ok(w, eps=1e-4)
    assert free_left.all() and not inside_right.any()
    # the truth's total signed area (sum over directed edges) is the free area
    seg = w.truth.segments()
    area = 0.5 * float(np.sum(seg[:, 0, 0] * seg[:, 1, 1] - seg[:, 1, 0] * seg[:, 0, 1]))
    assert area == pytest.approx(free.area)


def test_truth_wireframe_without_thin_walls_matches_rings():
    w = load_world("warehouse")
    again = truth_wireframe(w.free_space)
    assert again.almost_equal(w.truth)


# ---------------------------------------------------------------------- commands
def test_worlds_command_lists_builtins(capsys):
    assert cli_main(["worlds"]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert lines[0].split()[:2] == ["name", "size"]
    row = next(line for line in lines if line.startswith("paper-small"))
    assert "15 x 15" in row and " 42 " in row
    assert cli_main(["worlds", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["name"] for r in rows] == builtin_names()


def test_world_show_png_and_geojson(tmp_path, capsys):
    from agents.files.render import decode_png

    png, gj = tmp_path / "w.png", tmp_path / "w.geojson"
    assert cli_main(["world", "show", "paper-small", "--png", str(png), "--geojson", str(gj), "--max-px",
                     "400"]) == 0
    img = decode_png(png.read_bytes())
    assert img.shape[1] == 400
    w = load_world(str(gj))
    assert w.same_as(load_world("paper-small"), tol=0.0)
    # a planned route is written into the world file and read back
    gj2 = tmp_path / "w2.geojson"
    assert cli_main(["world", "show", "paper-small", "--plan", "--seed", "1", "--geojson", str(gj2)]) == 0
    assert load_world(str(gj2)).route is not None
    # no output flag: a summary
    assert cli_main(["world", "show", "office"]) == 0
    assert json.loads(capsys.readouterr().out)["corners"] == load_world("office").truth.n_vertices


def test_world_show_draws_the_unknown_start_fleet_routes(tmp_path, capsys):
    """`--plan --unknown-starts`: the routes `wiremap run --unknown-starts` drives with that seed,
    one per robot from its own random start (not the known-start split of one tour)."""
    import numpy as np

    from agents.fleet.unknown_run import random_routes
    from agents.sim.route import plan_routes, route_length

    png = tmp_path / "u.png"
    assert cli_main(["world", "show", "paper-small", "--plan", "--robots", "2", "--unknown-starts",
                     "--seed", "3", "--png", str(png)]) == 0
    err = capsys.readouterr().err
    w = load_world("paper-small")
    mine = random_routes(w, 2, np.random.default_rng(3))
    split = plan_routes(w, 2, np.random.default_rng(3), use_world_route=False)
    assert f"planned 2 route(s), {sum(route_length(r) for r in mine):.0f} m" in err, err
    assert sum(route_length(r) for r in mine) > 1.5 * sum(route_length(r) for r in split)
    assert png.read_bytes().startswith(b"\x89PNG")
    assert cli_main(["world", "show", "paper-small", "--unknown-starts"]) == 2
    assert "add --plan" in capsys.readouterr().err


def test_world_show_bad_world_exits_2(capsys, tmp_path):
    assert cli_main(["world", "show", "nowhere"]) == 2
    assert "unknown world 'nowhere'" in capsys.readouterr().err
    bad = tmp_path / "bad.geojson"
    bad.write_text(json.dumps(collection(poly_feature([(0, 0), (10, 10), (10, 0), (0, 10)]))))
    assert cli_main(["world", "show", str(bad), "--png", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "feature 0" in err and "Self-intersection" in err and len(err.strip().splitlines()) == 1


def test_world_svg_draws_every_planned_route_in_its_colour(tmp_path) -> None:
    """`--plan --robots 3 --svg`: one polyline per robot's route, in three colours (the PNG's)."""
    import re

    out = tmp_path / "w.svg"
    assert cli_main(["world", "show", "paper-small", "--plan", "--robots", "3", "--seed", "1",
                     "--svg", str(out)]) == 0
    lines = re.findall(r'<polyline class="trajectory" points="([^"]*)" fill="none" stroke="([^"]*)"',
                       out.read_text())
    assert len(lines) == 3 and len({c for _, c in lines}) == 3
    assert all(len(pts.split()) >= 2 for pts, _ in lines)
