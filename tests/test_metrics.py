"""Map-quality metrics on hand-made maps with known answers (mapping/metrics.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import metrics as M
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

ROOM = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]  # counterclockwise: free inside
BOX_CW = [(4.0, 4.0), (4.0, 6.0), (6.0, 6.0), (6.0, 4.0)]  # clockwise: an obstacle
ROOM_B = [(10.0, 0.0), (20.0, 0.0), (20.0, 10.0), (10.0, 10.0)]  # shares x=10 with ROOM


def room() -> Wireframe:
    return Wireframe.from_polylines([ROOM])


def room_with_box() -> Wireframe:
    return Wireframe.from_polylines([ROOM, BOX_CW])


def two_rooms() -> Wireframe:
    """Rooms A=[0,10]x[0,10] and B=[10,20]x[0,10]; the wall x=10 is thin (two opposite edges)."""
    return Wireframe.from_polylines([ROOM, ROOM_B])


def two_rooms_b_open() -> Wireframe:
    """:func:`two_rooms` without room B's right wall (20,0)-(20,10)."""
    pts = [*ROOM, (20.0, 0.0), (20.0, 10.0)]
    return Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 0), (1, 4), (5, 2), (2, 1)])


def reversed_edges(wf: Wireframe) -> Wireframe:
    return wf.replace(edges=wf.edges[:, ::-1])


# ---------------------------------------------------------------------------- free space
def test_cw_square_inside_ccw_room_is_an_obstacle() -> None:
    faces, votes = M.classify_faces(room_with_box())
    by_area = {round(f.area, 9): v for f, v in zip(faces, votes.tolist())}
    assert by_area == {96.0: 48.0, 4.0: -8.0}
    free = M.free_space(room_with_box())
    assert free.area == pytest.approx(96.0)
    assert shapely.contains_xy(free, 1.0, 1.0)
    assert not shapely.contains_xy(free, 5.0, 5.0)
    assert not shapely.contains_xy(free, 11.0, 5.0)


def test_cw_room_alone_is_obstacle_and_ccw_box_is_free() -> None:
    assert M.free_space(reversed_edges(room())).is_empty
    nested = Wireframe.from_polylines([ROOM, BOX_CW[::-1]])  # both counterclockwise
    assert M.free_space(nested).area == pytest.approx(100.0)


def test_dangling_thin_wall_makes_no_face() -> None:
    # Bottom wall split at (5,0); a thin wall from there up to (5,5), seen from both sides.
    pts = [(0, 0), (5, 0), (10, 0), (10, 10), (0, 10), (5, 5)]
    wf = Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 5), (5, 1)])
    faces, votes = M.classify_faces(wf)
    assert [f.area for f in faces] == [pytest.approx(100.0)]
    assert votes.tolist() == [pytest.approx(40.0)]
    assert M.free_space(wf).area == pytest.approx(100.0)


def test_dividing_thin_wall_leaves_both_sides_free() -> None:
    faces, votes = M.classify_faces(two_rooms())
    assert sorted(f.area for f in faces) == [pytest.approx(100.0)] * 2
    # Each room: three own walls (+30); the thin wall adds +10 and -10.
    assert votes.tolist() == [pytest.approx(30.0)] * 2
    assert M.free_space(two_rooms()).area == pytest.approx(200.0)


def test_thin_walled_closed_box_has_no_evidence_and_is_obstacle() -> None:
    wf = Wireframe.from_polylines([ROOM, BOX_CW, BOX_CW[::-1]])
    faces, votes = M.classify_faces(wf)
    inner = [v for f, v in zip(faces, votes.tolist()) if f.area == pytest.approx(4.0)]
    assert inner == [0.0]
    assert M.free_space(wf).area == pytest.approx(96.0)


def test_crossing_thin_walls_are_noded_into_four_free_faces() -> None:
    pts = [*ROOM, (5, -1), (5, 11), (-1, 5), (11, 5)]
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 4), (6, 7), (7, 6)]
    wf = Wireframe.build(pts, edges)
    faces, votes = M.classify_faces(wf)
    assert sorted(round(f.area, 9) for f in faces) == [25.0] * 4
    assert np.all(votes == pytest.approx(10.0))
    assert M.free_space(wf).area == pytest.approx(100.0)


def test_split_and_duplicated_edges_do_not_change_free_space() -> None:
    # The bottom wall as two collinear edges, and the top wall drawn twice.
    pts = [(0, 0), (4, 0), (10, 0), (10, 10), (0, 10)]
    wf = Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 4), (3, 4), (4, 0)])
    assert M.free_space(wf).area == pytest.approx(100.0)
    assert M.cell_error(room(), wf, 0.2) == 0.0


