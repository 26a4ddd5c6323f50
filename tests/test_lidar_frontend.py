"""Real-lidar front end (mapping.lidar_frontend) and the filter's point-match hook."""

import math

import numpy as np
import pytest

from mapping.config import with_overrides
from mapping.filter import FilterConfig, OdometryConfig, WireframeFilter
from mapping.lidar_frontend import FrontendConfig, LidarFrontend, odometry_overrides, scan_points
from mapping.scan_match import PointMatchConfig
from mapping.se2 import Pose

ANGLES = np.linspace(-math.pi / 2, math.pi / 2, 181)


def box_ranges(dx: float = 0.0) -> np.ndarray:
    """A 180-degree scan of a 6 x 8 m room from (dx, 0): walls at x = 4, y = -4, y = 4."""
    c, s = np.cos(ANGLES), np.sin(ANGLES)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 1e-9, (4.0 - dx) / c, np.inf)
        ty = np.where(np.abs(s) > 1e-9, 4.0 / np.abs(s), np.inf)
    return np.minimum(tx, ty)


def test_scan_points_drops_no_returns_and_near_ones() -> None:
    r = box_ranges()
    r[10] = np.inf
    r[20] = 0.1
    pts = scan_points(r, ANGLES, FrontendConfig())
    assert len(pts) == 179
    assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), np.delete(r, [10, 20]))
    fine = np.linspace(-math.pi / 2, math.pi / 2, 361)
    assert len(scan_points(np.full(361, 3.0), fine, FrontendConfig(point_stride=2))) == 181
    # A 2-degree scanner keeps every beam whatever the stride says.
    coarse = np.linspace(-math.pi / 2, math.pi / 2, 91)
    assert len(scan_points(np.full(91, 3.0), coarse, FrontendConfig(point_stride=2))) == 91
    with pytest.raises(ValueError):
        FrontendConfig(point_range=0.1, min_range=0.3)


def test_frontend_scan_has_walls_and_points() -> None:
    wf, pts = LidarFrontend().scan(box_ranges(), ANGLES, 20.0)
    assert wf.n_edges >= 3
    assert len(pts) == 181


def test_point_match_hook_corrects_odometry_error() -> None:
    fe = LidarFrontend()
    cfg = FilterConfig(particles=2, fov=math.pi + math.radians(1), max_range=20.0,
                       odometry=OdometryConfig(trans_per_m=0.1), point_match=PointMatchConfig(enabled=True))
    filt = WireframeFilter(cfg, np.random.default_rng(0))
    plain = WireframeFilter(FilterConfig(particles=2, fov=math.pi + math.radians(1), max_range=20.0),
                            np.random.default_rng(0))
    wf, pts = fe.scan(box_ranges(), ANGLES, 20.0)
    filt.step(Pose.identity(), wf, points=pts)
    plain.step(Pose.identity(), wf, points=pts)
    # The robot moves 0.5 m; odometry says 0.6 m.
    wf, pts = fe.scan(box_ranges(0.5), ANGLES, 20.0)
    info = filt.step(Pose(0.6, 0.0, 0.0), wf, points=pts)
    assert info.icp is not None and info.icp.accepted
    assert abs(filt.pose.x - 0.5) < 0.01
    # Without FilterConfig.point_match the points are ignored (the simulator's path).
    plain.step(Pose(0.6, 0.0, 0.0), wf, points=pts)
    again = WireframeFilter(FilterConfig(particles=2, fov=math.pi + math.radians(1), max_range=20.0),
                            np.random.default_rng(0))
    wf0, _ = fe.scan(box_ranges(), ANGLES, 20.0)
    again.step(Pose.identity(), wf0)
    again.step(Pose(0.6, 0.0, 0.0), wf)
    assert again.pose == plain.pose


def test_odometry_overrides_cover_the_logs_noise() -> None:
    o = odometry_overrides()
    assert o == {"odometry.trans_per_m": 0.07, "odometry.rot_per_m": 0.05}
    cfg = with_overrides(FilterConfig(), o)
    assert cfg.odometry.rot_per_m > math.radians(2.0) > FilterConfig().odometry.rot_per_m


def test_lidar_profile_splits_into_filter_extract_and_frontend() -> None:
    from agents.mapping_run import lidar_profile, split_profile

    prof = lidar_profile()
    fo, ecfg, fcfg = split_profile({**prof, "extract.jump_beams": 2.5, "frontend.point_range": 15})
    assert not any(k.startswith(("extract.", "frontend.")) for k in fo)
    assert ecfg.jump_beams == 2.5 and fcfg.point_range == 15.0
    cfg = with_overrides(FilterConfig(), fo)
    assert cfg.odometry.rot_per_m == prof["odometry.rot_per_m"]
    # The simulator's defaults are not the profile's.
    assert FilterConfig().odometry.rot_per_m < cfg.odometry.rot_per_m


