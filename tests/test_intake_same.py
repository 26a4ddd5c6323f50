"""A map sent again (its body byte for byte the robot's latest accepted body) takes the short
path of :meth:`FusionState.offer` (the body not read again, the values computed from the
wireframe kept: :mod:`agents.fleet.fusion.facts`) and gets exactly the outcome the full path
gives: every return value, drop reason and detail, counter, quarantine record, held map and
fused map, payload after payload.

The reference is a :class:`FusionState` whose decoder always reads the body and whose facts
are new for every payload (so no map is ever the latest map's object). Both are fed the same
payloads: honest robots re-sending their maps, and hostile variants of a re-sent body (an
older, equal or far-ahead seq, a new boot with and without a restart on the bus, another
start pose, another resolution, a broken CRC, another sender, the body replayed on another
robot's key, a clock gone back, a fleet that changed under an unchanged map, a spent work
budget, thresholds under which a map fails against itself)."""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
import pytest

from agents.fleet.fusion import FusionConfig, FusionState, decode_message, encode_message
from agents.fleet.fusion.budget import BudgetConfig, WorkBudget
from agents.fleet.fusion.facts import MapFacts
from agents.fleet.fusion.intake import InputLimits, implausible, over_budget
from agents.fleet.fusion.quarantine import QuarantineConfig, _samples, against_history, history_judge
from agents.fleet.fusion.state import RobotEntry
from agents.fleet.robot import robot_map_message
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.tree_util import robot_views
from wire_codec.message import MapMessage

T0 = 1_700_000_000 * 10**9
BOOT = T0 - 60 * 10**9


class FullPath(FusionState):
    """The reference: every payload's body decoded, no facts shared between two payloads."""

    def _decode(self, raw: bytes, prior: RobotEntry | None) -> tuple[MapMessage, Any, MapFacts]:
        msg = decode_message(raw, self._codec_limits)
        return msg, None, MapFacts(msg.wireframe)


ORIGIN = Pose.identity()


def payload(rid: str, wf: Wireframe, seq: int, origin: Pose = ORIGIN, boot: int = BOOT,
            resolution: float = 0.05, sender: str | None = None, stamp: int | None = None) -> bytes:
    stamp = T0 + min(seq, 1000) * 10**8 if stamp is None else stamp
    msg = robot_map_message(sender or rid, origin, resolution, wf, Pose.identity(), seq, stamp,
                            {"boot": boot, "t": 0.1 * seq, "step": seq})
    return encode_message(msg)


def snapshot(st: FusionState) -> Any:
    s = st.stats.as_dict()
    s.pop("same_body")
    s.pop("latency_ms")
    return (
        s,
        st.last_drop,
        {r: (e.key, e.rev, e.gen, e.since_ns, e.at_ns, e.raw) for r, e in sorted(st.robots.items())},
        st.quarantine.summary(),
        {r: raw for r, (_, raw) in sorted(st.held.items())},
        sorted(st._held_restart),
        sorted(st._pending.items()),
        dict(st.forgotten),
    )


class Pair:
    """The state under test and the reference, fed alike and compared after every step."""

    def __init__(self, quarantine: QuarantineConfig | None = None, **kw: Any) -> None:
        cfg = FusionConfig(threshold=0.4, refine=False)
        q = QuarantineConfig() if quarantine is None else quarantine
        self.new = FusionState(cfg, quarantine=q, **kw)
        self.ref = FullPath(cfg, quarantine=q, **kw)
        for st in (self.new, self.ref):
            st.restart_by_token = True

    def offer(self, data: bytes, key: str, now: int) -> bool:
        a = self.new.offer(data, key, now)
        b = self.ref.offer(data, key, now)
        assert a == b
        assert snapshot(self.new) == snapshot(self.ref)
        return a

    def offer_latest(self, group: list[bytes], key: str, now: int) -> None:
        a = self.new.offer_latest(group, key, now)
        b = self.ref.offer_latest(group, key, now)
        assert a == b
        assert snapshot(self.new) == snapshot(self.ref)

    def alive(self, rid: str, now: int) -> None:
        self.new.note_alive(rid, now)
        self.ref.note_alive(rid, now)
        assert snapshot(self.new) == snapshot(self.ref)

    def fuse(self) -> None:
        assert self.new.fuse(max_realign=0) == self.ref.fuse(max_realign=0)
        assert encode_message(self.new.fused_message(0)) == encode_message(self.ref.fused_message(0))
        assert snapshot(self.new) == snapshot(self.ref)


