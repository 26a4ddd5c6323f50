"""The fusion core (no network): latest-map bookkeeping, fusion, store. The map algorithms it
uses (frontier closing, map-to-map alignment, the fold tree's shape) are tested in
tests/test_fleet_map.py."""

from __future__ import annotations

import json
import math
from unittest.mock import patch

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.fleet.fusion import (
    FusionConfig,
    FusionState,
    LatencyWindow,
    StoreWriter,
    append_latency_log,
    decode_message,
    encode_message,
    latency_summary,
    order_key,
    read_latency_log,
    read_store,
)
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe
from wire_codec.message import MapMessage, MessageKind

N, F = Label.NOMINAL, Label.FRONTIER
RES = 0.2

# A 12 x 5 m room (outer wall counterclockwise). r1 saw its left part, r2 its right part, r3 the
# middle; each partial view ends in frontier vertices where a wall leaves its view.
VIEWS = {
    "r1": ([(5, 5), (0, 5), (0, 0), (5, 0)], [F, N, N, F]),
    "r2": ([(4, 0), (12, 0), (12, 5), (4, 5)], [F, N, N, F]),
    "r3": ([(3, 0), (8, 0)], [F, F]),
}
ORIGINS = {"r1": Pose(1.0, 1.0, 0.3), "r2": Pose(10.0, 2.5, 2.0), "r3": Pose(6.0, 4.0, -1.2)}


def chain(points, labels) -> Wireframe:
    n = len(points)
    return Wireframe.build(points, [(i, i + 1) for i in range(n - 1)], labels)


def robot_msg(
    rid: str, seq: int = 1, wf_fleet: Wireframe | None = None, boot: int = 1, origin=None
) -> MapMessage:
    """A robot map message: the fleet-frame view expressed in the robot's odometry frame."""
    origin = origin or ORIGINS[rid]
    if wf_fleet is None:
        wf_fleet = chain(*VIEWS[rid])
    return MapMessage(
        kind=MessageKind.ROBOT_MAP,
        sender=rid,
        seq=seq,
        stamp_ns=1_000_000 * seq,
        pose=Pose.identity(),
        frame=f"odom/{rid}",
        origin=origin,
        resolution=RES,
        wireframe=wf_fleet.transformed(origin.inverse()),
        meta={"boot": boot, "t": float(seq)},
    )


# ---------------------------------------------------------------------- bookkeeping
def test_offer_drops_malformed_and_mismatched_payloads():
    st_ = FusionState()
    good = encode_message(robot_msg("r1"))
    assert not st_.offer(b"\x00garbage")
    assert not st_.offer(good[:-1])
    assert not st_.offer(good, "r2")  # the envelope says r1, the key says r2
    assert st_.stats.malformed == 2 and st_.stats.rejected == 1 and not st_.robots
    assert st_.offer(good, "r1") and "r1" in st_.robots
    assert st_.robots["r1"].raw == good
    fused = FusionState()
    fused.add(robot_msg("r1"))
    fused.fuse()
    assert not st_.offer(encode_message(fused.fused_message(5)), "r1")  # a fused map is no robot map


def test_latest_wins_duplicates_and_old_are_ignored():
    st_ = FusionState()
    assert st_.add(robot_msg("r1", seq=2))
    assert not st_.add(robot_msg("r1", seq=2))  # duplicate
    assert not st_.add(robot_msg("r1", seq=1))  # older
    assert st_.stats.duplicates == 1 and st_.stats.outdated == 1
    moved = chain([(0, 0), (5, 0)], [N, F])
    assert st_.add(robot_msg("r1", seq=3, wf_fleet=moved))
    assert st_.robots["r1"].message.seq == 3
    # same content, newer seq: accepted as latest but "not changed"
    assert not st_.add(robot_msg("r1", seq=4, wf_fleet=moved))
    assert st_.robots["r1"].message.seq == 4
    # a restarted robot (new boot) starts its seq again and still wins
    assert st_.add(robot_msg("r1", seq=1, boot=2))
    assert st_.robots["r1"].key[:2] == (2, 1)


def test_order_key_is_total_and_content_based():
    a, b = robot_msg("r1", seq=1), robot_msg("r1", seq=1, wf_fleet=chain([(0, 0), (1, 0)], [N, N]))
    ka, kb = order_key(a, encode_message(a)), order_key(b, encode_message(b))
    assert ka[:2] == kb[:2] and ka != kb


