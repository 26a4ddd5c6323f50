"""Real CARMEN logs as robots wrote them: the committed excerpt of freiburg-101 reads, maps and is
scored; format variants and error paths of the reader, ``wiremap map --strict`` and
``wiremap bench lidar`` (tiny synthetic logs written here)."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.cli import main
from agents.files.carmen import CarmenError, read_carmen_log, read_truth_tsv, scan_truth, truth_path_for
from mapping.se2 import Pose

DATA = Path(__file__).parent / "data"
EXCERPT = DATA / "freiburg-101-head.log.gz"


# ---------------------------------------------------------------- the real excerpt
def test_real_excerpt_reads_as_it_is() -> None:
    log = read_carmen_log(EXCERPT, strict=True)
    assert log.issues == [] and log.laser == "FLASER" and log.lasers == {"FLASER": 60}
    assert len(log.scans) == 60
    s = log.scans[0]
    # PARAM lines carry "nohost 0" after the value.
    assert log.params["robot_frontlaser_offset"] == "-0.04"
    assert s.max_range == 80.99  # robot_front_laser_max
    # 360 beams at laser_front_laser_resolution 0.5 degrees: from -90 to +89.5 (CARMEN's start angle).
    assert s.ranges.size == 360
    assert (s.angles[0] == pytest.approx(-math.radians(90.0))
            and s.angles[-1] == pytest.approx(math.radians(89.5)))
    assert np.isfinite(s.ranges).sum() > 300
    # Both pose triples are equal: the odometry is the laser's own pose, no offset composed.
    assert s.mount.almost_equal(Pose())
    assert s.odom.almost_equal(Pose(0.105722, -0.032289, 0.551487), tol=1e-6)
    assert s.t == pytest.approx(158.415)
    assert [sc.index for sc in log.scans] == list(range(60))


def test_real_excerpt_truth_rows_match_scans() -> None:
    log = read_carmen_log(EXCERPT)
    assert truth_path_for(EXCERPT) == DATA / "freiburg-101-head.truth.tsv"
    truth = scan_truth(log)
    assert truth is not None and len(truth) == 60
    rows = read_truth_tsv(DATA / "freiburg-101-head.truth.tsv")
    assert truth[5].almost_equal(rows[5][1])
    # The drifting odometry starts at the truth and drifts from it.
    first = truth[0].distance(log.scans[0].odom)
    last = truth[-1].distance(log.scans[-1].odom)
    assert first < 0.01 and last > first


def test_map_scores_the_real_excerpt_against_its_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert main(["map", "--carmen", str(EXCERPT), "--steps", "30", "--seed", "1", "--quiet", "--out",
                 str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["laser"] == "FLASER" and report["steps"] == 30 and report["skipped_lines"] == 0
    assert report["edges"] > 10
    # The mapper beats nothing here on purpose; these bounds only say the scoring is wired to
    # the truth (a map in the wrong frame scores near 0 precision and metres of ATE).
    assert report["ate_rmse_m"] < 0.5 and report["ate_max_m"] >= report["ate_rmse_m"]
    assert report["map_precision"] > 0.5 and 0.0 < report["map_coverage"] <= 1.0
    assert report["odometry_ate_rmse_m"] > 0.0
    assert (out / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "ATE" in capsys.readouterr().out
    # the ROS map: walls occupied, and free what the scans' beams crossed (the walls alone close
    # no room here); the first pose is free, a cell on a wall is occupied, and the space beyond
    # the beams stays unknown
    from agents.files.export import FREE, OCCUPIED, UNKNOWN, read_pgm

    grid = read_pgm((out / "map.pgm").read_bytes())
    meta = (out / "map.yaml").read_text()
    assert "image: map.pgm" in meta and "mode: trinary" in meta
    counts = {v: int((grid == v).sum()) for v in (FREE, OCCUPIED, UNKNOWN)}
    assert counts[FREE] > 10_000 and counts[OCCUPIED] > 200 and counts[UNKNOWN] > 0
    assert counts[FREE] + counts[OCCUPIED] + counts[UNKNOWN] == grid.size
    res, ox, oy = 0.05, *(float(v) for v in meta.split("origin: [")[1].split("]")[0].split(",")[:2])
    x0, y0, th0 = (float(v) for v in (out / "trajectory.tsv").read_text().split()[1:4])

    def at(x: float, y: float) -> int:
        return int(grid[grid.shape[0] - 1 - int((y - oy) / res), int((x - ox) / res)])

    assert at(x0 + 0.5 * math.cos(th0), y0 + 0.5 * math.sin(th0)) == FREE  # in front of the laser


def test_bench_lidar_json_on_the_excerpt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "lidar", str(EXCERPT), "--steps", "15", "--particles", "3", "--baseline", "--json",
            "--quiet", "--out", str(tmp_path)]
    assert main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(lines[-1])
    assert set(summary) == {"logs", "median", "profile", "settings"}
    assert summary["profile"] == "lidar-slam" and summary["settings"]["slam.enabled"] is True
    assert summary["settings"]["odometry.rot_per_m"] == 0.05
    row = summary["logs"]["freiburg-101-head"]
    for key in ("scans", "ate_rmse_m", "ate_max_m", "rpe_1m_m", "map_precision", "map_coverage",
                "best_map_bytes", "particle_bytes", "time_s", "ms_per_scan", "odometry_ate_rmse_m"):
        assert key in row and key in summary["median"], key
    assert (row["scans"] == 15 and row["best_map_bytes"] > 0
            and row["particle_bytes"] > row["baseline"]["particle_bytes"] / 2)
    assert row["baseline"]["scans"] == 15 and "baseline" in summary["median"]
    # The SLAM's odometry calibration, reported: 15 scans give too few pairs to widen the prior.
    assert row["slam_odo_prior_widened"] is False and row["odometry_noise_pairs"] < 50
    assert row["slam_odo_rot_per_m_deg"] == pytest.approx(math.degrees(0.035), abs=1e-6)
    assert summary["median"]["ate_rmse_m"] == row["ate_rmse_m"]  # one log: the median is it
    assert any(line.startswith("freiburg-101-head  odometry") for line in lines)
    assert ((tmp_path / "freiburg-101-head.png").is_file()
            and (tmp_path / "freiburg-101-head-baseline.png").is_file())


def test_bench_lidar_truth_poses_maps_on_the_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--truth-poses`: the filter once more, fed the truth's increments: its trajectory is the
    truth's (to float rounding), its map is scored like the filter's, and it has a table row,
    a median and a PNG of its own; the filter's own row is the same as without the flag."""
    args = ["bench", "lidar", str(EXCERPT), "--steps", "20", "--particles", "2", "--json", "--quiet",
            "--out", str(tmp_path)]
    assert main(args) == 0
    plain = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["logs"]["freiburg-101-head"]
    assert main([*args, "--truth-poses"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(lines[-1])
    row = summary["logs"]["freiburg-101-head"]
    at_truth = row.pop("truth_poses")
    assert at_truth["scans"] == 20 and at_truth["ate_max_m"] < 1e-6 < row["ate_max_m"]
    assert 0.0 < at_truth["map_precision"] <= 1.0 and 0.0 < at_truth["map_coverage"] <= 1.0
    assert "truth_poses" in summary["median"]
    assert any(line.startswith("freiburg-101-head  truth-poses") for line in lines)
    assert (tmp_path / "freiburg-101-head-truth-poses.png").is_file()
    timing = ("time_s", "ms_per_scan")
    def scores(r: dict[str, object]) -> dict[str, object]:
        return {k: v for k, v in r.items() if k not in timing}

    assert scores(row) == scores(plain)


def test_bench_register_pairs_from_the_excerpt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`wiremap bench register --data DIR`: CARMEN pairs from the excerpt (read by the project's
    reader, at its truth) register, none falsely, and the JSON has the issue's keys; a missing
    --data is one line, exit 2."""
    args = ["bench", "register", "--pairs", "6", "--cross", "2", "--carmen", "4", "--data", str(DATA),
            "--worlds", "paper-small", "--seed", "3", "--json", "--quiet"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("pairs", "cross_pairs", "false_merges", "success_rate_overlap_ge_30", "trans_err_m_p95",
                "rot_err_deg_p95", "ms_per_attempt_p50", "by_overlap"):
        assert key in summary, key
    assert summary["carmen_pairs"] == 4 and summary["pairs"] == 12
    assert summary["false_merges"] == 0 and summary["false_merges_cross"] == 0
    assert summary["success_rate_overlap_ge_30"] > 0.0
    assert main(["bench", "register", "--quick", "--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--data" in err[0], err


def test_bench_lidar_profile_and_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "lidar", str(EXCERPT), "--steps", "5", "--particles", "2", "--json", "--quiet",
            "--out", str(tmp_path), "--profile", "none", "--set", "odometry.rot_per_m=0.02",
            "--set", "extract.jump_beams=3"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["profile"] == "none"
    assert summary["settings"] == {"odometry.rot_per_m": 0.02, "extract.jump_beams": 3.0}  # as numbers
    for bad in ("odometry.nope=1", "odometry.rot_per_m=-1", "extract.jump=0", "novalue"):
        assert main(["bench", "lidar", str(EXCERPT), "--steps", "2", "--quiet", "--set", bad]) == 2
        assert "--set" in capsys.readouterr().err


def test_bench_lidar_slam_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "lidar", str(EXCERPT), "--steps", "30", "--particles", "2", "--json", "--quiet",
            "--out", str(tmp_path), "--profile", "lidar-slam", "--set", "slam.map_radius=0"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["profile"] == "lidar-slam"
    assert summary["settings"]["slam.enabled"] is True and summary["settings"]["slam.map_radius"] == 0.0
    assert summary["logs"]["freiburg-101-head"]["ate_rmse_m"] < summary["logs"]["freiburg-101-head"][
        "odometry_ate_rmse_m"]
    assert main(["bench", "lidar", str(EXCERPT), "--steps", "2", "--quiet", "--set", "slam.nope=1"]) == 2


def test_a_two_scan_log_reports_strict_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Too short for the laser yaw's or the odometry's pairs: the estimates are null, not NaN or
    Infinity, in ``report.json`` and in the bench's JSON line (strict JSON for jq and browsers)."""
    def strict(text: str) -> Any:
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"non-finite {c} in the JSON"))

    assert main(["map", "--carmen", str(EXCERPT), "--steps", "2", "--quiet", "--out", str(tmp_path)]) == 0
    report = strict((tmp_path / "report.json").read_text())
    assert report["laser_yaw_se_deg"] is None and report["odometry_heading_noise_deg_per_m"] is None
    capsys.readouterr()
    args = ["bench", "lidar", str(EXCERPT), "--steps", "2", "--particles", "1", "--json", "--quiet",
            "--out", str(tmp_path / "bench")]
    assert main(args) == 0
    row = strict(capsys.readouterr().out.strip().splitlines()[-1])["logs"]["freiburg-101-head"]
    assert row["laser_yaw_se_deg"] is None and row["odometry_heading_noise_deg_per_m"] is None


