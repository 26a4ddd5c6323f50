"""Bad input to the fusion service: random bytes, truncated and oversized payloads, valid codec
payloads with absurd content, an old format version, bad keys, a flood from one key.

Each is dropped with a counter (:class:`agents.fleet.fusion.FusionStats`, served on
``wiremap/<fleet>/fused/stats``) and a rate-limited log line; the fused map stays the last good
one; memory stays bounded. The first part tests the pieces without a network, the last one a
real fusion process behind a real router.
"""

from __future__ import annotations

import math
import signal
import time
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.fleet.bus import FleetKeys
from agents.fleet.fusion import (
    DropLog,
    FusionConfig,
    FusionState,
    InputLimits,
    Intake,
    encode_message,
    implausible,
)
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind

N, F = Label.NOMINAL, Label.FRONTIER
ORIGIN = Pose(1.0, 2.0, 0.0)
ROOM = Wireframe.build([(0, 0), (4, 0), (4, 3), (0, 3)], [(0, 1), (1, 2), (2, 3), (3, 0)], [N, N, N, N])


def robot_msg(
    rid: str = "r1",
    seq: int = 1,
    wf: Wireframe = ROOM,
    origin: Pose = ORIGIN,
    meta: dict[str, Any] | None = None,
    resolution: float = 0.1,
) -> MapMessage:
    return MapMessage(
        kind=MessageKind.ROBOT_MAP,
        sender=rid,
        seq=seq,
        stamp_ns=1_000 + seq,
        pose=Pose.identity(),
        frame=f"odom/{rid}",
        origin=origin,
        resolution=resolution,
        wireframe=wf,
        meta={"boot": 1, "t": float(seq)} if meta is None else meta,
    )


GOOD = encode_message(robot_msg())


def resealed(fields: list[Any]) -> bytes:
    """A message from 12 envelope fields with a correct CRC (as FORMAT.md describes), so that
    the decoder gets past the checksum to the field under test."""
    packed = msgpack.packb(fields, use_bin_type=True)
    head = b"\x9d" + packed[1:]
    return head + b"\xce" + zlib.crc32(head).to_bytes(4, "big")


def fields_of(data: bytes) -> list[Any]:
    return list(msgpack.unpackb(data, raw=False)[:12])


