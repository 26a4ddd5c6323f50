"""Routes (coverage planning) and motion (driving with noisy odometry)."""

import itertools
import math

import numpy as np
import pytest
import shapely
from hypothesis import example, given, settings
from hypothesis import strategies as st

from agents.sim.motion import OdometryNoise, Step, dead_reckon, drive, noisy_increment
from agents.sim.route import (
    navigable_region,
    plan_fleet_routes,
    plan_route,
    plan_routes,
    route_clearance,
    route_length,
    split_route,
)
from agents.sim.world import builtin_names, load_world, world_from_geojson
from mapping import Pose


def room_world(walls=(), route=None):
    feats = [
        {
            "type": "Feature",
            "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [12, 0], [12, 8], [0, 8], [0, 0]]]},
        }
    ]
    for w in walls:
        feats.append({"type": "Feature", "properties": {},
                      "geometry": {"type": "LineString", "coordinates": w}})
    if route is not None:
        feats.append({"type": "Feature", "properties": {"kind": "route"},
                      "geometry": {"type": "LineString", "coordinates": route}})
    return world_from_geojson({"type": "FeatureCollection", "features": feats}, name="room")


def exact_clearance(world, route):
    """Independent check: route inside the free space, distance to every wall."""
    line = shapely.LineString(route)
    assert world.free_space.covers(line)
    walls = [shapely.LineString(p.exterior.coords) for p in world.free_space.geoms]
    walls += [shapely.LineString(h.coords) for p in world.free_space.geoms for h in p.interiors]
    walls += list(world.thin_walls)
    return min(float(line.distance(w)) for w in walls)


_ROUTES = {}


def planned(name):
    if name not in _ROUTES:
        w = load_world(name)
        _ROUTES[name] = (w, plan_route(w, np.random.default_rng(7)))
    return _ROUTES[name]


def densify(route, step):
    """Points every ``step`` metres (at most) along a polyline."""
    out = [route[0]]
    for a, b in itertools.pairwise(route):
        n = max(1, math.ceil(float(np.hypot(*(b - a))) / step))
        out += [a + (b - a) * k / n for k in range(1, n + 1)]
    return np.array(out)


def wall_points(world, step=0.5):
    """Points every ``step`` metres along every wall face, 5 cm into the free space."""
    pts = []
    for s in world.truth.segments():
        d = s[1] - s[0]
        length = float(np.hypot(*d))
        u = d / length
        n = np.array([-u[1], u[0]])
        k = max(1, int(length / step))
        t = (np.arange(k) + 0.5) / k * length
        pts.append(s[0] + t[:, None] * u + 0.05 * n)
    return np.concatenate(pts)


def seen_fraction(world, route, reach):
    """Independent check: the share of wall points that some point of the route sees (a
    straight segment crossing no wall) from at most ``reach`` metres."""
    return float(seen_mask(world, route, reach).mean())


def seen_mask(world, route, reach):
    """Which of :func:`wall_points` some point of the route sees (:func:`seen_fraction`)."""
    from scipy.spatial import cKDTree

    pts = wall_points(world)
    rp = densify(route, 0.25)
    pairs = cKDTree(pts).query_ball_tree(cKDTree(rp), reach)
    ti = np.repeat(np.arange(len(pts)), [len(p) for p in pairs])
    ri = np.concatenate([np.asarray(p, dtype=int) for p in pairs])
    walls = world.walls()
    shapely.prepare(walls)
    clear = ~shapely.intersects(walls, shapely.linestrings(np.stack([pts[ti], rp[ri]], axis=1)))
    seen = np.zeros(len(pts), dtype=bool)
    seen[ti[clear]] = True
    return seen


# ---------------------------------------------------------------------- routes
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == "museum" else n for n in builtin_names()]
)
def test_builtin_route_is_collision_free_and_covers_the_walls(name):
    w, r = planned(name)
    assert r.ndim == 2 and r.shape[1] == 2 and len(r) > 5
    assert exact_clearance(w, r) >= 0.4 - 1e-9
    assert route_clearance(w, r) >= 0.4 - 1e-9
    # (how fast a route is planned: `wiremap bench speed --pieces`, plan_route_s)
    # every wall is seen from nearby: within 0.75 of the 8 m sensing range (the coverage radius
    # of 4 m plus the 2 m the smoothed route may pass a waypoint by), in sight
    assert seen_fraction(w, r, 6.0) >= 0.99, name
    # little of the route is blind (no wall within 6 m): walls are covered from near them, and
    # travel is routed along walls rather than through the middle of large halls
    d = shapely.distance(w.walls(), shapely.points(densify(r, 0.5)))
    assert np.mean(d > 6.0) <= 0.05, name
    assert np.all(np.hypot(*np.diff(r, axis=0).T) > 0)