def views(n: int = 12, seed: int = 3) -> list[MapMessage]:
    return robot_views("museum", n, seed=seed)


def test_honest_resends_take_the_short_path_with_the_same_outcomes() -> None:
    p = Pair()
    msgs = views()
    for j in range(12):
        now = T0 + j * 10**8 + 5 * 10**7
        for m in msgs:
            wf = m.wireframe
            if j % 4 == 3:  # a change now and then
                wf = wf.subgraph_edges(np.arange(wf.n_edges) % 5 != 0)
            p.offer(payload(m.sender, wf, j + 1, m.origin), m.sender, now)
        p.fuse()
    s = p.new.stats
    assert s.same_body >= 0.4 * s.received  # half of them were sent again
    assert p.ref.stats.same_body == 0
    assert s.accepted == s.received


def test_hostile_variants_of_a_resent_body() -> None:
    p = Pair()
    msgs = views(8)
    now = T0
    for j in range(3):  # an accepted fleet, every map twice
        now = T0 + j * 10**8
        for m in msgs:
            p.offer(payload(m.sender, m.wireframe, j + 1, m.origin), m.sender, now)
        p.fuse()
    m = msgs[0]
    rid, wf = m.sender, m.wireframe
    raw = payload(rid, wf, 4, m.origin)
    now += 10**8
    p.offer(raw, rid, now)  # accepted, same content
    p.offer(raw, rid, now)  # duplicates (the same bytes)
    p.offer(payload(rid, wf, 2, m.origin), rid, now)  # outdated
    p.offer(payload(rid, wf, 10**6, m.origin), rid, now)  # absurd: seq_jump
    assert p.new.last_drop is not None and p.new.last_drop[1] == "seq_jump"
    bad = bytearray(payload(rid, wf, 5, m.origin))
    bad[-1] ^= 0x5A  # the CRC
    p.offer(bytes(bad), rid, now)  # malformed
    bad = bytearray(payload(rid, wf, 5, m.origin))
    bad[-8] ^= 0x01  # inside the body, CRC not redone
    p.offer(bytes(bad), rid, now)
    body_flip = bytearray(payload(rid, wf, 5, m.origin))  # a body byte changed and the CRC redone
    body_flip[-7] ^= 0x10
    body_flip[-4:] = zlib.crc32(bytes(body_flip[:-5])).to_bytes(4, "big")
    p.offer(bytes(body_flip), rid, now)
    p.offer(payload(rid, wf, 6, m.origin, sender=msgs[1].sender), rid, now)  # sender_mismatch
    p.offer(payload(msgs[1].sender, wf, 7, m.origin), msgs[1].sender, now)  # r1's body on r2's key
    p.offer(payload(rid, wf, 8, m.origin, resolution=0.04), rid, now)  # another resolution
    p.offer(payload(rid, wf, 9, Pose(m.origin.x + 4.0, m.origin.y - 3.0, m.origin.theta + 0.3)), rid, now)
    p.offer(payload(rid, wf, 10, m.origin), rid, now)  # back to its start pose
    p.offer(payload(rid, wf, 11, m.origin), rid, T0 - 10**12)  # the fusion's clock far back
    far = Wireframe.build([[70.0, 0.0], [75.0, 0.0], [75.0, 4.0]], [[0, 1], [1, 2]])  # 70 m from the start
    p.offer(payload("far", far, 1), "far", now)  # accepted (60 s after its boot)
    p.offer(payload("far", far, 2), "far", BOOT + 3 * 10**9)  # the same map, 3 s after its boot: reach
    p.offer(payload(rid, wf, 12, m.origin, boot=BOOT + 10**9), rid, now)  # a new boot, no restart seen
    p.alive(rid, now)  # the token: the held restart is taken
    p.offer(payload(rid, wf, 1, m.origin, boot=BOOT + 2 * 10**9), rid, now)
    p.offer(payload(rid, wf, 13, m.origin, boot=BOOT - 10**9), rid, now)  # an older boot: outdated
    p.offer(payload(rid, wf, 14, m.origin, boot=T0 + 10**15), rid, now)  # a boot from the future
    p.offer_latest([payload(rid, wf, 20, m.origin, boot=BOOT + 2 * 10**9), bytes(bad),
                    payload(rid, wf, 21, m.origin, boot=BOOT + 2 * 10**9)], rid, now)
    p.fuse()
    drops = {r for by in ("absurd_by", "rejected_by", "malformed_by") for r in p.new.stats.as_dict()[by]}
    assert {"seq_jump", "sender_mismatch", "reach", "future", "ChecksumError"} <= drops
    assert p.new.stats.same_body >= 8


