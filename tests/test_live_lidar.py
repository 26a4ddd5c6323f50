"""A robot's own lidar, live: ROS 2 ``LaserScan`` and ``Odometry`` (CDR, as zenoh-bridge-ros2dds
or rmw_zenoh put them on Zenoh) made from the committed CARMEN excerpt.

* :class:`agents.mapping_run.LiveInputs` gives, scan by scan, the inputs ``carmen_inputs``
  gives for the whole log (the online SLAM profile; calibration held, then streamed);
* :class:`agents.fleet.live_lidar.LiveLidar` poses each scan by the odometry interpolated at its
  stamp, as the bag reader does, and counts and drops what it cannot use;
* ``wiremap robot --scan-key ... --odom-key ...`` over a real router maps what it is sent, the
  same map as the offline stream, and survives garbage on both keys; its flags' errors are one
  line, exit 2.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents import mapping_run as mr
from agents.files.carmen import read_carmen_log
from agents.fleet.live_lidar import LiveLidar, live_filter, parse_mount
from mapping.filter import WireframeFilter
from mapping.se2 import Pose, wrap_angle
from tests.rosbag_util import MessageMaker

DATA = Path(__file__).parent / "data"
EXCERPT = DATA / "freiburg-101-head.log.gz"
MOUNT = Pose(0.12, -0.03, 0.05)
CALIBRATION = 20  # scans held for the calibrations here (the profile's 100 exceed the excerpt)


@pytest.fixture(scope="module")
def scans() -> list[Any]:
    log = read_carmen_log(EXCERPT, strict=True)
    return log.scans


def profile(calibration: int = CALIBRATION) -> tuple[dict[str, Any], Any, Any]:
    settings, extract, frontend = mr.split_profile(mr.lidar_profile("lidar-slam-online"))
    return settings, extract, replace(frontend, calibration_scans=calibration)


def messages(scans: list[Any], mount: Pose | None = None) -> list[tuple[str, bytes]]:
    """``("odom" | "scan", CDR bytes)`` in publishing order: per scan, the robot's odometry a
    little before and at the scan's stamp (the robot's pose: the laser's composed with ``mount``
    inverted), then the scan."""
    mk = MessageMaker()
    unmount = (mount or Pose()).inverse()
    out: list[tuple[str, bytes]] = []
    for k, s in enumerate(scans):
        robot = s.odom.compose(unmount)
        if k:
            prev = scans[k - 1].odom.compose(unmount)
            mid = Pose(0.5 * (prev.x + robot.x), 0.5 * (prev.y + robot.y),
                       prev.theta + 0.5 * wrap_angle(robot.theta - prev.theta))
            out.append(("odom", mk.serialize(mk.odometry(0.5 * (scans[k - 1].t + s.t), mid))))
        out.append(("odom", mk.serialize(mk.odometry(s.t, robot))))
        a = np.asarray(s.angles)
        inc = float(a[-1] - a[0]) / (a.size - 1)
        out.append(("scan", mk.serialize(mk.scan(s.t, s.ranges, float(a[0]), inc, angle_max=float(a[-1]),
                                                  range_max=s.max_range, time_increment=s.time_increment))))
    return out


def posed_scans(src: LiveLidar, scans: list[Any], mount: Pose) -> list[Any]:
    """``scans`` sent to ``src`` as :func:`messages`, and every scan it posed, taken as it came."""
    out = []
    for kind, data in messages(scans, mount):
        (src.on_scan if kind == "scan" else src.on_odometry)(data)
        while (ls := src.take(0.0)) is not None:
            out.append(ls)
    return out


# ---------------------------------------------------------------- the stream is the log
def test_live_inputs_are_the_logs_inputs_scan_for_scan(scans: list[Any]) -> None:
    """Held for the calibration, then one by one: every input (time, odometry, points, corner
    scan) is the one carmen_inputs makes of the whole log, bit for bit; nothing comes out while
    calibrating; a stream that ends before the calibration is complete still maps its scans."""
    _, extract, frontend = profile()
    want = list(mr.carmen_inputs(scans, max_range=20.0, extract=extract, frontend=frontend))
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)
    got: list[Any] = []
    for k, ls in enumerate(scans):
        out = live.add(ls)
        assert live.calibrating == (k + 1 < CALIBRATION)
        assert len(out) == (CALIBRATION if k + 1 == CALIBRATION else 0 if k + 1 < CALIBRATION else 1)
        got += out
    assert live.finish() == []
    assert len(got) == len(want) == len(scans)
    for g, w in zip(got, want):
        assert g.t == w.t and g.odometry == w.odometry
        assert (g.warp is None) == (w.warp is None)  # the graph's moves too (follow_graph)
        if g.warp is not None:
            assert all(np.array_equal(a, b) for a, b in zip(g.warp, w.warp, strict=True))
        assert np.array_equal(g.points, w.points)
        assert np.array_equal(g.scan.points, w.scan.points) and np.array_equal(g.scan.edges, w.scan.edges)
    short = mr.LiveInputs(max_range=20.0, extract=extract, frontend=profile(100)[2])
    assert sum(len(short.add(ls)) for ls in scans[:30]) == 0
    rest = short.finish()
    want30 = list(mr.carmen_inputs(scans[:30], max_range=20.0, extract=extract, frontend=profile(100)[2]))
    assert [r.odometry for r in rest] == [w.odometry for w in want30]


def test_the_motion_filter_takes_a_scan_per_distance_or_turn(scans: list[Any]) -> None:
    """Scans 5 cm apart: one in ten is taken at 0.49 m (0.5 m a step's rounding away); a turn of
    12 degrees on the spot is taken at 10; thresholds of 0 take every scan; negative thresholds
    are refused."""
    _, extract, frontend = profile(5)
    base = scans[0]
    moved = [replace(base, t=0.1 * k, odom=base.odom.compose(Pose(0.05 * k, 0.0, 0.0))) for k in range(31)]
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend, min_travel=0.49,
                         min_turn=math.radians(10.0))
    taken = sum(len(live.add(ls)) for ls in moved) + len(live.finish())
    assert (taken, live.skipped) == (4, 27)  # at 0, 0.5, 1.0, 1.5 m
    turned = replace(base, t=9.0, odom=moved[-1].odom.compose(Pose(0.0, 0.0, math.radians(12.0))))
    assert len(live.add(turned)) == 1
    every = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)
    assert sum(len(every.add(ls)) for ls in moved) == len(moved) and every.skipped == 0
    with pytest.raises(ValueError, match=">= 0"):
        mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend, min_travel=-1.0)


def test_a_live_scan_that_took_time_is_turned_back_by_the_turn_since_the_one_before(scans: list[Any]) -> None:
    """The live robot de-skews at the wheels' velocity from the scan before (it has no scan after
    yet): turning on the spot at 2 rad/s, each beam 1 ms after the one before it is turned 2
    mrad more."""
    _, extract, frontend = profile(5)  # both scans held for the calibration
    base = replace(scans[0], time_increment=0.001)
    turning = [replace(base, t=0.1 * k, odom=base.odom.compose(Pose(0.0, 0.0, 0.2 * k))) for k in range(2)]
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)
    for ls in turning:
        live.add(ls)
    held = live._held  # the calibration's scans, as the mapper will get them
    assert np.array_equal(held[0].angles, base.angles)  # no scan before it: no turn known
    assert held[1].angles[7] - base.angles[7] == pytest.approx(7 * 0.001 * 2.0)
    plain = mr.LiveInputs(max_range=20.0, extract=extract, frontend=replace(frontend, deskew=False))
    for ls in turning:
        plain.add(ls)
    assert np.array_equal(plain._held[1].angles, base.angles)


def test_a_live_scan_waits_for_the_odometry_past_its_last_beam_and_is_de_skewed_over_its_sweep() -> None:
    """A 5 Hz spinning lidar (beams 1 ms apart, a 0.1 s sweep) on a robot that stands, then turns
    at 1 rad/s: the scan waits until the odometry passes its last beam, carries the laser's pose
    there (``odom_end``), and is turned back by the turn over its own sweep, which the velocity
    since the scan before (none: it stood) would miss. With the odometry silent for ``max_wait``
    the scan goes on without it."""
    from mapping.lidar_frontend import deskew

    mk = MessageMaker()
    now = [0.0]
    src = LiveLidar(mount=MOUNT, max_wait=0.5, clock=lambda: now[0])
    unmount = MOUNT.inverse()

    def scan(t: float) -> bytes:
        return mk.serialize(mk.scan(t, np.full(101, 2.0), -0.5, 0.01, time_increment=0.001))

    src.on_odometry(mk.serialize(mk.odometry(10.0, Pose())))
    src.on_scan(scan(10.0))
    assert src.take(0.0) is None  # its last beam is at 10.1 s: no odometry there yet
    src.on_odometry(mk.serialize(mk.odometry(10.05, Pose())))
    assert src.take(0.0) is None
    # stood until 10.05 s, then turned at 1.2 rad/s: 0.06 rad over the sweep (10.0-10.1 s),
    # all of it in its second half (the beams are float32: 1e-6 tolerances)
    src.on_odometry(mk.serialize(mk.odometry(10.35, Pose(0.0, 0.0, 0.36))))
    first = src.take(0.0)
    assert first is not None and first.odom_end is not None
    assert first.odom_end.almost_equal(Pose(0.0, 0.0, 0.06).compose(MOUNT), tol=1e-6, angle_tol=1e-6)
    assert mr.sweep_velocity(first)[2] == pytest.approx(0.6, rel=1e-6)
    _, extract, frontend = profile(5)
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)
    live.add(first)
    held = live._held[0]  # no scan before it: only its sweep's odometry knew of the turn
    want = deskew(first.ranges, first.angles, first.time_increment, mr.sweep_velocity(first))
    assert np.array_equal(held.angles, want[1]) and np.array_equal(held.ranges, want[0])
    assert held.angles[-1] - first.angles[-1] > 0.9 * 0.1 * 0.6
    src.on_scan(scan(10.2))  # its last beam at 10.3 s: the odometry is there
    second = src.take(0.0)
    assert second is not None and second.odom_end is not None
    assert second.odom_end.compose(unmount).theta == pytest.approx(0.3, abs=1e-6)
    src.on_scan(scan(10.4))  # past the odometry: waits, then goes on without it
    assert src.take(0.0) is None
    src.on_odometry(mk.serialize(mk.odometry(10.45, Pose(0.0, 0.0, 0.48))))
    assert src.take(0.0) is None
    now[0] = 0.6
    late = src.take(0.0)
    assert late is not None and late.odom_end is None and src.counts.unposed == 0
    assert (src.counts.posed, src.counts.swept) == (3, 2)


def test_live_inputs_refuse_a_front_end_that_needs_the_whole_log() -> None:
    _, extract, frontend = mr.split_profile(mr.lidar_profile("lidar-slam"))
    with pytest.raises(ValueError, match="scan by scan"):
        mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)
    _, extract, frontend = profile(0)
    with pytest.raises(ValueError, match="calibration_scans"):
        mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend)


# ---------------------------------------------------------------- pairing and bad payloads
def test_scans_are_posed_at_their_stamp_as_the_bag_reader_does(scans: list[Any]) -> None:
    """Each scan gets the odometry at its stamp through the mount; times count from the first
    scan; ranges and bearings are the log's to float32 precision."""
    src = LiveLidar(mount=MOUNT)
    got = posed_scans(src, scans, MOUNT)
    assert len(got) == len(scans) and src.counts.posed == len(scans)
    for g, c in zip(got, scans):
        assert g.t == pytest.approx(c.t - scans[0].t, abs=1e-6)
        assert g.odom.almost_equal(c.odom, tol=1e-6, angle_tol=1e-6)
        assert g.mount == MOUNT
        hit = np.isfinite(c.ranges)
        assert np.array_equal(np.isfinite(g.ranges), hit)
        assert np.allclose(g.ranges[hit], c.ranges[hit], rtol=1e-6)
        assert np.allclose(g.angles, c.angles, atol=1e-6)
    c = src.counts
    assert (c.bad_scans, c.bad_odometry, c.unposed, c.out_of_order, c.behind) == (0, 0, 0, 0, 0)