def test_latency_bookkeeping():
    st_ = FusionState()
    st_.add(robot_msg("r1", seq=1))  # stamp 1 ms
    st_.add(robot_msg("r2", seq=2))  # stamp 2 ms
    assert st_.fuse()
    lat = st_.take_latencies(12_000_000)
    assert sorted(lat) == [10.0, 11.0]
    assert st_.take_latencies(20_000_000) == []
    s = latency_summary(st_.stats.latencies_ms)
    assert s["n"] == 2 and s["p50"] == pytest.approx(10.5)
    assert latency_summary([])["p50"] is None


# ---------------------------------------------------------------------- fusion
def test_fused_map_of_three_partial_views():
    st_ = FusionState(FusionConfig(refine=False))
    for rid in ("r1", "r2", "r3"):
        st_.add(robot_msg(rid))
    assert st_.fuse() and st_.version == 1
    wf = st_.fused
    assert st_.fused_robots == ("r1", "r2", "r3")
    # every contributor mask is a non-empty subset of the three robots
    assert np.all(wf.sources > 0) and np.all(wf.sources < 8)
    # the bottom wall was seen by all three robots: some fused edge there carries all bits
    # (the codec quantises each robot's map to half a resolution step in its own frame, and the
    # merge snaps corners onto lines by up to the threshold: allow 0.3 m)
    bottom = [int(s) for (a, b), s in zip(wf.segments(), wf.sources) if abs(a[1]) < 0.3 and abs(b[1]) < 0.3]
    assert bottom and (np.bitwise_or.reduce(bottom) == 0b111)
    # the bottom wall is covered from x=0 to x=12, and no frontier is left on it
    xs = np.linspace(0.1, 11.9, 60)
    segs = [s for s in wf.segments() if abs(s[0][1]) < 0.3 and abs(s[1][1]) < 0.3]
    assert all(any(min(a[0], b[0]) - 0.15 <= x <= max(a[0], b[0]) + 0.15 for a, b in segs) for x in xs)
    on_bottom = (np.abs(wf.points[:, 1]) < 0.3) & (wf.points[:, 0] > 0.5) & (wf.points[:, 0] < 11.5)
    assert not np.any(wf.labels[on_bottom] == F)
    # re-fusing without news changes nothing
    assert not st_.fuse() and st_.version == 1


def test_fused_map_travels_through_the_codec():
    st_ = FusionState(FusionConfig(refine=False))
    for rid in ("r1", "r2"):
        st_.add(robot_msg(rid))
    st_.fuse()
    msg = decode_message(encode_message(st_.fused_message(123, {"stale": ["r2"]})))
    assert msg.kind == MessageKind.FUSED_MAP and msg.seq == st_.version and msg.robots == ("r1", "r2")
    assert msg.meta["stale"] == ["r2"] and msg.meta["version"] == 1
    assert msg.wireframe.n_edges == st_.fused.n_edges
    assert np.array_equal(np.sort(msg.wireframe.sources), np.sort(st_.fused.sources))


def _all_messages() -> list[MapMessage]:
    short_r1 = chain([(0, 5), (0, 0), (3, 0)], [N, N, F])
    return [
        robot_msg("r1", 1, short_r1),
        robot_msg("r1", 2),
        robot_msg("r2", 1),
        robot_msg("r3", 1, chain([(3, 0), (6, 0)], [F, F])),
        robot_msg("r3", 2),
    ]


_ALL = _all_messages()
_RAW = [encode_message(m) for m in _ALL]


def _reference() -> FusionState:
    ref = FusionState(FusionConfig())
    for m, raw in zip(_ALL, _RAW):
        ref.offer(raw, m.sender)
    ref.fuse(full=True)
    return ref


_REF: list[FusionState] = []


@given(
    st.permutations(range(len(_ALL))),
    st.lists(st.integers(0, len(_ALL) - 1), max_size=6),
    st.lists(st.booleans(), min_size=11, max_size=11),
)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_fused_map_independent_of_order_and_duplicates(order, dups, fuse_between):
    """Any order of arrival, with repeated deliveries and fusing at any point in between, gives
    the same fused map as delivering each robot's latest map once."""
    if not _REF:
        _REF.append(_reference())
    ref = _REF[0]
    st_ = FusionState(FusionConfig())
    seq = list(order) + list(dups)
    for i, k in enumerate(seq):
        st_.offer(_RAW[k], _ALL[k].sender)
        if fuse_between[i % len(fuse_between)]:
            st_.fuse()  # the fast path, with whatever alignments it has cached by then
    st_.fuse(full=True)
    assert st_.converged
    assert st_.fused_robots == ref.fused_robots
    assert {r: e.key for r, e in st_.robots.items()} == {r: e.key for r, e in ref.robots.items()}
    assert st_.fused.almost_equal(ref.fused, tol=1e-9)
    # recomputed from the same set in the same order: identical arrays, not just equivalent
    for name in ("points", "labels", "edges", "likelihood", "sources"):
        assert np.array_equal(getattr(st_.fused, name), getattr(ref.fused, name)), name


