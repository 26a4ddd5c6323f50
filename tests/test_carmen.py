"""Tests of CARMEN log reading and writing (agents.files.carmen)."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from agents.errors import UserError
from agents.files.carmen import CarmenError, LaserScan, flaser_angles, read_carmen, write_carmen
from agents.sim.lidar import LidarConfig, raycast
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

ROOM = Wireframe.from_polylines([[(0, 0), (8, 0), (8, 5), (0, 5)], [(3, 2), (3, 3), (4, 3), (4, 2)]])


def simulated_scans(cfg: LidarConfig, n: int = 12) -> list[LaserScan]:
    rng = np.random.default_rng(3)
    out = []
    for k in range(n):
        pose = Pose(1.0 + 0.4 * k, 1.0 + 0.1 * k, -2.5 + 0.5 * k)
        r = raycast(ROOM.segments(), pose, cfg, rng)
        out.append(LaserScan(12.5 + 0.1 * k, r, cfg.angles(), cfg.max_range, pose))
    return out


def write(tmp_path: Path, text: str, name: str = "log.txt") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# ---------------------------------------------------------------- round trips
@pytest.mark.parametrize("fov", [math.pi, 2 * math.pi, math.radians(240)])
def test_write_then_read_gives_the_same_scans(tmp_path: Path, fov: float) -> None:
    cfg = LidarConfig(beams=181, fov=fov, max_range=6.0, sigma=0.01)
    scans = simulated_scans(cfg)
    assert any(np.isinf(s.ranges).any() for s in scans)  # some beams see nothing within 6 m
    path = tmp_path / "sim.log"
    assert write_carmen(path, scans, fov=fov, max_range=cfg.max_range) == len(scans)
    back = read_carmen(path)
    assert len(back) == len(scans)
    for a, b in zip(scans, back):
        assert b.t == pytest.approx(a.t, abs=1e-6)
        assert b.max_range == cfg.max_range
        assert np.allclose(b.angles, a.angles, atol=1e-9)
        assert np.array_equal(np.isinf(b.ranges), np.isinf(a.ranges))
        fin = np.isfinite(a.ranges)
        assert np.allclose(b.ranges[fin], a.ranges[fin], atol=5e-5 + 1e-12)
        assert b.odom.almost_equal(a.odom, tol=1e-6, angle_tol=1e-6)
    assert not list(tmp_path.glob(".*tmp"))  # the atomic write left no temporary file



def test_the_time_between_beams_round_trips(tmp_path: Path) -> None:
    cfg = LidarConfig(beams=181, fov=math.pi, max_range=6.0, sigma=0.01)
    scans = simulated_scans(cfg, n=3)
    write_carmen(tmp_path / "spin.log", scans, fov=math.pi, max_range=6.0, time_increment=1.25e-4)
    assert {s.time_increment for s in read_carmen(tmp_path / "spin.log")} == {1.25e-4}
    write_carmen(tmp_path / "still.log", scans, fov=math.pi, max_range=6.0)
    assert {s.time_increment for s in read_carmen(tmp_path / "still.log")} == {0.0}
    assert "time_increment" not in (tmp_path / "still.log").read_text()
    with pytest.raises(ValueError, match="time_increment"):
        write_carmen(tmp_path / "bad.log", scans, fov=math.pi, max_range=6.0, time_increment=math.inf)

def test_returns_just_below_max_range_survive(tmp_path: Path) -> None:
    a = flaser_angles(3, math.pi)
    scan = LaserScan(1.0, np.array([4.99999, 5.0, np.nan]), a, 5.0, Pose())
    write_carmen(tmp_path / "x.log", [scan], fov=math.pi, max_range=5.0)
    (back,) = read_carmen(tmp_path / "x.log")
    assert back.ranges[0] == pytest.approx(4.9999)
    assert np.isinf(back.ranges[1:]).all()


def test_write_checks_its_arguments(tmp_path: Path) -> None:
    scan = LaserScan(0.0, np.ones(5), np.linspace(-1, 1, 5), 5.0, Pose())
    with pytest.raises(ValueError, match="bearings"):
        write_carmen(tmp_path / "x.log", [scan], fov=math.pi, max_range=5.0)
    with pytest.raises(ValueError):
        write_carmen(tmp_path / "x.log", [], fov=0.0, max_range=5.0)
    with pytest.raises(ValueError):
        write_carmen(tmp_path / "x.log", [], fov=math.pi, max_range=math.inf)
    with pytest.raises(ValueError):
        LaserScan(0.0, np.ones(3), np.ones(4), 5.0)


# ---------------------------------------------------------------- hand-written logs
HAND = """\
# a hand-written log
PARAM laser_front_laser_fov 90
PARAM robot_front_laser_max 5.0
PARAM robot_name tiny robot
ODOM 0.0 0.0 0.0 0.0 0.0 0.0 100.0 host 100.01
FLASER 5 1.0 2.0 5.0 7.5 0.0 9.0 9.0 1.5 0.1 0.2 0.3 100.5 host 100.52
TRUEPOS 1 2 3 4 5 6 100.6 host 100.6
ODOM 1.0 0.5 0.2 0.0 0.0 0.0 101.0 host 101.01