def test_what_cannot_be_used_is_counted_and_dropped(scans: list[Any]) -> None:
    """Garbage, a zero stamp, a scan whose fields disagree, a scan or odometry out of order, a
    scan older than the odometry kept, a scan that waits while odometry keeps coming and goes once
    the odometry has been silent for max_wait (fake clock), a backlog past its bound: each is
    counted with its reason and dropped; the good scans still come."""
    mk = MessageMaker()
    now = [0.0]
    src = LiveLidar(max_wait=0.5, max_backlog=3, clock=lambda: now[0])
    src.on_scan(b"\x00\x01\x00\x00garbage")
    src.on_odometry(b"")
    assert (src.counts.bad_scans, src.counts.bad_odometry) == (1, 1)
    assert "deserialised" in src.counts.last_issue
    src.on_scan(mk.serialize(mk.scan(0.0, [1.0, 2.0], 0.0, 0.1)))
    assert src.counts.bad_scans == 2 and "zero stamp" in src.counts.last_issue
    src.on_scan(mk.serialize(mk.scan(5.0, [1.0, 2.0, 3.0], 0.0, 0.1, angle_max=2.0)))
    assert src.counts.bad_scans == 3 and "3 ranges" in src.counts.last_issue
    src.on_odometry(mk.serialize(mk.odometry(10.0, Pose(0.0, 0.0, 0.0))))
    src.on_odometry(mk.serialize(mk.odometry(9.0, Pose(0.0, 0.0, 0.0))))
    assert src.counts.out_of_order == 1
    src.on_scan(mk.serialize(mk.scan(9.5, [1.0, 2.0], 0.0, 0.1)))  # before the odometry kept
    assert src.counts.unposed == 1
    src.on_scan(mk.serialize(mk.scan(10.5, [1.0, 2.0], 0.0, 0.1)))  # waits for odometry
    src.on_scan(mk.serialize(mk.scan(10.4, [1.0, 2.0], 0.0, 0.1)))  # out of order
    assert src.counts.out_of_order == 2 and src.take(0.0) is None
    now[0] = 0.4
    src.on_odometry(mk.serialize(mk.odometry(10.2, Pose(0.0, 0.0, 0.0))))  # odometry still coming
    now[0] = 0.8
    assert src.take(0.0) is None and src.counts.unposed == 1  # waited 0.8 s, odometry 0.4 s ago
    now[0] = 1.0  # the odometry has been silent for 0.6 s
    assert src.take(0.0) is None and src.counts.unposed == 2
    assert "no odometry for 0.5 s" in src.counts.last_issue
    for k in range(5):  # five posed scans, a backlog of three
        src.on_odometry(mk.serialize(mk.odometry(11.0 + k, Pose(0.1 * k, 0.0, 0.0))))
        src.on_scan(mk.serialize(mk.scan(11.0 + k, [1.0, 2.0], 0.0, 0.1)))
    assert src.counts.posed == 5 and src.counts.behind == 2
    kept = [src.take(0.0) for _ in range(3)]
    assert [round(ls.odom.x, 6) for ls in kept if ls is not None] == [0.2, 0.3, 0.4]
    assert src.take(0.0) is None