def test_icp_refinement_removes_a_start_pose_error():
    """r2's start pose is off by 0.29 m and 2 degrees: the refinement pulls r2's map back onto
    r1's, so the fused walls come out single (not doubled)."""
    wrong = ORIGINS["r2"]
    err = Pose(0.25, -0.15, math.radians(2.0))
    room = chain([(12, 5), (0, 5), (0, 0), (12, 0), (12, 5)], [N, N, N, N, N])
    msgs = [robot_msg("r1", wf_fleet=room)]
    bad = robot_msg("r2", wf_fleet=room)
    # r2 reports a start pose with an error; its map is its true odometry-frame map
    msgs.append(MapMessage(**{**bad.__dict__, "origin": wrong.compose(err)}))
    plain = FusionState(FusionConfig(refine=False))
    refined = FusionState(FusionConfig(refine=True))
    for m in msgs:
        plain.add(m)
        refined.add(m)
    plain.fuse()
    refined.fuse()
    assert "r2" in refined.corrections and "r2" not in plain.corrections

    def worst(state: FusionState) -> float:
        pts = state.robot_in_fleet("r2").points
        return float(
            np.max(np.min(np.hypot(*(pts[:, None, :] - room.points[None]).transpose(2, 0, 1)), axis=1))
        )

    # the codec's quantisation alone leaves ~0.07 m; the uncorrected error is ~0.3 m
    assert worst(plain) > 0.25
    assert worst(refined) < 0.15
    assert refined.fused.n_edges <= plain.fused.n_edges


# ---------------------------------------------------------------------- store
def test_store_round_trip_resumes_the_same_map(tmp_path):
    st_ = FusionState(FusionConfig())
    for rid in ("r1", "r2", "r3"):
        st_.add(robot_msg(rid))
    st_.fuse()
    st_.take_latencies(5_000_000)
    st_.add(robot_msg("r1", seq=2, wf_fleet=Wireframe.from_polylines([[(2, 2), (2, 3), (3, 3), (3, 2)]])))
    st_.fuse()
    assert st_.version == 2
    st_.save(tmp_path / "store")
    assert sorted(p.name for p in (tmp_path / "store" / "robots").iterdir()) == ["r1.wfm", "r2.wfm", "r3.wfm"]
    back = FusionState.load(tmp_path / "store", FusionConfig())
    assert back.version == 2
    assert back.fused.almost_equal(st_.fused, tol=1e-9)
    assert back.fused_robots == st_.fused_robots
    assert {r: e.raw for r, e in back.robots.items()} == {r: e.raw for r, e in st_.robots.items()}
    assert back.stats.latencies_ms == st_.stats.latencies_ms
    # a newer map after the restart continues the version sequence
    assert back.add(robot_msg("r2", seq=5, wf_fleet=chain([(4, 0), (12, 0)], [F, N])))
    assert back.fuse() and back.version == 3
    # no temporary files are left behind
    assert not [p for p in (tmp_path / "store").rglob(".*.tmp")]


def test_store_tolerates_a_corrupt_robot_file_and_missing_store(tmp_path, capsys):
    assert FusionState.load(tmp_path / "none").version == 0
    st_ = FusionState(FusionConfig())
    st_.add(robot_msg("r1"))
    st_.add(robot_msg("r2"))
    st_.fuse()
    st_.save(tmp_path / "s")
    (tmp_path / "s" / "robots" / "r2.wfm").write_bytes(b"junk")
    back = FusionState.load(tmp_path / "s", FusionConfig())
    # no silent loss: r2 comes back from the snapshot, the damage is reported and repaired
    assert set(back.robots) == {"r1", "r2"}
    assert back.version == st_.version and back.fused.almost_equal(st_.fused, tol=1e-9)
    assert back.store_rewrite == {"r2"} and back.store_report
    assert "r2.wfm is damaged" in capsys.readouterr().err


