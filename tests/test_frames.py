"""Robots of unknown start pose: the registration graph (agents.fleet.fusion.frames) in the pure
fusion core, without any network."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from functools import cache

import numpy as np

from agents.fleet.fusion import FusionState
from agents.fleet.fusion.frames import (
    ORIGIN_UNKNOWN,
    FleetFrames,
    FramesConfig,
    RegistrationRecord,
    origin_unknown,
)
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.message import MapMessage, MessageKind


@cache
def _truth(name: str) -> Wireframe:
    from agents.sim.world import load_world

    return load_world(name).truth


def _crop(wf: Wireframe, xmin: float, xmax: float) -> Wireframe:
    mid = wf.segments().mean(axis=1)
    return wf.subgraph_edges((mid[:, 0] >= xmin) & (mid[:, 0] < xmax))


def _msg(rid: str, wf_world: Wireframe, start: Pose, seq: int = 1, unknown: bool = True) -> MapMessage:
    """The map of a robot that started at ``start`` (world frame), in its own frame."""
    meta = {"boot": 1, "t": float(seq)}
    if unknown:
        meta[ORIGIN_UNKNOWN] = True
    return MapMessage(
        kind=MessageKind.ROBOT_MAP, sender=rid, seq=seq, stamp_ns=seq * 1_000_000, pose=Pose.identity(),
        frame=f"odom/{rid}", origin=Pose.identity() if unknown else start, resolution=0.05,
        wireframe=wf_world.transformed(start.inverse()), meta=meta,
    )


def _noisy(wf: Wireframe, seed: int, sigma: float = 0.01) -> Wireframe:
    rng = np.random.default_rng(seed)
    return wf.replace(points=wf.points + rng.normal(0.0, sigma, wf.points.shape))


def _register_all(st: FusionState, limit: int = 10) -> list[object]:
    out = []
    for _ in range(limit):
        rec = st.register_step()
        if rec is None:
            break
        out.append(rec)
    st.fuse(full=True)
    return out


def _halves(name: str) -> tuple[Wireframe, Wireframe]:
    truth = _truth(name)
    xmin, _, xmax, _ = truth.bounds()
    w = xmax - xmin
    return _noisy(_crop(truth, xmin, xmin + 0.7 * w), 1), _noisy(_crop(truth, xmin + 0.3 * w, xmax + 1), 2)


def test_two_robots_in_unrelated_frames_form_one_fleet_map() -> None:
    a, b = _halves("paper-small")
    sa, sb = Pose(3.0, 2.0, 0.7), Pose(-20.0, 11.0, -2.4)
    st = FusionState()
    st.add(_msg("r1", a, sa))
    st.add(_msg("r2", b, sb))
    st.fuse(full=True)
    # before registration: the fleet is r1 alone, r2 an island in its own frame
    assert st.fused_robots == ("r1",)
    assert set(st.islands()) == {"r2"}
    recs = _register_all(st)
    assert any(r.accepted for r in recs)  # type: ignore[attr-defined]
    assert st.fused_robots == ("r1", "r2")
    assert st.islands() == {}
    # r2's pose in the fleet frame (r1's) is its true start relative to r1's
    true = sa.inverse().compose(sb)
    got = st.robots["r2"].message.origin
    assert math.hypot(got.x - true.x, got.y - true.y) < 0.1
    assert abs(math.remainder(got.theta - true.theta, 2 * math.pi)) < math.radians(1.0)
    meta = st.fused_message(0).meta["frames"]
    assert meta["registered"] == ["r1", "r2"] and meta["islands"] == {}
    # the fused map in r1's frame lies on the truth moved into r1's frame
    from mapping.metrics import evaluate

    m = evaluate(_truth("paper-small").transformed(sa.inverse()), st.fused, 0.2)
    assert m["wall_precision"] >= 0.95


def test_islands_register_to_each_other_and_then_to_the_fleet() -> None:
    truth = _truth("paper-small")
    xmin, _, xmax, _ = truth.bounds()
    w = xmax - xmin
    parts = [_noisy(_crop(truth, xmin + f0 * w, xmin + f1 * w), k) for k, (f0, f1) in
             enumerate([(0.0, 0.55), (0.25, 0.8), (0.5, 1.01)])]
    starts = [Pose(1.0, 1.0, 0.3), Pose(40.0, -3.0, 1.9), Pose(-7.0, 25.0, -1.0)]
    st = FusionState(frames=FramesConfig(anchor="r3"))
    for k, (p, s) in enumerate(zip(parts, starts)):
        st.add(_msg(f"r{k + 1}", p, s))
    _register_all(st)
    assert st.fused_robots == ("r1", "r2", "r3")
    # the anchor's frame is the fleet frame
    assert st.robots["r3"].message.origin.almost_equal(Pose.identity(), 1e-12, 1e-12)


def test_an_island_stays_an_island_when_registration_refuses() -> None:
    # a symmetric world: a robot's map of one side matches either side, registration refuses
    a = _noisy(_truth("paper-small"), 3)
    b = _noisy(_truth("office"), 4)
    st = FusionState()
    st.add(_msg("r1", a, Pose(1.0, 2.0, 0.1)))
    st.add(_msg("r2", b, Pose(5.0, -2.0, 1.1)))
    recs = _register_all(st)
    assert recs and not any(r.accepted for r in recs)  # type: ignore[attr-defined]
    assert st.fused_robots == ("r1",)
    assert set(st.islands()) == {"r2"}
    members, wf = st.islands()["r2"]
    assert members == ("r2",) and wf.n_edges == st.robots["r2"].message.wireframe.n_edges
    # no retry until a map grew
    assert st.register_step() is None


def test_cross_world_pairs_never_merge() -> None:
    names = ["paper-small", "office", "warehouse", "museum"]
    for i, x in enumerate(names):
        for y in names[i + 1:]:
            st = FusionState()
            st.add(_msg("r1", _crop(_truth(x), -1e9, 1e9), Pose(0.0, 0.0, 0.0)))
            st.add(_msg("r2", _crop(_truth(y), -1e9, 1e9), Pose(3.0, 1.0, 2.0)))
            _register_all(st)
            assert st.fused_robots == ("r1",), (x, y)


def test_known_start_fleets_never_register() -> None:
    a, b = _halves("paper-small")
    st = FusionState()
    st.add(_msg("r1", a, Pose(0.0, 0.0, 0.0), unknown=False))
    st.add(_msg("r2", b, Pose(1.0, 0.0, 0.5), unknown=False))
    assert not st.frames.active
    assert st.register_step() is None
    st.fuse(full=True)
    assert st.fused_robots == ("r1", "r2")
    assert "frames" not in st.fused_message(0).meta


def test_origin_unknown_flag() -> None:
    a, _ = _halves("paper-small")
    assert origin_unknown(_msg("r1", a, Pose.identity()))
    assert not origin_unknown(_msg("r1", a, Pose.identity(), unknown=False))


def test_retry_only_after_growth() -> None:
    fr = FleetFrames(FramesConfig(retry_growth_m=5.0, retry_growth_fraction=0.1, min_length_m=1.0))
    fr.track("r1")
    fr.track("r2")
    lengths = {"r1": 20.0, "r2": 20.0}

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(lengths[m] for m in members)

    assert fr.next_pair(length) == ("r1", "r2")
    fr._tried[(("r1",), ("r2",))] = (20.0, 20.0, None)
    assert fr.next_pair(length) is None
    lengths["r2"] = 24.0
    assert fr.next_pair(length) is None
    lengths["r2"] = 25.0
    assert fr.next_pair(length) == ("r1", "r2")


def test_a_map_that_stopped_growing_is_tried_again_after_a_while() -> None:
    """Short of the growth rule, a pair whose maps changed by ``retry_min_m`` is tried again once
    ``retry_after_s`` passed on the caller's clock (never without a clock, never unchanged)."""
    cfg = FramesConfig(retry_growth_m=5.0, retry_growth_fraction=0.2, retry_after_s=5.0, retry_min_m=1.0,
                       min_length_m=1.0)
    fr = FleetFrames(cfg)
    fr.track("r1")
    fr.track("r2")
    lengths = {"r1": 100.0, "r2": 100.0}

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(lengths[m] for m in members)

    a, b = _halves("office")
    maps = {"r1": a, "r2": b.transformed(Pose(40.0, 40.0, 2.0))}  # far apart: refused, not joined
    rec = fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], now=100.0)
    assert not rec.accepted and fr._tried[(("r1",), ("r2",))][2] == 100.0  # the attempt's clock
    fr._tried[(("r1",), ("r2",))] = (100.0, 100.0, 100.0)  # at the lengths this test's `length` gives
    lengths["r2"] = 110.0  # grew, but short of max(5 m, 20 %)
    assert fr.next_pair(length, now=104.9) is None
    assert fr.next_pair(length) is None  # without a clock: the growth rule only
    assert fr.next_pair(length, now=105.0) == ("r1", "r2")
    lengths["r2"] = 100.5  # back within retry_min_m of the last attempt: nothing new to try
    assert fr.next_pair(length, now=200.0) is None
    off = FleetFrames(FramesConfig(retry_after_s=0.0, min_length_m=1.0))
    off.track("r1")
    off.track("r2")
    off._tried[(("r1",), ("r2",))] = (100.0, 100.0, 100.0)
    lengths["r2"] = 110.0
    assert off.next_pair(length, now=1e6) is None