def test_hostile_values_are_refused_and_a_stream_out_of_order_starts_again(scans: list[Any]) -> None:
    """Valid CDR with hostile values: an odometry pose 1.7e308 m out and a stamp with 4e9
    nanoseconds are refused; one odometry message from the future holds the odometry back for
    RESET_AFTER messages, then the stream starts again and scans are posed again; the same for a
    scan from the future (which goes with the reset instead of holding the scans behind it)."""
    from agents.fleet.live_lidar import RESET_AFTER

    mk = MessageMaker()
    now = [0.0]
    src = LiveLidar(clock=lambda: now[0])
    src.on_odometry(mk.serialize(mk.odometry(10.0, Pose(1.7e308, 0.0, 0.0))))
    assert src.counts.bad_odometry == 1 and "from its frame's origin" in src.counts.last_issue
    bad_ns = mk.scan(10.0, [1.0, 2.0], 0.0, 0.1)
    bad_ns.header.stamp.nanosec = 4_000_000_000
    src.on_scan(mk.serialize(bad_ns))
    assert src.counts.bad_scans == 1 and "nanoseconds" in src.counts.last_issue
    src.on_odometry(mk.serialize(mk.odometry(2e9, Pose())))  # from the future
    t = 10.0
    for _ in range(RESET_AFTER + 3):
        t += 0.1
        src.on_odometry(mk.serialize(mk.odometry(t, Pose(t, 0.0, 0.0))))
        src.on_scan(mk.serialize(mk.scan(t, [1.0, 2.0], 0.0, 0.1)))
    assert src.counts.out_of_order == RESET_AFTER - 1 and src.counts.resets == 1
    assert src.counts.posed >= 3
    posed = src.counts.posed
    src.on_scan(mk.serialize(mk.scan(2e9, [1.0, 2.0], 0.0, 0.1)))  # a scan from the future
    for _ in range(RESET_AFTER + 3):
        t += 0.1
        src.on_odometry(mk.serialize(mk.odometry(t, Pose(t, 0.0, 0.0))))
        src.on_scan(mk.serialize(mk.scan(t, [1.0, 2.0], 0.0, 0.1)))
    assert src.counts.resets == 2 and src.counts.posed >= posed + 3