# ---------------------------------------------------------------------- fast path and full path
def _fake_refine(source: Wireframe, target: Wireframe, max_shift: float, max_turn: float) -> Pose:
    """A stand-in for ICP whose correction depends on the reference (its edge count and extent)
    and on the map aligned (its extent), so that a stale alignment shows in the result (by
    several steps of the fold's 0.05 m grid, ``agents.fleet.fusion.tree.wire_snap``)."""
    return Pose(0.05 * target.n_edges,
                0.025 * float(np.ptp(target.points[:, 0]) + np.ptp(source.points[:, 0])), 0.0)


class _Counting:
    def __init__(self) -> None:
        self.calls: list[int] = []

    def __call__(self, source, target, max_shift, max_turn):
        self.calls.append(source.n_vertices)
        return _fake_refine(source, target, max_shift, max_turn)


def _arrays(wf: Wireframe) -> tuple:
    return tuple(getattr(wf, n).tobytes() for n in ("points", "labels", "edges", "likelihood", "sources"))


def _full_of(raws: dict[str, bytes], config: FusionConfig | None = None) -> FusionState:
    ref = FusionState(config or FusionConfig())
    for rid, raw in sorted(raws.items()):
        ref.offer(raw, rid)
    ref.fuse(full=True)
    return ref


def _staggered() -> list[MapMessage]:
    """r3 sees an obstacle nobody else sees (its correction moves it in the fused map) and
    arrives before r2, whose map grows later: r3's alignment (onto the fold of r1 and r2)
    goes stale twice."""
    obstacle = Wireframe.from_polylines([[(6, 2), (6, 3), (7, 3), (7, 2)]])
    r2_pts, r2_lab = VIEWS["r2"]
    return [
        robot_msg("r1", 1),
        robot_msg("r3", 1, obstacle),
        robot_msg("r2", 1, chain(r2_pts[:3], [*r2_lab[:2], F])),
        robot_msg("r2", 2),
    ]


_MIXED = [*_ALL[:3], *_staggered()[1:]]  # r1 twice, r2 three times, r3 once
_MIXED_RAW = [encode_message(m) for m in _MIXED]


@given(
    st.permutations(range(len(_MIXED))),
    st.lists(st.integers(0, len(_MIXED) - 1), max_size=6),
    st.lists(st.booleans(), min_size=11, max_size=11),
)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_full_path_is_a_function_of_the_set_with_reference_dependent_alignments(order, dups, fuse_between):
    """With an alignment that depends on the fold before it, the fast path's result depends on
    history (alignments go stale), the full path's never does."""
    with patch("agents.fleet.fusion.state.align_maps", _fake_refine):
        latest: dict[str, bytes] = {}
        st_ = FusionState(FusionConfig())
        for i, k in enumerate(list(order) + list(dups)):
            st_.offer(_MIXED_RAW[k], _MIXED[k].sender)
            if fuse_between[i % len(fuse_between)]:
                st_.fuse()
        for m, raw in zip(_MIXED, _MIXED_RAW):  # the latest of each robot: the greatest order key
            if m.sender not in latest or order_key(m, raw) > order_key(
                decode_message(latest[m.sender]), latest[m.sender]
            ):
                latest[m.sender] = raw
        ref = _full_of(latest)
        st_.fuse(full=True)
        assert st_.converged and st_.fused_robots == ref.fused_robots
        assert _arrays(st_.fused) == _arrays(ref.fused)
        assert {r: c.as_tuple() for r, c in st_.corrections.items()} == {
            r: c.as_tuple() for r, c in ref.corrections.items()
        }


def test_fast_path_reuses_alignments_and_realigns_on_growth_and_age():
    counting = _Counting()
    cfg = FusionConfig(realign_vertices=2, realign_fraction=0.0, realign_s=5.0)
    with patch("agents.fleet.fusion.state.align_maps", counting):
        st_ = FusionState(cfg)
        st_.add(robot_msg("r1"))
        st_.add(robot_msg("r2"))
        assert st_.fuse(now=0.0)
        assert len(counting.calls) == 1  # r2 aligned onto r1; r1 is the anchor
        assert st_.converged and "r2" in st_.corrections
        # r2's map changes by one vertex: the cached correction is kept (no ICP)
        r2_pts, r2_lab = VIEWS["r2"]
        grown1 = chain([*r2_pts, (4, 6)], [*r2_lab, F])
        st_.add(robot_msg("r2", seq=2, wf_fleet=grown1))
        st_.fuse(now=1.0)
        assert len(counting.calls) == 1 and not st_.converged
        assert st_.alignments["r2"].rev != st_.robots["r2"].rev
        # ... until it grows by more than realign_vertices
        grown3 = chain([*r2_pts, (4, 6), (3, 6), (3, 7)], [*r2_lab, N, N, F])
        st_.add(robot_msg("r2", seq=3, wf_fleet=grown3))
        st_.fuse(now=2.0)
        assert len(counting.calls) == 2 and st_.converged
        # r1 changes: r2's reference moved, its own map did not; realigned only once old enough
        st_.add(robot_msg("r1", seq=2, wf_fleet=chain([(5, 5), (0, 5), (0, 0), (6, 0)], [F, N, N, F])))
        st_.fuse(now=3.0)
        assert len(counting.calls) == 2 and not st_.converged
        st_.fuse(now=7.5)  # nothing new, but r2's alignment is 5.5 s old and stale
        assert len(counting.calls) == 3 and st_.converged
        st_.fuse(now=20.0)  # current alignments are never redone
        assert len(counting.calls) == 3


