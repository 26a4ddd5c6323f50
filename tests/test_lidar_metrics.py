"""Tests of the real-lidar scores (mapping.lidar_metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.lidar_metrics import align_to_points, ate, map_coverage, map_precision, rpe, scan_endpoints
from mapping.se2 import Pose
from mapping.wireframe import Wireframe


def straight(n: int = 21, step: float = 0.25) -> np.ndarray:
    """Poses along the x axis, facing +x."""
    return np.stack([np.arange(n) * step, np.zeros(n), np.zeros(n)], axis=1)


def test_ate_is_unaligned_rmse_and_max() -> None:
    t = straight(4)
    e = t.copy()
    e[:, 1] += [0.0, 0.3, 0.0, 0.4]  # errors 0, 0.3, 0, 0.4
    rmse, mx = ate(e, t)
    assert rmse == pytest.approx(math.sqrt((0.09 + 0.16) / 4))
    assert mx == pytest.approx(0.4)
    # A constant offset is an error (no alignment).
    assert ate(t + np.array([1.0, 0.0, 0.0]), t) == pytest.approx((1.0, 1.0))
    assert all(math.isnan(v) for v in ate(np.zeros((0, 3)), np.zeros((0, 3))))
    with pytest.raises(ValueError, match="differ in length"):
        ate(t[:2], t)


def test_rpe_ignores_a_constant_offset_but_sees_drift() -> None:
    t = straight(21, 0.25)  # 5 m, poses 0.25 m apart: pairs 4 scans apart
    assert rpe(t + np.array([3.0, -2.0, 0.0]), t, 1.0) == pytest.approx(0.0, abs=1e-12)
    # Odometry 10 % short: each 1 m pair is 0.1 m short.
    e = t.copy()
    e[:, 0] *= 0.9
    assert rpe(e, t, 1.0) == pytest.approx(0.1)
    # A heading error at the start turns every later motion: the relative error sees it
    # wherever the pair starts before the turn, not after.
    turned = t.copy()
    turned[:, 2] = 0.1
    assert rpe(turned, t, 1.0) == pytest.approx(2 * math.sin(0.05) * 1.0)
    assert math.isnan(rpe(t, t, 100.0))
    with pytest.raises(ValueError):
        rpe(t, t, 0.0)


def test_scan_endpoints_place_returns_at_the_poses() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, math.pi / 2]])
    ranges = [np.array([1.0, np.inf, 2.0]), np.array([0.5, 9.0, np.nan])]
    angles = [np.array([0.0, 0.5, math.pi / 2]), np.array([0.0, 0.1, 0.2])]
    pts = scan_endpoints(poses, ranges, angles, max_range=5.0)
    assert pts.shape == (3, 2)  # inf, nan and 9 m (beyond 5 m) are dropped
    assert np.allclose(pts, [[1.0, 0.0], [0.0, 2.0], [1.0, 1.5]])
    with pytest.raises(ValueError):
        scan_endpoints(poses, ranges[:1], angles)


def test_precision_and_coverage_against_endpoints() -> None:
    wall = Wireframe.from_polylines([[(0.0, 0.0), (4.0, 0.0)]])
    # Endpoints along the first 2 m of the wall, 5 cm off it, every 1 cm; more 3 m away.
    along = np.stack([np.arange(0.0, 2.0, 0.01), np.full(200, 0.05)], axis=1)
    far = np.stack([np.arange(0.0, 2.0, 0.01), np.full(200, 3.0)], axis=1)
    pts = np.concatenate([along, far])
    # Half the wall is within 0.2 m of an endpoint (2 m + the 0.2 m reach past the last one).
    assert map_precision(wall, pts, tol=0.2) == pytest.approx(2.2 / 4.0, abs=0.02)
    assert map_coverage(wall, pts, tol=0.2) == pytest.approx(0.5)
    assert map_coverage(wall, pts, tol=0.04) == 0.0  # 5 cm off the wall
    assert map_precision(wall, along + np.array([0.0, 0.3]), tol=0.2) == 0.0
    empty = Wireframe.from_polylines([])
    assert math.isnan(map_precision(empty, pts))
    assert map_coverage(empty, pts) == 0.0
    assert math.isnan(map_coverage(wall, np.zeros((0, 2))))
    with pytest.raises(ValueError):
        map_precision(wall, pts, tol=-1.0)


def test_score_run_is_the_pieces_together() -> None:
    from mapping.lidar_metrics import ate, map_coverage, map_precision, rpe, score_run
    from mapping.wireframe import Wireframe

    truth = np.array([[0.1 * k, 0.0, 0.0] for k in range(40)])
    est = truth + np.array([0.0, 0.05, 0.0])
    wf = Wireframe.from_polylines([[(0.0, 1.0), (4.0, 1.0)]])
    ends = np.array([[x, 1.02] for x in np.linspace(0, 3, 31)])
    s = score_run(est, truth, wf, ends)
    assert (s["ate_rmse_m"], s["ate_max_m"]) == ate(est, truth)
    assert s["rpe_1m_m"] == rpe(est, truth, 1.0)
    assert s["map_precision"] == map_precision(wf, ends) and s["map_coverage"] == map_coverage(wf, ends)
    assert 0.75 < s["map_precision"] < 0.85 and s["map_coverage"] == 1.0
    # The wall already lies on the endpoints: aligning it changes next to nothing (the
    # point-to-point pairs may slide it a few centimetres along itself).
    assert s["map_precision_aligned"] == pytest.approx(s["map_precision"], abs=0.02)
    assert s["alignment_m"] < 0.1 and abs(s["alignment_deg"]) < 0.5


def test_score_run_tells_a_turned_map_from_a_bent_one() -> None:
    from mapping.lidar_metrics import score_run

    ends = room_points()
    truth = np.zeros((3, 3))
    turned = room_map().transformed(Pose(0.0, 0.0, math.radians(3.0)))
    s = score_run(truth, truth, turned, ends, tol=0.1)
    assert s["map_precision"] < 0.7 and s["map_precision_aligned"] > 0.99
    assert s["alignment_deg"] == pytest.approx(-3.0, abs=0.5)  # stalls a little short, as above


def room_points(step: float = 0.02) -> np.ndarray:
    """Endpoints along the four walls of an 8 x 5 m room and an inner 2 m wall (no symmetry)."""
    t = np.arange(0.0, 1.0, step / 8.0)[:, None]
    sides = [((0, 0), (8, 0)), ((8, 0), (8, 5)), ((8, 5), (0, 5)), ((0, 5), (0, 0)), ((3, 0), (3, 2))]
    return np.concatenate([np.array(a) + t * (np.array(b) - np.array(a)) for a, b in sides])


def room_map() -> Wireframe:
    pts = np.array([[0, 0], [8, 0], [8, 5], [0, 5], [3, 0], [3, 2]], dtype=float)
    return Wireframe.build(pts, np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5]]))


def test_align_to_points_undoes_a_small_rigid_offset() -> None:
    ends = room_points()
    off = Pose(0.25, -0.15, math.radians(2.0))
    moved = room_map().transformed(off)
    assert map_precision(moved, ends, 0.05) < 0.5
    fix = align_to_points(moved, ends)
    back = fix.compose(off)
    # point-to-point pairs stall a couple of centimetres short along the walls: far below the
    # 0.2 m the scores take
    assert abs(back.x) < 0.03 and abs(back.y) < 0.03 and abs(back.theta) < math.radians(0.3)
    assert map_precision(moved.transformed(fix), ends, 0.05) > 0.99


def test_align_to_points_leaves_a_far_map_and_checks_its_arguments() -> None:
    far = room_map().transformed(Pose(50.0, 0.0, 0.0))
    assert align_to_points(far, room_points()).as_tuple() == Pose.identity().as_tuple()
    with pytest.raises(ValueError, match="positive"):
        align_to_points(room_map(), room_points(), step=0.0)
    with pytest.raises(ValueError, match="keep"):
        align_to_points(room_map(), room_points(), keep=1.5)
