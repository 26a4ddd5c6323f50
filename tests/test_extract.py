"""Tests of split-and-merge corner extraction (mapping.extract) on simulated lidar scans."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, Polygon

from agents.sim.lidar import LidarConfig, raycast
from mapping.extract import ExtractConfig, extract_corners
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

NOM, OCC, FRO = int(Label.NOMINAL), int(Label.OCCLUSION), int(Label.FRONTIER)

# A 10 x 6 room (counterclockwise) with a 1 x 1 box (clockwise) in it.
ROOM = [(0.0, 0.0), (10.0, 0.0), (10.0, 6.0), (0.0, 6.0)]
BOX = [(5.0, 2.5), (5.0, 3.5), (6.0, 3.5), (6.0, 2.5)]
ROOM_BOX = Wireframe.from_polylines([ROOM, BOX])

# An L-shaped room with a square and a diamond obstacle, for many-pose checks.
L_ROOM = [(0.0, 0.0), (6.0, 0.0), (6.0, 3.0), (3.0, 3.0), (3.0, 5.0), (0.0, 5.0)]
SQ = [(1.0, 1.0), (1.0, 2.0), (2.0, 2.0), (2.0, 1.0)]
DIAMOND = [(4.0, 1.0), (4.5, 1.6), (5.0, 1.0), (4.5, 0.6)]
L_WORLD = Wireframe.from_polylines([L_ROOM, SQ, DIAMOND])
L_FREE = Polygon(L_ROOM).difference(Polygon(SQ)).difference(Polygon(DIAMOND))
L_CORNERS = L_WORLD.points


def scan(world: Wireframe, pose: Pose, cfg: LidarConfig, rng: np.random.Generator | None = None) -> Wireframe:
    """Extracted corner scan, mapped back to the world frame for easy comparison."""
    r = raycast(world.segments(), pose, cfg, rng)
    return extract_corners(r, cfg.angles(), cfg.max_range).transformed(pose)


def assert_scan_shape(s: Wireframe, pose: Pose) -> None:
    """Robot on the left of every edge (counterclockwise around the robot)."""
    local = pose.apply_inverse(s.points)
    for a, b in s.edges:
        pa, pb = local[a], local[b]
        assert pa[0] * pb[1] - pa[1] * pb[0] > 0.0, "an edge does not run counterclockwise"


def dist_to_walls(p: np.ndarray, wf: Wireframe) -> float:
    seg = wf.segments()
    a, ab = seg[:, 0], seg[:, 1] - seg[:, 0]
    t = np.clip(((p - a) * ab).sum(1) / (ab * ab).sum(1), 0.0, 1.0)
    return float(np.hypot(*(a + t[:, None] * ab - p).T).min())


def random_poses(n: int, seed: int) -> list[Pose]:
    rng = np.random.default_rng(seed)
    inner = L_FREE.buffer(-0.2)
    out: list[Pose] = []
    while len(out) < n:
        x, y = rng.uniform(0, 6), rng.uniform(0, 5)
        if inner.contains(Point(x, y)):
            out.append(Pose(x, y, rng.uniform(-math.pi, math.pi)))
    return out


# ---------------------------------------------------------------- configuration and inputs
@pytest.mark.parametrize(
    "kwargs",
    [
        {"split_tol": 0.0},
        {"jump": -1.0},
        {"min_points": 1},
        {"min_points": 3.5},
        {"max_vertices": -1},
        {"merge_angle": 2.0},
        {"min_length": math.nan},
        {"max_gap": -1},
        {"max_extrapolation": -0.1},
        {"lost_gap": -0.5},
        {"lost_gap": math.inf},
    ],
)
def test_config_rejects_bad_values(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        ExtractConfig(**kwargs)  # type: ignore[arg-type]


def test_bad_angles_raise() -> None:
    a = LidarConfig().angles()
    with pytest.raises(ValueError):
        extract_corners(np.ones(10), a, 10.0)
    with pytest.raises(ValueError):
        extract_corners(np.ones(361), a[::-1], 10.0)
    with pytest.raises(ValueError):
        extract_corners(np.ones(3), np.array([0.0, 1.0, 7.0]), 10.0)
    with pytest.raises(ValueError):
        extract_corners(np.ones(361), a, 0.0)
    with pytest.raises(ValueError):
        extract_corners(np.ones(2), np.array([0.0, np.nan]), 10.0)


@pytest.mark.parametrize(
    "ranges",
    [
        np.full(361, np.inf),
        np.full(361, np.nan),
        np.full(361, 10.0),  # all at max range: no return
        np.full(361, 25.0),
        np.zeros(361),  # "no echo" as zero
        -np.ones(361),
    ],
)
def test_no_returns_give_an_empty_scan(ranges: np.ndarray) -> None:
    s = extract_corners(ranges, LidarConfig().angles(), 10.0)
    assert s.n_vertices == 0 and s.n_edges == 0


def test_tiny_inputs() -> None:
    assert extract_corners(np.zeros(0), np.zeros(0), 5.0).n_vertices == 0
    assert extract_corners(np.ones(1), np.zeros(1), 5.0).n_vertices == 0
    assert extract_corners(np.ones(3), np.array([0.0, 0.1, 0.2]), 5.0).n_vertices == 0


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    beams=st.integers(2, 400),
    full=st.booleans(),
    nan_share=st.floats(0, 1),
)
def test_garbage_never_crashes(seed: int, beams: int, full: bool, nan_share: float) -> None:
    rng = np.random.default_rng(seed)
    cfg = LidarConfig(beams=max(beams, 2), fov=2 * math.pi if full else 3.0, max_range=8.0)
    r = rng.choice([rng.uniform(0, 9), 0.0, np.inf], size=cfg.beams) + rng.normal(0, 0.5, cfg.beams)
    r[rng.random(cfg.beams) < nan_share] = np.nan
    s = extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(max_vertices=30))
    assert s.n_vertices <= 30
    assert np.all(np.isfinite(s.points))
    assert_scan_shape(s, Pose())


# ---------------------------------------------------------------- hand-made scenes
def test_room_with_a_box_known_corner_scan() -> None:
    cfg = LidarConfig(sigma=0.0)  # 361 beams, 180 degrees, 10 m
    pose = Pose(2.0, 3.0, 0.0)
    s = scan(ROOM_BOX, pose, cfg)
    # Counterclockwise from the right edge of the view (bearing -90 degrees).
    want = [
        ((2.0, 0.0), FRO, 0.001),  # field-of-view edge on the bottom wall
        ((10.0, 0.0), NOM, 0.002),
        ((10.0, 5.0 / 3.0), FRO, 0.05),  # on the far wall, behind the box corner (5, 2.5)
        ((5.0, 2.5), OCC, 0.02),
        ((5.0, 3.5), OCC, 0.02),
        ((10.0, 13.0 / 3.0), FRO, 0.05),
        ((10.0, 6.0), NOM, 0.002),
        ((2.0, 6.0), FRO, 0.001),
    ]
    assert s.n_vertices == len(want)
    for k, ((x, y), lab, tol) in enumerate(want):
        assert s.labels[k] == lab, f"vertex {k}"
        assert math.hypot(s.points[k, 0] - x, s.points[k, 1] - y) <= tol, f"vertex {k} at {s.points[k]}"
    assert sorted(map(tuple, s.edges.tolist())) == [(0, 1), (1, 2), (3, 4), (5, 6), (6, 7)]
    # Frontiers lie exactly on the far wall and on the line of sight through their occlusion.
    assert s.points[2, 0] == pytest.approx(10.0, abs=1e-3) and s.points[5, 0] == pytest.approx(10.0, abs=1e-3)
    for occ, fro in ((3, 2), (4, 5)):
        a, b = pose.apply_inverse(s.points[[occ, fro]])
        assert abs(a[0] * b[1] - a[1] * b[0]) / np.hypot(*b) < 1e-6
    assert np.all(s.likelihood == 1.0) and np.all(s.sources == 0)
    assert_scan_shape(s, pose)


def test_square_room_full_turn_is_a_closed_counterclockwise_ring() -> None:
    square = Wireframe.from_polylines([[(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)]])
    for theta in (0.0, 0.3, 2.0, -2.9):
        pose = Pose(1.3, 1.1, theta)
        s = scan(square, pose, LidarConfig(fov=2 * math.pi, sigma=0.0))
        assert s.n_vertices == 4 and s.n_edges == 4
        assert np.all(s.labels == NOM)
        assert square.almost_equal(s, tol=0.002)  # the same directed ring
        bearings = np.arctan2(*(pose.apply_inverse(s.points) - 0.0)[:, ::-1].T)
        assert np.all(np.diff(bearings) > 0), "vertices are not in counterclockwise order"


def test_square_room_half_turn_ends_at_the_field_of_view() -> None:
    square = Wireframe.from_polylines([[(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)]])
    s = scan(square, Pose(1.3, 1.1, 0.0), LidarConfig(sigma=0.0))
    assert s.labels.tolist() == [FRO, NOM, NOM, FRO]
    assert np.allclose(s.points, [(1.3, 0.0), (4.0, 0.0), (4.0, 3.0), (1.3, 3.0)], atol=0.002)
    assert s.edges.tolist() == [[0, 1], [1, 2], [2, 3]]


def test_wall_leaving_the_range_ends_on_the_range_circle() -> None:
    corridor = Wireframe.from_polylines([[(0, 0), (30, 0), (30, 4), (0, 4)],
                                         [(5, 1.5), (5, 2.5), (6, 2.5), (6, 1.5)]])
    cfg = LidarConfig(sigma=0.0, max_range=10.0)
    pose = Pose(2.0, 2.0, 0.0)
    s = scan(corridor, pose, cfg)
    far = 2.0 + math.sqrt(96.0)
    want = [((2, 0), FRO), ((far, 0), FRO), ((5, 1.5), OCC), ((5, 2.5), OCC), ((far, 4), FRO), ((2, 4), FRO)]
    assert s.n_vertices == len(want)
    for k, ((x, y), lab) in enumerate(want):
        assert s.labels[k] == lab
        if x == far:  # short of the circle: at most max_extrapolation past the last return
            assert abs(s.points[k, 1] - y) < 0.02 and far - 0.4 < s.points[k, 0] <= far + 1e-9
        else:
            assert math.hypot(s.points[k, 0] - x, s.points[k, 1] - y) < 0.02
    # exit_on_circle: on the range circle (a wall ending just short of the range limit is then
    # extended to it, which the union of a merge keeps)
    r = raycast(corridor.segments(), pose, cfg)
    on = extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(exit_on_circle=True)).transformed(pose)
    for k in (1, 4):
        assert math.hypot(on.points[k, 0] - far, on.points[k, 1] - want[k][0][1]) < 0.02
    # The box's silhouette corners have nothing within range behind them: occlusions, no partner.
    assert s.edges.tolist() == [[0, 1], [2, 3], [4, 5]]


def test_nearer_and_farther_jumps_label_both_sides() -> None:
    # A free-standing wall with a panel in front of part of it. From the robot: the wall's
    # lower end (nothing behind it), the wall up to where the panel hides it (frontier), the
    # panel (an occlusion at each end), the wall again from behind the panel (frontier) up to its
    # upper end (nothing behind it within range: occlusion).
    world = Wireframe.from_polylines([[(4, -3), (4, 6)], [(2, 0.5), (2, 2.5)]], closed=False)
    pose = Pose(0.0, 0.0, 0.0)
    s = scan(world, pose, LidarConfig(sigma=0.0, fov=2.4))
    want = [((4, -3), OCC, 0.03), ((4, 1), FRO, 0.03), ((2, 0.5), OCC, 0.02), ((2, 2.5), OCC, 0.02),
            ((4, 5), FRO, 0.05), ((4, 6), OCC, 0.05)]
    assert s.labels.tolist() == [lab for _, lab, _ in want]
    for k, ((x, y), _, tol) in enumerate(want):
        assert math.hypot(s.points[k, 0] - x, s.points[k, 1] - y) <= tol, f"vertex {k} at {s.points[k]}"
    assert s.edges.tolist() == [[0, 1], [2, 3], [4, 5]]
    # Each frontier is on the line of sight through the panel's occlusion next to it.
    for occ, fro in ((2, 1), (3, 4)):
        a, b = s.points[occ], s.points[fro]
        assert abs(a[0] * b[1] - a[1] * b[0]) / np.hypot(*b) < 1e-6


def test_end_face_of_a_thick_wall_is_kept() -> None:
    # A 0.3 m thick wall (clockwise obstacle): its end face is shorter than min_length but meets
    # the long face in a corner, so it is structure, not clutter.
    world = Wireframe.from_polylines([[(0, 0), (10, 0), (10, 8), (0, 8)],
                                      [(4, 2), (4, 5), (4.3, 5), (4.3, 2)]])
    pose = Pose(2.0, 6.5, 0.3)
    s = scan(world, pose, LidarConfig(beams=720, fov=2 * math.pi, sigma=0.0))
    corner = int(np.argmin(np.hypot(s.points[:, 0] - 4.0, s.points[:, 1] - 5.0)))
    end = int(np.argmin(np.hypot(s.points[:, 0] - 4.3, s.points[:, 1] - 5.0)))
    assert s.labels[corner] == NOM and np.hypot(*(s.points[corner] - (4.0, 5.0))) < 0.002
    assert s.labels[end] == OCC and np.hypot(*(s.points[end] - (4.3, 5.0))) < 0.02
    assert [corner, end] in s.edges.tolist()
    assert_scan_shape(s, pose)


def test_clutter_is_dropped_and_dropouts_are_bridged() -> None:
    room = Wireframe.from_polylines([ROOM])
    legs = [[(7.0, 2.0 + d), (7.05, 2.0 + d), (7.05, 2.05 + d), (7.0, 2.05 + d)][::-1] for d in (0.0, 0.4)]
    world = Wireframe.from_polylines([ROOM, *legs])
    cfg = LidarConfig(sigma=0.0)
    pose = Pose(2.0, 3.0, 0.0)
    r = raycast(world.segments(), pose, cfg)
    s = extract_corners(r, cfg.angles(), cfg.max_range).transformed(pose)
    # No vertex near the legs; the far wall is split behind them, its pieces end in frontiers.
    near_legs = np.hypot(s.points[:, 0] - 7.0, s.points[:, 1] - 2.2) < 0.5
    assert not near_legs.any()
    on_far_wall = np.isclose(s.points[:, 0], 10.0, atol=0.01)
    assert (s.labels[on_far_wall & (s.labels == FRO)]).size >= 2
    # A single drop-out inside a wall does not split it.
    r2 = raycast(room.segments(), pose, cfg)
    r2[[100, 250, 251]] = np.nan
    s2 = extract_corners(r2, cfg.angles(), cfg.max_range)
    s_ref = extract_corners(raycast(room.segments(), pose, cfg), cfg.angles(), cfg.max_range)
    assert s2.almost_equal(s_ref, tol=0.01)


@pytest.mark.parametrize(("lost", "width", "label"), [(0.0, 5, "occ"), (0.5, 5, "fro"), (0.5, 20, "occ")])
def test_lost_beams_inside_a_wall_are_not_its_end(lost: float, width: int, label: str) -> None:
    """A burst of lost beams inside a wall (five at 3 m: 13 cm) leaves two silhouette corners
    unless ``lost_gap`` says the wall goes on beyond them (frontiers at the last points); a
    gap wider than ``lost_gap`` (twenty beams: 0.53 m, a doorway with nothing behind) stays
    where the wall ends."""
    wall = np.array([[[-10.0, 3.0], [10.0, 3.0]]])
    cfg = LidarConfig(beams=720, fov=2 * math.pi, max_range=8.0, sigma=0.0)
    r = raycast(wall, Pose(0.0, 0.0, 0.0), cfg)
    r[560:560 + width] = np.inf  # beam 540 points along +y, at the wall
    s = extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(lost_gap=lost))
    assert s.n_edges == 2
    inner = np.abs(s.points[:, 0]) < 5.0  # the two ends at the gap
    assert inner.sum() == 2
    want = OCC if label == "occ" else FRO
    assert np.all(s.labels[inner] == want)
    assert np.allclose(s.points[:, 1], 3.0, atol=1e-6)


def test_vertex_budget_keeps_the_longest_walls() -> None:
    # A long back wall behind a row of small pillars: many short walls.
    pillars = [[(3 + k, 1.0), (3 + k, 1.3), (3.3 + k, 1.3), (3.3 + k, 1.0)][::-1] for k in range(6)]
    world = Wireframe.from_polylines([[(0, 0), (12, 0), (12, 8), (0, 8)], *pillars])
    cfg = LidarConfig(sigma=0.0, fov=2 * math.pi)
    pose = Pose(6.1, 4.0, 0.2)
    r = raycast(world.segments(), pose, cfg)
    full = extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(min_length=0.1))
    capped = extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(min_length=0.1, max_vertices=6))
    assert full.n_vertices > 6
    assert capped.n_vertices <= 6
    assert capped.total_length() > 0.5 * sum(sorted(full.edge_lengths())[-3:])
    assert capped.edge_lengths().min() >= np.sort(full.edge_lengths())[-capped.n_edges] - 1e-9
    assert extract_corners(r, cfg.angles(), cfg.max_range, ExtractConfig(max_vertices=0)).n_vertices == 0


def test_deterministic() -> None:
    cfg = LidarConfig(sigma=0.01)
    r = raycast(L_WORLD.segments(), Pose(1.5, 2.7, -0.4), cfg, np.random.default_rng(4))
    a = extract_corners(r, cfg.angles(), cfg.max_range)
    b = extract_corners(r.copy(), cfg.angles(), cfg.max_range)
    assert a.almost_equal(b, tol=0.0)
    assert np.array_equal(a.points, b.points)


# ---------------------------------------------------------------- grazing angles (issue 3)
FULL_TURN = LidarConfig(beams=720, fov=2 * math.pi, max_range=8.0, sigma=0.0)


def edge_between(
    s: Wireframe, p: tuple[float, float], q: tuple[float, float], tol: float = 0.03
) -> int | None:
    """Index of the edge running from near ``p`` to near ``q``, or None."""
    for k, (a, b) in enumerate(s.edges.tolist()):
        if np.hypot(*(s.points[a] - p)) <= tol and np.hypot(*(s.points[b] - q)) <= tol:
            return k
    return None


@pytest.mark.parametrize("x", [3.1, 3.2])
def test_end_face_seen_end_on_is_a_wall_from_a_nominal_corner(x: float) -> None:
    """The 0.4 m end face of a thick wall, seen from the room almost in its own plane, returns one
    or two beams: too few to fit. It is reported (a stub from the corner through its returns),
    and the long face ends in that NOMINAL corner -- as the corner sensor reports it. Before, the
    long face ended in a frontier and the end face was missing, so the filter's prediction of
    the map's jamb looked seen-through and a door jamb was mutated away."""
    thick = Wireframe.from_polylines([[(-5, 2), (3, 2), (3, 2.4), (-5, 2.4)], [(-6, 6), (12, 6)]],
                                     closed=False)
    pose = Pose(x, 0.0, 0.3)
    s = scan(thick, pose, FULL_TURN)
    assert_scan_shape(s, pose)
    corner = np.flatnonzero(np.hypot(*(s.points - (3.0, 2.0)).T) < 0.02)
    assert len(corner) == 1 and s.labels[corner[0]] == NOM
    c = int(corner[0])
    arriving = [a for a, b in s.edges.tolist() if b == c]  # the end face, from its far end
    leaving = [b for a, b in s.edges.tolist() if a == c]  # the long face
    assert len(arriving) == 1 and len(leaving) == 1
    d = s.points[c] - s.points[arriving[0]]
    assert 0.15 < np.hypot(*d) < 0.5 and abs(d[0]) < 0.02  # along the end face x = 3
    assert s.labels[arriving[0]] == OCC  # its far end is a silhouette
    assert abs(s.points[leaving[0], 1] - 2.0) < 0.02
    # without stubs: the old free end
    r = raycast(thick.segments(), pose, FULL_TURN)
    old = extract_corners(r, FULL_TURN.angles(), FULL_TURN.max_range,
                          ExtractConfig(stubs=False)).transformed(pose)
    assert not np.any(np.hypot(*(old.points[old.labels == NOM] - (3.0, 2.0)).T) < 0.05)


