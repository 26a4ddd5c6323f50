"""Quarantine (agents/fleet/fusion/quarantine.py): maps inconsistent with their robot's own
history or with the other robots' walls are kept aside, counted, never merged; honest maps that
grow and wobble are not; robot ids that never send a plausible map are forgotten."""

from __future__ import annotations

import numpy as np

from agents.fleet.fusion import FusionConfig, FusionState, encode_message
from agents.fleet.fusion.intake import InputLimits, too_dense
from agents.fleet.fusion.quarantine import FleetView, QuarantineConfig, _cell_codes
from agents.sim.world import load_world
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from wire_codec.message import MapMessage, MessageKind

S = 10**9
BOOT = 10**18


def part(truth: Wireframe, centre: tuple[float, float], radius: float) -> Wireframe:
    """The truth's edges with both ends within ``radius`` of ``centre``."""
    d = np.hypot(truth.points[:, 0] - centre[0], truth.points[:, 1] - centre[1])
    keep = (d[truth.edges[:, 0]] <= radius) & (d[truth.edges[:, 1]] <= radius)
    used = np.unique(truth.edges[keep])
    index = np.full(truth.n_vertices, -1)
    index[used] = np.arange(len(used))
    return Wireframe.build(truth.points[used], index[truth.edges[keep]])


def raw_map(rid: str, wf_fleet: Wireframe, origin: Pose, seq: int, boot: int = BOOT) -> bytes:
    """A robot map sent in its odometry frame (the fleet-frame walls moved by origin^-1)."""
    return encode_message(
        MapMessage(
            kind=MessageKind.ROBOT_MAP, sender=rid, seq=seq, stamp_ns=boot + seq * S, pose=Pose.identity(),
            frame=f"odom/{rid}", origin=origin, resolution=0.05,
            wireframe=wf_fleet.transformed(origin.inverse()),
            meta={"boot": boot, "t": float(seq), "step": seq},
        )
    )  # fmt: skip


def fleet() -> tuple[FusionState, Wireframe]:
    truth = load_world("museum").truth
    # first maps of up to 150 m (a robot the fleet has heard of for a while; see test_a_first_map...)
    cfg = QuarantineConfig(growth_slack_m=100.0)
    st = FusionState(FusionConfig(threshold=0.4, refine=False), quarantine=cfg, limits=InputLimits())
    return st, truth