def test_report_scores_every_attempt_against_the_true_starts():
    """report.json's attempts carry their transform's error against the true relative start,
    and the tally tells a merge lost to caution (refused, right) from a false merge avoided."""
    from agents.fleet.unknown_run import _attempts_against_truth

    starts = {"r1": Pose(2.0, 1.0, 0.3), "r2": Pose(-4.0, 6.0, -1.2), "r3": Pose(0.0, 0.0, 0.0)}
    right = starts["r1"].inverse().compose(starts["r2"])
    off = right.compose(Pose(3.0, 0.0, 0.0))  # one office along
    recs = [
        {"a": "r1", "b": "r2", "accepted": True, "transform": list(right.as_tuple())},
        {"a": "r1", "b": "r2", "accepted": False, "transform": list(off.as_tuple())},
        {"a": "r1", "b": "r2", "accepted": False, "transform": list(right.as_tuple())},
        {"a": "r1", "b": "r3", "accepted": False, "transform": None},
        {"a": "fleet", "b": "r3", "accepted": True, "transform": [0.0, 0.0, 0.0]},
        {"a": "r1", "b": "r2", "accepted": False, "pending": True, "transform": list(off.as_tuple())},
    ]
    out = _attempts_against_truth(recs, starts)
    regs = out["registrations"]
    assert regs[0]["truth_err_m"] < 1e-6 and regs[0]["truth_err_deg"] < 1e-6
    assert abs(regs[1]["truth_err_m"] - 3.0) < 1e-6
    assert "truth_err_m" not in regs[3] and "truth_err_m" not in regs[4]
    assert out["registration_truth"] == {"accepted_right": 1, "accepted_wrong": 0, "pending_right": 0,
                                         "pending_wrong": 1, "refused_right": 1, "refused_wrong": 1}
    assert _attempts_against_truth(recs, {})["registration_truth"] == {}