def test_the_mapper_yields_while_it_holds_or_skips_scans(scans: list[Any]) -> None:
    """live_steps gives the agent a step (None) for every scan held for the calibration or left
    out by the motion filter, so that a parked robot's agent keeps publishing: one next() per
    scan, none waiting for more; once calibrated, the held scans come out as steps."""
    import types

    from agents.fleet.live_lidar import live_steps

    src = LiveLidar()
    posed = posed_scans(src, scans, Pose())
    for ls in posed:  # the source hands them out again, one per take()
        src._ready.append(ls)
    opts = types.SimpleNamespace(lidar_profile="lidar-slam-online", particles=2, threshold=0.2, seed=0,
                                 filter_overrides={}, extra={"calibration_scans": 30})
    stop = threading.Event()
    steps = live_steps(opts, src, stop)
    t0 = time.monotonic()
    first = [next(steps) for _ in range(29)]
    assert first == [None] * 29 and time.monotonic() - t0 < 20.0
    made = [next(steps) for _ in range(30)]  # the 30th scan releases all thirty
    assert all(m is not None for m in made) and [m.index for m in made] == list(range(30))
    stop.set()
    rest = list(steps)
    assert all(r is None or r.index >= 30 for r in rest)


def test_a_take_waits_for_a_scan_from_another_thread(scans: list[Any]) -> None:
    src = LiveLidar()
    msgs = messages(scans[:2])

    def feed() -> None:
        time.sleep(0.1)
        for kind, data in msgs:
            (src.on_scan if kind == "scan" else src.on_odometry)(data)

    th = threading.Thread(target=feed)
    th.start()
    t0 = time.monotonic()
    first = src.take(5.0)
    th.join()
    assert first is not None and first.t == 0.0 and 0.05 < time.monotonic() - t0 < 4.0
    assert src.take(0.0) is not None


def test_parse_mount() -> None:
    assert parse_mount("0.1,-0.2") == Pose(0.1, -0.2, 0.0)
    assert parse_mount("0.1,-0.2,0.5") == Pose(0.1, -0.2, 0.5)
    for bad in ("x", "1", "1,2,3,4", "1,nan"):
        with pytest.raises(ValueError, match="laser-mount"):
            parse_mount(bad)


# ---------------------------------------------------------------- the agent over a real router
def offline_map(
    scans: list[Any], mount: Pose, particles: int, seed: int, min_travel: float, min_turn_deg: float
) -> tuple[Any, int, int]:
    """The map the live robot should end with, the scans it maps and those its motion filter
    drops: the posed scans through LiveInputs (``CALIBRATION`` scans held) and the filter, as
    :func:`agents.fleet.live_lidar.live_steps` runs them."""
    posed = posed_scans(LiveLidar(mount=mount), scans, mount)
    settings, extract, frontend = profile()
    live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=frontend, min_travel=min_travel,
                         min_turn=math.radians(min_turn_deg))
    cfg = mr.filter_config_for(particles, 0.2, min(20.0, posed[0].max_range),
                               fov=mr.scan_fov(posed[0].angles), overrides=settings)
    filt = WireframeFilter(cfg, mr.seeds_for(seed)["filter"], initial_pose=Pose.identity())
    mapped = 0
    for ls in [*posed, None]:
        for _ in mr.run_filter(live.add(ls) if ls is not None else live.finish(), filt):
            mapped += 1
    return filt.best, mapped, live.skipped


@pytest.mark.fleet
def test_a_live_robot_maps_what_its_lidar_sends(scans: list[Any], tmp_path: Path) -> None:
    """A ``wiremap robot`` on a live lidar, over a real router: the test publishes the excerpt's
    odometry and scans as CDR (with garbage on both keys), the robot maps every scan and its
    last map is the offline stream's; its status counts the garbage; it stops cleanly."""
    import zenoh

    from agents.fleet.bus import FleetKeys, decode_pose
    from tests.fleet_util import client, in_process_router, log_text, spawn, stop_process, wait_until
    from wire_codec import decode

    keys = FleetKeys("t")
    latest: dict[str, Any] = {}
    lock = threading.Lock()

    def on_map(sample: Any) -> None:
        with lock:
            latest["map"] = decode(sample.payload.to_bytes())

    def on_pose(sample: Any) -> None:
        with lock:
            latest["status"] = decode_pose(sample.payload.to_bytes())["status"]

    status_file = tmp_path / "status.json"
    with in_process_router() as ep, client(ep) as s:
        subs = [s.declare_subscriber(keys.robot_map("live1"), on_map),
                s.declare_subscriber(keys.robot_pose("live1"), on_pose)]
        alive = s.liveliness().declare_subscriber(
            keys.alive("live1"), lambda _s: latest.setdefault("alive", 1), history=True)
        proc = spawn(["robot", "--id", "live1", "--scan-key", "lidar/scan",
                      "--odom-key", "lidar/odom", "--laser-mount", "0.12,-0.03,0.05", "--particles", "3",
                      "--seed", "2", "--calibration-scans", str(CALIBRATION), "--min-travel", "1.02",
                      "--min-turn", "30", "--connect", ep, "--fleet", "t",
                      "--status-file", str(status_file)],
                     tmp_path / "robot.log")
        try:
            wait_until(lambda: "alive" in latest, 60, "the robot's token")
            time.sleep(0.3)
            s.put("lidar/scan", b"not a scan")
            s.put("lidar/odom", b"\x00\x01\x00\x00")
            for kind, data in messages(scans, MOUNT):
                s.put(f"lidar/{kind}", data, congestion_control=zenoh.CongestionControl.BLOCK)
                time.sleep(0.01)
            want, mapped, still = offline_map(scans, MOUNT, 3, 2, min_travel=1.02, min_turn_deg=30.0)
            assert 0 < still < len(scans) // 2 and mapped == len(scans) - still
            wait_until(lambda: latest.get("status", {}).get("step") == mapped, 120,
                       "every scan mapped", step=0.2)
            wait_until(lambda: latest["map"].wireframe.n_edges == want.n_edges, 10, "the last map")
            assert stop_process(proc, timeout=20) == 0, log_text(proc, tmp_path / "robot.log")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            for sub in subs:
                sub.undeclare()
            alive.undeclare()
    got = latest["map"]
    assert got.meta.get("origin_unknown") is True and got.frame == "odom/live1"
    assert np.allclose(np.sort(got.wireframe.points, axis=0), np.sort(want.points, axis=0), atol=0.026)
    status = json.loads(status_file.read_text())
    assert status["step"] == mapped
    live = status["live"]
    assert live["posed"] == len(scans) and live["still"] == still
    assert live["bad_scans"] == 1 and live["bad_odometry"] == 1
    assert live["unposed"] == 0 and live["behind"] == 0
    # every scan mapped is a node of the SLAM's graph, or posed on an old one
    assert live["graph"] + live["revisits"] == mapped and live["loops"] >= live["settled"] >= 0
    assert "refined" in live  # the online refinement's count (the excerpt has no revisit to refine)
    text = (tmp_path / "robot.log").read_text()
    assert "live lidar: scans on lidar/scan" in text and "bad_scans 1" in text


