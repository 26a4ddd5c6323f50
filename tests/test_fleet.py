"""Multi-process fleet tests: a real Zenoh router, real processes, loopback, free ports.

Every test stops and reaps what it started (``Fleet`` context manager) and closes its sessions.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import decode_message, encode_message
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from tests.fleet_util import (
    Fleet,
    FusedWatcher,
    client,
    free_port,
    in_process_router,
    query_fused,
    query_stats,
    tcp_endpoint,
    wait_until,
)
from wire_codec.message import MapMessage, MessageKind

pytestmark = pytest.mark.fleet

N, F = Label.NOMINAL, Label.FRONTIER


def robot_map(rid: str, pts, labels, origin: Pose, seq: int = 1) -> bytes:
    wf = Wireframe.build(pts, [(i, i + 1) for i in range(len(pts) - 1)], labels)
    return encode_message(
        MapMessage(
            kind=MessageKind.ROBOT_MAP,
            sender=rid,
            seq=seq,
            stamp_ns=time.time_ns(),
            pose=Pose.identity(),
            frame=f"odom/{rid}",
            origin=origin,
            resolution=0.2,
            wireframe=wf.transformed(origin.inverse()),
            meta={"boot": 1, "t": float(seq)},
        )
    )


def test_fusion_service_with_scripted_robots(tmp_path: Path):
    """The fusion process: fuses two robots' maps, answers a late querier at once, survives
    garbage, flags a robot whose liveliness token went away, stops on SIGTERM, and resumes the
    same fused map from its store."""
    keys = FleetKeys("t1")
    store = tmp_path / "store"
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        fleet.start(
            "fuse", ["fuse", "--connect", ep, "--fleet", "t1", "--store", store, "--rrd", tmp_path / "f.rrd"]
        )
        fleet.wait_log("fuse", "fusion service ready")
        w = FusedWatcher(s, keys)
        try:
            tok = s.liveliness().declare_token(keys.alive("r1"))
            m1 = robot_map("r1", [(5, 5), (0, 5), (0, 0), (5, 0)], [F, N, N, F], Pose(1, 1, 0.3))
            m2 = robot_map("r2", [(4, 0), (12, 0), (12, 5), (4, 5)], [F, N, N, F], Pose(10, 2.5, 2.0))
            s.put(keys.robot_map("r1"), b"not a map at all")
            s.put(keys.robot_map("r2"), m1)  # envelope says r1: rejected
            # the subscription may still be propagating: repeat (maps are idempotent)
            deadline = time.monotonic() + 15
            got = None
            while got is None and time.monotonic() < deadline:
                s.put(keys.robot_map("r1"), m1)
                s.put(keys.robot_map("r2"), m2)
                try:
                    got = w.wait_for(lambda m: m.robots == ("r1", "r2"), 0.5, "r1 and r2")
                except TimeoutError:
                    pass
            assert got is not None, fleet.log("fuse")
            assert got.kind == MessageKind.FUSED_MAP and got.frame == "fleet"
            wf = got.wireframe
            assert wf.n_edges == 4 and not np.any(wf.labels == F)  # the two halves close the room
            # a late joiner: a new session asks and has the current map within a second
            with client(ep) as late:
                t0 = time.monotonic()
                q = query_fused(late, keys, timeout=1.0)
                assert q is not None and time.monotonic() - t0 < 1.0
                assert q.seq >= got.seq and q.robots == ("r1", "r2")
            # r1's process goes away: it is flagged stale, its walls stay
            tok.undeclare()
            stale = w.wait_for(lambda m: "r1" in m.meta.get("stale", []), 10, "r1 stale")
            assert stale.wireframe.n_edges == 4
            # once idle, the service re-fuses by the full path (every alignment current) and may
            # publish one more version: the store must hold the version it converged to
            doc = wait_until(
                lambda: (d := query_stats(s, keys)) is not None and d["converged"] and d, 10, "convergence"
            )
            version = doc["version"]
            assert w.wait_for(lambda m: m.seq == version, 5, f"version {version}").wireframe.n_edges == 4
        finally:
            w.close()
        t0 = time.monotonic()
        assert fleet.stop("fuse", signal.SIGTERM, timeout=10) == 0
        assert time.monotonic() - t0 < 5
        out = fleet.log("fuse")
        assert "Traceback" not in out and "1 malformed" in out and "1 rejected" in out, out
        state = json.loads((store / "state.json").read_text())
        assert state["version"] == version and sorted(state["robots"]) == ["r1", "r2"]
        # restart from the store: the same map is served at once, before any robot speaks
        fleet.start("fuse2", ["fuse", "--connect", ep, "--fleet", "t1", "--store", store])
        fleet.wait_log("fuse2", "fusion service ready")
        q = wait_until(lambda: query_fused(s, keys, 1.0), 10, "resumed fused map")
        assert q.seq == version and q.wireframe.n_edges == 4 and q.robots == ("r1", "r2")
        assert fleet.stop("fuse2", signal.SIGINT, timeout=10) == 0


class _FakeFilter:
    def __init__(self, wf: Wireframe) -> None:
        self.best = wf
        self.particles = (wf, wf)
        self.weights = np.array([0.5, 0.5])


class _FakeStep:
    """What agents.fleet.robot needs from a simulation step, scripted: the robot sees more and more
    of the bottom wall of a 12 x 5 room."""

    def __init__(self, k: int, origin: Pose) -> None:
        self.t = 0.2 * k
        x = min(2.0 + k, 12.0)
        fleet = Wireframe.build([(0, 5), (0, 0), (x, 0)], [(0, 1), (1, 2)], [F, N, F if x < 12 else N])
        self.true_pose = Pose(1.0 + 0.1 * k, 1.0, 0.0)
        self.pose = origin.inverse().compose(self.true_pose)
        self.scan = fleet.transformed(self.true_pose.inverse())
        self.filter = _FakeFilter(fleet.transformed(origin.inverse()))


def test_robot_agent_shell_publishes_map_pose_and_token():
    """The robot shell in this process with a scripted simulation: a token while it runs, a
    map per change (seq increasing, sender and origin set), heartbeats when nothing changes,
    poses with a status at ~10 Hz."""
    from agents.fleet.bus import StopFlag, decode_pose
    from agents.fleet.robot import RobotAgent, RobotOptions

    keys = FleetKeys("t2")
    origin = Pose(1.0, 1.0, 0.0)
    opts = RobotOptions(robot="rx", world="unused", start=origin, rate=20.0, heartbeat_s=0.3, viz_hz=5.0)
    steps = iter([_FakeStep(k, origin) for k in range(12)])
    maps: list[MapMessage] = []
    poses: list[dict] = []
    alive: list[str] = []
    cond = threading.Condition()

    def on_map(s):
        with cond:
            maps.append(decode_message(s.payload.to_bytes()))
            cond.notify_all()

    def on_pose(s):
        with cond:
            poses.append(decode_pose(s.payload.to_bytes()))

    def on_alive(s):
        with cond:
            alive.append(str(s.kind))
            cond.notify_all()

    with in_process_router() as ep, client(ep) as s, client(ep) as obs:
        subs = [
            obs.declare_subscriber(keys.robot_map("rx"), on_map),
            obs.declare_subscriber(keys.robot_pose("rx"), on_pose),
            obs.liveliness().declare_subscriber(keys.all_alive, on_alive, history=True),
        ]
        stop = StopFlag()
        agent = RobotAgent(s, keys, opts, steps)
        agent.start()
        th = threading.Thread(target=agent.run, args=(stop,))
        th.start()
        try:
            with cond:
                # 12 steps with 11 distinct maps (x grows 2..12, then stays), then heartbeats
                assert cond.wait_for(lambda: len(maps) >= 13 and maps[-1].meta["step"] == 12, 20)
                assert "SampleKind.PUT" in alive
        finally:
            stop.set()
            th.join(10)
            agent.close()
        with cond:
            assert cond.wait_for(lambda: "SampleKind.DELETE" in alive, 5)
        for sub in subs:
            sub.undeclare()
    seqs = [m.seq for m in maps]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(m.sender == "rx" and m.kind == MessageKind.ROBOT_MAP for m in maps)
    assert all(m.origin.almost_equal(origin, 1e-3, 1e-5) and m.frame == "odom/rx" for m in maps)
    assert len({m.meta["boot"] for m in maps}) == 1
    # the last map is the whole bottom wall, in the odometry frame
    last = maps[-1].wireframe.transformed(origin)
    assert np.isclose(last.points[:, 0].max(), 12.0, atol=0.1)
    # heartbeats repeat the same map with a new seq
    assert maps[-1].wireframe.almost_equal(maps[-2].wireframe, tol=1e-9)
    assert agent.status.step == 12 and agent.status.finished
    assert agent.status.maps_sent >= len(maps)
    distinct = {
        round(float(m.wireframe.points[:, 0].max() - m.wireframe.points[:, 0].min()), 1) for m in maps
    }
    assert len(distinct) >= 10  # one map per change (the very first may precede the subscription)
    assert sum(1 for m in maps if m.meta["step"] == 11) == 1
    assert poses and poses[-1]["status"]["step"] == 12
    assert poses[-1]["truth"] is not None


# ---------------------------------------------------------------------- real robots
def test_run_three_robots_on_paper_small(tmp_path: Path):
    """`wiremap run` end to end: 3 robots + fusion + embedded router on paper-small. The fused
    map reaches wall recall >= 90 % and is at least as good as the best robot; a subscriber
    that joins during the run has the current fused map within a second; the recording opens
    and holds the expected entities and the sim_time timeline; every output is written."""
    from agents.files.render import decode_png
    from agents.files.rerun_log import read_recording

    port = free_port()
    ep = tcp_endpoint(port)
    out = tmp_path / "out"
    keys = FleetKeys()  # wiremap run uses the default fleet
    with Fleet(tmp_path) as fleet:
        p = fleet.start(
            "run",
            ["run", "--world", "paper-small", "--robots", "3", "--duration", "60", "--seed", "1",
             "--rate", "20", "--out", out, "--listen", ep, "--stop-when-done"],
        )
        fleet.wait_log("run", "router on", 30)
        # a late joiner: connect once the fleet has published, ask, get the map within 1 s
        with client(ep) as s:
            w = FusedWatcher(s, keys)
            try:
                first = w.wait_for(lambda m: len(m.robots) == 3, 60, "three robots")
            finally:
                w.close()
        with client(ep) as late:
            t0 = time.monotonic()
            q = query_fused(late, keys, timeout=1.0)
            assert q is not None and time.monotonic() - t0 < 1.0
            assert q.seq >= first.seq and q.kind == MessageKind.FUSED_MAP
        assert p.wait(timeout=90) == 0, fleet.log("run")
    log = (tmp_path / "run.log").read_text()
    assert "Traceback" not in log, log
    for name in ("fused.geojson", "fused.wfm", "fused.png", "recording.rrd", "report.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    # each robot's track (fleet frame), which `export --trajectory` reads for the ROS map's free space
    from agents.files.export import read_track

    assert sorted(p.name for p in (out / "tracks").glob("*.tsv")) == ["r1.tsv", "r2.tsv", "r3.tsv"]
    assert all(len(read_track(p)) > 10 for p in (out / "tracks").glob("*.tsv"))
    rep = json.loads((out / "report.json").read_text())
    assert rep["world"] == "paper-small" and rep["robots"] == 3 and 0 < rep["duration_s"] < 60
    fused, per = rep["fused"], rep["per_robot"]
    assert fused["wall_recall"] >= 0.90, rep
    assert fused["wall_recall"] >= max(r["wall_recall"] for r in per.values())
    assert fused["cell_error"] <= 0.01  # every robot finished: the fused map is closed and scored
    assert all(r["cell_error"] is None and "partial" in r["cell_error_note"] for r in per.values())
    assert set(per) == {"r1", "r2", "r3"}
    for r in per.values():
        assert r["maps_sent"] > 0 and r["bytes_sent"] > 0
        assert r["finished"] and r["steps"] > 20  # every robot drove its whole route
    assert rep["latency_ms"]["p50"] is not None and rep["latency_ms"]["p99"] >= rep["latency_ms"]["p50"]
    # the .wfm is the fused message; the GeoJSON has the same walls with their robots
    msg = decode_message((out / "fused.wfm").read_bytes())
    assert msg.kind == MessageKind.FUSED_MAP and msg.robots == ("r1", "r2", "r3")
    doc = json.loads((out / "fused.geojson").read_text())
    walls = [f for f in doc["features"] if f["properties"]["kind"] == "wall"]
    assert len(walls) == msg.wireframe.n_edges == fused["edges"]
    assert all(
        w["properties"]["robots"] and set(w["properties"]["robots"]) <= {"r1", "r2", "r3"} for w in walls
    )
    assert {r for w in walls for r in w["properties"]["robots"]} == {"r1", "r2", "r3"}
    assert decode_png((out / "fused.png").read_bytes()).ndim == 3
    # the recording
    entities, timelines = read_recording(out / "recording.rrd")
    assert {"sim_time", "fleet_time"} <= timelines
    expected = {"/world/truth", "/fused/walls", "/fused/corners/nominal", "/fused/corners/frontier", "/log"}
    for rid in ("r1", "r2", "r3"):
        expected |= {f"/robots/{rid}/{leaf}" for leaf in ("pose", "true_pose", "scan", "particles", "map",
                                                          "trajectory")}
        expected.add(f"/stats/robots/{rid}/alive")
    assert expected <= entities, expected - entities


def test_two_routers_fusion_on_a_includes_robots_on_b(tmp_path: Path):
    """Routers A and B (B connects to A, from the example files), the fusion service and one
    robot on A, one robot on B: the fused map on A includes B's robot."""
    pa, pb = free_port(), free_port()
    ea, eb = tcp_endpoint(pa), tcp_endpoint(pb)
    keys = FleetKeys("two")
    cfg = Path(__file__).resolve().parent.parent / "broker_config"
    common = ["--world", "paper-small", "--rate", "20", "--duration", "6", "--fleet", "two"]
    with Fleet(tmp_path) as fleet:
        fleet.start("A", ["router", "--config", cfg / "router-a.json5", "--listen", ea])
        fleet.start("B", ["router", "--config", cfg / "router-b.json5", "--listen", eb, "--connect", ea])
        fleet.start("fuse", ["fuse", "--connect", ea, "--fleet", "two"])
        fleet.start("ra",
                    ["robot", "--id", "ra", "--start", "2,2,0", "--route", "2,2;6,2", "--connect",
                     ea, *common])
        fleet.start("rb",
                    ["robot", "--id", "rb", "--start", "12,12,3.14159", "--route", "12,12;9,12", "--connect",
                     eb, *common])
        with client(ea) as s:
            w = FusedWatcher(s, keys)
            try:
                m = w.wait_for(lambda m: set(m.robots) == {"ra", "rb"} and m.wireframe.n_edges > 0, 60,
                               "ra and rb")
            finally:
                w.close()
        bits = np.bitwise_or.reduce(m.wireframe.sources.astype(np.uint64))
        assert int(bits) == 0b11  # both robots contributed walls
        for name in ("ra", "rb", "fuse", "B", "A"):
            assert fleet.stop(name, signal.SIGTERM, timeout=10) == 0, fleet.log(name)


