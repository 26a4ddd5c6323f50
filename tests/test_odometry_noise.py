"""The wheel odometry's heading noise measured from the scans themselves
(mapping.lidar_frontend.odometry_noise) and the SLAM's heading prior fitted to it
(calibrated_slam, SlamConfig.odo_calibration)."""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any

import numpy as np
import pytest

from agents import mapping_run as mr
from mapping.lidar_frontend import FrontendConfig, OdometryNoise, calibrated_slam, odometry_noise, run_slam
from mapping.lidar_slam import SlamConfig
from mapping.se2 import Pose
from tests.test_laser_yaw import _scans
from tests.test_lidar_slam import _hall_drive


def _wheels(route: list[Pose], noise_deg_per_m: float, bias_deg_per_m: float = 0.0,
            seed: int = 9) -> list[Pose]:
    """Increments along ``route`` whose heading errs by ``bias`` plus Gaussian ``noise`` degrees
    per metre driven (the shared logs' kind of odometry)."""
    rng = np.random.default_rng(seed)
    out = [Pose.identity()]
    for a, b in itertools.pairwise(route):
        inc = a.between(b)
        d = math.hypot(inc.x, inc.y)
        err = math.radians(bias_deg_per_m + noise_deg_per_m * rng.standard_normal()) * d
        out.append(Pose(inc.x, inc.y, inc.theta + err))
    return out


@pytest.mark.parametrize("noise", [1.0, 3.0])
def test_the_wheels_noise_is_measured_from_the_scans(noise: float) -> None:
    route, _, scans = _hall_drive()
    est = odometry_noise(scans, _wheels(route, noise), FrontendConfig())
    assert est.pairs >= 50
    assert 0.6 * noise < math.degrees(est.rot_per_m) < 1.5 * noise, math.degrees(est.rot_per_m)


def test_a_biased_wheel_counts_as_noise() -> None:
    """A heading bias (unequal wheels) is measured about zero, not about the bias: the prior
    must cover it as much as it covers noise. (A constant reads as 1.48 times itself, the
    normal's factor from median absolute value to sigma: wider, the safe side.)"""
    route, _, scans = _hall_drive()
    est = odometry_noise(scans, _wheels(route, 0.1, bias_deg_per_m=2.5), FrontendConfig())
    assert 2.5 < math.degrees(est.rot_per_m) < 4.2, math.degrees(est.rot_per_m)


def test_calibration_widens_never_narrows_and_is_capped() -> None:
    cfg = SlamConfig(odo_rot_per_m=0.035, odo_calibration_scale=3.0, odo_calibration_max=0.15)
    assert calibrated_slam(cfg, OdometryNoise(0.02, 200)).odo_rot_per_m == pytest.approx(0.06)
    assert calibrated_slam(cfg, OdometryNoise(0.005, 200)) == cfg  # better wheels: the floor
    assert calibrated_slam(cfg, OdometryNoise(1.0, 200)).odo_rot_per_m == 0.15  # the cap
    assert calibrated_slam(cfg, OdometryNoise(0.02, 49)) == cfg  # too few pairs
    assert calibrated_slam(cfg, OdometryNoise(math.nan, 0)) == cfg
    only = calibrated_slam(cfg, OdometryNoise(0.02, 200))
    assert dataclasses.replace(only, odo_rot_per_m=cfg.odo_rot_per_m) == cfg  # nothing else moves


@pytest.mark.parametrize("bad", [{"odo_calibration_scale": 0.0}, {"odo_calibration_max": -1.0},
                                 {"odo_calibration_min_pairs": 1}])
def test_bad_calibration_settings_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        SlamConfig(**bad)  # type: ignore[arg-type]