def test_route_follows_walls_not_the_floor():
    """In a large empty hall the route keeps near the walls: the old floor-coverage planner sent
    the robot through the middle, where an 8 m sensor sees nothing."""
    feats = [{"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [
        [[0, 0], [40, 0], [40, 30], [0, 30], [0, 0]]]}}]
    w = world_from_geojson({"type": "FeatureCollection", "features": feats}, name="hall")
    r = plan_route(w, np.random.default_rng(2), start=(20.0, 15.0))
    assert seen_fraction(w, r, 6.0) == 1.0
    d = shapely.distance(w.walls(), shapely.points(densify(r, 0.5)))
    # the centre is 15 m from the nearest wall: the route leaves it and stays near the walls
    assert np.mean(d <= 6.0) >= 0.9
    # the tour is short: about once around the hall at a few metres from the walls
    assert route_length(r) < 2 * (40 + 30) + 20


@pytest.mark.slow
def test_museum_route_length_is_reasonable():
    _w, r = planned("museum")
    length = route_length(r)
    assert 2000 < length < 9000


def test_route_is_reproducible_and_seed_dependent():
    w = load_world("paper-small")
    a = plan_route(w, np.random.default_rng(5))
    b = plan_route(w, np.random.default_rng(5))
    c = plan_route(w, np.random.default_rng(6))
    assert np.array_equal(a, b)
    assert not (a.shape == c.shape and np.allclose(a, c))


def test_route_start_and_parameters():
    w = room_world()
    r = plan_route(w, np.random.default_rng(0), start=(1.0, 1.0), clearance=0.5, spacing=3.0)
    assert np.hypot(*(r[0] - (1.0, 1.0))) < 0.3
    assert exact_clearance(w, r) >= 0.5 - 1e-9
    # a smaller spacing makes a longer route
    r2 = plan_route(w, np.random.default_rng(0), start=(1.0, 1.0), clearance=0.5, spacing=1.5)
    assert route_length(r2) > route_length(r)


def test_route_respects_thin_walls():
    # a thin wall splits the room except for a 2 m opening at the top
    w = room_world(walls=[[[6, 0], [6, 6]]])
    r = plan_route(w, np.random.default_rng(1), start=(2.0, 2.0), spacing=2.0)
    assert exact_clearance(w, r) >= 0.4 - 1e-9
    assert not shapely.LineString(r).intersects(w.thin_walls[0])
    assert r[:, 0].max() > 9.0  # it reached the far side through the opening
    # a start right beside the wall starts on its own side
    r2 = plan_route(w, np.random.default_rng(1), start=(6.1, 1.0), spacing=2.0)
    assert 6.0 < r2[0, 0] < 7.0


def test_route_errors():
    w = room_world()
    with pytest.raises(ValueError, match="not in the free space"):
        plan_route(w, np.random.default_rng(0), start=(20.0, 1.0))
    with pytest.raises(ValueError, match="no room"):
        plan_route(w, np.random.default_rng(0), clearance=4.5)
    with pytest.raises(ValueError, match="clearance"):
        plan_route(w, np.random.default_rng(0), clearance=-1.0)
    with pytest.raises(ValueError, match="spacing"):
        plan_route(w, np.random.default_rng(0), spacing=0.0)
    with pytest.raises(ValueError, match="clearance"):
        navigable_region(w, float("nan"))


def test_world_route_is_used_when_given():
    w = room_world(route=[[1, 1], [11, 1], [11, 7]])
    r = plan_route(w, np.random.default_rng(0))
    assert r.tolist() == [[1, 1], [11, 1], [11, 7]]
    planned_anyway = plan_route(w, np.random.default_rng(0), use_world_route=False)
    assert len(planned_anyway) > 3
    parts = plan_routes(w, 2, np.random.default_rng(0))
    assert route_length(parts[0]) == pytest.approx(8.0) and route_length(parts[1]) == pytest.approx(8.0)


def test_plan_routes_share_the_coverage():
    w = load_world("office")
    full = plan_route(w, np.random.default_rng(11))
    parts = plan_routes(w, 3, np.random.default_rng(11))
    assert len(parts) == 3
    assert sum(route_length(p) for p in parts) == pytest.approx(route_length(full))
    starts = np.array([p[0] for p in parts])
    assert min(np.hypot(*(starts[i] - starts[j])) for i in range(3) for j in range(i + 1, 3)) > 1.0
    for p in parts:
        assert exact_clearance(w, p) >= 0.4 - 1e-9
    assert np.allclose(parts[0][-1], parts[1][0]) and np.allclose(parts[1][-1], parts[2][0])
    with pytest.raises(ValueError):
        plan_routes(w, 0, np.random.default_rng(0))