def test_run_stops_cleanly_on_sigterm_and_sigint(tmp_path: Path):
    """`wiremap run` and its children exit within a few seconds of SIGTERM (outputs still
    written); robot and fusion processes alone exit on SIGINT; nothing is left behind."""
    from tests.fleet_util import alive, children_of

    out = tmp_path / "out"
    with Fleet(tmp_path) as fleet:
        p = fleet.start(
            "run",
            ["run", "--world", "paper-small", "--robots", "2", "--duration", "300", "--rate", "10",
             "--out", out, "--no-progress"],
        )
        kids = wait_until(lambda: len(children_of(p.pid)) >= 3 and children_of(p.pid), 30, "3 children")
        # wait until the fleet works (a fused map on disk), then stop it
        wait_until(lambda: (out / "store" / "fused.wfm").is_file(), 60, "a fused map in the store")
        t0 = time.monotonic()
        assert fleet.stop("run", signal.SIGTERM, timeout=20) == 130, fleet.log("run")  # INTERRUPTED
        assert time.monotonic() - t0 < 10
        assert not [k for k in kids if alive(k)]
    log = (tmp_path / "run.log").read_text()
    assert "interrupted" in log and "Traceback" not in log
    assert (out / "report.json").is_file() and json.loads((out / "report.json").read_text())["interrupted"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_robot_and_fusion_exit_on_signal_even_without_router(tmp_path: Path, sig):
    """Processes waiting for a router that never comes still stop at once on a signal."""
    ep = tcp_endpoint(free_port())
    with Fleet(tmp_path) as fleet:
        fleet.start("r",
                    ["robot", "--id", "r1", "--world", "paper-small", "--start", "2,2,0", "--connect", ep])
        fleet.start("f", ["fuse", "--connect", ep])
        fleet.wait_log("r", "waiting for a router", 30)
        fleet.wait_log("f", "waiting for a router", 30)
        for name in ("r", "f"):
            t0 = time.monotonic()
            assert fleet.stop(name, sig, timeout=10) == 0
            assert time.monotonic() - t0 < 5


def test_robot_options_split_quantisation_from_the_filter_threshold():
    """``wiremap robot``: ``--resolution`` (default 0.05) quantises the published map,
    ``--threshold`` (default 0.2) is the filter's merge threshold (what
    :func:`agents.mapping_run.robot_steps` merges at)."""
    import argparse

    from agents.commands.robot import add_arguments, options_from_args
    from agents.fleet.robot import map_message

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    opts = options_from_args(parser.parse_args(["--id", "r1", "--world", "paper-small", "--start", "1,1,0"]))
    assert (opts.resolution, opts.threshold) == (0.05, 0.2)
    wf = Wireframe.build([(0.0, 0.0), (1.03, 0.0)], [(0, 1)], [Label.NOMINAL] * 2)
    msg = decode_message(encode_message(map_message(opts, wf, Pose.identity(), 1, 0, {})))
    assert msg.resolution == 0.05 and np.isclose(msg.wireframe.points[:, 0].max(), 1.05)
    opts = options_from_args(parser.parse_args(
        ["--id", "r1", "--world", "museum", "--start", "1,1,0", "--resolution", "0.1", "--threshold", "0.4"]
    ))
    assert (opts.resolution, opts.threshold) == (0.1, 0.4)


def test_run_unknown_starts_on_paper_small(tmp_path: Path):
    """`wiremap run --unknown-starts`: robots start at random poses and publish in their own
    frames; the fusion service registers them (no false merge: every registered pose is within
    0.5 m / 2 degrees of the true relative start), the report lists `registered` and `islands`,
    and every attempt is in the recording."""
    import json

    from agents.files.rerun_log import read_recording

    out = tmp_path / "out"
    with Fleet(tmp_path) as fleet:
        fleet.start(
            "run",
            ["run", "--world", "paper-small", "--robots", "2", "--unknown-starts", "--duration", "12.5",
             "--seed", "3", "--rate", "20", "--out", out, "--no-progress"],
        )
        p = fleet.procs["run"]
        wait_until(lambda: p.poll() is not None, 180, "wiremap run to finish")
        assert p.returncode == 0, fleet.log("run")
    report = json.loads((out / "report.json").read_text())
    assert report["unknown_starts"] is True
    regs = set(report["registered"])
    isl = {m for ms in report["islands"].values() for m in ms}
    assert regs | isl == {"r1", "r2"} and not regs & isl
    assert report["fleet_root"] in regs
    for rid, err in report["registration_errors"].items():
        assert err["trans_err_m"] <= 0.5 and err["rot_err_deg"] <= 2.0, (rid, err)
    assert set(report["registration_errors_local"]) == regs - {report["fleet_root"]}
    for rid, err in report["registration_errors_local"].items():
        assert err["trans_err_m"] <= 0.5, (rid, err)
    assert report["registration_truth"]["accepted_wrong"] == 0
    assert sum(report["registration_truth"].values()) <= len(report["registrations"])
    # every attempt is listed (the fused map's meta carries only the last few)
    assert len(report["registrations"]) == report["registration_attempts"] >= 1
    log = (out / "logs" / "fuse.log").read_text()
    entities, _ = read_recording(out / "recording.rrd")
    if "registration " in log:
        assert "/registrations" in entities or "registrations" in entities
    assert (out / "fused.png").is_file() and (out / "fused.geojson").is_file()
    # The summary's robot table has what the robots' statuses said (it printed n/a), and a fleet
    # stopped by --duration has no cell error, as a run from known starts does not.
    for rid in ("r1", "r2"):
        r = report["per_robot"][rid]
        assert r["steps"] >= 1 and r["sim_time_s"] > 0.0, r
    table = [ln.split() for ln in fleet.log("run").splitlines() if ln.strip().startswith(("r1 ", "r2 "))]
    assert table and all(row[1] != "n/a" for row in table), table
    if not all(report["per_robot"][r]["finished"] for r in ("r1", "r2")):
        assert report["fused"]["cell_error"] is None and "cell_error_note" in report["fused"]


def test_run_carmen_log_as_two_robots(tmp_path: Path):
    """`wiremap run --carmen LOG --robots 2` on the committed excerpt (60 scans): the robots start
    without ``--particles`` (it used to reach them as "None") and with the real-lidar profile,
    every robot is either registered or an island, and fused.png is the map over the log's real
    scan endpoints (grey pixels)."""
    import json

    from agents.files.render import POINTS_COLOR, decode_png

    out = tmp_path / "out"
    log = Path(__file__).parent / "data" / "freiburg-101-head.log.gz"
    with Fleet(tmp_path) as fleet:
        fleet.start("run", ["run", "--carmen", log, "--robots", "2", "--rate", "20", "--out", out,
                            "--no-progress"])
        p = fleet.procs["run"]
        wait_until(lambda: p.poll() is not None, 180, "wiremap run --carmen to finish")
        assert p.returncode == 0, fleet.log("run")
    report = json.loads((out / "report.json").read_text())
    assert set(report["per_robot"]) == {"r1", "r2"}
    # The robots map through the default real-lidar profile, as `wiremap map --carmen` does.
    assert report["lidar_profile"] == "lidar-slam"
    assert "(lidar profile lidar-slam)" in (out / "logs" / "r1.log").read_text()
    regs = set(report["registered"])
    isl = {m for ms in report["islands"].values() for m in ms}
    assert regs | isl == {"r1", "r2"} and not regs & isl
    # every registered robot but the fleet's root is scored at its walls too
    assert set(report["registration_errors_local"]) == regs - {report["fleet_root"]}
    for err in report["registration_errors_local"].values():
        assert err["trans_err_m"] <= 0.5, report["registration_errors_local"]
    img = decode_png((out / "fused.png").read_bytes())
    assert (img == np.asarray(POINTS_COLOR, dtype=np.uint8)).all(axis=2).sum() > 200


def test_run_rosbag_as_two_robots(tmp_path: Path):
    """`wiremap run --rosbag BAG --robots 2 --truth-topic T`: the committed excerpt written as a
    ROS 2 (mcap) bag with its truth runs as the log does: each robot replays its stretch of the
    bag (its log says so), the report names the bag and scores the robots against the truth, and
    every robot is registered or an island."""
    import json

    from agents.files.carmen import read_carmen_log, scan_truth
    from tests.rosbag_util import write_scans_bag

    log = read_carmen_log(Path(__file__).parent / "data" / "freiburg-101-head.log.gz", strict=True)
    bag = write_scans_bag(tmp_path / "run-mcap", "mcap", log.scans, truth=scan_truth(log))
    out = tmp_path / "out"
    with Fleet(tmp_path) as fleet:
        fleet.start("run", ["run", "--rosbag", bag, "--truth-topic", "/ground_truth", "--robots", "2",
                            "--rate", "20", "--out", out, "--no-progress"])
        p = fleet.procs["run"]
        wait_until(lambda: p.poll() is not None, 180, "wiremap run --rosbag to finish")
        assert p.returncode == 0, fleet.log("run")
    report = json.loads((out / "report.json").read_text())
    assert report["rosbag"] == str(bag) and "carmen" not in report
    assert set(report["per_robot"]) == {"r1", "r2"}
    for rid in ("r1", "r2"):
        assert json.loads((out / "routes" / f"{rid}.json").read_text())["log"] == str(bag)
        assert report["per_robot"][rid]["endpoint_precision_own_scans"] > 0.5, report["per_robot"]
    assert "(lidar profile lidar-slam)" in (out / "logs" / "r1.log").read_text()
    regs = set(report["registered"])
    isl = {m for ms in report["islands"].values() for m in ms}
    assert regs | isl == {"r1", "r2"} and not regs & isl
    assert report["fused"]["endpoint_precision"] > 0.5


def test_run_with_the_realistic_lidar(tmp_path: Path):
    """`wiremap run --sensor lidar-real`: every robot process simulates the realistic lidar
    (its log says so), the report records the sensor, and the fused map of two robots keeps
    the walls (precision and recall at the merge threshold's cells, >= 0.85) despite glass,
    clutter, people and noise."""
    out = tmp_path / "out"
    with Fleet(tmp_path) as fleet:
        fleet.start(
            "run",
            ["run", "--world", "paper-small", "--robots", "2", "--sensor", "lidar-real", "--duration", "60",
             "--seed", "1", "--rate", "40", "--out", out, "--stop-when-done", "--no-progress"],
        )
        p = fleet.procs["run"]
        wait_until(lambda: p.poll() is not None, 120, "wiremap run to finish")
        assert p.returncode == 0, fleet.log("run")
    report = json.loads((out / "report.json").read_text())
    assert report["sensor"] == "lidar-real", report
    for rid in ("r1", "r2"):
        log = (out / "logs" / f"{rid}.log").read_text()
        assert "(sensor lidar-real)" in log, log
        assert report["per_robot"][rid]["finished"], report["per_robot"]
    fused = report["fused"]
    assert fused["wall_precision"] >= 0.85 and fused["wall_recall"] >= 0.85, report