def body_claiming(n: int) -> bytes:
    """A body whose vertex count (Exp-Golomb order 0, FORMAT.md 3.1) says ``n`` and then ends."""
    u = n + 1
    bits = "0" * (u.bit_length() - 1) + format(u, "b")
    bits += "0" * (-len(bits) % 8)
    return int(bits, 2).to_bytes(len(bits) // 8, "big")


def bad_payloads() -> dict[str, tuple[bytes, str, str]]:
    """name -> (payload for robots/r1/map, counter, reason)."""
    f = fields_of(GOOD)
    nan_pose = list(f)
    nan_pose[5] = [math.nan, 0, 0]  # the codec allows no float in a pose
    old = list(f)
    old[0] = 0  # format version 0
    huge = list(f)
    huge[11] = body_claiming(10**6)
    rng = np.random.default_rng(6)
    return {
        "random": (rng.bytes(300), "malformed", ""),
        "truncated": (GOOD[:-9], "malformed", "TruncatedError"),
        "nan_in_pose": (resealed(nan_pose), "malformed", "FormatError"),
        "old_version": (resealed(old), "malformed", "VersionError"),
        "million_vertices": (resealed(huge), "malformed", "LimitError"),
        "kilometres_away": (encode_message(robot_msg(origin=Pose(5000.0, 0.0, 0.0))), "malformed",
                            "LimitError"),
        "far_in_fleet_frame": (
            encode_message(robot_msg(origin=Pose(800.0, 0.0, 0.0),
                                     wf=ROOM.transformed(Pose(400.0, 0.0, 0.0)))),
            "absurd",
            "extent",
        ),
        "nan_in_meta": (encode_message(robot_msg(meta={"boot": 1, "t": math.nan})), "absurd", "meta"),
        "huge_resolution": (encode_message(robot_msg(resolution=50.0)), "absurd", "resolution"),
        "boot_not_int": (encode_message(robot_msg(meta={"boot": "yesterday"})), "absurd", "meta"),
        "someone_else": (encode_message(robot_msg("r2")), "rejected", "sender_mismatch"),
        "fused_on_robot_key": (
            encode_message(
                MapMessage(
                    kind=MessageKind.FUSED_MAP, sender="fusion", seq=9, stamp_ns=1, pose=Pose.identity(),
                    frame="fleet", origin=Pose.identity(), resolution=0.1, wireframe=ROOM, robots=("r1",),
                    meta={},
                )
            ),
            "rejected",
            "not_robot_map",
        ),
    }  # fmt: skip


# ---------------------------------------------------------------------- the pure core
def good_state() -> FusionState:
    st_ = FusionState(FusionConfig(refine=False))
    assert st_.offer(GOOD, "r1")
    assert st_.fuse()
    return st_


@pytest.mark.parametrize("name", sorted(bad_payloads()))
def test_each_bad_payload_is_dropped_with_its_reason(name: str) -> None:
    data, counter, reason = bad_payloads()[name]
    st_ = good_state()
    fused, version = st_.fused, st_.version
    assert st_.offer(data, "r1", now_ns=time.time_ns()) is False
    assert getattr(st_.stats, counter) == 1, st_.stats
    assert st_.stats.dropped == 1
    assert st_.last_drop is not None and st_.last_drop[0] == counter
    if reason:
        assert getattr(st_.stats, f"{counter}_by") == {reason: 1}
    assert not st_.fuse() and st_.version == version and st_.fused is fused
    assert set(st_.robots) == {"r1"} and st_.robots["r1"].raw == GOOD


def test_million_vertex_claim_is_refused_by_the_codec_limit_before_allocating() -> None:
    data = bad_payloads()["million_vertices"][0]
    assert len(data) < 200
    st_ = FusionState()
    assert not st_.offer(data, "r1")
    assert "vertices" in st_.last_drop[2] and "3000" in st_.last_drop[2]  # the per-robot budget  # type: ignore[index]


def test_bad_key_and_future_boot() -> None:
    st_ = good_state()
    assert st_.reject_key("wiremap/x/robots/not~an~id/map") is False
    assert st_.stats.rejected_by == {"bad_key": 1}
    now = 2_000_000_000 * 10**9
    future = encode_message(robot_msg(seq=2, meta={"boot": now + 2 * 3600 * 10**9, "t": 1.0}))
    assert not st_.offer(future, "r1", now_ns=now)
    assert st_.stats.absurd_by == {"future": 1}
    st_.offer(future, "r1")  # without a clock the check is off
    assert st_.robots["r1"].key[0] == now + 2 * 3600 * 10**9 and st_.stats.accepted == 2
    st2 = good_state()
    ok = encode_message(robot_msg(seq=3, meta={"boot": now + 60 * 10**9, "t": 1.0}))  # within the skew
    st2.offer(ok, "r1", now_ns=now)
    assert st2.robots["r1"].key[:2] == (now + 60 * 10**9, 3) and st2.stats.absurd == 0


def test_implausible_reasons_directly() -> None:
    lim = InputLimits(max_extent_m=100.0, max_resolution_m=1.0)
    assert implausible(robot_msg(), lim) is None
    assert implausible(robot_msg(origin=Pose(150.0, 0, 0)), lim)[0] == "extent"  # type: ignore[index]
    assert implausible(  # type: ignore[index]
        robot_msg(origin=Pose(90.0, 0, 0), wf=ROOM.transformed(Pose(20, 0, 0))), lim
    )[0] == "extent"
    assert implausible(robot_msg(resolution=1.5), lim)[0] == "resolution"  # type: ignore[index]
    for meta in ({"boot": -1}, {"boot": True}, {"t": math.inf}, {"t": -1.0}, {"step": 1.5}, {"t": "now"}):
        assert implausible(robot_msg(meta=meta), lim)[0] == "meta", meta  # type: ignore[index]
    assert implausible(robot_msg(meta={}), lim) is None  # every meta field is optional


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=400))
def test_random_bytes_never_raise_and_never_change_the_map(data: bytes) -> None:
    st_ = good_state()
    before = st_.fused
    changed = st_.offer(data, "r1", now_ns=time.time_ns())
    assert not changed
    assert st_.stats.received == 2 and st_.stats.accepted == 1
    assert st_.stats.dropped + st_.stats.duplicates + st_.stats.outdated == 1
    assert not st_.fuse() and st_.fused is before


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(min_value=0, max_value=len(GOOD) - 1),
       flip=st.integers(min_value=0, max_value=8 * len(GOOD) - 1))