def test_fast_path_realigns_at_most_the_budget_per_fuse_then_converges():
    counting = _Counting()
    with patch("agents.fleet.fusion.state.align_maps", counting):
        st_ = FusionState(FusionConfig(max_realign_per_fuse=1))
        for rid in ("r1", "r2", "r3"):
            st_.add(robot_msg(rid))
        st_.fuse()
        assert len(counting.calls) == 1 and set(st_.alignments) == {"r1", "r2"}  # r3 waits
        assert not st_.converged and "r3" not in st_.corrections
        st_.fuse()
        assert len(counting.calls) == 2 and st_.converged
        ref = _full_of({r: e.raw for r, e in st_.robots.items()})
        assert _arrays(st_.fused) == _arrays(ref.fused)


def test_fast_path_converges_to_the_full_path_once_alignments_are_refreshed():
    """Maps arrive one by one with fast fuses in between: alignments go stale (the fused map is
    not the full path's); fast fuses with the clock moving on refresh them one per fuse, after
    which the fast path's map is exactly the full path's, and the full path changes nothing."""
    with patch("agents.fleet.fusion.state.align_maps", _fake_refine):
        st_ = FusionState(FusionConfig(realign_s=1.0))
        for k, m in enumerate(_staggered()):
            st_.add(m)
            st_.fuse(now=0.1 * k)
        ref = _full_of({r: e.raw for r, e in st_.robots.items()})
        assert not st_.converged
        assert _arrays(st_.fused) != _arrays(ref.fused)
        now = 10.0
        for _ in range(len(st_.robots)):
            st_.fuse(now=now)
            now += 1.0
        assert st_.converged
        assert _arrays(st_.fused) == _arrays(ref.fused)
        version = st_.version
        assert not st_.fuse(full=True) and st_.version == version


def test_resent_map_with_new_seq_keeps_the_cache():
    counting = _Counting()
    with patch("agents.fleet.fusion.state.align_maps", counting):
        st_ = FusionState()
        st_.add(robot_msg("r1"))
        st_.add(robot_msg("r2"))
        st_.fuse(full=True)
        nodes_before = dict(st_._nodes)
        merges = st_.merges
        assert not st_.add(robot_msg("r1", seq=5))  # the same content again (a heartbeat)
        assert not st_.fuse(full=True)
        assert len(counting.calls) == 1 and st_.merges == merges
        assert st_._nodes.keys() == nodes_before.keys()
        assert all(st_._nodes[p][1] is nodes_before[p][1] for p in nodes_before)  # the very same objects


# ---------------------------------------------------------------------- latencies and the store writer
def test_latency_window_ring_total_and_cached_summary():
    w = LatencyWindow(capacity=4)
    w.extend([1.0, 2.0, 3.0], at_ns=10)
    assert list(w) == [1.0, 2.0, 3.0] and w.total == 3
    w.extend([4.0, 5.0, 6.0], at_ns=20)
    assert list(w) == [3.0, 4.0, 5.0, 6.0] and len(w) == 4 and w.total == 6
    v, t = w.tail(2)
    assert v.tolist() == [5.0, 6.0] and t.tolist() == [20, 20]
    s = w.summary()
    assert s["n"] == 4 and s["total"] == 6 and s["max"] == 6.0 and s["p50"] == pytest.approx(4.5)
    w.extend([100.0])
    stale = w.summary(fresh=False)
    assert stale["total"] == 7 and stale["max"] == 6.0  # the percentiles of last time
    assert w.summary()["max"] == 100.0