def test_bench_lidar_needs_logs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "lidar"]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["bench", "lidar", "--data", str(tmp_path)]) == 2  # no logs there
    assert main(["bench", "lidar", "--data", str(tmp_path / "none")]) == 2
    (tmp_path / "x.log").write_text("FLASER 3 1 1 1 0 0 0 0 0 0 1.0 h 1.0\n")
    assert main(["bench", "lidar", str(tmp_path / "x.log"), "--quiet"]) == 2  # no truth beside it
    err = capsys.readouterr().err
    assert "no truth" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exc:  # argparse's one-line error
        main(["bench", "lidar", str(EXCERPT), "--steps", "0"])
    assert exc.value.code == 2 and "--steps" in capsys.readouterr().err


# ---------------------------------------------------------------- format variants
def write(tmp_path: Path, text: str, name: str = "log.txt", newline: str = "\n") -> Path:
    p = tmp_path / name
    p.write_bytes(text.replace("\n", newline).encode())
    return p



def flaser(x: float, t: float, ranges: str = "1.0 2.0 3.0") -> str:
    p = f"{x} 0.0 0.0"
    return f"FLASER 3 {ranges} {p} {p} {t} nohost {t}\n"


def test_crlf_line_ends(tmp_path: Path) -> None:
    text = "PARAM robot_front_laser_max 5.0 nohost 0\n" + flaser(0.0, 1.0) + flaser(0.5, 2.0)
    log = read_carmen_log(write(tmp_path, text, newline="\r\n"), strict=True)
    assert len(log.scans) == 2 and log.scans[1].t == 2.0 and log.scans[0].max_range == 5.0