def test_wall_seen_at_a_grazing_angle_between_two_corners_is_one_wall() -> None:
    """A 2 m wall 9 cm off the robot's line of sight returns three beams 0.3-1 m apart, each cut
    off from the next by a range jump. On one line with the corners at its ends, they are that
    wall (before: nothing, and the scan 'saw through' the wall)."""
    counter = Wireframe.from_polylines([[(1.8, -1.0), (1.8, 0.0), (3.8, 0.0), (3.8, 2.0)]], closed=False)
    for heading in (0.0, 0.2):
        pose = Pose(0.0, 0.09, heading)
        s = scan(counter, pose, FULL_TURN)
        assert_scan_shape(s, pose)
        k = edge_between(s, (1.8, 0.0), (3.8, 0.0))
        assert k is not None
        assert s.labels[s.edges[k]].tolist() == [NOM, NOM]


def test_one_return_at_each_end_of_a_wall_seen_edge_on_is_the_whole_wall() -> None:
    """From a doorway, 1 cm off the plane of a 2.8 m wall face: one beam hits the face next to each
    end and no ray passes between them. Both returns lie on one line with the two walls' ends:
    one wall, not two stubs with a gap the scan would claim to have seen through."""
    door = Wireframe.from_polylines([[(0.6, 0.4), (0.6, 0.0), (3.4, 0.0), (3.4, -3.0)]], closed=False)
    pose = Pose(0.0, -0.01, math.radians(0.28))
    s = scan(door, pose, FULL_TURN)
    assert_scan_shape(s, pose)
    k = edge_between(s, (3.4, 0.0), (0.6, 0.0))
    assert k is not None and s.labels[s.edges[k]].tolist() == [NOM, NOM]