def head(route, length):
    """The first ``length`` metres of a polyline."""
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])
    return route[: int(np.searchsorted(cum, length)) + 1]


def test_fleet_routes_share_the_coverage_from_their_own_starts():
    """Robots switched on at random points: each route leaves from its own start, together they
    see every wall within about a fleet's share of one robot's tour each, and each goes on over
    the others' parts (so that their maps come to share walls)."""
    w = load_world("office")
    starts = [(20.5, 18.6), (6.1, 18.7), (12.6, 8.5), (32.8, 8.2)]
    routes = plan_fleet_routes(w, starts, np.random.default_rng(3))
    again = plan_fleet_routes(w, starts, np.random.default_rng(3))
    assert all(np.array_equal(a, b) for a, b in zip(routes, again))
    share = 90.0  # a quarter of one robot's tour of the office (308 m), and the way to its part
    for s, r in zip(starts, routes):
        assert np.hypot(*(r[0] - s)) < 1.0
        assert exact_clearance(w, r) >= 0.4 - 1e-9
        assert route_length(r) > 3 * share  # the own phase goes on past the shared one
    assert seen_fraction(w, routes[0], 6.0) >= 0.95  # ... and the own phase over most of the world
    shares = [seen_mask(w, head(r, share), 6.0) for r in routes]
    assert max(m.mean() for m in shares) < 0.6  # each share alone is a part of the world
    assert np.any(shares, axis=0).mean() >= 0.99  # together they see every wall
    with pytest.raises(ValueError, match="not in the free space"):
        plan_fleet_routes(w, [(-5.0, -5.0)], np.random.default_rng(0))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-50, 50, allow_subnormal=False), st.floats(-50, 50, allow_subnormal=False)),
        min_size=2,
        max_size=12,
    ),
    st.integers(1, 6),
    st.floats(0.0, 0.5),
)
@example([(1.0, 15.0), (0.0, 0.0), (0.0, 3.0182584683714705e-195)], 3, 0.0)  # a 3e-195 m segment
@example([(0.0, 1.0), (3.219874091585074e-247, 1.0), (0.0, 0.0)], 1, 0.0)  # and a 3e-247 m one
def test_split_route_pieces(points, n, overlap):
    r = np.array(points)
    total = route_length(r)
    parts = split_route(r, n, overlap)
    assert len(parts) == n
    if total < 1e-6:  # degenerate route: nothing to cut
        return
    lengths = [route_length(p) for p in parts]
    for i, length in enumerate(lengths):
        expect = min(total, total * (i + 1 + overlap) / n) - total * i / n
        assert length == pytest.approx(expect, rel=1e-6, abs=1e-6)
    if overlap == 0:
        for a, b in itertools.pairwise(parts):
            assert np.allclose(a[-1], b[0])
    assert np.allclose(parts[0][0], r[0]) and np.allclose(parts[-1][-1], r[-1])
    line = shapely.LineString(r)
    # every piece lies on the route (on a segment whose squared length underflows to zero, below
    # ~1e-162 m, GEOS's distance raises a divide-by-zero or invalid flag that numpy reports as a
    # warning; the distance is still right)
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = shapely.distance(line, shapely.points(np.concatenate(parts)))
    assert dist.max() < 1e-6


# ---------------------------------------------------------------------- motion
ROUTE = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [1.0, 5.0]])


def dist_to_polyline(route, xy):
    return float(shapely.LineString(route).distance(shapely.Point(xy)))


def test_drive_follows_the_route_exactly():
    steps = drive(ROUTE, speed=0.5, dt=0.5, rng=np.random.default_rng(0))
    assert isinstance(steps[0], Step)
    assert steps[0].t == 0.0 and steps[0].odometry == Pose.identity()
    assert steps[0].true_pose.almost_equal(Pose(0.0, 0.0, 0.0))
    length = route_length(ROUTE)
    assert steps[-1].t == pytest.approx(math.ceil(length / 0.25) * 0.5)
    assert np.allclose([steps[-1].true_pose.x, steps[-1].true_pose.y], ROUTE[-1])
    for s in steps:
        assert dist_to_polyline(ROUTE, (s.true_pose.x, s.true_pose.y)) < 1e-9
    ts = np.array([s.t for s in steps])
    assert np.allclose(np.diff(ts), 0.5)
    # consecutive true poses are at most speed * dt apart
    xy = np.array([[s.true_pose.x, s.true_pose.y] for s in steps])
    assert np.hypot(*np.diff(xy, axis=0).T).max() <= 0.25 + 1e-9
    # heading is the direction of the segment being driven
    mid = steps[3].true_pose
    assert mid.theta == pytest.approx(0.0)
    on_second = [s for s in steps if 0.1 < s.true_pose.y < 2.9]
    assert all(s.true_pose.theta == pytest.approx(math.pi / 2) for s in on_second)