def test_truncated_last_line_is_skipped_and_reported(tmp_path: Path) -> None:
    text = flaser(0.0, 1.0) + flaser(0.5, 2.0) + "FLASER 3 1.0 2.0 3.0 0.5 0.0"  # cut mid-line
    log = read_carmen_log(write(tmp_path, text))
    assert len(log.scans) == 2
    assert len(log.issues) == 1 and ":3: FLASER" in log.issues[0] and "truncated last line" in log.issues[0]
    assert log.lasers["FLASER"] == 3  # the skipped line still counts: truth rows stay aligned
    with pytest.raises(CarmenError, match="truncated"):
        read_carmen_log(tmp_path / "log.txt", strict=True)


def test_nan_and_inf_readings_are_no_return_but_a_nan_pose_is_unreadable(tmp_path: Path) -> None:
    text = (
        "PARAM robot_front_laser_max 10 nohost 0\n"
        + flaser(0.0, 1.0, "nan inf 2.5")
        + "FLASER 3 1.0 2.0 3.0 nan 0 0 nan 0 0 2.0 nohost 2.0\n"
        + flaser(1.0, 3.0, "-inf 1.0 NaN")
    )
    log = read_carmen_log(write(tmp_path, text))
    assert len(log.scans) == 2 and len(log.issues) == 1 and ":3:" in log.issues[0]
    a, b = log.scans
    assert np.isinf(a.ranges[:2]).all() and a.ranges[2] == 2.5
    assert np.isinf(b.ranges[[0, 2]]).all() and b.ranges[1] == 1.0
    assert b.index == 2