def test_honest_growing_maps_are_never_quarantined() -> None:
    st, truth = fleet()
    rng = np.random.default_rng(3)
    starts = {"r1": (40.0, 40.0), "r2": (60.0, 50.0)}
    for seq in range(1, 40):
        for rid, c in starts.items():
            origin = Pose(c[0], c[1], 0.3)
            wf = part(truth, c, 5.0 + 2.0 * seq)
            wobble = Wireframe.build(
                wf.points + rng.normal(0, 0.15, wf.points.shape), wf.edges
            )  # a particle's drift
            assert st.offer(raw_map(rid, wobble, origin, seq), rid, BOOT + seq * S + S // 2) or True
        st.fuse()
    assert st.stats.quarantined == 0, st.quarantine.summary()
    assert st.stats.accepted == 78


def test_a_map_shifted_from_its_own_history_is_quarantined_and_not_merged() -> None:
    st, truth = fleet()
    origin = Pose(50.0, 50.0, 0.0)
    big = part(truth, (50.0, 50.0), 40.0)
    assert st.offer(raw_map("r1", big, origin, 1), "r1", BOOT + S)
    st.fuse()
    before = st.fused
    shifted = big.transformed(Pose(8.0, 5.0, 0.2))
    assert not st.offer(raw_map("r1", shifted, origin, 2), "r1", BOOT + 2 * S)
    assert st.stats.quarantined_by == {"history_walls": 1}
    assert st.last_drop is not None and st.last_drop[0] == "quarantined"
    assert "r1" in st.quarantine.summary()
    st.fuse()
    assert st.fused is before or st.fused.content_digest() == before.content_digest()
    # the next consistent map is accepted and clears the quarantine entry
    assert st.offer(raw_map("r1", big, origin, 3), "r1", BOOT + 3 * S) is False  # same content as before
    assert "r1" not in st.quarantine.summary()


def test_an_extent_jump_is_quarantined() -> None:
    truth = load_world("museum").truth
    st = FusionState(FusionConfig(threshold=0.4, refine=False), quarantine=QuarantineConfig())
    origin = Pose(50.0, 50.0, 0.0)
    small = part(truth, (50.0, 50.0), 30.0)
    assert st.offer(raw_map("r1", small, origin, 1), "r1", BOOT + 100 * S)  # within its reach after 100 s
    far = Wireframe.build(np.concatenate([small.points, [[180.0, 180.0], [181.0, 180.0]]]),
                          np.concatenate([small.edges, [[small.n_vertices, small.n_vertices + 1]]]))  # fmt: skip  # noqa: E501
    assert not st.offer(raw_map("r1", far, origin, 2), "r1", BOOT + 101 * S)  # but not one second later
    assert st.stats.quarantined_by == {"extent_jump": 1}


def beside_walls(st: FusionState) -> Wireframe:
    """2 m walls 2.5 m beside the fleet's walls, in the cells the fleet has seen well (where it
    saw free space)."""
    cfg = QuarantineConfig()
    view = FleetView.of(st.fused, cfg)
    seg = st.fused.segments()
    seg = seg[np.hypot(*(seg[:, 1] - seg[:, 0]).T) > 3.0]
    d = (seg[:, 1] - seg[:, 0]) / np.hypot(*(seg[:, 1] - seg[:, 0]).T)[:, None]
    a = seg.mean(axis=1) + 2.5 * np.stack([-d[:, 1], d[:, 0]], axis=1)
    keep = np.isin(_cell_codes(a, cfg.cell_m), view.cells)
    a, d = a[keep], d[keep]
    n = len(a)
    return Wireframe.build(np.concatenate([a, a + 2.0 * d]),
                           np.stack([np.arange(n), np.arange(n, 2 * n)], axis=1))


def test_walls_in_the_fleets_free_space_are_quarantined() -> None:
    st, truth = fleet()
    for rid, c in (("r1", (50.0, 50.0)), ("r2", (100.0, 100.0))):
        assert st.offer(raw_map(rid, part(truth, c, 60.0), Pose(c[0], c[1], 0.0), 1), rid, BOOT + 100 * S)
    st.fuse()
    junk = beside_walls(st)
    assert not st.offer(raw_map("r3", junk, Pose(75.0, 75.0, 0.0), 1), "r3", BOOT + 100 * S)
    assert st.stats.quarantined_by == {"fleet_walls": 1}
    assert "r3" not in st.robots and "r3" in st.quarantine.summary()
    # an honest newcomer on the same rooms is accepted
    assert st.offer(raw_map("r4", part(truth, (80.0, 80.0), 30.0), Pose(80.0, 80.0, 0.0), 1), "r4",
                    BOOT + 100 * S)


def test_an_id_that_never_sends_a_plausible_map_is_forgotten() -> None:
    st, truth = fleet()
    st.offer(raw_map("r1", part(truth, (100.0, 100.0), 80.0), Pose(100.0, 100.0, 0.0), 1), "r1",
             BOOT + 100 * S)
    st.fuse()
    junk = beside_walls(st)
    t = BOOT + 100 * S
    for seq in range(1, 5):
        st.offer(raw_map("evil", junk, Pose(50.0, 50.0, 0.0), seq), "evil", t + seq * S)
    assert st.forget_implausible(t + 10 * S) == []
    assert st.forget_implausible(t + 301 * S) == ["evil"]
    assert "evil" not in st.quarantine.summary() and "never plausible" in st.forgotten["evil"]
    assert st.forget_implausible(t + 400 * S) == []  # r1 had a map accepted: never forgotten


def test_stacked_walls_are_over_the_density_budget() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 1.0, size=(200, 2))
    wf = Wireframe.build(pts, np.stack([np.arange(199), np.arange(1, 200)], axis=1))
    assert too_dense(wf, InputLimits()) is not None
    star = Wireframe.build(np.array([[0.5, 0.5]] + [[0.5 + 3 * np.cos(a), 0.5 + 3 * np.sin(a)] for a in np.linspace(0, 6, 40)]),  # noqa: E501
                           np.array([[0, k] for k in range(1, 41)]))  # fmt: skip
    bad = too_dense(star, InputLimits(max_cell_vertices=100))
    assert bad is not None and "walls" in bad[1]
    truth = load_world("museum").truth
    assert too_dense(truth, InputLimits()) is None


def test_a_first_map_reaches_no_further_than_since_the_fusion_heard_of_the_robot() -> None:
    truth = load_world("museum").truth
    st = FusionState(FusionConfig(threshold=0.4, refine=False), quarantine=QuarantineConfig())
    t = BOOT + 3600 * S  # it claims to have been up for an hour (reach 10.9 km by its boot)
    assert st.offer(raw_map("r0", part(truth, (40.0, 40.0), 20.0), Pose(40.0, 40.0, 0.0), 1),
                    "r0", t - 60 * S)
    big = part(truth, (100.0, 100.0), 70.0)
    assert not st.offer(raw_map("r1", big, Pose(30.0, 30.0, 0.0), 1), "r1", t)
    assert st.stats.quarantined_by == {"extent_jump": 1} and st.last_drop is not None
    assert "first map" in st.last_drop[2]
    assert st.offer(raw_map("r1", big, Pose(30.0, 30.0, 0.0), 2), "r1", t + 60 * S)  # 60 s later: 230 m


def test_robots_already_sending_when_the_state_began_keep_their_claimed_boot() -> None:
    """A fusion service started late (no store, a takeover in a fusion tree) takes the first maps
    of robots it hears of in its first 3 s by their claimed boot (over_budget's reach)."""
    truth = load_world("museum").truth
    st = FusionState(FusionConfig(threshold=0.4, refine=False), quarantine=QuarantineConfig())
    t = BOOT + 3600 * S
    big = part(truth, (100.0, 100.0), 70.0)
    assert st.offer(raw_map("r1", big, Pose(30.0, 30.0, 0.0), 1), "r1", t)
    assert st.offer(raw_map("r2", big, Pose(30.0, 30.0, 0.0), 1), "r2", t + 2 * S)
    assert st.stats.quarantined == 0