def test_a_drifting_robot_is_scored_at_its_walls_too():
    """A robot whose own map turned 3 degrees about its start (drift), registered so that its
    walls lie on the other robot's: at its start the registration is 3 degrees off the true
    relative start (``registration_errors``: wrong by the 2-degree line), at its walls against
    the local truth it is right (``registration_errors_local``); a registration one metre off
    is off at its walls too."""
    from agents.fleet.unknown_run import _local_errors, _pose_errors

    walls = Wireframe.from_polylines([[(0, 0), (12, 0), (12, 3), (5, 3), (5, 9), (0, 9)], [(8, 6), (10, 6)]],
                                     closed=False)
    start_b = Pose(25.0, 14.0, 0.4)  # far from the walls: a small turn moves them far
    drift = Pose(0.0, 0.0, math.radians(3.0))
    maps = {"r1": walls, "r2": walls.transformed(drift.compose(start_b.inverse()))}
    starts = {"r1": Pose.identity(), "r2": start_b}
    right = start_b.compose(drift.inverse())  # lays r2's walls on r1's
    for found, local_ok in ((right, True), (right.compose(Pose(1.0, 0.0, 0.0)), False)):
        fr = {"fleet_root": "r1", "registered": ["r1", "r2"],
              "poses": {"r1": [0.0, 0.0, 0.0], "r2": list(found.as_tuple())}}
        at_start = _pose_errors(fr, starts)["r2"]
        local = _local_errors(fr, starts, maps)
        assert set(local) == {"r2"}
        if local_ok:
            assert abs(at_start["rot_err_deg"] - 3.0) < 1e-3, at_start
            assert local["r2"]["trans_err_m"] < 0.02 and local["r2"]["rot_err_deg"] < 0.1, local
        else:
            assert local["r2"]["trans_err_m"] > 0.9, local