def room_ranges(pose: Pose) -> np.ndarray:
    """A 180-degree scan from ``pose`` inside the room [-2, 6] x [-4, 4] (walls only)."""
    from agents.sim.lidar import LidarConfig, raycast

    room = np.array([[[-2.0, -4.0], [6.0, -4.0]], [[6.0, -4.0], [6.0, 4.0]], [[6.0, 4.0], [-2.0, 4.0]],
                     [[-2.0, 4.0], [-2.0, -4.0]], [[3.0, 1.0], [3.0, 2.5]]])
    cfg = LidarConfig(beams=181, fov=math.pi + math.radians(1.0), max_range=20.0, sigma=0.0)
    return raycast(room, pose, cfg, None)


def test_scan_increment_recovers_the_turn_the_wheels_got_wrong() -> None:
    from mapping.lidar_frontend import scan_increment

    cfg = FrontendConfig(scan_odometry=True)
    a = np.linspace(-(math.pi + math.radians(1.0)) / 2, (math.pi + math.radians(1.0)) / 2, 181)
    true = Pose(0.5, 0.05, math.radians(8.0))
    p0 = scan_points(room_ranges(Pose.identity()), a, cfg)
    p1 = scan_points(room_ranges(true), a, cfg)
    wheels = Pose(0.55, 0.0, math.radians(6.0))  # 2 degrees and 5 cm off
    inc, matched = scan_increment(p0, p1, wheels, cfg)
    assert matched
    err = true.inverse().compose(inc)
    assert math.hypot(err.x, err.y) < 0.01 and abs(err.theta) < math.radians(0.2)
    # Nothing to match: the wheels' increment as it was.
    assert scan_increment(p0[:2], p1, wheels, cfg) == (wheels, False)


# ---------------------------------------------------------------- the motion filter
def test_the_motion_filter_keeps_a_scan_once_the_wheels_moved_or_turned_enough() -> None:
    from mapping.lidar_frontend import motion_filter, within_motion_limits

    # 0.1 m steps straight on, then a turn on the spot in 4-degree steps, then a step back
    poses = [Pose(0.1 * k, 0.0, 0.0) for k in range(12)]
    poses += [Pose(1.1, 0.0, math.radians(4.0 * k)) for k in range(1, 6)]
    poses += [Pose(1.0, 0.0, math.radians(20.0))]
    kept = motion_filter(poses, 0.5, math.radians(10.0))
    # the first; 0.5 m on (index 5; 0.1 m steps reach 0.5 m at the fifth); again (10); turned 12
    # degrees since index 10 (index 14: 8 degrees at 13); 20 degrees at 16 is only 8 since 14
    assert kept == [0, 5, 10, 14]
    assert within_motion_limits(Pose(0.3, 0.3, 0.0), 0.5, 0.2)  # 0.42 m
    assert not within_motion_limits(Pose(0.4, 0.4, 0.0), 0.5, 0.2)  # 0.57 m
    assert not within_motion_limits(Pose(0.0, 0.0, -0.25), 0.5, 0.2)  # turned the other way
    assert within_motion_limits(Pose(0.0, 0.0, 2 * math.pi - 0.1), 0.5, 0.2)  # a turn of -0.1
    assert motion_filter(poses, 0.0, 0.0) == list(range(len(poses)))  # 0 and 0: every scan
    assert motion_filter([], 0.5, 0.2) == []


def test_a_log_is_dense_when_most_of_its_scans_lie_within_the_limits_of_the_last() -> None:
    from mapping.lidar_frontend import dense_share

    lidar = [Pose(0.05 * k, 0.0, 0.0) for k in range(101)]  # 10 Hz at 0.5 m/s
    carmen = [Pose(0.8 * k, 0.0, 0.3 * (k % 2)) for k in range(101)]  # a scan every 0.8 m
    assert dense_share(lidar, 0.5, math.radians(10.0)) == 1.0
    assert dense_share(carmen, 0.5, math.radians(10.0)) == 0.0
    assert dense_share(lidar[:1], 0.5, 0.2) == 0.0
    with pytest.raises(ValueError, match="dense_share"):
        FrontendConfig(dense_share=1.5)
    with pytest.raises(ValueError, match="min_travel"):
        FrontendConfig(min_travel=-0.1)