def walls(a: np.ndarray, b: np.ndarray) -> Wireframe:
    """One wall from each point of ``a`` to the same row of ``b``."""
    m = len(a)
    return Wireframe.build(np.concatenate([a, b]), np.stack([np.arange(m), np.arange(m, 2 * m)], 1))


def beside(wf: Wireframe, d: float) -> Wireframe:
    """Walls parallel to ``wf``'s, ``d`` metres to their left (in the free space beside them)."""
    seg = wf.segments()
    u = (seg[:, 1] - seg[:, 0]) / np.hypot(*(seg[:, 1] - seg[:, 0]).T)[:, None]
    off = d * np.stack([-u[:, 1], u[:, 0]], axis=1)
    m = len(seg)
    return Wireframe.build(np.concatenate([seg[:, 0] + off, seg[:, 1] + off]),
                           np.stack([np.arange(m), np.arange(m, 2 * m)], 1))


def test_an_unchanged_map_is_judged_against_the_present_fleet() -> None:
    """A robot re-sends the map it had accepted when the fused map was empty: walls beside
    another robot's, in its free space. Meanwhile the others' maps were fused: the fleet test
    runs on the re-sent map against the present fleet and quarantines it, on both paths."""
    p = Pair(QuarantineConfig(min_overlap_m=5.0))
    msgs = views(6, seed=5)
    junk = beside(msgs[1].wireframe, 2.5)
    quarantined = 0
    for j in range(1, 6):
        now = T0 + j * 10**8
        p.offer(payload("lone", junk, j, msgs[1].origin), "lone", now)
        quarantined += p.new.last_drop is not None and p.new.last_drop[0] == "quarantined"
        for m in msgs[1:]:
            p.offer(payload(m.sender, m.wireframe, j, m.origin), m.sender, now)
        p.fuse()
    assert quarantined > 0
    assert p.new.stats.same_body > 0
    assert p.new.quarantine.summary()["lone"]["reason"] == "fleet_walls"


def test_a_map_that_fails_against_itself_is_quarantined_on_both_paths() -> None:
    """Thresholds under which a map contradicts itself (negative growth, nothing may disagree
    and everything is judged): the short path must not pass it."""
    for cfg in (QuarantineConfig(growth_slack_m=-1000.0),
                QuarantineConfig(min_overlap_m=0.0, max_disagree=-1.0, far_m=0.0)):
        p = Pair(cfg)
        m = views(1)[0]
        for j in range(1, 5):
            p.offer(payload(m.sender, m.wireframe, j, m.origin), m.sender, T0 + j * 10**8)
        assert p.new.stats.quarantined > 0


def test_held_for_the_work_budget() -> None:
    p = Pair()
    for st in (p.new, p.ref):
        st.budget = WorkBudget(BudgetConfig(share=0.0, burst_s=1e-12))
    m = views(1)[0]
    for j in range(1, 5):
        p.offer(payload(m.sender, m.wireframe, j, m.origin), m.sender, T0 + j * 10**8)
    assert p.new.stats.held > 0


