"""The laser's yaw against the wheel odometry (mapping.lidar_frontend.laser_yaw) and where the
pipeline turns the bearings by it (agents.mapping_run.calibrate_log, carmen_inputs)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agents import mapping_run as mr
from agents.files.carmen import LaserScan
from agents.sim.lidar import LidarConfig, raycast
from mapping.extract import ExtractConfig, extract_corners
from mapping.lidar_frontend import FrontendConfig, laser_yaw, scan_points
from mapping.se2 import Pose
from tests.test_lidar_slam import _hall_drive, room_segments

CFG = LidarConfig(beams=181, fov=math.pi, max_range=20.0, sigma=0.01)


def _scans(yaw_deg: float, seed: int = 5, heading_noise_deg_per_m: float = 0.0) -> list[LaserScan]:
    """The hall drive's scans from a laser turned ``yaw_deg`` on the robot: each beam measured
    at ``bearing + yaw`` but logged at ``bearing``; the odometry is the true pose (so its
    direction of travel is the robot's) with 2 % noise on each step's length (and, when
    given, Gaussian heading noise per metre driven)."""
    route, _, _ = _hall_drive()
    rng = np.random.default_rng(seed)
    yaw = math.radians(yaw_deg)
    out, odom = [], route[0]
    for k, p in enumerate(route):
        if k:
            inc = route[k - 1].between(p)
            s = 1.0 + 0.02 * rng.standard_normal()
            turn = 0.0
            if heading_noise_deg_per_m:  # drawn only then: the other tests' scans stay as they were
                per_m = math.radians(heading_noise_deg_per_m)
                turn = per_m * math.hypot(inc.x, inc.y) * rng.standard_normal()
            odom = odom.compose(Pose(inc.x * s, inc.y * s, inc.theta + turn))
        ranges = raycast(room_segments(), Pose(p.x, p.y, p.theta + yaw), CFG, rng)
        out.append(LaserScan(float(k), ranges, CFG.angles(), CFG.max_range, odom, Pose.identity(),
                             "FLASER", k))
    return out


@pytest.mark.parametrize("yaw_deg", [0.7, -1.2])
def test_a_turned_laser_is_found_and_applied(yaw_deg: float) -> None:
    scans = _scans(yaw_deg)
    fc = FrontendConfig(yaw_calibration=True, yaw_min_pairs=20)
    est = laser_yaw(mr.carmen_points(scans, fc), mr.wheel_increments(scans), fc)
    assert est.pairs >= 40
    # The matched motion is turned by -yaw in the logged frame; the estimate says so.
    assert math.degrees(est.yaw) == pytest.approx(-yaw_deg, abs=0.15)
    assert est.applied and est.correction == est.yaw and est.se < math.radians(0.1)


def test_a_straight_laser_is_left_alone() -> None:
    scans = _scans(0.0)
    fc = FrontendConfig(yaw_calibration=True, yaw_min_pairs=20)
    est = laser_yaw(mr.carmen_points(scans, fc), mr.wheel_increments(scans), fc)
    assert abs(math.degrees(est.correction)) < 0.05
    # Too few pairs: nothing applied whatever the estimate.
    few = laser_yaw(mr.carmen_points(scans[:10], fc), mr.wheel_increments(scans[:10]), fc)
    assert not few.applied and few.correction == 0.0
    # Standing still gives no direction at all.
    still = [LaserScan(s.t, s.ranges, s.angles, s.max_range, scans[0].odom, s.mount, s.kind, s.index)
             for s in scans]
    none = laser_yaw(mr.carmen_points(still, fc), mr.wheel_increments(still), fc)
    assert none.pairs == 0 and not none.applied


def test_the_points_and_the_corners_are_turned_the_same_way() -> None:
    """``calibrate_log`` and ``carmen_inputs`` turn the bearings by ``-yaw``: the points are
    those of the bearings minus yaw, and so are the corners the extractor sees."""
    scans = _scans(0.0)[:5]
    fc, ec = FrontendConfig(), ExtractConfig()
    yaw = math.radians(2.0)
    cal = mr.calibrate_log(scans, fc, yaw)
    pts, est = cal.points, cal.estimate
    assert est is None
    for s, p in zip(scans, pts):
        assert np.allclose(p, scan_points(s.ranges, s.angles - yaw, fc), atol=1e-12)
    inputs = list(mr.carmen_inputs(scans, max_range=20.0, extract=ec, frontend=fc, yaw=yaw))
    for s, inp in zip(scans, inputs):
        want = extract_corners(np.where(s.ranges >= 20.0, np.inf, s.ranges), s.angles - yaw, 20.0, ec)
        assert inp.scan.almost_equal(want, tol=0.0) and inp.scan.n_vertices > 0
    # Without a yaw and with the calibration off, nothing is turned.
    cal = mr.calibrate_log(scans, fc)
    plain, est = cal.points, cal.estimate
    assert est is None and all(np.array_equal(a, b) for a, b in zip(plain, mr.carmen_points(scans, fc)))