def test_run_slam_fits_its_prior_to_noisy_wheels_and_stays_deterministic() -> None:
    route, _, scans = _hall_drive()
    wheels = _wheels(route, 4.0)
    start = np.array(route[0].as_tuple())
    plain = run_slam(scans, wheels, SlamConfig(refine_passes=0), start=start)
    fitted = run_slam(scans, wheels, SlamConfig(refine_passes=0, odo_calibration=True), start=start)
    assert plain.config.odo_rot_per_m == SlamConfig().odo_rot_per_m
    assert fitted.config.odo_rot_per_m > 2.0 * plain.config.odo_rot_per_m
    again = run_slam(scans, wheels, SlamConfig(refine_passes=0, odo_calibration=True), start=start)
    assert np.array_equal(again.poses, fitted.poses)
    truth = np.array([p.as_tuple() for p in route])
    err = np.hypot(*(fitted.poses[:, :2] - truth[:, :2]).T)
    assert float(np.sqrt(np.mean(err**2))) < 0.3


def test_the_report_says_what_the_slam_will_run_with() -> None:
    """``agents.mapping_run.odometry_report`` of ``calibrate_log``'s noise (``wiremap map``'s and
    ``bench lidar``'s keys): the
    wheels' measured noise and the prior the SLAM gets, widened for noisy wheels, as configured
    for good ones; nothing without the calibration."""
    def report(scans: list[Any], slam: SlamConfig) -> dict[str, Any]:
        return mr.odometry_report(mr.calibrate_log(scans, FrontendConfig(slam=slam)).noise, slam)

    slam = SlamConfig(enabled=True, odo_calibration=True, odo_calibration_min_pairs=20)
    noisy = report(_scans(0.0, heading_noise_deg_per_m=2.0), slam)
    assert noisy["odometry_noise_pairs"] >= 40 and noisy["slam_odo_prior_widened"] is True
    assert 1.2 < noisy["odometry_heading_noise_deg_per_m"] < 3.0, noisy
    assert noisy["slam_odo_rot_per_m_deg"] == pytest.approx(3.0 * noisy["odometry_heading_noise_deg_per_m"])
    good = report(_scans(0.0), slam)
    assert good["slam_odo_prior_widened"] is False
    assert good["slam_odo_rot_per_m_deg"] == pytest.approx(math.degrees(slam.odo_rot_per_m))
    assert report(_scans(0.0), SlamConfig(enabled=True)) == {}
    # Too short to measure: None (report.json stays JSON), the prior as configured.
    short = report(_scans(0.0)[:2], slam)
    assert short["odometry_heading_noise_deg_per_m"] is None and short["odometry_noise_pairs"] < 2
    assert short["slam_odo_prior_widened"] is False


# ---------------------------------------------------------------- drift that persists, and the wheels' scale
def _smooth_wheels(route: list[Pose], drift_deg_per_m: float, scale: float = 1.0) -> list[Pose]:
    """Increments along ``route`` whose heading drifts at a rate that changes slowly (a sine
    over 40 m of driving) and whose distance is ``scale`` times the true one."""
    out, s = [Pose.identity()], 0.0
    for a, b in itertools.pairwise(route):
        inc = a.between(b)
        d = math.hypot(inc.x, inc.y)
        s += d
        rate = math.radians(drift_deg_per_m) * math.sin(2.0 * math.pi * s / 40.0)
        out.append(Pose(scale * inc.x, scale * inc.y, inc.theta + rate * d))
    return out


def test_a_smooth_drift_is_measured_as_correlated_and_independent_noise_is_not() -> None:
    route, _, scans = _hall_drive()
    smooth = odometry_noise(scans, _smooth_wheels(route, 2.0), FrontendConfig())
    independent = odometry_noise(scans, _wheels(route, 2.0), FrontendConfig())
    assert smooth.correlation > 0.7, smooth
    assert abs(independent.correlation) < 3.0 / math.sqrt(independent.neighbours), independent
    assert smooth.neighbours >= 30 and smooth.neighbours <= smooth.pairs - 1