def test_no_wall_along_a_line_of_sight_through_a_jamb_and_a_face_behind() -> None:
    """A door jamb and, 4 m behind it, a box face almost on the same line of sight: their returns
    are nearly collinear, but a range jump of 4 m is no grazing wall (regression: a 5 m
    line-of-sight 'wall' from the jamb's corner to the box)."""
    world = Wireframe.from_polylines(
        [[(7.0, 7.0), (3.2, 7.0), (3.2, 7.4), (7.0, 7.4)],
         [(3.6, 11.0), (3.6, 13.0), (5.6, 13.0), (5.6, 11.0)]]
    )
    for dx in (-0.01, 0.0, 0.01, 0.02):
        pose = Pose(2.93 + dx, 4.62, 2.9)
        s = scan(world, pose, FULL_TURN)
        for seg in s.segments():
            assert not (seg[:, 1].min() < 7.5 and seg[:, 1].max() > 10.9), seg
            assert dist_to_walls(0.5 * (seg[0] + seg[1]), world) < 0.03


def test_free_ends_are_not_extrapolated_past_the_wall() -> None:
    """A silhouette corner seen at a grazing angle: the wall's free end is placed no further than
    max_extrapolation (0.1 m) beyond its last return. Before, up to 0.75 of the point spacing:
    from these poses a box face ran up to 0.17 m past its corner, and the merge (a union) keeps
    such an overshoot -- the box's outline no longer closes."""
    box = Wireframe.from_polylines([[(2.0, 1.0), (2.0, 2.0), (4.0, 2.0), (4.0, 1.0)]])
    for x, y in ((5.75, 0.64), (6.0, 0.62), (5.0, 0.74), (5.25, 0.66)):
        pose = Pose(x, y, 0.0)
        s = scan(box, pose, FULL_TURN)
        on_bottom = [(p, lab) for p, lab in zip(s.points, s.labels) if abs(p[1] - 1.0) < 0.02]
        assert any(lab != NOM for _, lab in on_bottom)  # the bottom face ends on a silhouette
        for p, lab in on_bottom:
            if lab != NOM:
                assert p[0] >= 2.0 - ExtractConfig().max_extrapolation - 1e-9