def test_latency_log_appends_rotates_and_reads_the_tail(tmp_path, monkeypatch):
    monkeypatch.setattr("agents.fleet.fusion.store.LATENCY_LOG_MAX_BYTES", 25)
    append_latency_log(tmp_path, [(1, 1.5, 7), (2, 2.25, 7)])
    append_latency_log(tmp_path, [(3, 3.0, 8)])
    append_latency_log(tmp_path, [(4, 4.0, 9), (5, 5.0, 9)])  # over 25 bytes: rotated first
    assert (tmp_path / "latency.log.1").read_text().splitlines() == ["1 1.500 7", "2 2.250 7", "3 3.000 8"]
    assert read_latency_log(tmp_path, 2) == [(4, 4.0), (5, 5.0)]
    assert read_latency_log(tmp_path, 4) == [(2, 2.25), (3, 3.0), (4, 4.0), (5, 5.0)]
    assert read_latency_log(tmp_path / "none", 3) == []


def test_store_writer_writes_in_the_background_and_combines_waiting_jobs(tmp_path):
    st_ = FusionState(FusionConfig(refine=False))
    st_.add(robot_msg("r1"))
    st_.fuse()
    st_.take_latencies(9_000_000)
    first = st_.store_job(tmp_path / "s", ["r1"], 5)
    st_.add(robot_msg("r2"))
    st_.fuse()
    st_.take_latencies(10_000_000)
    second = st_.store_job(tmp_path / "s", ["r2"], 6)
    both = first.then(second)
    assert both.views == {"r1", "r2"} and both.version == 2
    assert [i for i, _, _ in both.latencies] == [1, 2]
    writer = StoreWriter()
    try:
        writer.submit(first)
        writer.submit(second)
        assert writer.flush(10.0)
    finally:
        writer.close()
    assert writer.errors == 0 and 1 <= writer.written <= 2
    d = tmp_path / "s"
    assert sorted(p.name for p in (d / "robots").iterdir()) == ["r1.wfm", "r2.wfm"]
    state = json.loads((d / "state.json").read_text())
    assert state["version"] == 2 and state["latency_total"] == 2 and "latencies_ms" not in state
    assert state["stats"]["latency_ms"]["total"] == 2
    assert [ln.split()[0] for ln in (d / "latency.log").read_text().splitlines()] == ["1", "2"]
    assert read_store(d).fused.robots == ("r1", "r2")


def test_store_keeps_a_fast_path_map_and_its_version(tmp_path):
    """A fused map computed with stale alignments (not the full path's) comes back from the store
    exactly, with its version: the snapshot stores the corrections it was fused with."""
    with patch("agents.fleet.fusion.state.align_maps", _fake_refine):
        st_ = FusionState(FusionConfig(realign_s=1e9))
        for m in _staggered():
            st_.add(m)
            st_.fuse()
        assert not st_.converged
        st_.save(tmp_path / "s")
        back = FusionState.load(tmp_path / "s", FusionConfig())
        assert back.version == st_.version
        assert _arrays(back.fused) == _arrays(st_.fused)
        assert not back.converged
        assert back.fuse(full=True) and back.version == st_.version + 1 and back.converged


def test_realign_after_publishing_then_the_next_fuse_applies_it():
    """The service's order: fuse without ICP (publish), then align the robots the fuse wanted,
    then fuse again: the same map the full path gives."""
    counting = _Counting()
    with patch("agents.fleet.fusion.state.align_maps", counting):
        st_ = FusionState()
        for m in _staggered():
            st_.add(m)
        assert st_.fuse(max_realign=0)
        assert counting.calls == [] and st_.wanted == ["r2", "r3"] and not st_.converged
        assert st_.realign(now=0.0, limit=1) == ["r2"] and st_.wanted == ["r3"]
        assert st_.realign(now=0.0, limit=5) == ["r3"] and len(counting.calls) == 2
        st_.fuse(now=1.0, max_realign=0)
        assert st_.wanted == [] and not st_.converged  # r3's alignment is stale but young
        st_.fuse(now=10.0, max_realign=0)
        assert st_.wanted == ["r3"]  # r3 was aligned onto a fold without r2's correction
        st_.realign(now=10.0)
        # the new correction differs from the old by less than the fold's grid step (wire_snap):
        # the map need not change, but the fold is now the full path's
        st_.fuse(now=10.5, max_realign=0)
        assert st_.converged and st_.wanted == []
        ref = _full_of({r: e.raw for r, e in st_.robots.items()})
        assert _arrays(st_.fused) == _arrays(ref.fused)


