"""ROS bags: the committed CARMEN excerpt written as a ROS 1 bag and as ROS 2 bags (sqlite3 and
mcap) reads back as the same scans and maps to the same map as the log; the reader's beam,
odometry and mount conventions on small hand-made bags; ``wiremap map --rosbag`` error paths
(one line, exit 2) and unreadable messages (skipped and counted, fatal under ``--strict``)."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.cli import main
from agents.files.carmen import CarmenLog, read_carmen_log, scan_truth
from agents.files.rosbag import RosbagError, interpolate, read_rosbag
from mapping.se2 import Pose
from tests.rosbag_util import FORMATS, BagWriter, write_scans_bag

DATA = Path(__file__).parent / "data"
EXCERPT = DATA / "freiburg-101-head.log.gz"
STEPS = 30  # scans mapped per run: the maps of the log and the bags parted at step 6 when they differed
MOUNT = Pose(0.12, -0.03, 0.05)


@pytest.fixture(scope="module")
def excerpt() -> tuple[CarmenLog, list[Pose]]:
    log = read_carmen_log(EXCERPT, strict=True)
    truth = scan_truth(log)
    assert truth is not None and len(log.scans) == 60
    return log, truth


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory, excerpt: tuple[CarmenLog, list[Pose]]) -> dict[str, Path]:
    """The excerpt as a bag of each format (``/odom``), and as a ROS 1 bag with its odometry only
    on ``/tf`` (``tf``); each with the truth on ``/ground_truth``."""
    log, truth = excerpt
    d = tmp_path_factory.mktemp("bags")
    out = {fmt: write_scans_bag(d / name, fmt, log.scans, truth=truth) for fmt, name in FORMATS.items()}
    out["tf"] = write_scans_bag(d / "tf.bag", "ros1", log.scans, odometry="tf", truth=truth)
    return out


def same_scans(bag_scans: list[Any], log_scans: list[Any]) -> None:
    """The bag's scans are the log's: ranges to float32 precision, the same no-returns, bearings
    to float32 precision of the increment, times to the nanosecond, poses to 1e-9."""
    assert len(bag_scans) == len(log_scans)
    for k, (b, c) in enumerate(zip(bag_scans, log_scans)):
        hit = np.isfinite(c.ranges)
        assert np.array_equal(np.isfinite(b.ranges), hit), k
        assert np.allclose(b.ranges[hit], c.ranges[hit], rtol=1e-6, atol=0), k
        assert np.allclose(b.angles, c.angles, rtol=0, atol=1e-6), k
        assert b.t == pytest.approx(c.t, abs=1e-6) and b.index == c.index, k
        assert b.odom.almost_equal(c.odom, tol=1e-9, angle_tol=1e-9), (k, b.odom, c.odom)
        assert b.max_range == pytest.approx(c.max_range, rel=1e-6)


# ---------------------------------------------------------------- the excerpt as bags
@pytest.mark.parametrize("fmt", [*FORMATS, "tf"])
def test_bag_reads_back_the_carmen_scans(
    fmt: str, bags: dict[str, Path], excerpt: tuple[CarmenLog, list[Pose]]
) -> None:
    log, truth = excerpt
    bag = read_rosbag(bags[fmt], truth_topic="/ground_truth", strict=True)
    same_scans(bag.scans, log.scans)
    assert bag.truth is not None and all(a.almost_equal(b, 1e-9, 1e-9) for a, b in zip(bag.truth, truth))
    assert bag.format == {"sqlite3": "ros2-sqlite3", "mcap": "ros2-mcap"}.get(fmt, "ros1")
    assert bag.scan_topic == "/scan" and bag.odometry == ("/tf" if fmt == "tf" else "/odom")
    assert bag.issues == [] and bag.unposed == 0 and bag.mount_from is None
    assert bag.messages == {"/scan": 60, bag.odometry: 60, "/ground_truth": 60}


def test_ros2_file_inside_its_folder_and_a_folder_without_metadata(bags: dict[str, Path]) -> None:
    for fmt, suffix in (("sqlite3", ".db3"), ("mcap", ".mcap")):
        folder = bags[fmt]
        (file,) = folder.glob(f"*{suffix}")
        whole = read_rosbag(folder, odom_topic="/odom")
        assert [s.t for s in read_rosbag(file, odom_topic="/odom").scans] == [s.t for s in whole.scans]
        (folder / "metadata.yaml").rename(folder / "metadata.bak")
        try:
            alone = read_rosbag(folder, odom_topic="/odom")  # the single storage file, without metadata
            assert alone.format == f"ros2-{fmt}" and len(alone.scans) == len(whole.scans)
        finally:
            (folder / "metadata.bak").rename(folder / "metadata.yaml")


def test_tf_odometry_through_a_static_mount(tmp_path: Path, excerpt: tuple[CarmenLog, list[Pose]]) -> None:
    log, truth = excerpt
    for fmt in ("ros1", "mcap"):
        name = "mount.bag" if fmt == "ros1" else "mount"
        p = write_scans_bag(tmp_path / name, fmt, log.scans[:10], odometry="tf", mount=MOUNT,
                            truth=truth[:10])
        bag = read_rosbag(p, truth_topic="/ground_truth", strict=True)
        # The robot's odometry on /tf composed with the laser's mount gives back the laser's poses.
        same_scans(bag.scans, log.scans[:10])
        assert bag.mount.almost_equal(MOUNT, tol=1e-12, angle_tol=1e-12)
        assert bag.mount_from == "base_link -> laser"
        assert all(s.mount == bag.mount for s in bag.scans) and not bag.upside_down
        assert bag.truth is not None and bag.truth[3].almost_equal(truth[3], tol=1e-9, angle_tol=1e-9)
        assert bag.odom_frames == ("odom", "base_link") and bag.laser_frame == "laser"


def report_of(out: Path) -> dict[str, Any]:
    return dict(json.loads((out / "report.json").read_text()))


def test_every_format_maps_to_the_carmen_map(
    tmp_path: Path, bags: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    common = ["--seed", "3", "--steps", str(STEPS), "--quiet"]
    assert main(["map", "--carmen", str(EXCERPT), *common, "--out", str(tmp_path / "carmen")]) == 0
    want = report_of(tmp_path / "carmen")
    want_traj = np.loadtxt(tmp_path / "carmen" / "trajectory.tsv")
    assert want["input"] == "carmen" and want["steps"] == STEPS and want["edges"] > 10
    first_bag: tuple[Any, ...] | None = None
    for fmt, path in bags.items():
        out = tmp_path / fmt
        args = ["map", "--rosbag", str(path), "--truth-topic", "/ground_truth", *common, "--out", str(out)]
        assert main(args) == 0, fmt
        got = report_of(out)
        assert got["input"] == "rosbag" and got["scan_topic"] == "/scan" and got["scans"] == 60
        assert got["skipped_messages"] == 0 and got["unposed_scans"] == 0
        # The same trajectory and the same map's scores. The ranges and bearings went through
        # float32 (LaserScan's types): micrometres per return, which 60 scans of SLAM (annealed
        # gates, robust weights) carry to a millimetre or so. The filter's discrete choices (which
        # of two nearly equal walls a particle keeps) can flip on that much, so the map is held to
        # its size within 10 % and its scores within 0.01, not feature for feature (at the
        # lidar-slam profile's map-update gate, 4 corners of 60 and 3 walls of 42 differ).
        traj = np.loadtxt(out / "trajectory.tsv")
        assert np.abs(traj - want_traj).max() < 0.01, fmt
        for key in ("vertices", "edges", "best_bytes", "particle_bytes"):
            assert got[key] == pytest.approx(want[key], rel=0.1), (fmt, key)
        for key in ("ate_rmse_m", "ate_max_m", "odometry_ate_rmse_m"):
            assert got[key] == pytest.approx(want[key], abs=0.005), (fmt, key)
        for key in ("map_precision", "map_coverage"):
            assert got[key] == pytest.approx(want[key], abs=0.01), (fmt, key)
        # Between bags the scans are bit for bit the same, and so are the maps.
        mine = (json.loads((out / "map.geojson").read_text())["features"], traj.tolist())
        first_bag = first_bag or mine
        assert mine == first_bag, fmt
    assert "bag         60 scans from /scan, odometry /tf" in capsys.readouterr().out


# ---------------------------------------------------------------- conventions, on hand-made bags
def test_beams_no_returns_and_a_negative_increment(tmp_path: Path) -> None:
    p = tmp_path / "beams.bag"
    with BagWriter(p, "ros1") as bag:
        bag.write("/odom", 1.0, bag.odometry(1.0, Pose(1.0, 2.0, 0.5)))
        # nan, inf, below range_min, at range_max, a return; bearings -1 .. 1 by 0.5.
        bag.write("/scan", 1.0, bag.scan(1.0, [math.nan, math.inf, 0.05, 5.0, 2.0], -1.0, 0.5, range_min=0.1,
                                         range_max=5.0))
        # A clockwise scanner: bearings 1 .. -1, read back in increasing order.
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], 1.0, -1.0, range_max=5.0))
    a, b = read_rosbag(p, strict=True).scans
    assert np.array_equal(a.angles, [-1.0, -0.5, 0.0, 0.5, 1.0])
    assert np.isinf(a.ranges[:4]).all() and a.ranges[4] == 2.0 and a.max_range == 5.0
    assert a.odom.almost_equal(Pose(1.0, 2.0, 0.5)) and a.kind == "LaserScan" and a.t == 1.0
    assert np.array_equal(b.angles, [-1.0, 0.0, 1.0]) and np.array_equal(b.ranges, [3.0, 2.0, 1.0])
    assert b.index == 1


def test_the_time_between_beams_is_read_in_the_order_the_beams_are_kept(tmp_path: Path) -> None:
    p = tmp_path / "spin.bag"
    with BagWriter(p, "ros1") as bag:
        bag.write("/odom", 1.0, bag.odometry(1.0, Pose()))
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], -1.0, 1.0, time_increment=0.01))
        # clockwise: kept in increasing bearing order, so the last beam kept came first
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], 1.0, -1.0, time_increment=0.01))
        # a driver's nonsense (a 20 s scan; not a number): taken as simultaneous
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], -1.0, 1.0, time_increment=10.0))
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], -1.0, 1.0, time_increment=math.nan))
    a, b, c, d = read_rosbag(p, strict=True).scans
    assert a.time_increment == pytest.approx(0.01) and b.time_increment == pytest.approx(-0.01)
    assert c.time_increment == 0.0 and d.time_increment == 0.0


def test_a_scan_that_took_time_has_the_odometry_at_its_last_beam(tmp_path: Path) -> None:
    """The odometry at the last beam's stamp (the scan's plus its sweep) is the de-skew's
    (``odom_end``, through the mount); past the odometry, or with simultaneous beams, none."""
    p = tmp_path / "sweep.bag"
    with BagWriter(p, "ros1") as bag:
        bag.write("/odom", 1.0, bag.odometry(1.0, Pose()))
        bag.write("/odom", 1.2, bag.odometry(1.2, Pose(0.2, 0.0, 0.4)))
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0] * 11, -1.0, 0.2, time_increment=0.01))
        bag.write("/scan", 1.0, bag.scan(1.15, [1.0] * 11, -1.0, 0.2, time_increment=0.01))  # ends at 1.25
        bag.write("/scan", 1.0, bag.scan(1.1, [1.0] * 11, -1.0, 0.2))
    a, b, c = read_rosbag(p, strict=True).scans
    assert a.sweep == pytest.approx(0.1) and a.odom_end is not None
    assert a.odom_end.almost_equal(Pose(0.1, 0.0, 0.2), tol=1e-6, angle_tol=1e-6)
    assert b.odom_end is None and b.odom.almost_equal(Pose(0.15, 0.0, 0.3), tol=1e-6, angle_tol=1e-6)
    assert c.sweep == 0.0 and c.odom_end is None


def test_odometry_is_interpolated_at_each_scan_and_scans_outside_it_are_skipped(tmp_path: Path) -> None:
    p = tmp_path / "interp"
    with BagWriter(p, "sqlite3") as bag:
        for t, pose in ((1.0, Pose(0.0, 0.0, 0.0)), (2.0, Pose(1.0, 0.0, 3.0)), (3.0, Pose(1.0, 1.0, -3.0))):
            bag.write("/odom", t, bag.odometry(t, pose))
        for t in (0.5, 1.5, 2.5, 3.0, 3.5):
            bag.write("/scan", t, bag.scan(t, [1.0], 0.0, 0.1))
    bag = read_rosbag(p)
    assert [s.t for s in bag.scans] == [1.5, 2.5, 3.0] and bag.unposed == 2
    assert bag.scans[0].odom.almost_equal(Pose(0.5, 0.0, 1.5))
    # 3.0 to -3.0 rad: the shorter turn, through pi (not through 0).
    assert bag.scans[1].odom.almost_equal(Pose(1.0, 0.5, math.pi), angle_tol=1e-9)
    assert bag.scans[2].odom.almost_equal(Pose(1.0, 1.0, -3.0))
    stamps, poses = np.array([0.0, 1.0]), [Pose(), Pose(2.0, 0.0, 0.0)]
    assert interpolate(stamps, poses, 0.25) == Pose(0.5, 0.0, 0.0) and interpolate(stamps, poses, 1.5) is None


def test_zero_stamp_takes_the_record_time(tmp_path: Path) -> None:
    p = tmp_path / "zero.bag"
    with BagWriter(p, "ros1") as bag:
        bag.write("/odom", 4.0, bag.odometry(4.0, Pose()))
        bag.write("/odom", 6.0, bag.odometry(6.0, Pose(2.0, 0.0, 0.0)))
        msg = bag.scan(0.0, [1.0], 0.0, 0.1)  # header stamp 0: a driver that does not stamp
        bag.write_raw("/scan", msg.__msgtype__, 5.0, bag.serialize(msg))
    (s,) = read_rosbag(p).scans
    assert s.t == pytest.approx(5.0) and s.odom.almost_equal(Pose(1.0, 0.0, 0.0))


def test_chained_and_upside_down_mount(tmp_path: Path) -> None:
    p = tmp_path / "mount"
    with BagWriter(p, "mcap") as bag:
        mast = Pose(0.2, 0.0, math.pi / 2)
        bag.write("/tf_static", 0.0, bag.transforms(0.0, [("base_link", "mast", mast)]))
        # The laser hangs upside down under the mast, 0.1 m along the mast's x axis.
        bag.write("/tf_static", 0.0, bag.transforms(0.0, [("mast", "laser", Pose(0.1, 0.0, 0.0))],
                                                    upside_down=True))
        bag.write("/tf", 1.0, bag.transforms(1.0, [("odom", "base_link", Pose(1.0, 0.0, 0.0))]))
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0, 2.0, 3.0], -0.5, 0.25, range_max=10.0))
    bag = read_rosbag(p, strict=True)
    (s,) = bag.scans
    assert bag.mount_from == "base_link -> mast -> laser" and bag.upside_down
    assert bag.mount.almost_equal(Pose(0.2, 0.1, math.pi / 2), tol=1e-12, angle_tol=1e-12)
    assert s.odom.almost_equal(Pose(1.2, 0.1, math.pi / 2), tol=1e-12, angle_tol=1e-12)
    # Mirrored: the beam at -0.5 rad in the laser's frame points at +0.5 rad from its x axis.
    assert np.allclose(s.angles, [-0.0, 0.25, 0.5]) and np.array_equal(s.ranges, [1.0, 2.0, 3.0][::-1])


# ---------------------------------------------------------------- choosing topics: errors
def one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2, argv
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def small_bag(path: Path, fmt: str = "ros1", *, scans: tuple[str, ...] = ("/scan",),
              odoms: tuple[str, ...] = ("/odom",), tf: bool = False) -> Path:
    """Three 3-beam scans on each of ``scans``, odometry on each of ``odoms`` and (``tf``) as
    ``odom -> base_footprint`` on ``/tf``."""
    with BagWriter(path, fmt) as bag:
        for k in range(3):
            t = 1.0 + 0.5 * k
            for topic in odoms:
                bag.write(topic, t, bag.odometry(t, Pose(0.1 * k, 0.0, 0.0)))
            if tf:
                bag.write("/tf", t, bag.transforms(t, [("odom", "base_footprint", Pose(0.1 * k, 0.0, 0.0))]))
            for topic in scans:
                bag.write(topic, t, bag.scan(t, [1.0, 2.0, 3.0], -0.5, 0.5, range_max=10.0))
    return path


def test_missing_and_unreadable_bags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    real = small_bag(tmp_path / "real.bag").read_bytes()
    (tmp_path / "junk.bag").write_text("hello, not a bag\n")
    (tmp_path / "cut.bag").write_bytes(real[: len(real) // 3])
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n garbage")
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    out = ["--out", str(tmp_path / "o"), "--quiet"]
    for name, says in (("missing.bag", "no such file"), ("junk.bag", "not a readable ROS bag"),
                       ("cut.bag", "not a readable ROS bag"), ("junk.mcap", "not a readable ROS bag"),
                       ("notes.txt", "not a ROS bag"), ("empty", "no metadata.yaml")):  # fmt: skip
        line = one_line_exit_2(["map", "--rosbag", str(tmp_path / name), *out], capsys)
        assert name in line and says in line, line
    with pytest.raises(RosbagError, match="no such file"):
        read_rosbag(tmp_path / "missing.bag")


def test_scan_topic_choice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = ["--out", str(tmp_path / "o"), "--quiet"]
    none = small_bag(tmp_path / "none.bag", scans=())
    line = one_line_exit_2(["map", "--rosbag", str(none), *out], capsys)
    assert "no sensor_msgs/LaserScan topic" in line and "/odom (nav_msgs/msg/Odometry)" in line
    two = small_bag(tmp_path / "two", "sqlite3", scans=("/scan", "/scan_rear"))
    line = one_line_exit_2(["map", "--rosbag", str(two), *out], capsys)
    assert "2 sensor_msgs/LaserScan topics (/scan, /scan_rear)" in line and "--scan-topic" in line
    line = one_line_exit_2(["map", "--rosbag", str(two), "--scan-topic", "/front", *out], capsys)
    assert "--scan-topic /front: no such topic" in line and "/scan, /scan_rear" in line
    line = one_line_exit_2(["map", "--rosbag", str(two), "--scan-topic", "/odom", *out], capsys)
    assert "/odom is a nav_msgs/Odometry, not a sensor_msgs/LaserScan" in line
    # Chosen by name (with or without its slash), the other topic is left alone.
    bag = read_rosbag(two, scan_topic="scan_rear")
    assert bag.scan_topic == "/scan_rear" and len(bag.scans) == 3 and "/scan" not in bag.messages
    assert main(["map", "--rosbag", str(two), "--scan-topic", "/scan_rear", *out, "--particles", "2"]) == 0
    assert report_of(tmp_path / "o")["scan_topic"] == "/scan_rear"
    line = one_line_exit_2(["map", "--carmen", str(EXCERPT), "--scan-topic", "/scan", *out], capsys)
    assert "--scan-topic" in line and "--rosbag" in line


def test_odometry_choice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = ["--out", str(tmp_path / "o"), "--quiet"]
    line = one_line_exit_2(["map", "--rosbag", str(small_bag(tmp_path / "bare.bag", odoms=())), *out], capsys)
    assert "no odometry" in line and "/tf" in line
    two = small_bag(tmp_path / "two.bag", odoms=("/odom", "/odom_filtered"))
    line = one_line_exit_2(["map", "--rosbag", str(two), *out], capsys)
    assert "2 nav_msgs/Odometry topics (/odom, /odom_filtered)" in line and "--odom-topic" in line
    assert read_rosbag(two, odom_topic="/odom_filtered").odometry == "/odom_filtered"
    # The truth topic is not a candidate for the odometry.
    assert read_rosbag(two, truth_topic="/odom_filtered").odometry == "/odom"
    with pytest.raises(RosbagError, match="both /odom"):
        read_rosbag(two, odom_topic="odom", truth_topic="/odom")
    # /tf, whose odometry frame pair is not the default one: the line names the pairs it has.
    tf = small_bag(tmp_path / "tf.bag", odoms=(), tf=True)
    line = one_line_exit_2(["map", "--rosbag", str(tf), *out], capsys)
    assert "no odom -> base_link transform" in line and "odom -> base_footprint" in line
    bag = read_rosbag(tf, base_frame="base_footprint")
    assert bag.odometry == "/tf" and bag.scans[2].odom.almost_equal(Pose(0.2, 0.0, 0.0))
    assert main(["map", "--rosbag", str(tf), "--base-frame", "base_footprint", "--particles", "2", *out]) == 0
    assert report_of(tmp_path / "o")["odom_frames"] == ["odom", "base_footprint"]


# ---------------------------------------------------------------- unreadable messages
def damaged_bag(path: Path, fmt: str) -> Path:
    """Eight scans with odometry; scan 3 cut short, scan 5 with one range too few for its
    angles, scan 7 with a nan angle_min, odometry message 4 cut short."""
    with BagWriter(path, fmt) as bag:
        for k in range(1, 9):
            t = float(k)
            odom = bag.serialize(bag.odometry(t, Pose(0.1 * k, 0.0, 0.0)))
            bag.write_raw("/odom", "nav_msgs/msg/Odometry", t, odom[:20] if k == 4 else odom)
            ranges = [1.0, 2.0, 3.0, 4.0, 5.0]
            if k == 5:
                msg = bag.scan(t, ranges[:3], -1.0, 0.5, angle_max=1.0)  # 3 ranges for 5 beams
            elif k == 7:
                msg = bag.scan(t, ranges, math.nan, 0.5, angle_max=1.0)
            else:
                msg = bag.scan(t, ranges, -1.0, 0.5)
            data = bag.serialize(msg)
            bag.write_raw("/scan", msg.__msgtype__, t, data[: len(data) // 2] if k == 3 else data)
    return path


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_unreadable_messages_are_skipped_and_counted_unless_strict(
    fmt: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = damaged_bag(tmp_path / ("damaged.bag" if fmt == "ros1" else "damaged"), fmt)
    bag = read_rosbag(p)
    assert [s.index for s in bag.scans] == [0, 1, 3, 5, 7]  # skipped scans keep their number
    assert bag.skipped == {"/scan": 3, "/odom": 1} and len(bag.issues) == 4
    assert bag.messages == {"/scan": 8, "/odom": 8}
    issues = sorted(bag.issues)
    assert any(f"{p}: /odom message 4: cannot be deserialised" in i for i in issues)
    assert any(f"{p}: /scan message 3: cannot be deserialised" in i for i in issues)
    assert any("/scan message 5: sensor_msgs/LaserScan has 3 ranges" in i and "5.0 beams" in i
               for i in issues)
    assert any("/scan message 7: sensor_msgs/LaserScan angle_min is not finite" in i for i in issues)
    # The odometry around the missing message 4 is interpolated over it.
    assert bag.scans[1].odom.almost_equal(Pose(0.2, 0.0, 0.0))
    assert bag.scans[2].odom.almost_equal(Pose(0.4, 0.0, 0.0))
    out = tmp_path / "o"
    assert main(["map", "--rosbag", str(p), "--out", str(out), "--quiet", "--particles", "2"]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("wiremap: skipped ") == 4 and "/scan message 5" in captured.err
    assert "skipped 4 unreadable messages" in captured.out
    report = report_of(out)
    assert report["skipped_messages"] == 4 and report["skipped_by_topic"] == {"/scan": 3, "/odom": 1}
    assert report["scans"] == report["scans_in_log"] == 5 and report["messages"] == {"/scan": 8, "/odom": 8}
    # 0.2 m apart: a dense bag, thinned by the motion filter to a scan every 0.5 m
    assert report["steps"] == 5 - report["scans_left_out"] == 2
    line = one_line_exit_2(["map", "--rosbag", str(p), "--out", str(out), "--quiet", "--strict"], capsys)
    assert "message" in line and ("/scan message 3" in line or "/odom message 4" in line), line
    with pytest.raises(RosbagError, match="message"):
        read_rosbag(p, strict=True)


def test_no_scan_has_odometry(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "late"
    with BagWriter(p, "sqlite3") as bag:
        bag.write("/odom", 10.0, bag.odometry(10.0, Pose()))
        bag.write("/odom", 11.0, bag.odometry(11.0, Pose()))
        bag.write("/scan", 1.0, bag.scan(1.0, [1.0], 0.0, 0.1))
    line = one_line_exit_2(["map", "--rosbag", str(p), "--out", str(tmp_path / "o"), "--quiet"], capsys)
    assert "no scan to map" in line and "1 without odometry at their time" in line


def test_a_bag_run_and_its_robots_read_the_same_scans(
    tmp_path: Path, excerpt: tuple[CarmenLog, list[Pose]]
) -> None:
    """`wiremap run --rosbag --truth-topic` splits the scans that have a true pose; each robot
    is given the topics (the truth's too) and reads the same list, so that its --scans I0:I1 are
    the run's (a truth that starts at scan 10 left them ten scans apart)."""
    import argparse

    from agents.commands.run import _carmen_robot_argv
    from agents.fleet.carmen_fleet import read_log
    from agents.fleet.unknown_run import carmen_world

    log, truth = excerpt
    bag = write_scans_bag(tmp_path / "late.bag", "ros1", log.scans,
                          truth=[None] * 10 + list(truth[10:]))
    args = argparse.Namespace(carmen=str(bag), bag={"scan_topic": None, "odom_topic": None,
                                                    "truth_topic": "/ground_truth"},
                              rate=20.0, seed=0, lidar_profile="lidar-slam", resolution=0.05)
    world = carmen_world(args)
    assert len(world.scans) == 50 and args.bag["odom_topic"] == "/odom"
    argv = _carmen_robot_argv(args, tmp_path, "r1", 0, (0, 25), 0.2, [], [])
    given = dict(itertools.pairwise(argv))
    robot_bag = {"scan_topic": given["--scan-topic"], "odom_topic": given["--odom-topic"],
                 "truth_topic": given["--truth-topic"]}
    mine = read_log(given["--rosbag"], robot_bag)
    assert [s.t for s in mine] == [s.t for s in world.scans]


def test_a_turtlebot3_bag_maps_with_its_beams_taken_in_their_real_order(tmp_path: Path) -> None:
    """A TurtleBot3's bag as its LDS-01 driver writes it by default: 360 beams at 5 Hz, 3.5 m,
    no return as 0.0 under ``range_min``, beams swept last bearing first while
    ``time_increment`` says first bearing first, odometry at 30 Hz (a simulated drive,
    ``write_scanner_log(..., reversed_sweep=True)``). ``wiremap map --rosbag`` pairs each scan
    with the odometry at its last beam, judges the beams' order on the turning scans (reversed),
    turns the facing check on for the 3.5 m scanner, and maps the building within 0.1 m."""
    from agents.files.carmen import read_carmen, read_truth_tsv, truth_path_for
    from agents.sim.scanner_logs import SCANNERS, write_scanner_log

    log = tmp_path / "tb3.log.gz"
    write_scanner_log("paper-small", SCANNERS["lds-01"], 4, log, duration=40.0, reversed_sweep=True)
    scans, truth = read_carmen(log), [p for _, p in read_truth_tsv(truth_path_for(log))]
    stamps, odom = np.array([s.t for s in scans]), [s.odom for s in scans]
    bag_path = tmp_path / "tb3.bag"
    with BagWriter(bag_path, "ros1") as bag:
        for t in np.arange(scans[0].t, scans[-1].t, 1.0 / 30.0):
            pose = interpolate(stamps, odom, float(t))
            assert pose is not None
            bag.write("/odom", float(t), bag.odometry(float(t), pose))
        for s, true in zip(scans, truth, strict=True):
            a = np.asarray(s.angles)
            r = np.where(np.isfinite(s.ranges) & (s.ranges < s.max_range), s.ranges, 0.0)
            bag.write("/scan", s.t, bag.scan(s.t, r, float(a[0]), float(a[1] - a[0]), range_min=0.12,
                                             range_max=3.5, time_increment=s.time_increment))
            bag.write("/ground_truth", s.t, bag.odometry(s.t, true, frame="map"))
    read = read_rosbag(bag_path, truth_topic="/ground_truth").scans
    assert sum(s.odom_end is not None for s in read) == len(read) - 1  # the last: no odometry after it
    out = tmp_path / "out"
    assert main(["map", "--rosbag", str(bag_path), "--truth-topic", "/ground_truth", "--quiet",
                 "--out", str(out)]) == 0
    rep = report_of(out)
    assert rep["sweep_reversed"] is True and rep["sweep_check_gain"] > 0.01 and rep["scanner_range_m"] == 3.5
    assert rep["ate_rmse_m"] < 0.1 and rep["map_precision"] > 0.95, rep