def test_the_local_truth_owes_nothing_to_the_registrations_it_scores():
    """Three robots in a chain (r3's walls meet r2's, not r1's): r2 registered 1 m off, r3
    right. r2 is 1 m off at its walls; r3 is scored against r2 placed at r2's own local truth,
    not where the fleet put it, so r3 is right (with the others taken as registered, r3 would
    read 1 m off too)."""
    from agents.fleet.unknown_run import _local_errors

    a = [[(0, 0), (12, 0), (12, 2)], [(0, 4), (6, 4), (6, 7)], [(9, 3), (11, 5)]]
    b = [[(9, 3), (11, 5)], [(12, 2), (12, 0), (22, 0)], [(15, 4), (15, 8)], [(19, 2), (21, 3)],
         [(20, 6), (20, 9)]]
    c = [[(19, 2), (21, 3)], [(20, 6), (20, 9)], [(22, 0), (32, 0)], [(25, 4), (28, 4), (28, 7)]]
    starts = {"r1": Pose.identity(), "r2": Pose(10.0, -3.0, 0.5), "r3": Pose(24.0, -2.0, -0.7)}
    maps = {r: Wireframe.from_polylines(w, closed=False).transformed(starts[r].inverse())
            for r, w in (("r1", a), ("r2", b), ("r3", c))}
    found = {"r1": Pose.identity(), "r2": starts["r2"].compose(Pose(1.0, 0.0, 0.0)), "r3": starts["r3"]}
    fr = {"fleet_root": "r1", "registered": ["r1", "r2", "r3"],
          "poses": {r: list(p.as_tuple()) for r, p in found.items()}}
    local = _local_errors(fr, starts, maps)
    assert set(local) == {"r2", "r3"}
    assert abs(local["r2"]["trans_err_m"] - 1.0) < 0.02, local
    assert local["r3"]["trans_err_m"] < 0.02 and local["r3"]["rot_err_deg"] < 0.1, local


# ---------------------------------------------------------------- repeated buildings in a fleet
@cache
def _office_fleet(steps: int) -> dict[str, list[Wireframe]]:
    """The maps (in each robot's own frame, as sent) of `wiremap run --world office --robots 4
    --unknown-starts --seed 1`'s robots after each of their first ``steps`` scans, as that run
    was before the fleet shared its coverage out (each robot drove its own coverage route from
    its random start; that is where the false merge below was found), simulated here: the same
    routes and seeds as the run's, without processes or a bus."""
    from types import SimpleNamespace

    from agents.fleet.unknown_run import random_starts
    from agents.mapping_run import robot_steps
    from agents.sim.route import plan_route
    from agents.sim.world import load_world

    world, rng = load_world("office"), np.random.default_rng(1)
    routes = [plan_route(world, rng, start=s, clearance=0.4, use_world_route=False)
              for s in random_starts(world, 4, rng)]
    out: dict[str, list[Wireframe]] = {}
    for k, route in enumerate(routes):
        opts = SimpleNamespace(world="office", start=None, route=route, seed=1 + k + 1, particles=5,
                               threshold=0.2, resolution=0.05, extra={}, filter_overrides=None, duration=None)
        maps = []
        for i, s in enumerate(robot_steps(opts)):
            if i >= steps:
                break
            maps.append(s.filter.best)
        out[f"r{k + 1}"] = maps
    return out


def test_an_overlap_that_recurs_in_a_third_robots_map_is_not_joined() -> None:
    """The office world's r3 and r4 each saw one office first; registration matched them one
    office row apart (15 m off), with no sign of repetition in either map. r1 and r2 had
    already seen offices alike: the fleet refuses the join on their evidence."""
    from mapping.registration import prepare, recurrence_elsewhere, register_prepared

    maps = {rid: seq[39] for rid, seq in _office_fleet(60).items()}
    fa, fb = prepare(maps["r3"]), prepare(maps["r4"])
    res = register_prepared(fa, fb)
    assert res.accepted  # the pair alone: the false merge
    share, k = recurrence_elsewhere(fa, fb, res, [prepare(maps["r1"]), prepare(maps["r2"])])
    assert share > 0.55 and k in (0, 1)
    assert recurrence_elsewhere(fa, fb, res, []) == (0.0, -1)
    fr = FleetFrames(FramesConfig(confirm_after_s=0.0))
    for rid in maps:
        fr.track(rid)
    rec = fr.attempt(("r3", "r4"), lambda ms, root: maps[ms[0]])
    assert not rec.accepted and "recurs in r" in rec.reason, rec.reason
    assert fr.components() == {r: (r,) for r in ("r1", "r2", "r3", "r4")}
    off = FleetFrames(FramesConfig(confirm_after_s=0.0, recurrence=False))
    for rid in maps:
        off.track(rid)
    assert off.attempt(("r3", "r4"), lambda ms, root: maps[ms[0]]).accepted