@pytest.mark.parametrize(("argv", "needle"), [
    (["--scan-key", "scan"], "both --scan-key and --odom-key"),
    (["--scan-key", "scan", "--odom-key", "odom", "--world", "tiny"], "--rosbag or --world"),
    (["--scan-key", "scan", "--odom-key", "odom", "--lidar-profile", "lidar-slam"], "lidar-slam-online"),
    (["--scan-key", "a//b", "--odom-key", "odom"], "not a Zenoh key expression"),
    (["--scan-key", "scan", "--odom-key", "odom", "--laser-mount", "1,x"], "laser-mount"),
    (["--world", "tiny", "--start", "1,1", "--laser-mount", "0,0"], "for a live lidar"),
    (["--scan-key", "scan", "--odom-key", "odom", "--calibration-scans", "0"], "calibration-scans"),
    (["--scan-key", "scan", "--odom-key", "odom", "--calibration-scans", "1000000"], "calibration-scans"),
    (["--scan-key", "scan", "--odom-key", "odom", "--scans", "0:10"], "--scans is for"),
    (["--scan-key", "scan", "--odom-key", "odom", "--rate", "10"], "--rate is for"),
    (["--scan-key", "robot/**", "--odom-key", "robot/odom"], "overlap"),
    (["--scan-key", "scan", "--odom-key", "odom", "--laser-mount", "1e308,0"], "from the robot's base"),
    (["--scan-key", "scan", "--odom-key", "odom", "--laser-mount", "0,0", "--tf-key", "tf_static"],
     "not both"),
    (["--scan-key", "scan", "--odom-key", "odom", "--base-frame", "base"], "for --tf-key"),
    (["--scan-key", "scan", "--odom-key", "odom", "--tf-key", "**"], "overlap"),
    (["--world", "tiny", "--start", "1,1", "--tf-key", "tf_static"], "for a live lidar"),
])
def test_live_flags_errors_are_one_line(
    argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from agents.cli import main

    assert main(["robot", "--id", "r1", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err


# ---------------------------------------------------------------- wiremap play
def test_played_messages_read_back_as_the_logs_scans(scans: list[Any]) -> None:
    """What `wiremap play` sends (agents.files.ros_messages) for scans with a laser mount, read by
    a live robot's source given that mount: the log's scans (the laser's poses to 1e-6: the base's
    odometry composed with the mount), ranges to float32 precision."""
    from agents.files.ros_messages import Ros2Messages

    make = Ros2Messages()
    mounted = [replace(ls, mount=MOUNT) for ls in scans]  # the laser off the base: a mount to undo
    src = LiveLidar(mount=MOUNT)
    got = []
    for ls in mounted:
        odom, scan = make.of_scan(ls)
        src.on_odometry(odom)
        src.on_scan(scan)
        while (p := src.take(0.0)) is not None:
            got.append(p)
    assert len(got) == len(scans) and src.counts.bad_scans == src.counts.bad_odometry == 0
    for g, c in zip(got, scans):
        assert g.odom.almost_equal(c.odom, tol=1e-6, angle_tol=1e-6)
        hit = np.isfinite(c.ranges)
        assert np.array_equal(np.isfinite(g.ranges), hit)
        assert np.allclose(g.ranges[hit], c.ranges[hit], rtol=1e-6)
        assert np.allclose(g.angles, c.angles, atol=1e-6)


def test_play_times_scans_a_live_robot_can_pair(scans: list[Any]) -> None:
    """A log's increasing times are kept; times from zero are shifted to start at 1 s (a zero
    stamp means none); times that do not increase (orebro, belgioioso stamp every scan alike) are
    replaced by one every 1 / rate s."""
    from agents.commands.play import live_times

    assert live_times(scans, 10.0) == scans
    from_zero = live_times([replace(ls, t=ls.t - scans[0].t) for ls in scans], 10.0)
    assert from_zero[0].t == 1.0 and from_zero[-1].t == pytest.approx(1.0 + scans[-1].t - scans[0].t)
    alike = live_times([replace(ls, t=5.0) for ls in scans], 20.0)
    assert [ls.t for ls in alike] == [1.0 + k / 20.0 for k in range(len(scans))]


@pytest.mark.fleet
def test_wiremap_play_feeds_a_live_robot(scans: list[Any], tmp_path: Path) -> None:
    """`wiremap play --carmen LOG` over a real router into `wiremap robot --scan-key --odom-key`:
    the robot finds the laser's mount on the latched transforms play sends (`--tf-key`), poses
    and maps every scan of the excerpt (motion filter off), and play says what it sent and exits
    0. The excerpt is played as a scanner whose beams take 0.1 s: every scan but the last (no
    odometry after it) is posed with the odometry at its last beam, for its de-skew."""
    from agents.files.carmen import flaser_angles, write_carmen
    from tests.fleet_util import in_process_router, log_text, spawn, stop_process, wait_until

    swept = tmp_path / "swept.log"  # (the writer's bearings: -90 to 90 degrees, the excerpt's to 89.5)
    write_carmen(swept, [replace(ls, angles=flaser_angles(ls.angles.size, math.pi)) for ls in scans],
                 fov=math.pi, max_range=scans[0].max_range, time_increment=0.1 / 359)
    status_file = tmp_path / "status.json"
    robot_log, play_log = tmp_path / "robot.log", tmp_path / "play.log"
    with in_process_router() as ep:
        robot = spawn(["robot", "--id", "p1", "--scan-key", "pl/scan", "--odom-key", "pl/odom",
                       "--tf-key", "pl/tf_static", "--calibration-scans", "20", "--min-travel", "0",
                       "--min-turn", "0",
                       "--particles", "2", "--connect", ep, "--fleet", "t",
                       "--status-file", str(status_file)], robot_log)
        play = None
        try:
            wait_until(lambda: "on the bus" in robot_log.read_text(), 60, "the robot on the bus")
            play = spawn(["play", "--carmen", str(swept), "--speed", "200", "--scan-key", "pl/scan",
                          "--odom-key", "pl/odom", "--tf-key", "pl/tf_static", "--connect", ep,
                          "--fleet", "t"], play_log)
            wait_until(lambda: play.poll() is not None, 60, "play to finish")
            assert play.returncode == 0, log_text(play, play_log)
            assert "sent 60 scans in 1 full pass" in play_log.read_text()
            time.sleep(3)  # what was sent is mapped
            assert stop_process(robot, timeout=20) == 0, log_text(robot, robot_log)
        finally:
            for p in (robot, play):
                if p is not None:
                    stop_process(p, timeout=5)
    status = json.loads(status_file.read_text())
    assert status["live"]["posed"] == 60 and status["step"] == 60, status["live"]
    assert status["live"]["swept"] == 59, status["live"]
    assert status["live"]["sweep"].startswith("as declared, not judged"), status["live"]  # few turning scans
    assert status["live"]["mount"] == "base_link -> laser" and status["live"]["transforms"] == 1, status


@pytest.mark.parametrize(("argv", "needle"), [
    (["--carmen", "{log}", "--scan-key", "a/**", "--odom-key", "a/odom"], "overlap"),
    (["--carmen", "{missing}", "--scan-key", "scan", "--odom-key", "odom"], "no such file"),
    (["--carmen", "{log}", "--scan-key", "scan", "--odom-key", "odom", "--scans", "5:2"], "--scans"),
    (["--carmen", "{log}", "--scan-key", "scan", "--odom-key", "odom", "--speed", "0"], "--speed"),
    (["--carmen", "{log}", "--scan-key", "scan", "--odom-key", "odom", "--scan-topic", "/s"], "for --rosbag"),
    (["--carmen", "{log}", "--scan-key", "scan"], "--odom-key"),
    (["--carmen", "{log}", "--scan-key", "scan", "--odom-key", "odom", "--tf-key", "scan"], "overlap"),
])
def test_play_errors_are_one_line(argv: list[str], needle: str, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    from agents.cli import main

    argv = [a.replace("{log}", str(EXCERPT)).replace("{missing}", str(tmp_path / "none.log")) for a in argv]
    try:
        code = main(["play", *argv])
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err


def test_shift_drives_the_log_forward_and_back(scans: list[Any]) -> None:
    """``bench live``'s shift: forward, back, forward, the log's own scans, times increasing."""
    from agents.bench.live import shift

    few = scans[:4]
    got = shift(few, 3)
    assert [k for k, _ in got] == [0, 1, 2, 3, 3, 2, 1, 0, 0, 1, 2, 3]
    assert all(np.array_equal(ls.ranges, few[k].ranges) and ls.odom == few[k].odom for k, ls in got)
    times = [ls.t for _, ls in got]
    assert times == sorted(times) and len(set(times)) == len(times)


def test_bench_live_on_the_excerpt(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """``wiremap bench live LOG --passes 3 --json``: every scan of three passes fed, a row per
    pass, the map scored in the truth's frame (a precision near the offline map's, not the
    near-zero of a map left in the robot's frame), the RSS measured; the online profile settles
    loops. A bad flag is a one-line error."""
    from agents.cli import main

    assert main(["bench", "live", str(EXCERPT), "--passes", "3", "--calibration-scans", str(CALIBRATION),
                 "--set", "slam.loop_min_travel=12", "--out", str(tmp_path), "--json", "--quiet"]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == ["freiburg-101-head-pass-1.png", "freiburg-101-head-pass-3.png"]
    assert (tmp_path / pngs[0]).read_bytes().startswith(b"\x89PNG")
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    r = last["logs"]["freiburg-101-head"]
    assert r["scans_fed"] == 3 * r["scans"] == 180
    assert 0.8 * r["scans_fed"] < r["scans_mapped"] <= r["scans_fed"]
    assert [p["pass"] for p in r["by_pass"]] == [1, 2, 3]
    assert sum(p["scans_mapped"] for p in r["by_pass"]) == r["scans_mapped"]
    assert r["map_precision_first"] > 0.8 and r["map_precision_last"] > 0.8, r
    assert r["ate_rmse_m"] < 0.3, r
    assert r["rss_mb_last"] > 50 and r["ms_per_scan_first"] > 0
    moved = [p["moved_after_mapping_m_p90"] for p in r["by_pass"]]
    assert all(0 <= m < 1.0 for m in moved) and r["moved_after_mapping_m_p90_first"] == moved[0]
    assert last["settings"]["slam.loop_settled_xy"] == 0.02
    assert last["settings"]["slam.loop_min_travel"] == 12.0  # a --set value as a number, not its text
    # every scan mapped is a node of the SLAM's graph or posed on an old one (the later passes
    # drive where the graph holds two visits: most of the third pass's scans are no node)
    mapped = list(itertools.accumulate(p["scans_mapped"] for p in r["by_pass"]))
    revisits = list(itertools.accumulate(p["revisits"] for p in r["by_pass"]))
    assert [p["graph"] + v for p, v in zip(r["by_pass"], revisits, strict=True)] == mapped
    assert (r["graph_first"], r["graph_last"]) == (r["by_pass"][0]["graph"], r["by_pass"][-1]["graph"])
    assert r["revisits"] == revisits[-1] and r["by_pass"][0]["revisits"] == 0
    assert r["by_pass"][2]["revisits"] > r["by_pass"][2]["scans_mapped"] / 2
    # the online refinement matched nodes again while the graph grew (the profile's setting)
    assert last["settings"]["slam.refine_online_nodes"] > 0
    assert r["refined"] == sum(p["refined"] for p in r["by_pass"]) and r["by_pass"][1]["refined"] > 0
    assert last["settings"]["frontend.calibration_scans"] == CALIBRATION
    with pytest.raises(SystemExit) as exc:
        main(["bench", "live", str(EXCERPT), "--passes", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--passes" in err[0]
    for argv, needle in ((["--threshold", "nan"], "--threshold must be a number > 0, got nan"),
                         (["--set", "slam.online=false"], "a live robot needs a SLAM that runs scan by scan"),
                         (["--set", "frontend.calibration_scans=0"], "calibrates on its first scans")):
        assert main(["bench", "live", str(EXCERPT), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err


def test_bench_live_counts_a_pass_held_for_the_calibrations(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A log shorter than the calibration's scans: its first pass maps nothing (None, not a time
    per scan of nothing), the next pass that maps is the baseline, and the JSON line is JSON."""
    from agents.cli import main

    assert main(["bench", "live", str(EXCERPT), "--passes", "2", "--calibration-scans", "100",
                 "--out", str(tmp_path), "--json", "--quiet"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert "NaN" not in out
    r = json.loads(out)["logs"]["freiburg-101-head"]
    first, second = r["by_pass"]
    assert first["scans_mapped"] == 0 and first["ms_input"] is None
    assert second["scans_mapped"] == r["scans_mapped"] > 100  # the held scans mapped in the second pass
    assert r["ms_per_scan_first"] == pytest.approx(second["ms_input"] + second["ms_filter"], abs=1e-5)
    assert r["map_precision_first"] == second["map_precision"] > 0.8


def test_the_map_follows_the_slams_graph(scans: list[Any]) -> None:
    """``frontend.follow_graph`` (on in the online profile): when a loop optimises the SLAM's
    graph, the next input carries the nodes before and after (``warp``), and the filter fed it
    (``mapping_run.feed``) moves its maps with them before the step -- every particle's vertices
    as :func:`mapping.lidar_slam.graph_warp` moves them, edges and labels kept. Off, no input
    carries one, and the inputs are the same but for it."""
    from mapping.lidar_slam import graph_warp

    _, extract, frontend = profile()
    assert frontend.follow_graph

    def inputs(follow: bool) -> list[Any]:
        live = mr.LiveInputs(max_range=20.0, extract=extract, frontend=replace(frontend, follow_graph=follow),
                             min_travel=0.5, min_turn=math.radians(10))
        return [inp for ls in [*scans, *scans[::-1], *scans] for inp in live.add(ls)]

    on, off = inputs(True), inputs(False)
    warps = [k for k, inp in enumerate(on) if inp.warp is not None]
    assert warps and all(inp.warp is None for inp in off)
    assert [(a.odometry, a.t) for a in on] == [(b.odometry, b.t) for b in off]
    for k in warps:
        then, now = on[k].warp
        assert then.shape == now.shape and then.shape[1] == 3 and np.abs(now - then).max() > 0
    settings, _, _ = profile()
    filt, _ = live_filter(scans[0], 3, 0.2, 1, settings)
    for inp in on[: warps[0]]:
        mr.feed(filt, inp)
    before = filt.particles
    born = [filt._loops.births(p.points) for p in before]
    assert filt.best.n_vertices > 0 and all((b >= 0).all() for b in born)
    filt.warp(lambda p: graph_warp(*on[warps[0]].warp, p))
    for a, b, was in zip(before, filt.particles, born, strict=True):
        assert np.allclose(b.points, graph_warp(*on[warps[0]].warp, a.points))
        assert np.array_equal(a.edges, b.edges) and np.array_equal(a.labels, b.labels)
        assert np.array_equal(filt._loops.births(b.points), was)  # the corners keep their births
    # feed applies each input's warp before its step, and only those
    calls: list[int] = []
    plain = WireframeFilter.warp
    filt, _ = live_filter(scans[0], 3, 0.2, 1, settings)

    def counted(self: WireframeFilter, fn: Any) -> None:
        calls.append(self.steps)
        plain(self, fn)

    WireframeFilter.warp = counted  # type: ignore[method-assign]
    try:
        for inp in on:
            mr.feed(filt, inp)
    finally:
        WireframeFilter.warp = plain  # type: ignore[method-assign]
    assert calls == warps


def test_feed_warps_in_the_filters_frame() -> None:
    """The warp's nodes are in the SLAM's frame; a filter that started at ``origin`` maps in
    that frame moved by the origin, so ``feed`` moves the nodes there first: a map point follows
    its node as the SLAM's graph says, seen from the filter's frame."""
    from mapping.lidar_slam import graph_warp

    o = Pose(3.0, -1.0, 0.7)
    then = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    now = then + np.array([[0.5, 0.2, 0.1], [0.0, 0.0, 0.0]])
    seen: list[Any] = []

    class Recorder:  # feed's view of a filter: its origin, warp and step
        origin = o

        def warp(self, fn: Any) -> None:
            seen.append(fn)

        def step(self, *a: Any, **k: Any) -> None:
            return None

    inp = mr.ScanInput(0.0, Pose.identity(), mr.Wireframe.empty(), warp=(then, now))
    mr.feed(Recorder(), inp)  # type: ignore[arg-type]
    slam_pts = np.array([[1.0, 1.0], [9.0, -1.0]])
    in_filter = o.apply(slam_pts)
    assert np.allclose(seen[0](in_filter), o.apply(graph_warp(then, now, slam_pts)))


def test_the_warps_carry_every_node_to_where_the_graph_has_it(scans: list[Any]) -> None:
    """Over three passes of the excerpt, each node's position as the SLAM first gave it, carried
    through every warp :class:`mapping.lidar_frontend.OnlineSlam` reports (each point with its
    nearest node), ends where the final graph has the node: no move of the graph is missed or
    reported wrong."""
    from mapping.lidar_frontend import OnlineSlam
    from mapping.lidar_slam import graph_warp

    _, _, frontend = profile()
    laps = [*scans, *scans[::-1], *scans]
    cal = mr.calibrate_log(laps, frontend)
    online = OnlineSlam(frontend, cal.noise)
    carried = np.zeros((0, 2))
    warps = 0
    for pts, odo in zip(cal.points, mr.wheel_increments(laps), strict=True):
        online.add(pts, odo)
        if online.warp is not None:
            warps += 1
            carried = graph_warp(*online.warp, carried, neighbours=1)
        nodes = online.slam.poses
        carried = np.vstack([carried, nodes[len(carried):, :2]])
    assert warps > 0 and len(carried) == len(online.slam.poses)
    assert np.allclose(carried, online.slam.poses[:, :2], atol=1e-9)


# ---------------------------------------------------------------- the mount from /tf_static
def test_the_mount_is_found_from_the_transforms_and_scans_wait_for_them(scans: list[Any]) -> None:
    """With a base frame, the laser's mount comes from the TFMessages (base_link -> mast ->
    laser): scans before they come are dropped as unposed with the reason, then every scan is
    posed through the chain, as through --laser-mount; a transform that is not one is counted and
    dropped; the chain is in the counts."""
    mk = MessageMaker()
    now = [0.0]
    src = LiveLidar(use_transforms=True, base_frame="/base_link", clock=lambda: now[0])
    msgs = messages(scans[:6], MOUNT)
    for kind, data in msgs[:5]:  # two scans and their odometry, before any transform
        (src.on_scan if kind == "scan" else src.on_odometry)(data)
    assert src.take(0.0) is None and src.counts.unposed == 0  # waiting for the transforms
    now[0] = 1.5  # longer than max_wait: dropped
    assert src.take(0.0) is None and src.counts.unposed == 2
    assert "no transforms from base_link to the scans' frame 'laser' yet" in src.counts.last_issue
    mast = Pose(0.1, -0.03, 0.02)
    bad = mk.transforms(0.0, [("base_link", "base_link", Pose())])  # a frame onto itself
    src.on_transforms(mk.serialize(bad))
    src.on_transforms(b"\x00\x01 not a TFMessage")
    assert src.counts.bad_transforms == 2 and src.counts.transforms == 2
    src.on_transforms(mk.serialize(mk.transforms(0.0, [("base_link", "mast", mast)])))
    src.on_transforms(mk.serialize(mk.transforms(0.0, [("mast", "laser", mast.inverse().compose(MOUNT))])))
    for kind, data in msgs[5:]:
        (src.on_scan if kind == "scan" else src.on_odometry)(data)
    got = []
    while (ls := src.take(0.0)) is not None:
        got.append(ls)
    given = LiveLidar(mount=MOUNT)
    want = posed_scans(given, scans[:6], MOUNT)[-len(got):]
    assert len(got) >= 3 and src.counts.mount == "base_link -> mast -> laser"
    for a, b in zip(got, want, strict=True):
        assert a.odom.almost_equal(b.odom, tol=1e-9, angle_tol=1e-9) and a.mount.almost_equal(MOUNT, tol=1e-9)
        assert np.array_equal(a.ranges, b.ranges)


def test_transforms_that_are_no_mount_leave_the_scans_unposed_and_the_robot_running(scans: list[Any]) -> None:
    """A publisher on the transforms' key cannot crash the robot: a chain that puts the laser
    1e308 m away (or overflows) is refused, counted, and its scans dropped as unposed until good
    transforms come; a bad transform among good ones is left out alone; a message of too many
    transforms is refused whole. Without --base-frame the base is the odometry's child frame."""
    from agents.fleet.live_lidar import MAX_FRAMES

    mk = MessageMaker()
    now = [0.0]
    src = LiveLidar(use_transforms=True, clock=lambda: now[0])  # the base: the odometry's child frame
    far = Pose(1.5e308, 1.5e308, 0.0)
    src.on_transforms(mk.serialize(mk.transforms(0.0, [("base_link", "mast", far), ("mast", "laser", far)])))
    msgs = messages(scans[:4], MOUNT)
    for kind, data in msgs:
        (src.on_scan if kind == "scan" else src.on_odometry)(data)
    now[0] = 1.5
    assert src.take(0.0) is None and src.counts.unposed == 4 and src.counts.bad_transforms >= 1
    assert "not a mount" in src.counts.last_issue
    mixed = mk.transforms(0.0, [("base_link", "laser", MOUNT), ("x", "x", Pose())])
    src.on_transforms(mk.serialize(mixed))  # the good one kept, the bad one counted
    assert src.counts.bad_transforms >= 2
    for kind, data in messages(scans[4:8], MOUNT):
        (src.on_scan if kind == "scan" else src.on_odometry)(data)
    got = []
    while (ls := src.take(0.0)) is not None:
        got.append(ls)
    assert got and src.counts.mount == "base_link -> laser"
    assert all(ls.mount.almost_equal(MOUNT, tol=1e-9) for ls in got)
    many = mk.transforms(0.0, [("base_link", f"f{k}", Pose()) for k in range(MAX_FRAMES + 1)])
    before = src.counts.bad_transforms
    src.on_transforms(mk.serialize(many))
    assert src.counts.bad_transforms == before + 1 and "transforms (at most" in src.counts.last_issue


def test_reversed_sweep_reaches_the_live_robots_front_end() -> None:
    """`wiremap robot --scan-key --odom-key --reversed-sweep`: the live mapper's front end de-skews
    the beams the other way round; without the flag as the profile says."""
    import argparse

    from agents.commands.robot import add_arguments, options_from_args
    from agents.fleet.live_lidar import live_profile

    ap = argparse.ArgumentParser()
    add_arguments(ap)
    base = ["--id", "r1", "--scan-key", "l/scan", "--odom-key", "l/odom"]
    for extra, want in (([], False), (["--reversed-sweep"], True)):
        frontend = live_profile(options_from_args(ap.parse_args(base + extra)))[2]
        assert frontend.sweep_reversed is want and frontend.deskew