# ---------------------------------------------------------------- scans that take time
def test_deskew_turns_each_beam_back_by_the_turn_since_the_first() -> None:
    from mapping.lidar_frontend import deskew

    angles = np.linspace(-1.0, 1.0, 5)
    ranges = np.arange(1.0, 6.0)
    r, a = deskew(ranges, angles, 0.01, (0.0, 0.0, 2.0))  # beams 10 ms apart, turning at 2 rad/s
    assert np.allclose(a, angles + 2.0 * 0.01 * np.arange(5)) and np.allclose(r, ranges)
    _, a = deskew(ranges, angles, -0.01, (0.0, 0.0, 2.0))  # the last beam first: it is the one not turned
    assert np.allclose(a, angles - 0.02 * (np.arange(5) - 4))
    for dt, v in ((0.0, (1.0, 0.0, 2.0)), (0.01, (0.0, 0.0, 0.0))):  # simultaneous, or standing: as they are
        r, a = deskew(ranges, angles, dt, v)
        assert np.array_equal(a, angles) and np.array_equal(r, ranges)


def test_deskew_places_each_return_where_the_laser_stood_when_it_came() -> None:
    """Driving at 1 m/s past a wall 2 m to the left, beams 10 ms apart: every return lands on the
    wall, seen from the first beam's pose, and a no-return beam keeps its bearing."""
    from mapping.lidar_frontend import deskew

    angles = np.radians([60.0, 75.0, 90.0, 105.0, 120.0, 0.0 + 130.0])
    t = 0.01 * np.arange(6)
    ranges = 2.0 / np.sin(angles)  # from the laser where it stood at each beam
    ranges[5] = np.inf
    r, a = deskew(ranges, angles, 0.01, (1.0, 0.0, 0.0))
    x, y = r[:5] * np.cos(a[:5]), r[:5] * np.sin(a[:5])
    assert np.allclose(y, 2.0) and np.allclose(x, 2.0 / np.tan(angles[:5]) + t[:5])
    assert a[5] == angles[5] and np.isinf(r[5])


def test_deskew_keeps_a_full_turn_one_turn() -> None:
    from mapping.extract import extract_corners
    from mapping.lidar_frontend import deskew

    n = 360
    angles = -math.pi + 2 * math.pi * np.arange(n) / n
    ranges = np.full(n, 3.0)
    r, a = deskew(ranges, angles, 0.1 / n, (0.0, 0.0, 1.0))  # a 10 Hz spin turning 1 rad/s its way
    assert len(r) == len(a) < n and a[-1] - a[0] < 2 * math.pi
    assert n - len(a) == pytest.approx(math.degrees(0.1), abs=1.5)  # the beams that came round again
    extract_corners(r, a, 10.0)  # a valid scan (strictly increasing, at most a turn)
    r, a = deskew(ranges, angles, 0.1 / n, (0.0, 0.0, -1.0))  # against the spin: a gap at the seam
    assert len(a) == n and a[-1] - a[0] < 2 * math.pi


def test_deskew_never_gives_bearings_out_of_order() -> None:
    """Whatever the velocity (a reset odometry, a hostile robot's clock), the result is a valid
    scan: strictly increasing bearings, ranges alike in number; a turn against the sweep faster
    than its beams leaves the scan as it is; a near return carried past its neighbours is put
    where it is, among them."""
    from mapping.extract import extract_corners
    from mapping.lidar_frontend import deskew

    n = 360
    angles = -math.pi + 2 * math.pi * np.arange(n) / n
    empty = np.full(n, np.inf)
    r, a = deskew(empty, angles, 1.0 / 359, (0.0, 0.0, -7.0))  # against the sweep, faster than it
    assert np.array_equal(a, angles) and len(r) == n
    near = np.full(n, 5.0)
    near[100] = 0.02  # 2 cm away, driving 2 m/s sideways: carried past its neighbours
    for v in ((0.0, 2.0, 0.0), (0.0, -2.0, 0.0), (1.0, 1.0, 3.0), (0.0, 0.0, -3.0)):
        r, a = deskew(near, angles, 0.1 / n, v)
        assert len(r) == len(a) >= n - 20 and np.all(np.diff(a) > 0) and a[-1] - a[0] < 2 * math.pi
        extract_corners(r, a, 10.0)
    many = np.full(16000, 3.0)
    many[1] = 1e-5
    wide = np.linspace(-2.0, 2.0, 16000)
    r, a = deskew(many, wide, 1e-6, (0.5, 0.0, 1.0))  # one pass, not one per dropped beam
    assert np.all(np.diff(a) > 0) and len(r) == len(a)