def test_empty_wireframe_has_no_free_space() -> None:
    assert M.free_space(Wireframe.empty()).is_empty
    assert M.classify_faces(Wireframe.empty())[1].shape == (0,)


# ---------------------------------------------------------------------------- cell error
def test_identical_maps_score_perfectly() -> None:
    truth = room_with_box()
    got = M.evaluate(truth, truth, 0.2)
    assert list(got) == list(M.METRIC_KEYS)
    assert got == {
        "cell_error": 0.0,
        "wall_precision": 1.0,
        "wall_recall": 1.0,
        "mean_dist_m": 0.0,
        "p95_dist_m": 0.0,
    }
    assert all(type(v) is float for v in got.values())


def test_missing_obstacle_costs_its_cells() -> None:
    # 50 x 50 cells of 0.2 m; the 2 x 2 m box covers 10 x 10 of them.
    assert M.cell_error(room_with_box(), room(), 0.2) == pytest.approx(100 / 2500)
    xs, ys = M._grid(room_with_box(), 0.2)
    assert (len(xs), len(ys)) == (50, 50)
    assert np.count_nonzero(M.rasterize(room_with_box(), xs, ys)) == 2400


def test_open_map_counts_unclosed_room_as_obstacle() -> None:
    # Room B's right wall (20,0)-(20,10) is missing: B closes no face, A is still free.
    truth = two_rooms()
    b_open = two_rooms_b_open()
    assert b_open.n_edges == 4 + 3
    assert M.free_space(b_open).area == pytest.approx(100.0)
    assert M.cell_error(truth, b_open, 0.2) == pytest.approx(0.5)
    # A single room with a wall missing has no free space at all.
    u = Wireframe.from_polylines([ROOM], closed=False)
    assert M.free_space(u).is_empty
    assert M.cell_error(room(), u, 0.2) == 1.0


def test_shift_moves_whole_cell_columns_only() -> None:
    truth = room()
    # Shifted by 0.05 < r/2: no cell centre changes side.
    assert M.cell_error(truth, truth.transformed(Pose(0.05, 0.0, 0.0)), 0.2) == 0.0
    # Shifted by 0.15: the first column (centres x=0.1) leaves free space: 50 of 2500 cells.
    assert M.cell_error(truth, truth.transformed(Pose(0.15, 0.0, 0.0)), 0.2) == pytest.approx(0.02)


def test_grid_rounding_and_bad_arguments() -> None:
    xs, ys = M._grid(Wireframe.from_polylines([[(0, 0), (1, 0), (1, 0.3), (0, 0.3)]]), 0.1)
    assert (len(xs), len(ys)) == (10, 3)
    with pytest.raises(ValueError, match="resolution"):
        M.cell_error(room(), room(), 0.0)
    with pytest.raises(ValueError, match="no walls"):
        M.cell_error(Wireframe.empty(), room(), 0.2)
    with pytest.raises(ValueError, match="too large"):
        M.cell_error(room(), room(), 1e-3)


# ---------------------------------------------------------------------------- precision / recall
def test_deleted_wall_lowers_recall_by_exactly_its_share() -> None:
    truth = two_rooms()  # drawing length 40 + 30 = 70 m (the thin wall counts once)
    assert float(np.hypot(*np.diff(M.wall_pieces(truth), axis=1)[:, 0].T).sum()) == pytest.approx(70.0)
    b_open = two_rooms_b_open()
    p, r = M.wall_precision_recall(truth, b_open, 0.4)
    assert p == pytest.approx(1.0)
    assert r == pytest.approx(60.0 / 70.0, abs=1e-12)
    # Without the angle test the missing wall's ends (within tol of the perpendicular walls)
    # count as found: r is higher by 2 * tol / 70.
    _, r0 = M.wall_precision_recall(truth, b_open, 0.4, max_angle=None)
    assert r0 == pytest.approx((60.0 + 0.8) / 70.0, abs=1e-12)


def test_extra_wall_lowers_precision_by_its_share() -> None:
    extra = Wireframe.build([*ROOM, (2.0, 5.0), (7.0, 5.0)], [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5)])
    p, r = M.wall_precision_recall(room(), extra, 0.4)
    assert (p, r) == (pytest.approx(40.0 / 45.0, abs=1e-12), pytest.approx(1.0))


def test_thin_wall_counts_once() -> None:
    one_sided = Wireframe.build([*ROOM, (5.0, 0.0), (5.0, 10.0)], [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5)])
    both_sided = Wireframe.build(
        [*ROOM, (5.0, 0.0), (5.0, 10.0)], [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 4)]
    )
    assert M.wall_precision_recall(one_sided, both_sided, 0.4) == (1.0, 1.0)
    assert M.wall_precision_recall(room(), both_sided, 0.4)[0] == pytest.approx(40.0 / 50.0)