def test_a_first_acceptance_waits_for_a_second_look() -> None:
    """Early on (scan 29, 14.5 s) no map shows the office repeated yet and the false match passes
    every test; it is only pending. r3's map never grows past the office it matched, so the
    second look waits the longest wait (60 s of the robots' time), sees r1's offices and
    refuses."""
    seqs = _office_fleet(60)
    fr = FleetFrames(FramesConfig(confirm_after_s=10.0, min_length_m=1.0))
    for rid in seqs:
        fr.track(rid)
    early = {rid: seq[28] for rid, seq in seqs.items()}
    rec = fr.attempt(("r3", "r4"), lambda ms, root: early[ms[0]], t=14.5, now=100.0)
    assert rec.pending and not rec.accepted and "pending" in rec.line()
    assert fr.components()["r3"] == ("r3",)  # not joined

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(float(early[m].edge_lengths().sum()) for m in members)

    assert fr.next_pair(length, now=100.1, t=24.4) != ("r3", "r4")  # not before the wait (maps unchanged)
    assert fr.next_pair(length, now=100.1) != ("r3", "r4")  # nor without the robots' clock
    assert fr.next_pair(length, now=100.1, t=24.5) != ("r3", "r4")  # nor before the maps outgrow the match
    assert fr.next_pair(length, now=100.1, t=74.5) == ("r3", "r4")  # due first after the longest wait
    late = {rid: seq[59] for rid, seq in seqs.items()}
    rec = fr.attempt(("r3", "r4"), lambda ms, root: late[ms[0]], t=74.5, now=100.1)
    assert not rec.accepted and not rec.pending and "repetitive" in rec.reason, rec.reason
    assert fr.components()["r3"] == ("r3",)


def test_a_second_look_waits_until_both_maps_outgrow_the_match() -> None:
    """Two robots that have each seen one office match it whole: the second look waits until
    each map holds twice the wall matched (where a copy would show), or the longest wait."""
    a, b = _halves("paper-small")
    maps = {"r1": a, "r2": b.transformed(Pose(5.0, -3.0, 1.0))}
    fr = FleetFrames(FramesConfig(confirm_after_s=10.0, confirm_max_s=60.0, min_length_m=1.0))
    fr.track("r1")
    fr.track("r2")
    first = fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=0.0)
    assert first.pending
    lengths = {"r1": 1.9 * first.support, "r2": 3.0 * first.support}

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(lengths[m] for m in members)

    assert fr.next_pair(length, t=30.0) is None  # r1's map short of twice the match
    assert fr.next_pair(length, t=60.0) == ("r1", "r2")  # the longest wait
    lengths["r1"] = 2.0 * first.support
    assert fr.next_pair(length, t=9.9) is None  # grown, but before the wait
    assert fr.next_pair(length, t=10.0) == ("r1", "r2")
    assert fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=10.0).accepted


def _two_robots() -> tuple[FleetFrames, dict[str, Wireframe], dict[str, float], Callable[..., float]]:
    """Two robots of paper-small's halves in unrelated frames, a wait of 10 s (5 s when still),
    and the wall lengths ``next_pair`` reads (edit ``lengths`` to grow a map)."""
    a, b = _halves("paper-small")
    maps = {"r1": a, "r2": b.transformed(Pose(5.0, -3.0, 1.0))}
    lengths = {"r1": 100.0, "r2": 80.0}

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(lengths[m] for m in members)

    fr = FleetFrames(FramesConfig(confirm_after_s=10.0, retry_after_s=5.0, min_length_m=1.0))
    fr.track("r1")
    fr.track("r2")
    return fr, maps, lengths, length