# ---------------------------------------------------------------------- the fold tree
def _corridor_msg(k: int, pillar: bool = False, seq: int = 1) -> MapMessage:
    """Robot k's view of a long corridor: its walls from x = 2k to 2k + 3 (overlapping its
    neighbours'), frontiers at the ends, and maybe a pillar; start pose at its piece's origin."""
    x0, length = 2.0 * k, 3.0
    lines = [[(x0, 0.0), (x0 + length, 0.0)], [(x0 + length, 2.0), (x0, 2.0)]]
    if pillar:
        lines.append([(x0 + 1.0, 0.8), (x0 + 1.0, 1.2), (x0 + 1.4, 1.2), (x0 + 1.4, 0.8), (x0 + 1.0, 0.8)])
    wf = Wireframe.from_polylines(lines)
    wf = wf.replace(labels=np.full(wf.n_vertices, int(F), dtype=wf.labels.dtype))
    origin = Pose(x0, 1.0, 0.0)
    return MapMessage(
        kind=MessageKind.ROBOT_MAP, sender=f"r{k:02d}", seq=seq, stamp_ns=seq, pose=Pose.identity(),
        frame="", origin=origin, resolution=0.05, wireframe=wf.transformed(origin.inverse()),
        meta={"boot": 1, "t": float(seq)},
    )


def test_fold_tree_remerges_only_the_changed_robots_path():
    st_ = FusionState(FusionConfig(refine=False))
    for k in range(16):
        st_.add(_corridor_msg(k))
    st_.fuse()
    assert st_.merges == 15  # a binary tree over 16 leaves
    before = st_.merges
    st_.add(_corridor_msg(6, pillar=True, seq=2))
    assert st_.fuse()
    assert st_.merges - before <= 4  # its path to the root, not the 9 robots after it
    fresh = FusionState(FusionConfig(refine=False))
    for e in st_.robots.values():
        fresh.offer(e.raw, e.message.sender)
    fresh.fuse(full=True)
    assert _arrays(fresh.fused) == _arrays(st_.fused)  # the cache changes the cost, not the map
    # one corridor: every robot's walls are in it, each wall lists the robots that saw it
    assert fresh.fused.n_edges >= 2 and int(np.bitwise_or.reduce(fresh.fused.sources)) == (1 << 16) - 1


def test_fold_tree_is_the_left_fold_up_to_three_robots():
    from agents.fleet.fusion import default_merge

    st_ = FusionState(FusionConfig(refine=False, close_frontiers=False))
    msgs = [_corridor_msg(k) for k in range(3)]
    for m in msgs:
        st_.add(m)
    st_.fuse()
    ready = []
    for k, m in enumerate(msgs):
        wf = decode_message(encode_message(m)).wireframe.transformed(m.origin)
        ready.append(wf.replace(sources=np.full(wf.n_edges, 1 << k, dtype=np.uint64)))
    left = default_merge(default_merge(ready[0], ready[1], 0.2), ready[2], 0.2)
    assert left.almost_equal(st_.fused, tol=1e-9)


# ---------------------------------------------------------------------- quantisation and merge threshold
def test_robot_maps_quantised_at_5_cm_fuse_to_the_same_walls_at_a_20_cm_threshold():
    """The robots' quantisation step and the merge threshold are separate settings: maps at
    0.05 m fused at the default 0.2 m threshold give the walls that maps at 0.2 m gave, with
    corners closer to where the robots measured them, and the fused map travels at 0.05 m
    with its threshold in ``meta``."""
    from dataclasses import replace

    from agents.fleet.fusion import merge_threshold_of

    coarse, fine = FusionState(FusionConfig(refine=False)), FusionState(FusionConfig(refine=False))
    for rid in ("r1", "r2", "r3"):
        coarse.add(robot_msg(rid))  # RES = 0.2: the former default, quantisation = threshold
        fine.add(replace(robot_msg(rid), resolution=0.05))
    coarse.fuse()
    fine.fuse()
    assert coarse.threshold == fine.threshold == 0.2
    assert (fine.fused.n_vertices, fine.fused.n_edges) == (coarse.fused.n_vertices, coarse.fused.n_edges)
    assert fine.fused.almost_equal(coarse.fused, tol=0.15, likelihood_tol=1e-9)  # the same walls
    corners = np.array([(0, 0), (12, 0), (12, 5), (0, 5)], dtype=float)

    def error(wf: Wireframe) -> float:
        return float(max(np.min(np.hypot(*(wf.points - c).T)) for c in corners))

    # (the coarse fold's nodes sit on its 0.2 m grid, wire_snap, which holds these corners)
    assert error(fine.fused) <= 0.05
    msg = decode_message(encode_message(fine.fused_message(1)))
    assert msg.resolution == 0.05 and msg.meta["threshold"] == 0.2 and merge_threshold_of(msg) == 0.2
    old = decode_message(encode_message(coarse.fused_message(1)))
    assert old.resolution == 0.2 and merge_threshold_of(old) == 0.2
    # a fused map from before the split (no threshold in meta) is scored at its resolution
    assert merge_threshold_of(replace(msg, meta={"version": 1}, resolution=0.4)) == 0.4