# ---------------------------------------------------------------- many poses
def test_noise_free_corners_within_2cm_over_many_poses() -> None:
    """The acceptance criterion: extracted corners within 2 cm of the true corners."""
    cfg = LidarConfig(sigma=0.0)
    nominal, occl, front = [], [], []
    for pose in random_poses(60, seed=11):
        s = scan(L_WORLD, pose, cfg)
        assert_scan_shape(s, pose)
        for p, lab in zip(s.points, s.labels):
            if lab == FRO:
                front.append(dist_to_walls(p, L_WORLD))
            else:
                d = float(np.hypot(*(L_CORNERS - p).T).min())
                (nominal if lab == NOM else occl).append(d)
        for a, b in s.edges:  # every edge lies on a true wall
            assert dist_to_walls(0.5 * (s.points[a] + s.points[b]), L_WORLD) < 0.02
    nominal_a, occl_a, front_a = np.array(nominal), np.array(occl), np.array(front)
    assert len(nominal_a) > 60
    # corners between two fitted walls are exact to the fit; the corner at the foot of a short
    # wall seen end-on (a stub of one return) is known to half a beam along its wall only
    assert np.mean(nominal_a < 0.02) >= 0.98 and np.median(nominal_a) < 0.001
    assert np.median(occl_a) < 0.01 and np.mean(occl_a < 0.02) > 0.8  # half a beam, oblique
    assert np.mean(front_a < 0.02) > 0.95


