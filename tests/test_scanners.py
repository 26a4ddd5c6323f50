"""Simulated logs of real scanner models (agents.sim.scanner_logs) and ``wiremap bench scanners``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from agents.cli import main
from agents.files.carmen import read_carmen, read_truth_tsv, truth_path_for
from agents.sim.scanner_logs import SCANNERS, ScannerModel, Wheels, write_scanner_log
from mapping.se2 import Pose


def test_a_scanner_log_has_every_scan_at_the_scanners_rate_and_its_truth(tmp_path: Path) -> None:
    model = SCANNERS["rplidar-a2"]
    path = tmp_path / "a.log.gz"
    n = write_scanner_log("paper-small", model, 4, path, duration=12.0)
    scans = read_carmen(path)
    truth = read_truth_tsv(truth_path_for(path))
    assert n == len(scans) == len(truth) == 12 * 10 + 1  # 10 Hz, from t = 0
    assert {s.ranges.size for s in scans} == {400}
    assert np.allclose(np.diff([s.t for s in scans]), 0.1)
    assert scans[0].angles[0] == pytest.approx(-math.pi) and max(s.max_range for s in scans) == 12.0
    # the wheels start at the truth and drift from it
    assert scans[0].odom.almost_equal(truth[0][1], tol=1e-6, angle_tol=1e-6)
    assert not scans[-1].odom.almost_equal(truth[-1][1], tol=1e-3, angle_tol=1e-4)
    # the same arguments give the same log
    write_scanner_log("paper-small", model, 4, tmp_path / "b.log.gz", duration=12.0)
    again = read_carmen(tmp_path / "b.log.gz")
    assert [s.ranges.tolist() for s in again] == [s.ranges.tolist() for s in scans]
    with pytest.raises(ValueError):
        write_scanner_log("paper-small", model, 4, tmp_path / "c.log", duration=0.0)
    assert [s.time_increment for s in scans] == pytest.approx([model.sweep / 399] * n)  # a spinning lidar's
    with pytest.raises(ValueError):
        ScannerModel("bad", 400.0, 10, 5.0, 10.0, 0.1, "a field of view over a full turn")
    with pytest.raises(ValueError):
        ScannerModel("bad", 360.0, 10, 5.0, 10.0, 0.2, "a sweep longer than a scan's period")


@pytest.mark.parametrize("steps", [20, 400])  # 1 m in 5 cm steps or in 2.5 mm steps
def test_the_wheels_drift_per_metre_whatever_the_rate(steps: int) -> None:
    """The heading drift over 1 m driven straight: its spread is the same in 20 steps as in 400."""
    ends = []
    for seed in range(300):
        wheels, pose = Wheels(np.random.default_rng(seed)), Pose.identity()
        for _ in range(steps):
            pose = pose.compose(wheels.step(Pose(1.0 / steps, 0.0, 0.0)))
        ends.append(pose.theta)
    spread = math.degrees(float(np.std(ends)))
    assert 0.6 < spread < 1.4  # about 1 degree: the drift rate's standard deviation times a metre


def test_bench_scanners_maps_each_scanners_log_and_thins_the_dense_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench"
    assert main(["bench", "scanners", "--scanners", "lds-01,rplidar-a2", "--worlds", "paper-small",
                 "--seeds", "2", "--duration", "30", "--out", str(out), "--json", "--quiet"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    doc = json.loads(lines[-1])
    assert set(doc["runs"]) == {"paper-small/lds-01/s2", "paper-small/rplidar-a2/s2"}
    assert set(doc["scanners"]) == {"lds-01", "rplidar-a2"} and doc["seeds"] == [2]
    for name, r in doc["runs"].items():
        scanner = name.split("/")[1]
        assert r["scans_in_log"] == 30 * SCANNERS[scanner].rate + 1
        assert r["scans"] == r["scans_in_log"] - r["scans_left_out"] < r["scans_in_log"] / 2  # dense: thinned
        assert r["ate_rmse_m"] < r["odometry_ate_rmse_m"] and 0.0 <= r["map_precision"] <= 1.0
        assert (out / "logs" / f"paper-small-{scanner}-s2.log.gz").is_file()
        assert (out / f"paper-small-{scanner}-s2.png").is_file()
    assert doc["scanners"]["lds-01"]["ate_rmse_m"] == doc["runs"]["paper-small/lds-01/s2"]["ate_rmse_m"]
    assert any(ln.startswith("median lds-01") for ln in lines)


@pytest.mark.parametrize("args, needle", [
    (["--scanners", "velodyne"], "no scanner 'velodyne'"),
    (["--worlds", "atlantis"], "unknown world 'atlantis'"),
    (["--seeds", "one"], "--seeds"),
    (["--duration", "0"], "--duration"),
])
def test_bench_scanners_bad_flags_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                                         needle: str) -> None:
    assert main(["bench", "scanners", *args, "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1


def test_the_order_a_scanners_beams_came_in_is_judged_on_its_turning_scans(tmp_path: Path) -> None:
    """A 5 Hz LDS-01 whose beams swept last bearing first while the log says first bearing first
    (its ROS driver's default order): its turning scans fit each other better de-skewed the other
    way round, and the de-skew takes that order; a log that says its order right keeps it, as
    does one whose order was set by hand; a log without beam times is not judged."""
    from dataclasses import replace

    from agents import mapping_run as mr
    from mapping.lidar_frontend import FrontendConfig

    model = SCANNERS["lds-01"]
    logs = {}
    for rev in (False, True):
        path = tmp_path / f"{rev}.log.gz"
        write_scanner_log("paper-small", model, 4, path, duration=15.0, reversed_sweep=rev)
        logs[rev] = read_carmen(path)
    right, wrong = mr.sweep_check(logs[False], FrontendConfig()), mr.sweep_check(logs[True], FrontendConfig())
    assert not right.reversed and right.scans >= mr.SWEEP_CHECK_MIN and right.gain < -0.01
    assert wrong.reversed and wrong.gain > 0.01
    assert mr.sweep_check(logs[True], FrontendConfig(sweep_reversed=True)).reversed  # set by hand, kept
    taken = mr.deskewed(logs[True], FrontendConfig())
    by_hand = mr.deskewed(logs[True], FrontendConfig(sweep_reversed=True, sweep_check=False))
    assert all(np.array_equal(a.angles, b.angles) for a, b in zip(taken, by_hand, strict=True))
    assert mr.sweep_report(mr.judged_sweep(logs[True], FrontendConfig()))["sweep_reversed"] is True
    unjudged = mr.judged_sweep(logs[True], FrontendConfig(sweep_check=False))  # as set, not judged
    assert unjudged is not None and not unjudged.reversed and unjudged.scans == 0
    assert all(ls.time_increment == 0.0 and ls.odom_end is None for ls in taken)  # de-skewed once
    still = [replace(s, time_increment=0.0) for s in logs[True]]
    assert mr.sweep_check(still, FrontendConfig()).scans == 0
    assert mr.judged_sweep(still, FrontendConfig()) is None and mr.sweep_report(None) == {}


def test_a_live_robot_judges_the_beams_order_while_it_calibrates(tmp_path: Path) -> None:
    """The live mapper (``LiveInputs``) judges the order once, at its calibrations, on the
    consecutive scans that came meanwhile (each with the odometry at its last beam, as the live
    robot pairs it): a reversed LDS-01 log turns it, its held scans are de-skewed again; a right
    log keeps it."""
    from dataclasses import replace

    from agents import mapping_run as mr
    from agents.files.rosbag import interpolate

    for rev in (False, True):
        path = tmp_path / f"{rev}.log.gz"
        write_scanner_log("paper-small", SCANNERS["lds-01"], 4, path, duration=30.0, reversed_sweep=rev)
        scans = read_carmen(path)
        stamps, odom = np.array([s.t for s in scans]), [s.odom for s in scans]
        scans = [replace(s, odom_end=interpolate(stamps, odom, s.t + s.sweep)) for s in scans]
        _, extract, frontend = mr.split_profile({**mr.lidar_profile("lidar-slam-online"),
                                                 "frontend.calibration_scans": 30})
        live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend, min_travel=0.5,
                             min_turn=math.radians(10.0))
        for ls in scans:
            live.add(ls)
        live.finish()
        assert live.sweep is not None and live.sweep.scans >= mr.SWEEP_CHECK_MIN
        assert live.sweep.reversed is rev and live.frontend.sweep_reversed is rev
