"""The quarantine's cheaper judges (issue 21) give the references' verdicts, bit for bit.

* :meth:`FleetSamples.judge` (one k-d tree over the whole fused map, per-cell edge lists)
  against :func:`against_fleet` over :meth:`FleetSamples.view` (the k-d tree of the other
  robots' walls that was built for every map); its near test :meth:`FleetSamples._near_kept`
  against that tree's finite distances, point for point;
* :func:`history_judge` (no k-d tree when the walls a map shares with its last one, exactly,
  leave too few points to pass ``max_disagree``) against :func:`against_history`.

On honest maps, hostile ones (shifted, turned, junk beside the walls, a stolen map), random
ones and under loose and tight thresholds (so that both verdicts occur)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.fleet.fusion import FusionConfig, FusionState, encode_message
from agents.fleet.fusion.quarantine import (
    FleetSamples,
    QuarantineConfig,
    against_fleet,
    against_history,
    edge_keys,
    history_judge,
)
from mapping.se2 import Pose
from mapping.wireframe import Wireframe
from tests.tree_util import robot_views

CONFIGS = [
    QuarantineConfig(),
    QuarantineConfig(sample_m=0.7, cell_m=3.0, far_m=0.5),
    QuarantineConfig(min_overlap_m=0.0, max_disagree=0.05),  # judges nearly everything
    QuarantineConfig(min_overlap_m=5.0, max_disagree=0.2, far_m=0.3),
    QuarantineConfig(min_overlap_m=0.0, max_disagree=-1.0),  # nothing passes that is judged at all
]


def fused_fleet(n: int) -> tuple[FusionState, list[Wireframe]]:
    st = FusionState(FusionConfig(threshold=0.4, refine=False))
    msgs = robot_views("museum", n, seed=1)
    for m in msgs:
        st.offer(encode_message(m), m.sender)
    st.fuse()
    return st, [m.wireframe.transformed(m.origin) for m in msgs]


def candidates(fleet_maps: list[Wireframe], rng: np.random.Generator) -> list[Wireframe]:
    """Fleet-frame maps to judge: the robots' own, moved a little and a lot, cut, junk."""
    out: list[Wireframe] = []
    for wf in fleet_maps:
        out.append(wf)
        for dx, dy, th in ((0.3, 0.0, 0.0), (1.5, -1.0, 0.0), (6.0, 3.0, 0.3), (0.0, 0.0, 0.05)):
            c = wf.points.mean(axis=0)
            move = Pose(*c).compose(Pose(dx, dy, th)).compose(Pose(*(-c)))
            out.append(wf.transformed(move))
        if wf.n_edges > 2:
            out.append(wf.subgraph_edges(rng.random(wf.n_edges) < 0.5))
    lo = np.min([w.points.min(axis=0) for w in fleet_maps if w.n_vertices], axis=0)
    hi = np.max([w.points.max(axis=0) for w in fleet_maps if w.n_vertices], axis=0)
    for m in (3, 20, 80):  # random walls over the fleet's extent
        a = rng.uniform(lo, hi, (m, 2))
        b = a + rng.normal(0.0, 4.0, (m, 2))
        out.append(Wireframe.build(np.concatenate([a, b]), np.stack([np.arange(m), np.arange(m, 2 * m)], 1)))
    out.append(Wireframe.empty())
    return out