def test_the_correlation_is_measured_between_consecutive_scans_on_a_long_log() -> None:
    """With the calibration's pairs spread out (at most 12 over the drive), each is joined by the
    pair after it: the drift is still seen as correlated."""
    route, _, scans = _hall_drive()
    fc = FrontendConfig(yaw_max_pairs=12, yaw_min_pairs=2)
    spread = odometry_noise(scans, _smooth_wheels(route, 2.0), fc)
    assert spread.pairs <= 12 and spread.neighbours >= 8 and spread.correlation > 0.6, spread


def test_a_correlated_drift_widens_the_prior_by_its_correlation() -> None:
    cfg = SlamConfig(odo_rot_per_m=0.035, odo_calibration_scale=3.0, odo_calibration_max=0.15)
    # r = 0.8 over 100 pairs (8 standard errors): sqrt(1.8 / 0.2) = 3 times the prior
    assert calibrated_slam(cfg, OdometryNoise(0.005, 100, 0.8, 100)).odo_rot_per_m == pytest.approx(0.105)
    assert calibrated_slam(cfg, OdometryNoise(0.02, 100, 0.8, 100)).odo_rot_per_m == 0.15  # 0.06 x 3, capped
    assert calibrated_slam(cfg, OdometryNoise(0.005, 100, 0.25, 100)) == cfg  # 2.5 standard errors: chance
    assert calibrated_slam(cfg, OdometryNoise(0.005, 100, -0.6, 100)) == cfg  # alternating: not a drift
    assert calibrated_slam(cfg, OdometryNoise(0.005, 100, 0.8, 1)) == cfg  # one pair of neighbours: no test
    # fewer pairs than the noise needs: the correlation still counts (it has its own test)
    assert calibrated_slam(cfg, OdometryNoise(0.02, 30, 0.8, 30)).odo_rot_per_m == pytest.approx(0.105)
    off = SlamConfig(odo_rot_per_m=0.035, odo_correlation_sigmas=math.inf)
    assert calibrated_slam(off, OdometryNoise(0.005, 100, 0.8, 100)) == off


@pytest.mark.parametrize("scale, applied", [(1.03, True), (0.975, True), (1.004, False), (1.0, False)])
def test_the_wheels_scale_is_measured_from_the_scans_and_taken_off(scale: float, applied: bool) -> None:
    from mapping.lidar_frontend import ScaleEstimate, calibration_pairs, wheel_scale

    route, _, scans = _hall_drive()
    fc = FrontendConfig(scale_calibration=True)
    est = wheel_scale(calibration_pairs(scans, _smooth_wheels(route, 0.0, scale), fc), fc)
    assert est.pairs >= 20 and est.scale == pytest.approx(scale, abs=0.003)
    assert est.applied is applied and est.correction == (est.scale if applied else 1.0)
    assert wheel_scale([], fc) == ScaleEstimate(1.0, math.inf, 0, False)


def test_calibrate_log_divides_the_wheels_by_their_scale() -> None:
    from agents.files.carmen import LaserScan

    scans = _scans(0.0)
    long = [LaserScan(s.t, s.ranges, s.angles, s.max_range, Pose(1.03 * s.odom.x, 1.03 * s.odom.y,
                                                                 s.odom.theta))
            for s in scans]  # every metre of the wheels 3 % long
    fc = FrontendConfig(scale_calibration=True, slam=SlamConfig(enabled=False))
    cal = mr.calibrate_log(long, fc)
    assert cal.scale == pytest.approx(1.03, abs=0.006) and cal.scale_estimate.applied
    report = mr.yaw_report(cal)
    assert report["wheel_scale"] == cal.scale and report["wheel_scale_se"] > 0
    inputs = list(mr.carmen_inputs(long, frontend=fc, calibration=cal))
    true = mr.wheel_increments(scans)
    got = [math.hypot(i.odometry.x, i.odometry.y) for i in inputs[1:]]
    want = [math.hypot(o.x, o.y) for o in true[1:]]
    assert sum(got) == pytest.approx(sum(want), rel=0.006)  # the wheels' 3 % taken off
    off = FrontendConfig(slam=SlamConfig(enabled=False))
    assert "wheel_scale" not in mr.yaw_report(mr.calibrate_log(long, off))