def test_old_flaser_and_odom_field_counts(tmp_path: Path) -> None:
    # Old logs: a single timestamp after the poses, ODOM without hostname and logger time.
    text = (
        "PARAM laser_front_laser_fov 90\n"
        "ODOM 0 0 0 0 0 0 4.0\n"
        "FLASER 3 1.0 2.0 3.0 9 9 9 1.0 2.0 0.5 5.0\n"
        "FLASER 3 1.0 2.0 3.0 9 9 9 1.5 2.0 0.5 6.0 nohost 6.5\n"
    )
    log = read_carmen_log(write(tmp_path, text), strict=True)
    a, b = log.scans
    assert a.t == 5.0 and b.t == 6.5
    assert np.allclose(a.angles, np.radians([-45, 0, 45]))
    assert a.odom.almost_equal(Pose(1.0, 2.0, 0.5))


def test_param_with_and_without_host_and_timestamp(tmp_path: Path) -> None:
    text = (
        "PARAM robot_front_laser_max 4.0\n"
        "PARAM laser_front_laser_resolution 45 nohost 1234.5\n"
        "PARAM robot_name tiny robot\n"
        "PARAM robot_frontlaser_offset 0.5 somehost 17\n"
        "FLASER 3 1.0 2.0 4.5 9 9 9 1.0 2.0 0.0 5.0 h 5.0\n"
    )
    log = read_carmen_log(write(tmp_path, text), strict=True)
    assert log.params["robot_front_laser_max"] == "4.0"
    assert log.params["laser_front_laser_resolution"] == "45"
    assert log.params["robot_name"] == "tiny robot"
    (s,) = log.scans
    assert s.max_range == 4.0 and np.isinf(s.ranges[2])
    assert np.allclose(s.angles, np.radians([-45, 0, 45]))  # 3 beams 45 degrees apart
    # The pose triples differ: the odometry is the robot's, the 0.5 m offset is composed.
    assert s.mount.almost_equal(Pose(0.5, 0.0, 0.0)) and s.odom.almost_equal(Pose(1.5, 2.0, 0.0))