@pytest.mark.parametrize("n", [3, 16])
def test_fleet_judge_is_against_fleet_over_the_view(n: int) -> None:
    st, maps = fused_fleet(n)
    rng = np.random.default_rng(n)
    cands = candidates(maps, rng)
    verdicts = set()
    for cfg in CONFIGS:
        samples = FleetSamples.of(st.fused, cfg)
        for bit in [None, 0, 1, n // 2, n - 1, n + 3, 70]:
            view = samples.view(bit)
            for wf in cands:
                ref = against_fleet(wf, view, cfg)
                assert samples.judge(wf, bit) == ref, (cfg, bit)
                verdicts.add(ref is None)
    assert verdicts == {True, False}  # both verdicts were compared


@pytest.mark.parametrize("n", [3, 16])
def test_near_kept_is_the_views_finite_distance(n: int) -> None:
    st, _ = fused_fleet(n)
    rng = np.random.default_rng(7)
    lo, hi = st.fused.points.min(axis=0), st.fused.points.max(axis=0)
    pts = np.concatenate([rng.uniform(lo, hi, (3000, 2)), st.fused.points, st.fused.points + 0.9])
    for cfg in CONFIGS[:2]:
        samples = FleetSamples.of(st.fused, cfg)
        for bit in [None, 0, 1, n - 1, 70]:
            view = samples.view(bit)
            assert view.near is not None
            d, _ = view.near.query(pts, distance_upper_bound=cfg.far_m + cfg.sample_m / 4)
            keep = np.ones(st.fused.n_edges, bool) if bit is None else (
                (st.fused.sources & ~(np.uint64(1) << np.uint64(min(bit, 63)))) != 0 if bit < 64
                else st.fused.sources != 0)
            got = samples._near_kept(pts, keep[samples.near_owner], bit is None)
            assert np.array_equal(got, np.isfinite(d))


def test_fleet_judge_with_wide_masks_and_empty_maps() -> None:
    st, maps = fused_fleet(16)
    wide = st.fused.replace(sources=np.array([int(s) << 60 for s in st.fused.sources.tolist()], dtype=object))
    cands = candidates(maps[:4], np.random.default_rng(0))
    for cfg in CONFIGS[::2]:
        samples = FleetSamples.of(wide, cfg)
        for bit in [None, 60, 61, 64, 66]:
            view = samples.view(bit)
            for wf in cands:
                assert samples.judge(wf, bit) == against_fleet(wf, view, cfg)
    empty = FleetSamples.of(Wireframe.empty(), QuarantineConfig())
    assert empty.judge(maps[0], 1) is None and empty.judge(maps[0], None) is None


def grown(old: Wireframe, rng: np.random.Generator, extra: int, spread: float) -> Wireframe:
    """``old``'s walls (same end points, vertices shuffled) plus ``extra`` new walls near them."""
    perm = rng.permutation(old.n_vertices)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    pts = old.points[perm]
    edges = inv[old.edges]
    a = old.points[rng.integers(old.n_vertices, size=extra)] + rng.normal(0.0, spread, (extra, 2))
    b = a + rng.normal(0.0, 2.0, (extra, 2))
    n = len(pts)
    return Wireframe.build(np.concatenate([pts, a, b]),
                           np.concatenate([edges, np.stack([np.arange(n, n + extra), np.arange(n + extra, n + 2 * extra)], 1)]))  # fmt: skip  # noqa: E501


def test_history_judge_is_against_history() -> None:
    rng = np.random.default_rng(5)
    maps = [m.wireframe for m in robot_views("museum", 12, seed=2, radius=30.0)]
    verdicts = set()
    shortcut = 0  # the last new map lies wholly outside the old one's box (nothing inside)
    for cfg in CONFIGS:
        for old in maps:
            news = [old, grown(old, rng, 3, 0.5), grown(old, rng, 40, 0.5), grown(old, rng, 200, 3.0),
                    grown(old, rng, 40, 30.0), old.transformed(Pose(2.0, 1.0, 0.1)),
                    old.transformed(Pose(0.2, 0.0, 0.0)), old.subgraph_edges(rng.random(old.n_edges) < 0.7),
                    Wireframe.build(old.points.max(axis=0) + np.array([[1.0, 1.0], [3.0, 1.0]]), [[0, 1]]),
                    Wireframe.empty()]  # fmt: skip
            keys = set(edge_keys(old))
            for new in news:
                for seconds in (0.1, 5.0):
                    ref = against_history(new, old, seconds, 2.0, 10.0, cfg)
                    assert history_judge(new, old, seconds, 2.0, 10.0, cfg, keys) == ref
                    assert history_judge(new, old, seconds, 2.0, 10.0, cfg) == ref
                    verdicts.add(None if ref is None else ref[0])
                    shortcut += ref is None
    assert verdicts == {None, "history_walls", "extent_jump"}
    assert shortcut


def test_history_judge_skips_the_tree_for_a_grown_map(monkeypatch: pytest.MonkeyPatch) -> None:
    """An honest map that grew by a few walls is judged without a k-d tree (the shortcut is
    taken), a map moved away from its history still is (and is refused)."""
    import agents.fleet.fusion.quarantine as q

    old = robot_views("museum", 1, seed=3, radius=40.0)[0].wireframe
    new = grown(old, np.random.default_rng(0), 4, 0.5)
    cfg = QuarantineConfig()
    calls: list[int] = []
    real = q._near

    def counted(wf: Wireframe, c: QuarantineConfig) -> object:
        calls.append(1)
        return real(wf, c)

    monkeypatch.setattr(q, "_near", counted)
    assert history_judge(new, old, 1.0, 2.0, 10.0, cfg) is None
    assert calls == []
    moved = old.transformed(Pose(3.0, 2.0, 0.2))
    bad = history_judge(moved, old, 1.0, 2.0, 10.0, cfg)
    assert bad is not None and bad[0] == "history_walls" and calls == [1]


def test_near_kept_looks_past_many_own_points() -> None:
    """A robot's own walls crowding a point: the kept point behind them is still found (the
    query widens 4, 16, 64, ... up to every point), and one just past the bound is not."""
    rng = np.random.default_rng(11)
    m = 150
    a = rng.uniform(-0.4, 0.4, (m, 2))  # robot 0's short walls around the origin
    own = Wireframe.build(np.concatenate([a, a + 0.05]), np.stack([np.arange(m), np.arange(m, 2 * m)], 1))
    cfg = QuarantineConfig()
    for far_x, found in ((1.1, True), (1.5, False)):
        other = Wireframe.build(np.array([[far_x, -0.01], [far_x, 0.01]]), np.array([[0, 1]]))
        pts = np.concatenate([own.points, other.points])
        edges = np.concatenate([own.edges, other.edges + own.n_vertices])
        src = np.concatenate([np.full(m, 1, np.uint64), np.full(1, 2, np.uint64)])
        fused = Wireframe(pts, np.zeros(len(pts), np.uint8), edges.astype(np.int32), np.full(m + 1, 0.6), src)
        samples = FleetSamples.of(fused, cfg)
        q = np.array([[0.0, 0.0], [0.1, 0.05]])
        view = samples.view(0)
        assert view.near is not None
        d, _ = view.near.query(q, distance_upper_bound=cfg.far_m + cfg.sample_m / 4)
        keep = (src & ~np.uint64(1)) != 0
        got = samples._near_kept(q, keep[samples.near_owner], False)
        assert np.array_equal(got, np.isfinite(d)) and bool(got.all()) is found
