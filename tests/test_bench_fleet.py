"""The fleet benchmarks: their pure helpers, the replay robot's damage, and short real runs of
``wiremap bench fleet`` and ``wiremap bench soak`` (real router, fusion service and robot
processes on loopback) whose JSON is checked for keys and sanity."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.bench.common import (
    Frame,
    LatencyHarvest,
    Recording,
    crc_ok,
    grid_bytes,
    latency_total,
    load_recording,
    merge_counts,
    save_recording,
)
from agents.bench.fleet import parse_sizes
from agents.bench.replay_robot import corrupt
from agents.bench.soak import read_sent_log, rss_slope_mb_per_min
from agents.errors import UserError
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec import CodecError, MapMessage, MessageKind, decode, encode

REPO = Path(__file__).resolve().parent.parent
TINY = str(REPO / "tests" / "worlds" / "tiny.geojson")


def square(side: float = 2.0) -> Wireframe:
    pts = [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)]
    return Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 0)], [Label.NOMINAL] * 4)


def message(wf: Wireframe, seq: int = 1) -> bytes:
    return encode(
        MapMessage(
            kind=MessageKind.ROBOT_MAP, sender="r1", seq=seq, stamp_ns=123, pose=Pose.identity(),
            frame="odom/r1",
            origin=Pose(1.0, 2.0, 0.5), resolution=0.2, wireframe=wf, meta={"boot": 7, "t": 1.5},
        )
    )


# ---------------------------------------------------------------------- pure helpers
def test_grid_bytes_of_a_known_box() -> None:
    # a 2 m x 2 m square at 0.2 m: 10 x 10 cells
    assert grid_bytes(square(2.0), 0.2) == 100
    # 3.1 m x 2 m at 0.5 m: ceil(6.2) x 4 = 7 x 4
    wf = Wireframe.build([(0.0, 0.0), (3.1, 0.0), (3.1, 2.0)], [(0, 1), (1, 2)], [Label.NOMINAL] * 3)
    assert grid_bytes(wf, 0.5) == 28
    assert grid_bytes(Wireframe.empty(), 0.2) == 0
    # a single wall along x still needs one row
    wall = Wireframe.build([(0.0, 0.0), (1.0, 0.0)], [(0, 1)], [Label.NOMINAL] * 2)
    assert grid_bytes(wall, 0.2) == 5


def test_crc_ok_accepts_codec_messages_and_rejects_damage() -> None:
    data = message(square())
    assert crc_ok(data)
    assert not crc_ok(data[:-1])
    assert not crc_ok(b"")
    flipped = bytearray(data)
    flipped[10] ^= 0x01
    assert not crc_ok(bytes(flipped))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), side=st.floats(0.5, 20.0), seq=st.integers(1, 10**6))
def test_damaged_payloads_never_decode(seed: int, side: float, seq: int) -> None:
    data = message(square(side), seq)
    bad = corrupt(data, np.random.default_rng(seed))
    assert bad != data
    assert not crc_ok(bad)
    with pytest.raises(CodecError):
        decode(bad)


def test_corrupt_is_seeded_and_does_both_kinds() -> None:
    data = message(square())
    a = [corrupt(data, np.random.default_rng(s)) for s in range(40)]
    b = [corrupt(data, np.random.default_rng(s)) for s in range(40)]
    assert a == b
    assert any(len(x) == len(data) for x in a)  # flips
    assert any(len(x) < len(data) for x in a)  # truncations


def test_merge_counts_definition() -> None:
    stats = {"received": 20, "accepted": 10, "outdated": 3, "duplicates": 1, "superseded": 2, "malformed": 3,
             "rejected": 1, "overflow": 2, "rate_limited": 1, "oversized": 1, "dropped": 8}
    c = merge_counts(stats)
    assert (c["arrived"], c["received"], c["merged"], c["dropped"]) == (24, 20, 16, 8)
    assert (c["overflow"], c["rate_limited"]) == (2, 1)
    assert merge_counts({})["dropped"] == 0
    assert merge_counts({"received": "x"})["received"] == 0


def test_latency_harvest_collects_across_polls_and_a_rotation(tmp_path: Path) -> None:
    from agents.fleet.fusion import append_latency_log

    (tmp_path / "state.json").write_text(json.dumps({"latency_total": 2}))
    append_latency_log(tmp_path, [(1, 1.0, 100), (2, 2.0, 100)])
    h = LatencyHarvest(tmp_path)  # the first 2 are before the window
    append_latency_log(tmp_path, [(3, 3.0, 200)])
    with open(tmp_path / "latency.log", "a") as fh:
        fh.write("4 4.0")  # a line being written: not taken yet
    h.poll()
    h.poll()  # nothing new: nothing added
    assert h.samples == [3.0]
    with open(tmp_path / "latency.log", "a") as fh:
        fh.write("00 400\n")
    (tmp_path / "latency.log").rename(tmp_path / "latency.log.1")  # rotated
    append_latency_log(tmp_path, [(6, 6.0, 600)])  # 5 never written: missed
    h.poll()
    assert h.samples == [3.0, 4.0, 6.0] and h.missed == 1
    assert h.between(150, 450) == [3.0, 4.0]


def test_latency_total_reads_new_and_old_state_files() -> None:
    assert latency_total({"latency_total": 7, "stats": {"latency_ms": {"n": 3}}}) == 7
    assert latency_total({"stats": {"latency_ms": {"n": 3, "total": 5}}}) == 5
    assert latency_total({"stats": {"latency_ms": {"n": 3}}}) == 3
    assert latency_total({}) == 0


def test_recording_round_trip(tmp_path: Path) -> None:
    frames = (
        Frame(0.0, Pose.identity(), Pose(1.0, 2.0, 0.5), square(1.0)),
        Frame(0.5, Pose(0.25, 0.0, 0.01), None, square(2.0)),
    )
    rec = Recording("r1", "tiny", Pose(1.0, 2.0, 0.5), 0.2, frames, steps=3)
    save_recording(tmp_path / "r1.wrp", rec)
    back = load_recording(tmp_path / "r1.wrp")
    assert (back.robot, back.world, back.steps, len(back.frames)) == ("r1", "tiny", 3, 2)
    assert back.start.almost_equal(rec.start, 1e-3, 1e-6)
    assert back.frames[1].truth is None
    assert back.frames[0].truth is not None and back.frames[0].truth.almost_equal(
        Pose(1.0, 2.0, 0.5), 1e-9, 1e-9
    )
    assert back.frames[1].wireframe.almost_equal(square(2.0), tol=1e-9)
    (tmp_path / "bad.wrp").write_bytes(b"\x01\x02")
    with pytest.raises(UserError):
        load_recording(tmp_path / "bad.wrp")


def test_sent_log_and_rss_slope(tmp_path: Path) -> None:
    p = tmp_path / "r1.log"
    # last line cut by a kill
    p.write_text("B 100 1\nM 100 1 1 50\nM 100 2 0 10\nB 200 2\nM 200 1 1 60\nM 200 2")
    assert read_sent_log(p) == {"boots": [100, 200], "valid": 2, "corrupt": 1}
    assert read_sent_log(tmp_path / "absent.log") == {"boots": [], "valid": 0, "corrupt": 0}
    samples = [(60.0 * k, int((100 + 2 * k) * 1024 * 1024)) for k in range(5)]
    slope = rss_slope_mb_per_min(samples)
    assert slope is not None and math.isclose(slope, 2.0, rel_tol=1e-9)


def test_parse_sizes() -> None:
    assert parse_sizes("1,2, 4") == [1, 2, 4]
    assert parse_sizes("64,200") == [64, 200]  # past 64 robots: format version 2 (wire_codec.MAX_ROBOTS)
    for bad in ("", "a", "0", "4097", "1,,x"):
        with pytest.raises(UserError):
            parse_sizes(bad)


# ---------------------------------------------------------------------- real runs
def _bench(args: list[str], timeout: float) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "agents", "bench", *args, "--json"],
        cwd=REPO, capture_output=True, text=True, timeout=timeout, check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) > 2, proc.stdout  # a table before the JSON
    return json.loads(lines[-1])


SIZE_KEYS = {
    "robots_mode", "latency_ms_p50", "latency_ms_p99", "fusion_cpu_share", "bytes_per_s_per_robot",
    "grid_bytes_per_s_per_robot", "grid_ratio", "fused_recall", "fused_mean_dist_m", "maps_published",
    "maps_merged", "grid_ratio_msg", "grid_ratio_body", "mean_map_body_bytes", "transport_ms_p50",
    "transport_ms_p99",
    "grid_ratio_at_merge_threshold", "replay_processes", "robot_processes", "robots_cpu_share",
    "map_resolution_m", "merge_threshold_m",
}


@pytest.mark.fleet
def test_bench_fleet_short(tmp_path: Path) -> None:
    out = _bench(
        ["fleet", "--robots", "1,2", "--duration", "5", "--filter-upto", "1", "--warmup", "1",
         "--world", TINY, "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out")],
        timeout=120,
    )
    assert set(out) >= {"world", "rate_hz", "sizes"}
    assert out["world"] == "tiny" and out["rate_hz"] == 10.0
    assert set(out["sizes"]) == {"1", "2"}
    assert out["sizes"]["1"]["robots_mode"] == "filter"
    assert out["sizes"]["2"]["robots_mode"] == "replay"
    # replay robots share one process (one session each); filter robots have their own
    assert (out["sizes"]["2"]["replay_processes"], out["sizes"]["2"]["robot_processes"]) == (1, 1)
    assert (out["sizes"]["1"]["replay_processes"], out["sizes"]["1"]["robot_processes"]) == (0, 1)
    assert (out["map_resolution_m"], out["merge_threshold_m"], out["fuse_interval_s"]) == (0.05, 0.2, 0.0)
    assert list((tmp_path / "cache").glob("tiny-n2-*/r2.wrp"))  # the recordings were cached
    for n, r in out["sizes"].items():
        assert SIZE_KEYS <= set(r), n
        assert 0 < r["latency_ms_p50"] <= r["latency_ms_p99"] < 5000, r
        assert 0 < r["fusion_cpu_share"] < 2.0, r
        assert r["bytes_per_s_per_robot"] > 0
        assert r["grid_bytes_per_s_per_robot"] > r["bytes_per_s_per_robot"]
        assert r["grid_ratio"] > 1.0
        # the grid at the robots' 0.05 m quantisation has 16 times the cells of one at the 0.2 m
        # merge threshold (up to the rounding of each bounding box)
        assert (
            8 * r["grid_ratio_at_merge_threshold"] < r["grid_ratio"] < 20 * r["grid_ratio_at_merge_threshold"]
        ), r
        # the same maps compared message to message, and cells to the wireframe part alone
        assert r["grid_ratio"] < r["grid_ratio_msg"] < r["grid_ratio_body"], r
        assert 0 < r["mean_map_body_bytes"] < r["mean_map_bytes"]
        assert r["transport_ms_p50"] is not None and 0 <= r["transport_ms_p50"] <= r["transport_ms_p99"]
        assert r["maps_published"] > 0
        assert r["maps_merged"] == r["maps_published"] == r["maps_sent"], r
        # the tiny world is fully seen: the fused map must be good
        assert r["fused_recall"] >= 0.9 and r["fused_mean_dist_m"] < 0.1, r
    # replay robots publish one changed map per tick, never faster than --rate (how close to it
    # they come is the machine's speed: the bench's figure, not a test)
    assert 0 < out["sizes"]["2"]["maps_per_s_per_robot"] <= 10.5


@pytest.mark.fleet
def test_bench_soak_short(tmp_path: Path) -> None:
    out = _bench(
        ["soak", "--robots", "3", "--minutes", "0.2", "--corrupt", "0.05", "--kill-every", "4",
         "--warmup", "1",
         "--world", TINY, "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out")],
        timeout=120,
    )
    for k in ("valid_published", "maps_merged", "corrupt_dropped", "fusion_rss_mb_start", "fusion_rss_mb_end",
              "latency_ms_p99", "restarts", "restarts_survived"):
        assert k in out, k
    assert out["valid_published"] > 100
    assert out["maps_merged"] == out["valid_published"], out
    assert out["maps_lost"] == 0
    assert out["corrupt_dropped"] > 0
    assert out["corrupt_dropped"] == out["corrupt_published"], out
    # what the robots logged matches the bus up to the put in flight at each SIGKILL
    assert abs(out["valid_sent"] - out["valid_published"]) <= out["restarts"]
    assert out["latency_ms_p99"] > 0 and out["latency_ms_p50"] > 0
    assert out["restarts"] == 2  # at 4 and 8 s (12 s is the end)
    assert out["restarts_survived"] == out["restarts"]
    assert out["fusion_alive"] is True
    assert out["fusion_rss_mb_end"] > 0


# ---------------------------------------------------------------------- several replay robots in one process
@pytest.mark.fleet
def test_one_replay_process_publishes_for_each_robot_with_its_own_token(tmp_path: Path) -> None:
    """``replay_robot --id a --recording A --id b --recording B``: each robot puts its maps on
    its own key (sender = key), under its own liveliness token, from its own session; the
    tokens go when the process goes; ``--log`` with ``{id}`` gives one log per robot."""
    import signal
    import threading

    import zenoh

    from agents.fleet.bus import FleetKeys
    from tests.fleet_util import client, in_process_router, wait_until

    ids = ["ra", "rb", "rc"]
    recs: dict[str, Recording] = {}
    for k, rid in enumerate(ids):
        frames = tuple(Frame(0.5 * i, Pose.identity(), None, square(1.0 + 0.5 * i + k)) for i in range(4))
        recs[rid] = Recording(rid, "tiny", Pose(float(k), 0.0, 0.0), 0.05, frames, 4)
        save_recording(tmp_path / f"{rid}.wrp", recs[rid])
    keys = FleetKeys("t")
    maps: dict[str, list] = {r: [] for r in ids}
    alive: set[str] = set()
    lock = threading.Lock()

    def on_map(sample) -> None:
        rid = keys.robot_of(str(sample.key_expr))
        m = decode(sample.payload.to_bytes())
        with lock:
            maps.setdefault(rid or "?", []).append(m)

    def on_alive(sample) -> None:
        rid = keys.robot_of(str(sample.key_expr))
        with lock:
            (alive.add if sample.kind == zenoh.SampleKind.PUT else alive.discard)(rid)

    with in_process_router() as ep, client(ep) as s:
        subs = [s.declare_subscriber(keys.all_maps, on_map),
                s.liveliness().declare_subscriber(keys.all_alive, on_alive, history=True)]
        argv = ["-m", "agents.bench.replay_robot"]
        for rid in ids:
            argv += ["--id", rid, "--recording", str(tmp_path / f"{rid}.wrp")]
        argv += ["--rate", "20", "--log", str(tmp_path / "sent" / "{id}.log"), "--connect", ep,
                 "--fleet", "t"]
        fh = open(tmp_path / "replay.log", "wb")
        proc = subprocess.Popen([sys.executable, *argv], stdout=fh, stderr=subprocess.STDOUT, cwd=str(REPO))
        try:
            wait_until(lambda: all(len(maps[r]) >= 9 for r in ids), 30, "maps of every robot")
            with lock:
                assert alive == set(ids)
                for rid in ids:
                    assert {m.sender for m in maps[rid]} == {rid}  # each on its own key
                    assert {m.frame for m in maps[rid]} == {f"odom/{rid}"}
                    assert all(m.resolution == 0.05 for m in maps[rid])
                    seqs = [m.seq for m in maps[rid]]
                    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
                    # past the recording's end (bodies from the robot's own cache): each map is
                    # still the frame its meta names
                    for m in maps[rid]:
                        want = recs[rid].frames[m.meta["step"]].wireframe
                        assert sorted(map(tuple, m.wireframe.points.round(3).tolist())) == \
                            sorted(map(tuple, want.points.round(3).tolist()))
                    assert max(m.meta["step"] for m in maps[rid]) == 3
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=15) == 0
            wait_until(lambda: not alive, 10, "the tokens to go")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            fh.close()
            for sub in subs:
                sub.undeclare()
    for rid in ids:
        lines = (tmp_path / "sent" / f"{rid}.log").read_text().splitlines()
        assert lines[0].startswith("B ") and sum(ln.startswith("M ") for ln in lines) >= 5


def test_replay_robot_refuses_unpaired_or_untemplated_arguments(tmp_path: Path) -> None:
    from agents.bench.replay_robot import main

    rec = tmp_path / "r.wrp"
    save_recording(rec,
                   Recording("r1", "tiny", Pose.identity(), 0.05,
                             (Frame(0.0, Pose.identity(), None, square()),), 1))
    assert main(["--id", "a", "--id", "b", "--recording", str(rec)]) == 2
    assert main(["--id", "a", "--id", "a", "--recording", str(rec), "--recording", str(rec)]) == 2
    assert main(["--id", "a", "--id", "b", "--recording", str(rec), "--recording", str(rec),
                 "--log", str(tmp_path / "one.log")]) == 2