def test_robotlaser_old_and_new_and_rawlaser2(tmp_path: Path) -> None:
    head = "ROBOTLASER1 0 -0.5 1.0 0.5 4.0 0.01 0 3 1.0 2.0 4.5 0 "
    text = (
        head + "1.1 2.0 0.0 1.0 2.0 0.0 0.1 0.0 0.5 0.2 0.3 8.0 h 8.5\n"  # with tv rv ... turn_axis
        + head + "1.2 2.0 0.0 1.1 2.0 0.0 9.0\n"  # old: no velocities, one timestamp
        + "ODOM 3.0 4.0 0.5 0 0 0 9.0 h 9.0\n"
        + "RAWLASER2 0 -1.0 2.0 1.0 30.0 0.01 0 3 1.0 2.0 inf 0 10.0 h 10.5\n"
    )
    p = write(tmp_path, text)
    log = read_carmen_log(p, strict=True)
    assert log.laser == "ROBOTLASER1" and log.lasers == {"ROBOTLASER1": 2, "RAWLASER2": 1}
    a, b = log.scans
    assert a.t == 8.5 and b.t == 9.0
    assert b.odom.almost_equal(Pose(1.2, 2.0, 0.0)) and b.max_range == 4.0
    (raw,) = read_carmen_log(p, laser="RAWLASER2").scans
    assert raw.odom.almost_equal(Pose(3.0, 4.0, 0.5)) and np.isinf(raw.ranges[2])


def test_rear_laser_faces_backwards(tmp_path: Path) -> None:
    text = "PARAM robot_rearlaser_offset -0.2\nRLASER 3 1 1 1 9 9 9 1.0 0.0 0.0 5.0 h 5.0\n"
    (s,) = read_carmen_log(write(tmp_path, text), strict=True).scans
    assert s.kind == "RLASER" and s.odom.almost_equal(Pose(0.8, 0.0, math.pi), angle_tol=1e-9)


def test_truepos_track_scores_a_log(tmp_path: Path) -> None:
    text = (
        "TRUEPOS 0 0 0 0 0 0 0.0 h 0.0\n"
        "TRUEPOS 2 0 0 0 0 0 2.0 h 2.0\n"
        + flaser(0.0, 0.5) + flaser(0.5, 1.0)
    )
    log = read_carmen_log(write(tmp_path, text), strict=True)
    truth = scan_truth(log)
    assert truth is not None
    assert truth[0].almost_equal(Pose(0.5, 0, 0)) and truth[1].almost_equal(Pose(1.0, 0, 0))


def test_short_truth_file_is_an_error(tmp_path: Path) -> None:
    log_path = write(tmp_path, flaser(0.0, 1.0) + flaser(0.5, 2.0), name="a.log")
    (tmp_path / "a.truth.tsv").write_text("1.0 0 0 0\n")
    with pytest.raises(CarmenError, match="1 truth rows"):
        scan_truth(read_carmen_log(log_path))