def test_empty_map_and_bad_tolerance() -> None:
    assert M.wall_precision_recall(room(), Wireframe.empty(), 0.4) == (1.0, 0.0)
    got = M.evaluate(room(), Wireframe.empty(), 0.2)
    assert got["cell_error"] == 1.0 and got["wall_precision"] == 1.0 and got["wall_recall"] == 0.0
    assert math.isnan(got["mean_dist_m"]) and math.isnan(got["p95_dist_m"])
    with pytest.raises(ValueError, match="tolerance"):
        M.wall_precision_recall(room(), room(), -1.0)
    with pytest.raises(ValueError, match="no walls"):
        M.wall_precision_recall(Wireframe.empty(), room(), 0.4)


# ---------------------------------------------------------------------------- distance
def test_parallel_walls_shifted_by_d_have_distance_d() -> None:
    corridor = Wireframe.from_polylines([[(0.0, 0.0), (30.0, 0.0)], [(30.0, 3.0), (0.0, 3.0)]], closed=False)
    d = 0.05
    mean, p95 = M.distance_to_truth(corridor, corridor.transformed(Pose(0.0, d, 0.0)), 0.2)
    assert mean == pytest.approx(d, abs=1e-12)
    assert p95 == pytest.approx(d, abs=1e-12)


def test_shifted_room_distance_and_metrics() -> None:
    d = 0.05
    got = M.evaluate(room(), room().transformed(Pose(d, 0.0, 0.0)), 0.2)
    # Vertical walls are d away, horizontal ones lie on the truth (their 5 cm overhang is within
    # 5 cm of the corner): the mean is about d / 2 and the 95th percentile d.
    assert got["mean_dist_m"] == pytest.approx(d / 2, abs=2e-3)
    assert got["p95_dist_m"] == pytest.approx(d, abs=1e-9)
    assert got["wall_precision"] == 1.0 and got["wall_recall"] == 1.0
    assert got["cell_error"] == 0.0
    # Shifted diagonally by d: every wall is d / sqrt(2) from its truth (up to the corners).
    mean, _ = M.distance_to_truth(room(), room().transformed(Pose(d / math.sqrt(2), d / math.sqrt(2))), 0.2)
    assert mean == pytest.approx(d / math.sqrt(2), abs=2e-3)


def test_distance_percentile_is_length_weighted() -> None:
    truth = Wireframe.from_polylines([[(0.0, 0.0), (100.0, 0.0)]], closed=False)
    near_far = Wireframe.from_polylines([[(0.0, 0.0), (90.0, 0.0)], [(0.0, 1.0), (10.0, 1.0)]], closed=False)
    mean, p95 = M.distance_to_truth(truth, near_far, 0.5)
    assert (mean, p95) == (pytest.approx(0.1), 1.0)
    mostly_near = Wireframe.from_polylines(
        [[(0.0, 0.0), (96.0, 0.0)], [(0.0, 1.0), (4.0, 1.0)]], closed=False
    )
    mean, p95 = M.distance_to_truth(truth, mostly_near, 0.5)
    assert (mean, p95) == (pytest.approx(0.04), 0.0)


def test_sample_walls_weights_sum_to_drawing_length() -> None:
    _, w, dirs = M.sample_walls(two_rooms(), 0.3)
    assert w.sum() == pytest.approx(70.0)
    assert w.max() <= 0.3 + 1e-12
    assert np.allclose(np.hypot(dirs[:, 0], dirs[:, 1]), 1.0)
    with pytest.raises(ValueError, match="spacing"):
        M.sample_walls(room(), 0.0)


# ---------------------------------------------------------------------------- properties
rect = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(2.0, 30.0), st.floats(2.0, 30.0))


def _rect_ring(x: float, y: float, w: float, h: float) -> list[tuple[float, float]]:
    return [(x, y), (x + w, y), (x + w, y + h), (x, y + h)]


@settings(max_examples=25, deadline=None)
@given(
    rect,
    st.tuples(st.floats(0.1, 0.8), st.floats(0.1, 0.8), st.floats(0.05, 0.9), st.floats(0.05, 0.9)),
)
def test_room_with_obstacle_properties(
    room_r: tuple[float, float, float, float], box: tuple[float, ...]
) -> None:
    x, y, w, h = room_r
    fx, fy, fw, fh = box
    bx, by = x + fx * w, y + fy * h
    bw, bh = fw * (x + w - bx), fh * (y + h - by)
    outer = _rect_ring(x, y, w, h)
    inner = _rect_ring(bx, by, bw, bh)[::-1]  # clockwise
    wf = Wireframe.from_polylines([outer, inner])
    assert M.free_space(wf).area == pytest.approx(w * h - bw * bh, rel=1e-9)
    # Reversing every edge swaps free and obstacle among the bounded faces.
    assert M.free_space(reversed_edges(wf)).area == pytest.approx(bw * bh, rel=1e-9)
    got = M.evaluate(wf, wf, 0.5)
    assert got["cell_error"] == 0.0
    assert got["wall_precision"] == 1.0 and got["wall_recall"] == 1.0
    assert got["mean_dist_m"] == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=20, deadline=None)
