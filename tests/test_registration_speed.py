"""Registration's fast formulations (issue 20, part 3) against the plain ones they replace.

Each helper of :mod:`mapping.registration` written for speed is compared with the obvious
formulation of the same thing on random inputs, edge cases included: same values bit for bit
(or, where the helper defines a set, the set from its definition).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.registration import (
    RegistrationConfig,
    _angle_pairs,
    _cell_mask,
    _distinct,
    _final_matches,
    _match,
    _near_counts,
    _score,
    _sums_by_key,
    _top_cells,
    _within,
    _wrap,
    prepare,
    register,
)
from mapping.se2 import Pose
from mapping.wireframe import Wireframe


def _office(rng: np.random.Generator) -> Wireframe:
    from agents.sim.world import load_world

    wf = load_world("office").truth
    return wf.replace(points=wf.points + rng.normal(0.0, 0.02, wf.points.shape))


@pytest.mark.parametrize("seed", range(6))
def test_angle_pairs_are_every_pair_within_the_tolerance(seed: int) -> None:
    """Same key, wrapped difference within ``tol``: the pairs of a brute-force test of every
    pair, ordered by B's bin shift (-1, 0, +1), then B's entry, then A's sorted order."""
    rng = np.random.default_rng(seed)
    na, nb, q = int(rng.integers(0, 200)), int(rng.integers(0, 200)), int(rng.choice([4, 8, 720]))
    # Angles clustered on q directions (as walls are), some exactly on the wrap.
    ang_a = _wrap(rng.integers(0, q, na) * (2 * math.pi / q) - math.pi + rng.normal(0, 0.05, na))
    ang_b = _wrap(rng.integers(0, q, nb) * (2 * math.pi / q) - math.pi + rng.normal(0, 0.05, nb))
    ang_a[: na // 10] = -math.pi
    key_a, key_b = rng.integers(0, 2, na), rng.integers(0, 3, nb)
    tol = math.radians(float(rng.choice([6.0, 10.0, 45.0])))
    ia, ib = _angle_pairs(ang_a, key_a, ang_b, key_b, tol)
    want = {(i, j) for i in range(na) for j in range(nb)
            if key_a[i] == key_b[j] and abs(float(_wrap(np.array(ang_a[i] - ang_b[j])))) <= tol}
    got = list(zip(ia.tolist(), ib.tolist()))
    assert len(got) == len(set(got)) and set(got) == want
    nbin = max(3, int(2.0 * math.pi / tol))
    width = 2.0 * math.pi / nbin
    bin_a = ((ang_a + math.pi) / width).astype(np.int64) % nbin
    bin_b = ((ang_b + math.pi) / width).astype(np.int64) % nbin
    shift = [(int(bin_a[i]) - int(bin_b[j]) + 1) % nbin - 1 for i, j in got]
    rank = np.argsort(key_a * nbin + bin_a, kind="stable").argsort()
    assert got == sorted(got, key=lambda p: (shift[got.index(p)], p[1], rank[p[0]]))


def test_within_is_the_wrapped_test() -> None:
    """``_within`` wraps only where it matters: the same answer as wrapping every difference,
    also within an ulp of the tolerance and across the wrap."""
    rng = np.random.default_rng(3)
    tol = math.radians(12.0)
    a = _wrap(rng.uniform(-math.pi, math.pi, 4000))
    b = _wrap(a + rng.choice([-1.0, 1.0], 4000) * (tol + rng.normal(0, 1e-15, 4000)))
    b[:500] = -a[:500]  # across the wrap
    b[500:1000] = a[500:1000]
    d = (a - b).reshape(80, 50)
    assert np.array_equal(_within(d, tol), np.abs(_wrap(d)) <= tol)


def test_cell_mask_marks_the_cells_around_each_point() -> None:
    """A query is near exactly when its cell is one of the eight around a point's cell or that
    cell itself (every query within the radius of a point among them), also far off the grid,
    at infinity and NaN; ``near_xy`` on an array of any shape says the same."""
    rng = np.random.default_rng(4)
    pts = rng.uniform(-20.0, 30.0, (300, 2))
    cm = _cell_mask(pts, 0.3)
    assert cm is not None
    q = np.concatenate([pts + rng.normal(0, 0.4, pts.shape), rng.uniform(-60, 80, (3000, 2)),
                        [[1e9, 0.0], [-1e300, 5.0], [np.inf, 1.0], [np.nan, 2.0], [0.0, -np.inf]]])
    with np.errstate(invalid="ignore"):
        cq = np.floor(q / cm.cell)
    cp = np.floor(pts / cm.cell)
    want = (np.abs(cq[:, None, :] - cp[None, :, :]).max(axis=2) <= 1).any(axis=1)
    with np.errstate(invalid="ignore"):  # NaN and infinity cast to an integer cell
        got = cm.near(q)
        assert np.array_equal(cm.near_xy(q[:, 0].reshape(-1, 1), q[:, 1].reshape(-1, 1)), got[:, None])
    assert np.array_equal(got, want) and 100 < got.sum() < len(q) - 100
    with np.errstate(invalid="ignore"):
        close = np.hypot(*(q[:, None, :] - pts[None, :, :]).transpose(2, 0, 1)).min(axis=1) <= 0.3
    assert np.all(got[close])


def test_top_cells_are_the_k_strongest_and_every_tie() -> None:
    rng = np.random.default_rng(5)
    grid = np.zeros(5000)
    cells = rng.choice(5000, 400, replace=False)
    grid[cells] = rng.integers(1, 6, 400) * 4.0  # votes in whole multiples of the cap: ties
    for k in (1, 10, 48, 399, 400, 600):
        top = _top_cells(grid, k)
        voted = np.flatnonzero(grid > 0)
        kth = np.sort(grid[voted])[::-1][min(k, len(voted)) - 1]
        assert set(top.tolist()) == set(voted[grid[voted] >= kth].tolist())
        assert len(top) >= min(k, len(voted))


def test_sums_by_key_are_unique_and_bincount() -> None:
    """The same keys and, bit for bit, the same sums as ``np.unique`` and a ``bincount``."""
    rng = np.random.default_rng(6)
    base = rng.integers(0, 5000, 3000)
    keys = np.concatenate([base, base + 71, base + 1, base + 72])
    vals = rng.uniform(0.0, 4.0, len(keys)) * rng.uniform(0.0, 1.0, len(keys))
    uk, acc = _sums_by_key(keys, vals)
    ref_k, inv = np.unique(keys, return_inverse=True)
    assert np.array_equal(uk, ref_k) and np.array_equal(acc, np.bincount(inv, weights=vals))


def test_distinct_and_near_counts_move_points_as_pose_apply() -> None:
    """``_distinct`` and ``_near_counts`` compute on floats and on all poses at once what
    ``Pose.apply`` gives point by point."""
    rng = np.random.default_rng(7)
    f = prepare(_office(rng))
    cfg = RegistrationConfig()
    cm = f.end_cells
    assert cm is not None
    poses = [Pose(*rng.uniform([-5, -5, -4], [5, 5, 4])) for _ in range(40)]
    counts = _near_counts(cm, poses, f.end_points)
    assert counts.tolist() == [int(cm.near(T.apply(f.end_points)).sum()) for T in poses]
    base = poses[0]
    for T in [*poses, Pose(base.x + 1.0, base.y, base.theta), Pose(base.x, base.y, base.theta + 0.0873)]:
        pa, pb = T.apply(f.centre[None, :])[0], base.apply(f.centre[None, :])[0]
        want = (math.hypot(*(pa - pb)) > cfg.distinct_translation
                or abs(float(_wrap(np.array(T.theta - base.theta)))) > cfg.distinct_rotation)
        assert _distinct(T, base, f, cfg) == want


def test_a_refined_hypothesis_keeps_its_matches() -> None:
    """The matches kept with a hypothesis scored on every sample at ``match_dist`` are the ones
    ``_match`` finds again; one scored otherwise keeps none."""
    rng = np.random.default_rng(8)
    a, b = _office(rng), _office(rng).transformed(Pose(2.0, -1.0, 0.3))
    res = register(a, b)  # refused (identical offices), but its best hypothesis was refined
    assert res.best is not None and res.best.refined and res.best.matched is not None
    cfg = RegistrationConfig()
    fa, fb = prepare(a, cfg), prepare(b, cfg)
    ib, ia = _match(fa, fb, res.best.transform, cfg.match_dist, cfg)
    kb, ka = _final_matches(fa, fb, res.best, cfg)
    assert np.array_equal(ib, kb) and np.array_equal(ia, ka)
    coarse = _score(fa, fb, res.best.transform, cfg.coarse_match_dist, cfg, 0.0)
    assert coarse.matched is None and _score(fa, fb, res.best.transform, cfg.match_dist, cfg, 0.0,
                                             stride=2).matched is None