def test_a_pending_join_waits_on_the_service_clock_where_the_robots_clock_stands_still() -> None:
    """A log whose stamps do not move (belgioioso's, orebro's), or robots that are done: the wait
    runs on the service's clock, and only ``retry_after_s`` of it while no map changes."""
    fr, maps, lengths, length = _two_robots()
    assert fr.next_pair(length, now=0.0, t=7.0) == ("r1", "r2")
    assert fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=7.0, now=0.0).pending
    assert fr.next_pair(length, now=4.9, t=7.0) is None
    assert fr.next_pair(length, now=5.0, t=7.0) == ("r1", "r2")  # nothing changed: 5 s
    lengths["r2"] = 80.5  # a map changed (short of every retry rule): the whole wait
    assert fr.next_pair(length, now=9.9, t=7.0) is None
    assert fr.next_pair(length, now=10.0, t=7.0) == ("r1", "r2")
    assert fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=7.0, now=10.0).accepted


def test_a_second_look_refuses_a_transform_the_grown_maps_contradict() -> None:
    """A first look that matched (nearly) the whole smaller map: its transform is scored on the
    maps as they grew, and where the grown map's walls fall on the other's seen-free space past
    what acceptance allows, the join is refused (one office row apart, the office fleet's grown
    maps carried 4.5 m of such wall). A first look that matched a part of the map is not
    checked so (drift puts right transforms' walls on seen-free space as real maps grow)."""
    from mapping.registration import conflict_of, prepare

    a, b = _halves("paper-small")
    maps = {"r1": a, "r2": b.transformed(Pose(5.0, -3.0, 1.0))}
    grown = {"r1": a, "r2": maps["r2"].transformed(Pose(0.8, 0.3, 0.0))}  # now contradicts
    # every first look checked; none; the default (this match is 0.67 of the smaller map)
    for fraction, check in ((0.0, True), (1.01, False), (FramesConfig().confirm_conflict_fraction, False)):
        cfg = FramesConfig(confirm_after_s=2.0, confirm_growth=0.0, confirm_conflict_fraction=fraction)
        fr = FleetFrames(cfg)
        fr.track("r1")
        fr.track("r2")
        first = fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=0.0)
        assert first.pending and first.transform is not None
        assert (first.support_fraction >= fraction) is check
        second = fr.attempt(("r1", "r2"), lambda ms, root: grown[ms[0]], t=2.0)
        assert second.accepted is not check, second
        if check:
            assert "seen-free space" in second.reason and not second.pending
            T = Pose(*first.transform)
            c, limit = conflict_of(prepare(grown["r1"]), prepare(grown["r2"]), T)
            assert c > limit
            assert conflict_of(prepare(maps["r1"]), prepare(maps["r2"]), T)[0] <= limit


def test_a_pending_join_goes_on_when_a_side_grows_by_another_join() -> None:
    """r1-r2 is pending when r3 joins r1: r1 is still its component's root (same frame), so
    the first look's transform holds for (r1, r3) and r2, and the second look joins r2 (before,
    the pending join was dropped and r2 had to pass a new first look: orebro lost a robot so)."""
    a, b = _halves("paper-small")
    maps = {"r1": a, "r2": b.transformed(Pose(5.0, -3.0, 1.0)),
            "r3": _noisy(a, 3).transformed(Pose(-2.0, 4.0, 0.5))}
    lengths = {"r1": 100.0, "r2": 80.0, "r3": 100.0}

    def length(members: tuple[str, ...], root: str | None) -> float:
        return sum(lengths[m] for m in members)

    def fused(members: tuple[str, ...], root: str | None) -> Wireframe:
        return maps[root or members[0]]  # a component's map in its root's frame: the root's own

    fr = FleetFrames(FramesConfig(confirm_after_s=2.0, confirm_growth=0.0, min_length_m=1.0))
    for rid in maps:
        fr.track(rid)
    assert fr.attempt(("r1", "r2"), fused, t=0.0, now=0.0).pending
    assert fr.attempt(("r1", "r3"), fused).accepted  # no robots' clock: joined at once
    assert fr.components() == {"r1": ("r1", "r3"), "r2": ("r2",)}
    assert fr.next_pair(length, now=1.0, t=1.0) is None  # still waiting, under its new key
    assert fr.next_pair(length, now=2.0, t=2.0) == ("r1", "r2")
    rec = fr.attempt(("r1", "r2"), fused, t=2.0, now=2.0)
    assert rec.accepted and not rec.pending and rec.a_members == ("r1", "r3"), rec
    assert fr.components() == {"r1": ("r1", "r2", "r3")}