def test_drive_turn_rate_costs_time_and_turns_in_place():
    fast = drive(ROUTE, rng=np.random.default_rng(0))
    slow = drive(ROUTE, rng=np.random.default_rng(0), max_turn_rate=0.5)
    turns = abs(math.pi / 2) + abs(math.atan2(2, -3) - math.pi / 2)
    assert slow[-1].t - fast[-1].t == pytest.approx(turns / 0.5, abs=0.5 + 1e-9)
    for s in slow:
        assert dist_to_polyline(ROUTE, (s.true_pose.x, s.true_pose.y)) < 1e-9
    dth = [abs(b.true_pose.theta - a.true_pose.theta) for a, b in itertools.pairwise(slow)]
    assert max(min(d, 2 * math.pi - d) for d in dth) <= 0.5 * 0.5 + 1e-9


def test_drive_without_noise_dead_reckons_the_truth():
    steps = drive(ROUTE, rng=np.random.default_rng(0), noise=OdometryNoise.none(), max_turn_rate=1.0)
    est = dead_reckon(steps)
    for s, p in zip(steps, est):
        assert s.true_pose.almost_equal(p, tol=1e-9, angle_tol=1e-9)


def test_drive_is_reproducible():
    a = drive(ROUTE, rng=np.random.default_rng(3))
    b = drive(ROUTE, rng=np.random.default_rng(3))
    c = drive(ROUTE, rng=np.random.default_rng(4))
    assert all(x.odometry == y.odometry and x.true_pose == y.true_pose for x, y in zip(a, b))
    assert any(x.odometry != y.odometry for x, y in zip(a, c))


def test_odometry_noise_statistics():
    noise = OdometryNoise()
    rng = np.random.default_rng(42)
    inc = Pose(0.25, 0.0, math.pi / 2)
    samples = np.array([noisy_increment(inc, noise, rng).as_tuple() for _ in range(20000)])
    err = samples - np.array(inc.as_tuple())
    st_expect = 0.02 * 0.25
    sr_expect = 0.02 * math.pi / 2 + 0.002 * 0.25
    assert abs(err.mean(axis=0)).max() < 4 * sr_expect / math.sqrt(20000) + 1e-12
    assert err[:, 0].std() == pytest.approx(st_expect, rel=0.05)
    assert err[:, 1].std() == pytest.approx(st_expect, rel=0.05)
    assert err[:, 2].std() == pytest.approx(sr_expect, rel=0.05)
    # along a drive: the odometry error of straight steps scales with the distance
    route = np.array([[0.0, 0.0], [400.0, 0.0]])
    steps = drive(route, speed=1.0, dt=1.0, rng=np.random.default_rng(1))
    e = np.array([[s.odometry.x - 1.0, s.odometry.y, s.odometry.theta] for s in steps[1:]])
    assert e[:, 0].std() == pytest.approx(0.02, rel=0.15)
    assert e[:, 2].std() == pytest.approx(0.002, rel=0.15)


def test_odometry_noise_validation():
    with pytest.raises(ValueError, match="trans_per_m"):
        OdometryNoise(trans_per_m=-0.1)
    with pytest.raises(ValueError, match="rot_abs"):
        OdometryNoise(rot_abs=float("inf"))
    assert OdometryNoise(trans_abs=1).trans_abs == 1.0
    assert OdometryNoise().stds(Pose(3.0, 4.0, -1.0)) == pytest.approx((0.1, 0.02 + 0.01))


def test_drive_validation_and_degenerate_routes():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="speed"):
        drive(ROUTE, speed=0.0, rng=rng)
    with pytest.raises(ValueError, match="dt"):
        drive(ROUTE, dt=-1.0, rng=rng)
    with pytest.raises(ValueError, match="max_turn_rate"):
        drive(ROUTE, rng=rng, max_turn_rate=0.0)
    with pytest.raises(ValueError, match="shape"):
        drive(np.zeros((3, 3)), rng=rng)
    one = drive(np.array([[1.0, 2.0]]), rng=rng)
    assert len(one) == 1 and one[0].true_pose.almost_equal(Pose(1.0, 2.0, 0.0))
    dup = drive(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]]), rng=rng)
    assert dup[-1].true_pose.x == pytest.approx(1.0)


def test_drive_planned_route_stays_clear():
    w, r = planned("paper-small")
    steps = drive(r, rng=np.random.default_rng(9), max_turn_rate=1.0)
    xy = np.array([[s.true_pose.x, s.true_pose.y] for s in steps])
    assert w.is_free(xy).all()
    d = shapely.distance(w.walls(), shapely.points(xy))
    assert d.min() >= 0.4 - 1e-9
    assert steps[-1].t >= route_length(r) / 0.5