@given(st.floats(-100, 100), st.floats(-100, 100), st.floats(-math.pi, math.pi), st.integers(0, 2**32 - 1))
def test_wall_metrics_are_invariant_under_rigid_motion(x: float, y: float, th: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = two_rooms()
    noisy = truth.replace(points=truth.points + rng.normal(0.0, 0.1, truth.points.shape))
    pose = Pose(x, y, th)
    a = M.wall_precision_recall(truth, noisy, 0.3)
    b = M.wall_precision_recall(truth.transformed(pose), noisy.transformed(pose), 0.3)
    assert b == (pytest.approx(a[0], abs=1e-9), pytest.approx(a[1], abs=1e-9))
    da = M.distance_to_truth(truth, noisy, 0.2)
    db = M.distance_to_truth(truth.transformed(pose), noisy.transformed(pose), 0.2)
    assert db == (pytest.approx(da[0], abs=1e-9), pytest.approx(da[1], abs=1e-9))
    assert 0.0 <= a[0] <= 1.0 and 0.0 <= a[1] <= 1.0
    ce = M.cell_error(truth, noisy, 0.25)
    assert 0.0 <= ce < 0.1


def test_museum_scale_map_evaluates() -> None:
    """(How fast: `wiremap bench speed --pieces`, evaluate_museum_ms.)"""
    rng = np.random.default_rng(7)
    rings = [_rect_ring(0.0, 0.0, 200.0, 200.0)]
    for i in range(9):
        for j in range(9):
            rings.append(_rect_ring(5 + 22 * i, 5 + 22 * j, *rng.uniform(8.0, 17.0, 2))[::-1])
    truth = Wireframe.from_polylines(rings)
    assert truth.n_edges == 328
    noisy = truth.replace(points=truth.points + rng.normal(0.0, 0.15, truth.points.shape))
    got = M.evaluate(truth, noisy, 0.4)
    assert 0.0 < got["cell_error"] < 0.05
    assert got["wall_recall"] > 0.95 and got["wall_precision"] > 0.95
    assert 0.05 < got["mean_dist_m"] < 0.2


# ------------------------------------------------------------------ rigid alignment
def test_align_to_truth_undoes_a_rigid_motion_and_only_that():
    truth = Wireframe.from_polylines([ROOM, BOX_CW, [(12.0, 0.0), (20.0, 0.0), (20.0, 6.0), (12.0, 6.0)]])
    moved = truth.transformed(Pose(0.3, -0.2, math.radians(1.5)))
    assert M.distance_to_truth(truth, moved, 0.1)[0] > 0.1
    T = M.align_to_truth(truth, moved, 0.1)
    back = moved.transformed(T)
    assert np.allclose(back.points, truth.points, atol=0.01)
    assert M.distance_to_truth(truth, back, 0.1)[0] < 0.005
    # a map that is right needs no motion; an empty one gets the identity
    T0 = M.align_to_truth(truth, truth, 0.1)
    assert abs(T0.x) < 1e-6 and abs(T0.y) < 1e-6 and abs(T0.theta) < 1e-6
    assert M.align_to_truth(truth, Wireframe.empty(), 0.1) == Pose.identity()
    with pytest.raises(ValueError):
        M.align_to_truth(truth, moved, 0.0)
    with pytest.raises(ValueError):
        M.align_to_truth(truth, moved, 0.1, keep=0.0)


def test_aligned_distance_keeps_an_error_in_the_parts():
    """One wall 0.5 m off: no rigid motion removes it (the aligned distance stays > 0)."""
    truth = Wireframe.from_polylines([ROOM, [(12.0, 0.0), (20.0, 0.0), (20.0, 6.0), (12.0, 6.0)]])
    bent = truth.replace(points=truth.points + np.where(truth.points[:, :1] > 11, [[0.0, 0.5]], [[0.0, 0.0]]))
    T = M.align_to_truth(truth, bent, 0.1)
    assert M.distance_to_truth(truth, bent.transformed(T), 0.1)[0] > 0.05  # rigid case: < 0.005
