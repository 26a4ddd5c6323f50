"""Wireframe matching (paper Sec. IV-C): correspondences and the modified ICP."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import Label, Pose, Wireframe
from mapping.icp import (
    ICPConfig,
    correspond,
    edge_overlap,
    icp,
    information_split,
    match_edges,
    match_vertices,
    project_onto_segments,
)

# An L-shaped room (counterclockwise) with a box obstacle (clockwise), as a robot at `VIEW` would
# see all of it (no occlusion is needed for these tests: the geometry is what matters).
ROOM = Wireframe.from_polylines(
    [[(0, 0), (6, 0), (6, 4), (3, 4), (3, 5), (0, 5)], [(2, 1), (2, 2), (3, 2), (3, 1)]]
)
VIEW = Pose(1.0, 3.0, 0.3)


def reference() -> Wireframe:
    return ROOM.transformed(VIEW.inverse())


def scan_off_by(err: Pose, noise: float = 0.0, seed: int = 0) -> Wireframe:
    """The reference as measured from a pose that is off by `err` (scan = err^-1 applied)."""
    s = reference().transformed(err.inverse())
    if noise:
        rng = np.random.default_rng(seed)
        s = s.replace(points=s.points + rng.normal(0.0, noise, s.points.shape))
    return s


def test_identity_when_scan_equals_reference():
    res = icp(reference(), reference())
    assert res.accepted
    assert res.correction.almost_equal(Pose(), tol=1e-6, angle_tol=1e-6)
    assert res.rmse < 1e-6
    assert len(res.correspondences.vertex_pairs) == ROOM.n_vertices


def test_recovers_known_offset_with_noise():
    err = Pose(0.3, -0.2, 0.1)
    res = icp(scan_off_by(err, noise=0.02), reference())
    assert res.accepted, res.reason
    assert res.correction.distance(err) < 0.03
    assert abs(res.correction.theta - err.theta) < 0.01


@settings(max_examples=25, deadline=None)
@given(
    dx=st.floats(-0.35, 0.35),
    dy=st.floats(-0.35, 0.35),
    dth=st.floats(-0.08, 0.08),
)
def test_recovers_any_small_offset(dx, dy, dth):
    err = Pose(dx, dy, dth)
    res = icp(scan_off_by(err), reference())
    assert res.accepted, res.reason
    assert res.correction.distance(err) < 1e-3
    assert abs(res.correction.theta - err.theta) < 1e-3


def test_robust_to_outlier_walls():
    err = Pose(0.2, 0.15, -0.05)
    s = scan_off_by(err, noise=0.01, seed=3)
    rng = np.random.default_rng(7)
    # Three spurious short walls scattered in the room (clutter).
    junk = Wireframe.from_polylines([rng.uniform(-3, 3, size=(2, 2)) for _ in range(3)], closed=False)
    pts = np.concatenate([s.points, junk.points])
    edges = np.concatenate([s.edges, junk.edges + s.n_vertices])
    noisy = Wireframe.build(pts, edges)
    res = icp(noisy, reference())
    assert res.accepted, res.reason
    assert res.correction.distance(err) < 0.03
    assert abs(res.correction.theta - err.theta) < 0.01


def test_corridor_keeps_unobservable_direction_at_odometry():
    # Two long parallel walls along x: an offset along x cannot be observed; one across y can.
    corridor = Wireframe.build(
        [(-8, -1), (8, -1), (8, 1), (-8, 1)], [(0, 1), (2, 3)], labels=[Label.FRONTIER] * 4
    )
    err = Pose(0.0, 0.25, 0.0)
    res = icp(corridor.transformed(err.inverse()), corridor)
    assert abs(res.correction.y - 0.25) < 0.01
    assert abs(res.correction.x) < 0.01


def test_rejects_empty_and_too_few():
    assert not icp(Wireframe.empty(), reference()).accepted
    tiny = Wireframe.build([(1, 1), (2, 1)], [(0, 1)])
    res = icp(tiny, reference(), ICPConfig(min_constraints=6))
    assert not res.accepted
    assert "few" in res.reason or "residual" in res.reason


def test_match_vertices_is_one_to_one_and_gated():
    scan = np.array([[0.0, 0.0], [0.05, 0.0], [5.0, 5.0]])
    ref = np.array([[0.02, 0.0], [1.0, 0.0]])
    pairs, dist = match_vertices(scan, ref, gate=0.3)
    # Two scan points compete for ref 0: only one gets it; ref 1 is beyond the gate of both.
    assert pairs.tolist() in ([[0, 0]], [[1, 0]])
    assert dist[0] == pytest.approx(0.02 if pairs[0, 0] == 0 else 0.03)
    # Assignment, not greedy: with a wider gate the total distance is minimised.
    pairs, _ = match_vertices(scan, ref, gate=2.0)
    assert sorted(pairs.tolist()) == [[0, 0], [1, 1]] or sorted(pairs.tolist()) == [[0, 1], [1, 0]]
    assert sorted(pairs.tolist()) == [[0, 0], [1, 1]]


def test_frontier_penalty_prefers_same_kind():
    scan = np.array([[0.0, 0.0]])
    ref = np.array([[0.1, 0.0], [0.0, 0.15]])
    pairs, _ = match_vertices(scan, ref, 0.5, np.array([Label.FRONTIER], np.uint8),
                              np.array([Label.NOMINAL, Label.FRONTIER], np.uint8), frontier_penalty=0.25)
    assert pairs.tolist() == [[0, 1]]


def test_edges_of_opposite_direction_never_correspond():
    a = Wireframe.build([(0, 0), (2, 0)], [(0, 1)])
    b = Wireframe.build([(0, 0.05), (2, 0.05)], [(0, 1)])
    rev = Wireframe.build([(0, 0.05), (2, 0.05)], [(1, 0)])
    pairs, *_ = match_edges(a, b, np.zeros((0, 2), np.int64), 0.2, 0.3)
    assert pairs.tolist() == [[0, 0]]
    pairs, *_ = match_edges(a, rev, np.zeros((0, 2), np.int64), 0.2, 0.3)
    assert pairs.tolist() == []


def test_edge_correspondences_allow_duplicates_and_need_overlap():
    scan = Wireframe.build([(0, 0), (4, 0)], [(0, 1)])
    # Two collinear reference pieces under the scan edge, and one beyond its end.
    ref = Wireframe.build([(0, 0.02), (2, 0.02), (2, 0.02), (4, 0.02), (5, 0.0), (6, 0.0)],
                          [(0, 1), (2, 3), (4, 5)])
    corr = correspond(scan, ref, gate=0.1)
    assert sorted(corr.edge_pairs.tolist()) == [[0, 0], [0, 1]]
    assert np.allclose(corr.edge_offset, 0.02)


def test_edges_with_corresponding_ends_correspond():
    scan = Wireframe.build([(0, 0), (1, 0.0)], [(0, 1)])
    ref = Wireframe.build([(0, 0.1), (1, -0.1)], [(0, 1)])  # tilted more than max_angle
    corr = correspond(scan, ref, gate=0.3, max_angle=0.05)
    assert corr.edge_pairs.tolist() == [[0, 0]]


def test_edge_overlap_geometry():
    s = np.array([[[0.0, 0.0], [4.0, 0.0]]])
    r = np.array([[[1.0, 0.5], [3.0, 0.5]], [[-1.0, 0.0], [0.0, -1.0]]])
    cos, lo, hi, off, lr = edge_overlap(s, r)
    assert cos[0, 0] == pytest.approx(1.0)
    assert lo[0, 0] == pytest.approx(1.0) and hi[0, 0] == pytest.approx(3.0)
    assert off[0, 0] == pytest.approx(0.5)
    assert lr[0, 1] == pytest.approx(math.sqrt(2))


def test_project_onto_segments():
    segs = np.array([[[0.0, 0.0], [2.0, 0.0]], [[3.0, -1.0], [3.0, 1.0]]])
    idx, c, d = project_onto_segments(np.array([[1.0, 1.0], [2.9, 0.5], [-1.0, 0.0]]), segs)
    assert idx.tolist() == [0, 1, 0]
    assert np.allclose(c, [[1.0, 0.0], [3.0, 0.5], [0.0, 0.0]])
    assert np.allclose(d, [1.0, 0.1, 1.0])
    with pytest.raises(ValueError):
        project_onto_segments(np.zeros((1, 2)), np.zeros((0, 2, 2)))


@pytest.mark.parametrize(
    "kwargs",
    [{"gate_start": 0.1, "gate_end": 0.2}, {"huber": 0.0}, {"max_iterations": 0}, {"sigma": float("nan")}],
)
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        ICPConfig(**kwargs)


# ------------------------------------------------------------------ degeneracy-aware matching
def test_frontier_ends_do_not_pin_a_wall_along_itself():
    # One long wall seen with frontier ends, the scan shifted along it by 0.3 m and across by
    # 0.1 m: only the offset across the wall is observable.
    wall = Wireframe.build([(-4, 2), (4, 2)], [(0, 1)], labels=[Label.FRONTIER] * 2)
    scan = wall.transformed(Pose(0.3, -0.1, 0.0))
    res = icp(scan, wall)
    assert res.constrained <= 2
    assert abs(res.correction.y - 0.1) < 0.01
    assert abs(res.correction.x) < 0.01
    # the same wall with real corners at its ends pins it along itself too
    corners = wall.replace(labels=np.zeros(2, np.uint8))
    res = icp(corners.transformed(Pose(0.3, -0.1, 0.0)), corners)
    assert res.accepted, res.reason
    assert res.correction.distance(Pose(-0.3, 0.1, 0.0)) < 0.01


def test_information_split_against_the_prior():
    # Information only about x (a wall across x): one constrained direction, along x.
    H = np.diag([1e4, 0.0, 0.0])
    P = np.diag([0.1**2, 0.1**2, 0.05**2])
    L, lam, V, good = information_split(H, P, 0.5)
    assert np.allclose(L @ L.T, P)
    assert good.sum() == 1
    assert lam[good][0] == pytest.approx(1e4 * 0.01)
    direction = L @ V[:, good][:, 0]
    assert abs(direction[0]) > 0.99 * np.linalg.norm(direction)
    # a weak constraint (less informative than the prior) is degenerate
    _, _, _, good = information_split(np.diag([10.0, 0.0, 0.0]), P, 0.5)
    assert not good.any()


def test_tight_heading_prior_keeps_the_heading():
    err = Pose(0.2, 0.1, 0.05)
    scan = scan_off_by(err, noise=0.0)
    free = icp(scan, reference(), prior_covariance=np.diag([0.3**2, 0.3**2, 0.2**2]))
    assert free.accepted and abs(free.correction.theta - err.theta) < 1e-3
    # A heading prior of 0.001 rad: the scan's rotation is 50 sigma away -- not accepted
    tight = icp(scan, reference(), prior_covariance=np.diag([0.3**2, 0.3**2, 0.001**2]))
    assert not tight.accepted
    assert "unlikely" in tight.reason or "rotation" in tight.reason or "residual" in tight.reason


def test_posterior_covariance_shrinks_only_where_constrained():
    corridor = Wireframe.build(
        [(-8, -1), (8, -1), (8, 1), (-8, 1)], [(0, 1), (2, 3)], labels=[Label.FRONTIER] * 4
    )
    P = np.diag([0.2**2, 0.2**2, 0.02**2])
    res = icp(corridor.transformed(Pose(0.0, 0.05, 0.0).inverse()), corridor, prior_covariance=P)
    assert res.accepted, res.reason
    assert res.covariance[0, 0] == pytest.approx(P[0, 0], rel=1e-6)  # along the corridor: the prior
    assert res.covariance[1, 1] < 0.05 * P[1, 1]  # across: the walls know better
    assert res.information.shape == (3, 3) and res.information[0, 0] == pytest.approx(0.0, abs=1e-9)


def test_rejects_bad_prior():
    with pytest.raises(ValueError):
        icp(reference(), reference(), prior_covariance=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError):
        icp(reference(), reference(), prior_covariance=np.eye(2))


def test_one_long_wall_corrects_heading_and_offset_across_it():
    # A corridor robot that sees a single wall (frontier to frontier, 16 m) has two constraint
    # rows; they fix the heading and the offset across the wall, which is what keeps the map's
    # walls straight along a long corridor (the along-wall position stays the odometry's).
    wall = Wireframe.build([(-8, 2), (8, 2)], [(0, 1)], labels=[Label.FRONTIER] * 2)
    err = Pose(0.0, 0.05, math.radians(0.6))
    P = np.diag([0.1**2, 0.1**2, math.radians(1.0) ** 2])
    res = icp(wall.transformed(err.inverse()), wall, prior_covariance=P)
    assert res.n_constraints == 2
    assert res.accepted, res.reason
    assert abs(res.correction.theta - err.theta) < math.radians(0.05)
    assert abs(res.correction.y - err.y) < 0.01
    # with the older rule of four rows the same scan was rejected and the heading left drifting
    assert not icp(wall.transformed(err.inverse()), wall, ICPConfig(min_constraints=4),
                   prior_covariance=P).accepted


def test_a_scan_that_only_confirms_the_prediction_is_consistent():
    # Right after an accepted match the prior is tight: the next corridor scan knows no direction
    # better than it ("degenerate"), yet agrees with it -- consistent, correction the identity.
    corridor = Wireframe.build(
        [(-8, -1), (8, -1), (8, 1), (-8, 1)], [(0, 1), (2, 3)], labels=[Label.FRONTIER] * 4
    )
    tight = np.diag([0.005**2, 0.005**2, 1e-4**2])
    res = icp(corridor.transformed(Pose(0.0, 0.003, 0.0).inverse()), corridor, prior_covariance=tight)
    assert not res.accepted and res.reason.startswith("degenerate")
    assert res.consistent
    assert res.correction.distance(Pose.identity()) < 1e-9
    # a scan 0.3 m across the corridor from where the tight prior says is not consistent
    off = icp(corridor.transformed(Pose(0.0, 0.3, 0.0).inverse()), corridor, prior_covariance=tight)
    assert not off.accepted and not off.consistent
    # an accepted match is consistent
    assert icp(corridor.transformed(Pose(0.0, 0.05, 0.0).inverse()), corridor).consistent


def test_match_edges_with_the_index_equals_the_dense_test(monkeypatch: pytest.MonkeyPatch) -> None:
    """Over 4,096 edge pairs match_edges tests only the pairs within reach (a k-d tree of
    points along the segments): pairs, offsets and overlaps are the dense test's, bit for bit."""
    import mapping.icp as icp_mod
    from agents.sim.world import load_world

    rng = np.random.default_rng(11)
    truth = load_world("museum").truth
    for trial in range(12):
        ref = Wireframe.build(truth.points + rng.normal(0, 0.05, truth.points.shape), truth.edges)
        th = rng.normal(0, 0.03)
        c, s = np.cos(th), np.sin(th)
        pts = (truth.points + rng.normal(0, 0.1 * (trial % 4), truth.points.shape)) @ np.array(
            [[c, s], [-s, c]]
        )
        scan = Wireframe.build(pts + rng.normal(0, 0.2, 2), truth.edges)
        vp, _ = match_vertices(scan.points, ref.points, 0.5)
        vp = vp if trial % 3 else vp[:0]
        for gate, angle, overlap in [(0.5, 0.35, 0.1), (1.0, 0.2, 0.0), (0.3, 1.2, 0.5)]:
            monkeypatch.setattr(icp_mod, "_DENSE_EDGE_MAX", 10**12)
            dense = icp_mod.match_edges(scan, ref, vp, gate, angle, overlap)
            monkeypatch.setattr(icp_mod, "_DENSE_EDGE_MAX", 0)
            near = icp_mod.match_edges(scan, ref, vp, gate, angle, overlap)
            for a, b in zip(dense, near):
                assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