FLASER 5 1.5 nan 0 -1 4.999 9.0 9.0 1.5 1.1 0.7 0.4 101.5 host 101.53
"""


def test_hand_written_log(tmp_path: Path) -> None:
    scans = read_carmen(write(tmp_path, HAND))
    assert len(scans) == 2
    a, b = scans
    assert a.t == 100.52 and b.t == 101.53  # the last field, the logger timestamp
    assert np.allclose(a.angles, np.radians([-45, -22.5, 0, 22.5, 45]))
    assert a.max_range == 5.0
    # 5.0 and 7.5 are at or beyond the maximum range: no return.
    assert a.ranges[:2].tolist() == [1.0, 2.0] and np.isinf(a.ranges[2:]).all()
    # nan, 0 and negative readings are no return too.
    assert b.ranges[0] == 1.5 and np.isinf(b.ranges[1:4]).all() and b.ranges[4] == 4.999
    # The odometry fields are used, never the logged laser pose (9, 9, 1.5); FLASER's own
    # odometry wins over the ODOM lines.
    assert a.odom.almost_equal(Pose(0.1, 0.2, 0.3))
    assert b.odom.almost_equal(Pose(1.1, 0.7, 0.4))


def test_defaults_without_parameters(tmp_path: Path) -> None:
    text = "FLASER 3 1.0 81.91 2.0 0 0 0 0 0 0 5.0 h 5.0\nFLASER 3 81.91 3.0 1.0 0 0 0 1 2 3 6.0\n"
    scans = read_carmen(write(tmp_path, text))
    assert len(scans) == 2
    assert np.allclose(scans[0].angles, [-math.pi / 2, 0.0, math.pi / 2])  # 180 degrees
    # No maximum-range parameter: the largest reading (81.91) is the saturation value.
    assert scans[0].max_range == 81.91
    assert np.isinf(scans[0].ranges[1]) and np.isinf(scans[1].ranges[0])
    assert scans[1].t == 6.0  # old FLASER lines end in a single timestamp
    assert scans[1].odom.almost_equal(Pose(1, 2, 3))


def test_overrides_and_laser_offset(tmp_path: Path) -> None:
    text = (
        "PARAM robot_frontlaser_offset 0.25\n"
        "PARAM laser_front_laser_fov 180\n"
        "FLASER 3 1.0 2.0 3.0 0 0 0 1.0 2.0 1.5707963267948966 5.0 h 5.0\n"
    )
    (s,) = read_carmen(write(tmp_path, text))
    # The laser sits 0.25 m ahead of the robot, which faces +y: the laser is at (1, 2.25).
    assert s.odom.almost_equal(Pose(1.0, 2.25, math.pi / 2))
    (s2,) = read_carmen(tmp_path / "log.txt", fov=math.radians(60), max_range=2.5)
    assert np.allclose(s2.angles, np.radians([-30, 0, 30]))
    assert s2.max_range == 2.5 and np.isinf(s2.ranges[2])


def test_robotlaser_and_rawlaser_lines(tmp_path: Path) -> None:
    text = (
        "RAWLASER1 0 -1.0 2.0 1.0 30.0 0.01 0 3 1.0 2.0 3.0 0 7.0 h 7.0\n"  # before any ODOM: skipped
        "ROBOTLASER1 0 -0.5 1.0 0.5 4.0 0.01 0 3 1.0 2.0 4.5 2 9 9 "
        "1.1 2.0 0.3 1.0 2.0 0.3 0 0 0 0 0 8.0 h 8.5\n"
        "ODOM 3.0 4.0 0.5 0 0 0 9.0 h 9.0\n"
        "RAWLASER1 0 -1.0 2.0 1.0 30.0 0.01 0 3 1.0 2.0 3.0 0 10.0 h 10.5\n"
    )
    path = write(tmp_path, text)
    # One laser stream at a time: ROBOTLASER1 comes before RAWLASER1 by default.
    (rl,) = read_carmen(path)
    assert rl.kind == "ROBOTLASER1"
    (raw,) = read_carmen(path, laser="RAWLASER1")
    assert raw.kind == "RAWLASER1" and raw.index == 1  # the first RAWLASER1 line had no odometry
    assert np.allclose(rl.angles, [-0.5, 0.0, 0.5])
    assert rl.max_range == 4.0 and np.isinf(rl.ranges[2]) and rl.t == 8.5
    # The laser is 0.1 m ahead of the robot along its heading 0.3.
    assert rl.odom.almost_equal(Pose(1.1, 2.0, 0.3), tol=1e-9)
    assert np.allclose(raw.angles, [-1.0, 0.0, 1.0])
    assert raw.odom.almost_equal(Pose(3.0, 4.0, 0.5)) and raw.max_range == 30.0


def test_gzipped_log(tmp_path: Path) -> None:
    p = tmp_path / "log.gz"
    with gzip.open(p, "wt") as fh:
        fh.write(HAND)
    assert len(read_carmen(p)) == 2


# ---------------------------------------------------------------- malformed input
@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("FLASER 4 1.0 2.0 3.0 0 0 0 0 0 0 5.0 h 5.0", "fields"),  # 3 readings, not 4
        ("FLASER x 1.0", "count"),
        ("FLASER 3 1.0 two 3.0 0 0 0 0 0 0 5.0 h 5.0", "reading 2"),
        ("FLASER 3 1.0 2.0 3.0 0 0 0 0 zero 0 5.0 h 5.0", "not a number"),
        ("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 5.0 h host", "not a number"),
        ("ODOM 1.0 2.0", "fields"),
        ("ODOM 1.0 2.0 inf 0 0 0 1 h 1", "not finite"),
        ("ROBOTLASER1 0 -0.5 1.0 0.5 4.0 0.01 0 3 1.0 2.0 4.5 0 1 1 1 1 1 1 0 0 0 0 8.0 h 8.5", "fields"),
    ],
)
def test_malformed_line_names_its_number(tmp_path: Path, line: str, why: str) -> None:
    p = write(tmp_path, "# header\nPARAM laser_front_laser_fov 180\n" + line + "\n")
    with pytest.raises(CarmenError, match=why) as info:
        read_carmen(p)
    assert f"{p}:3:" in str(info.value)
    assert isinstance(info.value, UserError)


def test_bad_parameters_and_files(tmp_path: Path) -> None:
    with pytest.raises(CarmenError, match=":1: PARAM robot_front_laser_max"):
        read_carmen(write(tmp_path, "PARAM robot_front_laser_max far\n"))
    with pytest.raises(CarmenError, match="field of view"):
        read_carmen(write(tmp_path, "PARAM laser_front_laser_fov 400\n"))
    with pytest.raises(CarmenError, match="no such file"):
        read_carmen(tmp_path / "missing.log")
    assert read_carmen(write(tmp_path, "# nothing but comments\nUNKNOWN 1 2 3\n")) == []