# ---------------------------------------------------------------- wiremap map: strict and errors
def test_map_skips_unreadable_lines_unless_strict(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = [flaser(0.1 * k, float(k), "1.0 1.1 1.2") for k in range(6)]
    lines.insert(3, "FLASER 3 1.0 oops 1.2 0 0 0 0 0 0 9.0 h 9.0\n")
    log_path = write(tmp_path, "PARAM robot_front_laser_max 5.0 nohost 0\n" + "".join(lines))
    out = tmp_path / "run"
    assert main(["map", "--carmen", str(log_path), "--out", str(out), "--quiet", "--particles", "2"]) == 0
    captured = capsys.readouterr()
    assert f"{log_path}:5: FLASER line reading 2 is not a number: 'oops'" in captured.err
    assert "skipped 1 unreadable lines" in captured.out
    assert json.loads((out / "report.json").read_text())["skipped_lines"] == 1
    assert main(["map", "--carmen", str(log_path), "--out", str(out), "--quiet", "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ":5:" in err[0]


def test_map_error_paths_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = gzip.compress((flaser(0.0, 1.0) * 50).encode())
    cases = {
        "missing.log": None,
        "picture.log": b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00",
        "notes.log": b"hello, this is not a log\n",
        "cut.log.gz": good[: len(good) // 2],  # a truncated gzip stream
        "bad-crc.log.gz": good[:-8] + b"\x00" * 8,
    }
    for name, data in cases.items():
        p = tmp_path / name
        if data is not None:
            p.write_bytes(data)
        assert main(["map", "--carmen", str(p), "--out", str(tmp_path / "o"), "--quiet"]) == 2, name
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (name, err)
        assert name in err


def test_gzip_is_recognised_by_content_not_name(tmp_path: Path) -> None:
    plain = write(tmp_path, flaser(0.0, 1.0), name="plain.log.gz")  # a .gz name, plain text
    packed = tmp_path / "packed.log"
    packed.write_bytes(gzip.compress(flaser(0.0, 1.0).encode()))
    assert len(read_carmen_log(plain).scans) == len(read_carmen_log(packed).scans) == 1


@pytest.mark.fleet  # --jobs 2 starts worker processes
def test_bench_lidar_runs_logs_in_parallel(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    data.mkdir()
    for name in ("a", "b"):
        (data / f"{name}.log.gz").write_bytes(EXCERPT.read_bytes())
        (data / f"{name}.truth.tsv").write_text((DATA / "freiburg-101-head.truth.tsv").read_text())
    args = ["bench", "lidar", "--data", str(data), "--steps", "8", "--particles", "2", "--jobs", "2",
            "--json", "--out", str(tmp_path / "png")]
    assert main(args) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert list(summary["logs"]) == ["a", "b"]
    # Same scans, same seed: separate processes give the same figures.
    for key in ("ate_rmse_m", "map_precision", "best_map_bytes", "particle_bytes"):
        assert summary["logs"]["a"][key] == summary["logs"]["b"][key], key
    assert "[2/2 logs" in captured.err


@pytest.mark.parametrize(("beams", "degrees"), [(181, 180.0), (180, 179.0), (361, 180.0), (360, 179.5),
                                                (721, 180.0), (3, 180.0), (100, 180.0)])
def test_a_log_without_geometry_gets_the_standard_resolution(beams: int, degrees: float) -> None:
    from agents.files.carmen import default_width

    assert math.degrees(default_width(beams)) == pytest.approx(degrees)


def test_180_beams_without_parameters_are_one_degree_apart(tmp_path: Path) -> None:
    ranges = " ".join(["2.0"] * 180)
    log = write(tmp_path, f"FLASER 180 {ranges} 0 0 0 0 0 0 1.0 host 1.0\n")
    scan = read_carmen_log(log).scans[0]
    assert np.allclose(np.diff(scan.angles), math.radians(1.0))
    assert scan.angles[0] == pytest.approx(-math.radians(90.0))  # CARMEN's start angle, the last beam missing
    assert scan.angles[-1] == pytest.approx(math.radians(89.0))


# ---------------------------------------------------------------- the SLAM online (a robot driving)
def test_online_slam_feeds_each_scan_at_the_pose_the_slam_gave_it_then() -> None:
    """``slam.online``: the filter's increments are those between the poses
    :meth:`LidarSlam.add` returned scan by scan (the SLAM's ``online`` poses of a run without
    refine passes), not the smoothed ones; nothing of a later scan is used for an earlier one."""
    import dataclasses

    from agents import mapping_run as mr
    from mapping.lidar_frontend import run_slam
    from mapping.se2 import Pose, increments

    scans = read_carmen_log(EXCERPT).scans[:40]
    _, extract, frontend = mr.split_profile(mr.lidar_profile("lidar-slam-online"))
    frontend = dataclasses.replace(frontend, calibration_scans=0)  # the whole excerpt: no re-measuring
    cal = mr.calibrate_log(scans, frontend)
    got = [inp.odometry for inp in mr.carmen_inputs(scans, extract=extract, frontend=frontend,
                                                    calibration=cal)]
    slam_cfg = dataclasses.replace(frontend.slam, refine_passes=0)
    slam = run_slam(cal.points, [mr.scaled(o, cal.scale) for o in mr.wheel_increments(scans)], slam_cfg,
                    noise=cal.noise)
    want = increments([Pose(*map(float, p)) for p in slam.online])
    assert len(got) == len(want) == 40
    for a, b in zip(got, want, strict=True):
        assert a.distance(b) < 1e-9 and abs(a.theta - b.theta) < 1e-12
    # causal: the first 20 scans alone (same calibration) give the first 20 increments exactly
    head_cal = dataclasses.replace(cal, points=cal.points[:20])
    head = [inp.odometry for inp in mr.carmen_inputs(scans[:20], extract=extract, frontend=frontend,
                                                     calibration=head_cal)]
    assert [p.as_tuple() for p in head] == [p.as_tuple() for p in got[:20]]
    # and not the smoothed poses: the offline run's increments differ somewhere
    offline = [inp.odometry for inp in mr.carmen_inputs(
        scans, extract=extract, frontend=dataclasses.replace(frontend, slam=dataclasses.replace(
            frontend.slam, online=False)), calibration=cal)]
    assert max(a.distance(b) for a, b in zip(got, offline, strict=True)) > 1e-6


def test_calibration_scans_measure_on_the_first_scans_only() -> None:
    import dataclasses

    from agents import mapping_run as mr

    scans = read_carmen_log(EXCERPT).scans
    _, _, frontend = mr.split_profile(mr.lidar_profile("lidar-slam"))
    n = 30
    first = mr.calibrate_log(scans[:n], frontend)
    windowed = mr.calibrate_log(scans, dataclasses.replace(frontend, calibration_scans=n))
    assert windowed.turn == first.turn
    assert windowed.noise is not None and first.noise is not None
    assert windowed.noise.pairs == first.noise.pairs
    assert windowed.noise.rot_per_m == first.noise.rot_per_m or (
        math.isnan(windowed.noise.rot_per_m) and math.isnan(first.noise.rot_per_m))
    assert len(windowed.points) == len(scans)  # every scan's points, turned by the window's yaw
    with pytest.raises(ValueError, match="calibration_scans"):
        dataclasses.replace(frontend, calibration_scans=-1)


def test_bench_lidar_online_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "lidar", str(EXCERPT), "--steps", "30", "--particles", "2", "--json", "--quiet",
            "--out", str(tmp_path), "--profile", "lidar-slam-online"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["settings"]["slam.online"] is True
    row = summary["logs"]["freiburg-101-head"]
    assert row["ate_rmse_m"] < row["odometry_ate_rmse_m"] and row["map_precision"] > 0.5


def test_a_known_laser_yaw_is_taken_not_estimated(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``frontend.laser_yaw`` (degrees, measured once for the robot): every bearing turned by
    it, no estimate made; NaN (the default) estimates as before; out of range is refused."""
    from agents import mapping_run as mr

    scans = read_carmen_log(EXCERPT).scans[:30]
    _, _, known = mr.split_profile({**mr.lidar_profile("lidar-slam-online"), "frontend.laser_yaw": 0.29})
    cal = mr.calibrate_log(scans, known)
    assert cal.turn == math.radians(0.29) and cal.estimate is None
    _, _, default = mr.split_profile(mr.lidar_profile("lidar-slam-online"))
    assert math.isnan(default.laser_yaw) and mr.calibrate_log(scans, default).estimate is not None
    args = ["bench", "lidar", str(EXCERPT), "--steps", "5", "--particles", "1", "--json", "--quiet",
            "--out", str(tmp_path)]
    assert main([*args, "--set", "frontend.laser_yaw=400"]) == 2
    assert main([*args, "--set", "frontend.laser_yaw=0.29"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["logs"]["freiburg-101-head"]
    assert row["laser_yaw_deg"] == pytest.approx(0.29)


def test_the_online_slam_reports_the_wheels_noise_it_measured_last() -> None:
    """While the first ``calibration_scans`` gave too few scan pairs, the online SLAM measures
    the wheels again on every scan so far (each ``ONLINE_RECALIBRATE`` scans); ``on_noise``
    hears the measure it then runs with, which is what a report must give."""
    import dataclasses

    from agents import mapping_run as mr
    from mapping.lidar_frontend import ONLINE_RECALIBRATE, odometry_noise

    scans = read_carmen_log(EXCERPT).scans
    _, extract, frontend = mr.split_profile(mr.lidar_profile("lidar-slam-online"))
    slam = dataclasses.replace(frontend.slam, odo_calibration_min_pairs=15)
    frontend = dataclasses.replace(frontend, calibration_scans=10, slam=slam)
    cal = mr.calibrate_log(scans, frontend)
    assert cal.noise is not None and cal.noise.pairs < 15  # the first 10 scans: too few pairs
    heard: list[object] = []
    n = len(list(mr.carmen_inputs(scans, extract=extract, frontend=frontend, calibration=cal,
                                  on_noise=heard.append)))
    assert n == len(scans) and len(heard) == 1  # measured again once, then enough pairs
    want = odometry_noise(cal.points[:ONLINE_RECALIBRATE], mr.wheel_increments(scans)[:ONLINE_RECALIBRATE],
                          frontend)
    assert heard[0] == want and want.pairs >= 15
    assert mr.odometry_report(heard[0], frontend.slam) != mr.odometry_report(cal.noise, frontend.slam)