def test_a_pending_join_made_just_before_the_robots_stop_gets_its_second_look() -> None:
    """The robots' clock ran on after the first look and then stopped (the robots are done):
    their maps will not grow and no wait on that clock can end, so the second look comes
    ``retry_after_s`` of the service's clock after it stopped."""
    fr, maps, _lengths, length = _two_robots()
    assert fr.next_pair(length, now=0.0, t=220.0) == ("r1", "r2")
    assert fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=220.0, now=0.0).pending
    assert fr.next_pair(length, now=1.0, t=221.0) is None
    assert fr.next_pair(length, now=3.0, t=225.0) is None  # the robots' last step
    assert fr.next_pair(length, now=7.9, t=225.0) is None
    assert fr.next_pair(length, now=8.0, t=225.0) == ("r1", "r2")  # 5 s after the clock stopped
    assert fr.attempt(("r1", "r2"), lambda ms, root: maps[ms[0]], t=225.0, now=8.0).accepted


def _pending_pair() -> tuple[FusionState, RegistrationRecord | None, tuple[Wireframe, Wireframe, Pose, Pose]]:
    """A fusion core with r1 and r2 (paper-small's halves, unrelated frames, robots' time 1) and
    its first registration step (a pending join), with the maps and starts to send again."""
    a, b = _halves("paper-small")
    sa, sb = Pose(3.0, 2.0, 0.7), Pose(-20.0, 11.0, -2.4)
    st = FusionState()
    st.add(_msg("r1", a, sa, seq=1))
    st.add(_msg("r2", b, sb, seq=1))
    return st, st.register_step(t=st.registration_clock(), now=0.0), (a, b, sa, sb)


def test_the_fusion_core_joins_a_pending_pair_once_the_robots_clock_ran_on() -> None:
    """Through :class:`FusionState` as the service drives it (the robots' clock from the maps'
    ``meta["t"]``): the first acceptance leaves r2 an island; maps that do not grow wait the
    longest wait, and the second look 60 s of the robots' time later fuses it."""
    st, first, (a, b, sa, sb) = _pending_pair()
    assert first is not None and first.pending and not first.accepted
    st.fuse(full=True)
    assert st.fused_robots == ("r1",) and set(st.islands()) == {"r2"}
    assert st.register_step(t=st.registration_clock(), now=0.5) is None  # waiting: nothing due
    st.add(_msg("r1", a, sa, seq=12))  # 11 s of the robots' time later (same walls)
    st.add(_msg("r2", b, sb, seq=12))
    assert st.register_step(t=st.registration_clock(), now=1.0) is None  # the maps did not grow
    st.add(_msg("r1", a, sa, seq=62))  # 61 s later
    st.add(_msg("r2", b, sb, seq=62))
    second = st.register_step(t=st.registration_clock(), now=1.0)
    assert second is not None and second.accepted and not second.pending, second
    st.fuse(full=True)
    assert st.fused_robots == ("r1", "r2") and st.islands() == {}


def test_one_robot_far_in_the_future_does_not_end_a_pending_wait() -> None:
    """The wait runs on the robots' clock; a stolen robot whose maps say ``t`` = 1e9 (allowed by
    validation) must not make every second look due at once. The clock is the lower median of
    the robots' times: with r3 far ahead the pair still waits, and joins once the honest
    robots' time has run on."""
    st, first, (a, b, sa, sb) = _pending_pair()
    assert first is not None and first.pending
    small = Wireframe.from_polylines([[(0.0, 0.0), (2.0, 0.0)]])  # too little wall to be tried
    far = _msg("r3", small, Pose(40.0, 40.0, 1.0))
    st.add(dataclasses.replace(far, meta={**far.meta, "t": 1e9}))
    assert st.sim_time() == 1e9 and st.registration_clock() == 1.0
    assert st.register_step(t=st.registration_clock(), now=0.5) is None  # still waiting
    st.add(_msg("r1", a, sa, seq=62))
    st.add(_msg("r2", b, sb, seq=62))
    assert st.registration_clock() == 62.0
    second = st.register_step(t=st.registration_clock(), now=1.0)
    assert second is not None and second.accepted and second.b_members == ("r2",), second