def test_truncated_or_bit_flipped_good_payloads_are_dropped(cut: int, flip: int) -> None:
    st_ = good_state()
    assert not st_.offer(GOOD[:cut], "r1")
    flipped = bytearray(GOOD)
    flipped[flip // 8] ^= 0x80 >> (flip % 8)
    assert not st_.offer(bytes(flipped), "r1")
    assert (
        st_.stats.malformed
        + st_.stats.rejected
        + st_.stats.absurd
        + st_.stats.outdated
        + st_.stats.duplicates
        == 2
    )
    assert st_.robots["r1"].raw == GOOD


def test_store_refuses_absurd_maps_written_into_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A store edited by hand is read through the same checks as the bus."""
    st_ = good_state()
    st_.save(tmp_path / "s")
    (tmp_path / "s" / "robots" / "r2.wfm").write_bytes(bad_payloads()["nan_in_meta"][0].replace(b"r1", b"r2"))
    back = FusionState.load(tmp_path / "s", FusionConfig(refine=False))
    assert set(back.robots) == {"r1"}
    assert "r2" in capsys.readouterr().err


# ---------------------------------------------------------------------- intake and drop log
class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_intake_rate_limit_per_key() -> None:
    clk = Clock()
    it = Intake(InputLimits(rate_hz=10.0, burst=5), clock=clk)
    res = [it.put("k/a", b"x" * 30) for _ in range(8)]
    assert res == [None] * 5 + ["rate_limited"] * 3
    assert it.put("k/b", b"y") is None  # another key has its own bucket
    clk.t += 0.25  # 2.5 tokens
    assert [it.put("k/a", b"z") for _ in range(3)] == [None, None, "rate_limited"]
    assert it.rate_limited == 4 and it.arrived == 12
    got = it.drain()
    assert [k for k, _ in got] == ["k/a"] * 5 + ["k/b"] + ["k/a"] * 2  # arrival order
    assert it.drain() == [] and it.queued_bytes == 0


def test_intake_bounds_size_depth_bytes_and_keys() -> None:
    clk = Clock()
    lim = InputLimits(max_bytes=100, queue_depth=3, queue_bytes=250, max_keys=2, rate_hz=1000.0, burst=1000)
    it = Intake(lim, clock=clk)
    assert it.put("a", b"x" * 101) == "oversized"
    for i in range(4):  # depth 3: the oldest goes
        assert it.put("a", bytes([i]) * 10) == (None if i < 3 else "overflow")
    assert [d[:1] for _, d in it.drain()] == [b"\x01", b"\x02", b"\x03"]
    assert it.put("a", b"x" * 100) is None and it.put("a", b"x" * 100) is None
    assert it.put("a", b"x" * 100) == "overflow"  # 300 > 250 queued bytes
    assert it.put("b", b"x") is None
    assert it.put("c", b"x") == "overflow"  # a third key while a and b are busy
    it.drain()
    clk.t += 10.0  # a's and b's buckets refill and their queues are empty: forgotten
    assert it.put("c", b"x") is None
    assert (it.oversized, it.overflow) == (1, 3)


def test_intake_drain_waits_for_the_first_payload() -> None:
    import threading

    it = Intake(InputLimits())
    t0 = time.monotonic()
    assert it.drain(0.05) == [] and time.monotonic() - t0 >= 0.04
    threading.Timer(0.05, lambda: it.put("k", b"late")).start()
    assert it.drain(5.0) == [("k", b"late")]


def test_drop_log_is_rate_limited() -> None:
    clk = Clock()
    lines: list[str] = []
    log = DropLog(lines.append, period=5.0, clock=clk)
    assert log.flush() is None
    log.note("malformed", "k/r1", "TruncatedError: short")
    assert log.flush() is not None and len(lines) == 1  # the first drop at once
    assert "1 malformed" in lines[0] and "k/r1" in lines[0]
    for _ in range(100):
        clk.t += 0.04
        log.note("rate_limited", "k/r2")
        assert log.flush() is None  # within the period: counted, not said
    clk.t += 1.0
    log.note("oversized", "k/r2", "999 bytes")
    assert log.flush() == lines[-1] and len(lines) == 2
    assert "100 rate_limited" in lines[1] and "1 oversized" in lines[1] and "in the last 5 s" in lines[1]


# ---------------------------------------------------------------------- a real fusion process
@pytest.mark.fleet
def test_fusion_process_drops_bad_input_keeps_serving_and_stays_bounded(
    tmp_path: Path, record_property
) -> None:
    from tests.fleet_util import (
        Fleet,
        FusedWatcher,
        client,
        in_process_router,
        query_fused,
        query_stats,
        record,
        rss_kb,
        wait_until,
    )

    keys = FleetKeys("bad")
    block = zenoh.CongestionControl.BLOCK
    with in_process_router() as ep, Fleet(tmp_path) as fleet, client(ep) as s:
        p = fleet.start("fuse", ["fuse", "--connect", ep, "--fleet", keys.fleet, "--no-refine"])
        fleet.wait_log("fuse", "fusion service ready", 30)
        w = FusedWatcher(s, keys)
        try:
            good = wait_until(lambda: (s.put(keys.robot_map("r1"), GOOD, congestion_control=block),
                                       query_fused(s, keys, 0.5))[1], 20, "the good map fused")  # fmt: skip
            version = good.seq
            # each kind of bad payload once, plus an oversized one and a key that is no robot id
            bad = bad_payloads()
            for data, _, _ in bad.values():
                s.put(keys.robot_map("r1"), data, congestion_control=block)
            s.put(keys.robot_map("r1"), b"\x00" * 300_000, congestion_control=block)
            s.put(f"{keys.prefix}/robots/not~an~id/map", GOOD, congestion_control=block)
            expect = {"malformed": 6, "absurd": 4, "rejected": 3, "oversized": 1}

            def counted() -> dict[str, Any] | None:
                d = query_stats(s, keys)
                return d if d and all(d["stats"][k] >= v for k, v in expect.items()) else None

            doc = wait_until(counted, 20, "every bad payload counted")
            stats = doc["stats"]
            assert {k: stats[k] for k in expect} == expect, stats
            assert stats["rejected_by"] == {"bad_key": 1, "not_robot_map": 1, "sender_mismatch": 1}
            assert stats["absurd_by"] == {"extent": 1, "meta": 2, "resolution": 1}
            assert (
                stats["malformed_by"].get("VersionError") == 1
                and stats["malformed_by"].get("LimitError") == 2
            )
            record(record_property, "bad_input_counters", {k: stats[k] for k in (*expect, "accepted")})
            q = query_fused(s, keys)
            assert q is not None and q.seq == version and q.wireframe.almost_equal(good.wireframe)
            # a flood from one key: valid maps, garbage, oversized payloads, as fast as possible;
            # three times, so that "bounded" is visible as a flat RSS once the allocator has warmed up
            # (the first floods grow malloc arenas and zenoh's buffers; the last may add little)
            rng = np.random.default_rng(11)
            junk = [rng.bytes(200_000), rng.bytes(1_000_000), rng.bytes(5_000)]
            rss = [rss_kb(p.pid)]
            peak = rss[0]
            sent, served, seq, flood_s = 0, 0, 10, 0.0
            last: list[int] = [-1]

            def settled() -> dict[str, Any] | None:
                """The counters stopped moving between two polls and nothing is queued."""
                d = query_stats(s, keys)
                if not d:
                    return None
                n = (
                    d["stats"]["received"]
                    + d["stats"]["oversized"]
                    + d["stats"]["rate_limited"]
                    + d["stats"]["overflow"]
                )
                same, last[0] = n == last[0], n
                return d if same and d["queued_bytes"] == 0 else None

            for _round in range(3):
                t0 = time.monotonic()
                while time.monotonic() - t0 < 3.0:
                    for _ in range(20):
                        seq += 1
                        s.put(keys.robot_map("r1"), encode_message(robot_msg(seq=seq)))
                        s.put(keys.robot_map("r1"), junk[sent % 3])
                        sent += 2
                    got = query_fused(s, keys, 1.0)  # it keeps answering during the flood
                    assert got is not None and got.seq == version
                    served += 1
                    peak = max(peak, rss_kb(p.pid))
                flood_s += time.monotonic() - t0
                after = wait_until(settled, 30, "the flood to drain", step=0.5)
                rss.append(rss_kb(p.pid))
            st2 = after["stats"]
            record(record_property, "flood",
                   {"sent": sent, "seconds": round(flood_s, 2), "queries_served": served,
                                              "rate_limited": st2["rate_limited"],
                                              "oversized": st2["oversized"],
                                              "overflow": st2["overflow"], "malformed": st2["malformed"],
                                              "accepted": st2["accepted"]})  # fmt: skip
            record(record_property, "fusion_rss_kb_start_flood1_flood2_flood3_peak", (*rss, peak))
            assert st2["rate_limited"] > 0 and st2["oversized"] > 1
            assert st2["accepted"] <= 1 + 100 + 50 * (flood_s + 5.0)  # the token bucket held
            assert rss[3] - rss[2] < 24 * 1024, rss  # flat: the third flood adds (almost) nothing
            assert peak - rss[0] < 128 * 1024, (rss, peak)
            assert after["rss_kb"] is not None
            # still the same map, never re-versioned by the flood
            q = query_fused(s, keys)
            assert q is not None and q.seq == version and q.wireframe.almost_equal(good.wireframe)
            assert all(m.seq == version for m in w.msgs)
        finally:
            w.close()
        assert fleet.stop("fuse", signal.SIGTERM, timeout=20) == 0, fleet.log("fuse")
    log = fleet.log("fuse")
    drop_lines = [ln for ln in log.splitlines() if "dropped " in ln]
    record(record_property, "drop_log_lines", len(drop_lines))
    assert 1 <= len(drop_lines) <= 3 + flood_s / 5.0 + 30 / 5.0, drop_lines
    assert "Traceback" not in log