@pytest.mark.parametrize("seed", range(4))
def test_history_judge_of_a_map_against_itself(seed: int) -> None:
    """:func:`history_judge` given the same object twice (its proved pass) against
    :func:`against_history` on an equal copy, under sensible and absurd thresholds."""
    rng = np.random.default_rng(seed)
    maps = [m.wireframe for m in views(6, seed)] + [Wireframe.empty()]
    a = rng.uniform(-15, 15, (10, 2))
    maps.append(walls(a, a + 0.2))
    cfgs = [QuarantineConfig(), QuarantineConfig(growth_slack_m=-1000.0),
            QuarantineConfig(growth_slack_m=-45.0),
            QuarantineConfig(min_overlap_m=0.0, max_disagree=-1.0), QuarantineConfig(far_m=0.0),
            QuarantineConfig(far_m=float("nan")), QuarantineConfig(max_disagree=float("nan")),
            QuarantineConfig(min_overlap_m=float("nan")), QuarantineConfig(sample_m=0.3, min_overlap_m=-1.0),
            QuarantineConfig(sample_m=float("inf"))]
    for wf in maps:
        copy = Wireframe(wf.points.copy(), wf.labels.copy(), wf.edges.copy(), wf.likelihood.copy(),
                         wf.sources.copy())
        for cfg in cfgs:
            for seconds, speed, rng_m in ((0.1, 3.0, 40.0), (0.0, 0.0, 0.0), (5.0, 3.0, -60.0)):
                want = against_history(copy, wf, seconds, speed, rng_m, cfg)
                assert history_judge(wf, wf, seconds, speed, rng_m, cfg) == want, (cfg, seconds)


def _former_samples(wf: Wireframe, step: float) -> tuple[np.ndarray, np.ndarray]:
    """``_samples`` as it was written before issue 21's part 3 (the reference)."""
    if wf.n_edges == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    seg = wf.points[wf.edges]
    length = np.hypot(*(seg[:, 1] - seg[:, 0]).T)
    k = np.maximum(1, np.ceil(length / step).astype(np.int64))
    owner = np.repeat(np.arange(len(seg)), k)
    t = (np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k) + 0.5) / k[owner]
    return seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0]), owner


def test_samples_are_the_former_ones_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    maps = [m.wireframe for m in views(8)] + [Wireframe.empty()]
    for _ in range(100):
        n = int(rng.integers(2, 60))
        pts = rng.uniform(-50, 50, (n, 2)) * rng.choice([1e-3, 1.0, 10.0])
        maps.append(Wireframe.build(pts, np.stack([np.arange(n - 1), np.arange(1, n)], 1)))
    for wf in maps:
        for step in (1.0, 0.5, 0.3, 7.0):
            a, ao = _samples(wf, step)
            b, bo = _former_samples(wf, step)
            assert a.shape == b.shape and a.tobytes() == b.tobytes() and np.array_equal(ao, bo)


def test_content_checks_with_kept_facts_give_the_same_verdicts() -> None:
    """:func:`implausible` and :func:`over_budget` with a map's facts (asked twice: the second
    answer comes from what was kept) against without, on honest, dense, long, far and moved
    maps under default and tight limits, at several clocks."""
    rng = np.random.default_rng(11)
    maps = [m.wireframe for m in views(6)]
    a = rng.uniform(0.0, 0.5, (60, 2))  # 120 vertices in one square metre
    maps.append(walls(a, a + 0.3))
    maps.append(Wireframe.build([[0.0, 0.0], [900.0, 0.0]], [[0, 1]]))
    tight = InputLimits(max_robot_vertices=20, max_robot_wall_m=50.0, max_cell_vertices=2,
                        max_cell_wall_m=2.0, sensor_range_m=5.0, max_speed_mps=0.1, max_extent_m=100.0)
    seen = set()
    for wf in maps:
        facts = MapFacts(wf)
        for origin in (Pose.identity(), Pose(30.0, -20.0, 1.0), Pose(95.0, 0.0, 0.0)):
            msg = robot_map_message("r1", origin, 0.05, wf, Pose.identity(), 1, T0, {"boot": BOOT})
            for limits in (InputLimits(), tight):
                for now in (None, BOOT, T0, T0 + 10**12):
                    want = (implausible(msg, limits, now), over_budget(msg, limits, now))
                    for _ in range(2):
                        got = (implausible(msg, limits, now, facts), over_budget(msg, limits, now, facts))
                        assert got == want
                    seen.update(v[0] for v in want if v is not None)
    assert {"extent", "budget_vertices", "budget_walls", "budget_density", "reach"} <= seen