def test_noisy_corner_error_over_many_poses() -> None:
    """Range noise sigma = 1 cm: corner error of split-and-merge on noisy lidar."""
    cfg = LidarConfig(sigma=0.01)
    rng = np.random.default_rng(5)
    nominal = []
    n_scans = 0
    for pose in random_poses(100, seed=12):
        s = scan(L_WORLD, pose, cfg, rng)
        n_scans += 1
        assert_scan_shape(s, pose)
        d = np.hypot(L_CORNERS[None, :, 0] - s.points[:, None, 0],
                     L_CORNERS[None, :, 1] - s.points[:, None, 1])
        nominal.extend(d.min(axis=1)[s.labels == NOM].tolist())
    e = np.array(nominal)
    assert len(e) > n_scans
    assert np.median(e) < 0.006  # measured about 2.5 mm
    assert np.percentile(e, 95) < 0.02  # measured about 9 mm


def test_rotating_a_full_turn_scan_by_one_beam_changes_nothing() -> None:
    cfg = LidarConfig(beams=360, fov=2 * math.pi, sigma=0.0)
    pose = Pose(1.5, 2.5, 0.1)
    r = raycast(L_WORLD.segments(), pose, cfg)
    a = extract_corners(r, cfg.angles(), cfg.max_range).transformed(pose)
    step = 2 * math.pi / cfg.beams
    pose2 = Pose(1.5, 2.5, 0.1 + 7 * step)
    r2 = raycast(L_WORLD.segments(), pose2, cfg)
    b = extract_corners(r2, cfg.angles(), cfg.max_range).transformed(pose2)
    assert a.almost_equal(b, tol=1e-6)


# How fast corners are extracted is a benchmark figure, not a test:
# `wiremap bench speed --pieces` (extract_ms).


def test_jump_beams_grows_the_run_break_with_range() -> None:
    """Neighbouring returns 1 degree apart on a wall seen at 30 degrees are 0.35 m apart at
    10 m: a break for the fixed ``jump`` (0.3 m), not with ``jump_beams = 3`` (0.52 m there);
    a range step of 0.35 m at 1 m is a break either way."""
    from mapping.extract import _far

    a = np.radians(1.0)
    far_p = np.array([[10.0, 0.0]])
    far_q = 10.3 * np.array([[math.cos(a), math.sin(a)]])  # 0.35 m from far_p
    near_p, near_q = np.array([[1.0, 0.0]]), 1.35 * np.array([[math.cos(a), math.sin(a)]])
    assert _far(far_p, far_q, ExtractConfig()).tolist() == [True]
    assert _far(far_p, far_q, ExtractConfig(jump_beams=3.0)).tolist() == [False]
    assert _far(near_p, near_q, ExtractConfig(jump_beams=3.0)).tolist() == [True]
    with pytest.raises(ValueError):
        ExtractConfig(jump_beams=-1.0)