def test_merge_threshold_default_configured_and_raised_by_a_coarse_map():
    from dataclasses import replace

    st_ = FusionState()
    assert st_.threshold == 0.2 and st_.resolution == 0.05  # no robots yet
    st_.add(replace(robot_msg("r1"), resolution=0.05))
    assert st_.threshold == 0.2 and st_.resolution == 0.05
    st_.add(replace(robot_msg("r2"), resolution=0.5))
    assert st_.threshold == 0.5 and st_.resolution == 0.05  # corners may be a whole step apart
    assert FusionState(FusionConfig(threshold=0.4)).threshold == 0.4


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(1, 12), st.integers(0, 2**32 - 1),
       st.sampled_from(["same", "permuted", "moved", "relabelled", "lik", "src"]))
def test_quick_difference_test_never_contradicts_almost_equal(n, seed, change):
    """``almost_equal`` (and so ``_same_wireframe``) skips the vertex matching when sorted
    coordinates, labels, likelihoods or sources already differ; the quick test must agree with
    the full one."""
    from agents.fleet.fusion.state import _same_wireframe
    from mapping.wireframe import _surely_differ

    rng = np.random.default_rng(seed)
    pts = rng.integers(0, 6, (n, 2)) * 0.5
    edges = [(i, (i + 1) % n) for i in range(n - 1)] if n > 1 else []
    a = Wireframe.build(pts, edges, rng.integers(0, 3, n), rng.random(len(edges)),
                        rng.integers(0, 4, len(edges)))
    perm = rng.permutation(n)
    inv = np.argsort(perm)
    b = Wireframe.build(
        a.points[perm], [(int(inv[x]), int(inv[y])) for x, y in a.edges.tolist()][::-1], a.labels[perm],
        a.likelihood[::-1], a.sources[::-1],
    )
    if change == "same":
        b = a.replace()
    elif change == "moved":
        b = b.replace(points=b.points + rng.choice([0.0, 1e-6], b.points.shape))
    elif change == "relabelled":
        b = b.replace(labels=(b.labels + rng.integers(0, 2, n)) % 3)
    elif change == "lik" and b.n_edges:
        b = b.replace(likelihood=np.clip(b.likelihood + rng.choice([0.0, 1e-3], b.n_edges), 0.0, 1.0))
    elif change == "src" and b.n_edges:
        b = b.replace(sources=b.sources ^ rng.integers(0, 2, b.n_edges).astype(np.uint64))
    equal = a.almost_equal(b, tol=1e-9)
    if _surely_differ(a, b, 1e-9):
        assert not equal
    assert _same_wireframe(a, b) == equal
    if change in ("same", "permuted"):  # the same graph: never reported as surely different
        assert not _surely_differ(a, b, 1e-9)


def test_a_restart_whose_map_comes_before_its_token_loses_nothing() -> None:
    """A restarted robot's first map can arrive before its liveliness token (they travel
    apart): it is refused while the token has not come back, held, and taken once the token
    shows within the hold time; a claimed restart whose token never comes stays refused."""
    import time

    from agents.fleet.fusion.state import RESTART_HOLD_S

    st = FusionState()
    st.restart_by_token = True
    st.note_alive("r1", 0)
    first = robot_msg("r1", 1, boot=1)
    assert st.add(first)
    reboot = robot_msg("r1", 1, boot=2)
    assert not st.add(reboot)
    assert st.stats.rejected_by.get("boot_without_restart") == 1
    st.note_alive("r1")  # the token of the new session arrives
    assert st.robots["r1"].key[0] == 2
    assert st.stats.rejected == 0 and "boot_without_restart" not in st.stats.rejected_by
    # a restart claimed without the token, then a token far too late: stays refused
    again = robot_msg("r1", 1, boot=3)
    assert not st.add(again)
    st.note_alive("r1", time.time_ns() + int((RESTART_HOLD_S + 1) * 1e9))
    assert st.robots["r1"].key[0] == 2
    assert st.stats.rejected_by.get("boot_without_restart") == 1
