"""The compiled point-to-line match (mapping.kernels) against a NumPy reference: the grid's
nearest neighbour against scipy's k-d tree, and the whole Gauss-Newton match against the NumPy
implementation it replaced (kept here as the reference), on simulated and random scenes."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapping import kernels as sk
from mapping.lidar_slam import SlamConfig, Submap, match_scan, scan_normals
from mapping.se2 import Pose, wrap_angle
from tests.test_lidar_slam import points_at, room_segments, submap_of


def reference_match(points: np.ndarray, submap: Submap, guess: np.ndarray, config: SlamConfig,
                    prior_information: np.ndarray | None = None,
                    inlier_distance: float = 0.1) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The match as it was written in NumPy with a k-d tree (``match_scan`` before it was
    compiled): the reference the compiled kernel is held to."""
    tree = cKDTree(submap.points if len(submap.points) else np.zeros((1, 2)) + 1e9)
    pose = np.asarray(guess, dtype=np.float64).copy()
    prior = np.zeros((3, 3)) if prior_information is None else prior_information
    w_sigma = 1.0 / config.sigma**2
    hess = np.zeros((3, 3))
    matched = 0
    half = max(1, config.iterations // 2)
    for it in range(config.iterations):
        gate = config.gate_start * (config.gate_end / config.gate_start) ** min(1.0, it / half)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        world = points @ np.array([[c, s], [-s, c]]) + pose[:2]
        dist, idx = tree.query(world, distance_upper_bound=gate)
        ok = np.isfinite(dist)
        matched = int(np.count_nonzero(ok))
        d = pose - guess
        d[2] = wrap_angle(d[2])
        if matched < 3:
            hess = np.zeros((3, 3))
            g = prior @ d
            h = prior + 1e-9 * np.eye(3)
        else:
            nr = submap.normals[idx[ok]]
            w_ = world[ok]
            r = np.einsum("ij,ij->i", nr, w_ - submap.points[idx[ok]])
            rel = w_ - pose[:2]
            jac = np.column_stack([nr, -nr[:, 0] * rel[:, 1] + nr[:, 1] * rel[:, 0]])
            wts = min(1.0, config.effective_points / matched) * w_sigma / (1.0 + (r / config.kernel) ** 2)
            hess = (jac * wts[:, None]).T @ jac
            g = (jac * wts[:, None]).T @ r + prior @ d
            h = hess + prior + 1e-9 * np.eye(3)
        step = -np.linalg.solve(h, g)
        pose = pose + step
        pose[2] = wrap_angle(pose[2])
        if it >= half and abs(step[0]) + abs(step[1]) < 1e-4 and abs(step[2]) < 1e-5:
            break
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world = points @ np.array([[c, s], [-s, c]]) + pose[:2]
    dist, idx = tree.query(world, distance_upper_bound=max(config.gate_end, inlier_distance))
    ok = np.isfinite(dist)
    r = np.abs(np.einsum("ij,ij->i", submap.normals[idx[ok]], world[ok] - submap.points[idx[ok]]))
    return pose, hess, float(np.count_nonzero(r <= inlier_distance)) / max(1, len(points)), matched


def assert_same_match(points: np.ndarray, sub: Submap, guess: np.ndarray, config: SlamConfig,
                      prior: np.ndarray | None = None) -> None:
    got = match_scan(points, sub, guess, config, prior_information=prior)
    pose, hess, inliers, matched = reference_match(points, sub, guess, config, prior)
    assert np.abs(got.pose - pose).max() < 1e-9
    assert np.abs(got.hessian - hess).max() <= 1e-9 * max(1.0, np.abs(hess).max())
    assert got.inliers == inliers and got.matched == matched


@pytest.mark.parametrize("seed", range(4))
def test_nearest_is_the_k_d_trees_nearest_within_the_gate(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # Clusters and a sparse spread, as a voxel-thinned submap has, and queries near and far.
    pts = np.vstack([rng.normal(rng.uniform(-5, 5, 2), 0.3, (200, 2)), rng.uniform(-8, 8, (100, 2))])
    queries = np.vstack([rng.uniform(-9, 9, (400, 2)), rng.uniform(-200, 200, (20, 2)),
                         pts[:50] + rng.normal(0, 0.01, (50, 2))])
    tree = cKDTree(pts)
    for cell in (0.05, 0.15, 0.7):
        grid = sk.PointGrid.build(pts, cell)
        for gate in (0.01, 0.15, 0.5, 2.0):
            dist, idx = tree.query(queries, distance_upper_bound=gate)
            want = np.where(np.isfinite(dist), idx, -1)
            assert np.array_equal(sk.nearest(grid, queries, gate), want), (cell, gate)


def test_nearest_on_an_empty_grid_a_point_and_a_non_finite_query() -> None:
    empty = sk.PointGrid.build(np.zeros((0, 2)))
    assert sk.nearest(empty, np.array([[0.0, 0.0]]), 1.0).tolist() == [-1]
    one = sk.PointGrid.build(np.array([[1.0, 2.0]]))
    q = np.array([[1.0, 2.0], [1.5, 2.0], [np.nan, 2.0], [np.inf, 0.0]])  # 0.5 exactly
    assert sk.nearest(one, q, 0.6).tolist() == [0, 0, -1, -1]
    assert sk.nearest(one, q, 0.5).tolist() == [0, -1, -1, -1]  # strictly within the gate
    assert sk.nearest(one, np.array([[900.0, -700.0]]), 2000.0).tolist() == [0]
    with pytest.raises(ValueError, match="finite"):
        sk.nearest(one, q, math.inf)
    with pytest.raises(ValueError, match="finite"):
        sk.PointGrid.build(np.array([[0.0, np.nan]]))


def test_nearest_on_a_lattice_of_points_on_cell_borders() -> None:
    """Points exactly on cell borders, queries half way between them, the gate just over
    that: the ring bound must not skip a border point by a rounding."""
    for cell in (0.15, 0.25):
        s = cell / 3.0
        ax = np.arange(-12, 13) * s
        pts = np.stack(np.meshgrid(ax, ax), axis=-1).reshape(-1, 2)
        q = pts[:200] + np.array([s / 2.0, 0.0])
        grid = sk.PointGrid.build(pts, cell)
        for gate in (s / 2.0 + 1e-12, 0.6 * s, 1.5 * s):
            dist, _ = cKDTree(pts).query(q, distance_upper_bound=gate)
            got = sk.nearest(grid, q, gate)
            assert np.array_equal(got >= 0, np.isfinite(dist)), (cell, gate)
            d = np.hypot(*(pts[np.maximum(got, 0)] - q).T)
            assert np.allclose(d[got >= 0], dist[np.isfinite(dist)], rtol=0, atol=1e-12)


def test_a_wide_point_set_gets_coarser_cells_and_the_same_neighbours() -> None:
    rng = np.random.default_rng(5)
    pts = np.vstack([rng.uniform(0, 1, (50, 2)), rng.uniform(0, 1, (50, 2)) + 5000.0])
    grid = sk.PointGrid.build(pts)
    assert grid.nx * grid.ny <= sk.MAX_CELLS and grid.cell > sk.CELL
    # Long and thin too: the cap holds whatever the shape.
    line = np.stack([np.linspace(0, 1e6, 50), np.zeros(50)], axis=1)
    thin = sk.PointGrid.build(line)
    assert thin.nx * thin.ny <= sk.MAX_CELLS
    assert sk.nearest(thin, line[[7]] + 0.1, 0.5).tolist() == [7]
    q = np.vstack([pts + rng.normal(0, 0.2, pts.shape), rng.uniform(0, 5001, (100, 2))])
    dist, idx = cKDTree(pts).query(q, distance_upper_bound=0.5)
    assert np.array_equal(sk.nearest(grid, q, 0.5), np.where(np.isfinite(dist), idx, -1))


def test_the_match_is_the_numpy_reference_on_the_room() -> None:
    cfg = SlamConfig()
    sub = submap_of([Pose(1.5, 1.0, 0.4), Pose(2.5, 1.2, 0.5), Pose(3.0, 8.0, -1.0)])
    rng = np.random.default_rng(3)
    prior = np.diag([1 / 0.1**2, 1 / 0.1**2, 1 / 0.05**2])
    for k in range(12):
        truth = Pose(rng.uniform(1, 4), rng.uniform(1, 10), rng.uniform(-math.pi, math.pi))
        pts = points_at(truth, rng, sigma=0.01)
        guess = np.array([truth.x, truth.y, truth.theta]) + rng.normal(0, [0.2, 0.2, 0.05])
        assert_same_match(pts, sub, guess, cfg, prior if k % 2 else None)


def test_the_match_is_the_numpy_reference_on_random_clouds_and_edge_cases() -> None:
    rng = np.random.default_rng(11)
    cfg = SlamConfig()
    for _ in range(10):
        walls = room_segments()
        t = rng.uniform(0, 1, (300, 1))
        seg = walls[rng.integers(0, len(walls), 300)]
        pts = seg[:, 0] + t * (seg[:, 1] - seg[:, 0]) + rng.normal(0, 0.02, (300, 2))
        normals = scan_normals(pts[np.argsort(np.arctan2(pts[:, 1] - 6, pts[:, 0] - 6))], 0.6)
        sub = Submap.build([(pts, rng.normal(0, 1, (300, 2)) / math.sqrt(2)), (pts, normals)], 0.05)
        scan = sub.points[rng.integers(0, len(sub.points), 150)] + rng.normal(0, 0.03, (150, 2))
        assert_same_match(scan, sub, rng.normal(0, [0.1, 0.1, 0.02]), cfg)
    # Too few points to match (the prior alone), and an empty submap.
    sub = submap_of([Pose(1.5, 1.0, 0.4)])
    assert_same_match(np.array([[50.0, 50.0]]), sub, np.array([1.0, 1.0, 0.1]), cfg, np.eye(3))
    empty = Submap.build([], 0.05)
    assert_same_match(points_at(Pose(2, 2, 0)), empty, np.array([2.0, 2.0, 0.0]), cfg, np.eye(3))


def test_the_match_is_the_numpy_reference_when_points_run_out_and_across_pi() -> None:
    """Sparse submaps: the matches fall under three as the gate shrinks, after the pose has
    moved (the prior's branch with a real gradient: it takes the pose back to the guess),
    headings on both sides of +-pi, and an inlier distance wider than the last gate."""
    rng = np.random.default_rng(0)
    branch = 0
    for k in range(400):
        n = int(rng.integers(3, 8))
        sp = rng.uniform(-1, 1, (n, 2))
        nr = rng.normal(0, 1, (n, 2))
        nr /= np.linalg.norm(nr, axis=1)[:, None]
        sub = Submap.build([(sp, nr)], 0.05)
        scan = sp[rng.permutation(n)[: rng.integers(3, n + 1)]] + rng.normal(0, 0.18, (1, 2))
        guess = rng.normal(0, [0.1, 0.1, 0.3])
        guess[2] = wrap_angle(guess[2] + rng.choice([0.0, math.pi]))
        prior = np.diag(rng.uniform(0.5, 50, 3))
        inlier = 0.3 if k % 2 else 0.1
        got = match_scan(scan, sub, guess, SlamConfig(), prior_information=prior, inlier_distance=inlier)
        pose, hess, inliers, matched = reference_match(scan, sub, guess, SlamConfig(), prior, inlier)
        assert np.abs(got.pose - pose).max() < 1e-9 and np.abs(got.hessian - hess).max() < 1e-6
        assert (got.inliers, got.matched) == (inliers, matched)
        branch += 0 < got.matched < 3  # points left, too few: the prior's branch (back to the guess)
    assert branch >= 20  # the case this test is for did occur


def test_the_match_refuses_non_finite_input() -> None:
    sub = submap_of([Pose(1.5, 1.0, 0.4)])
    with pytest.raises(ValueError, match="finite"):
        match_scan(np.array([[1.0, np.nan], [2.0, 1.0]]), sub, np.zeros(3), SlamConfig())
    with pytest.raises(ValueError, match="finite"):
        match_scan(points_at(Pose(2, 2, 0)), sub, np.array([np.inf, 0.0, 0.0]), SlamConfig())


def test_the_three_by_three_solve_is_numpys() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        a = rng.normal(0, 1, (3, 3)) + 3 * np.eye(3) * rng.uniform(0, 1)
        if abs(np.linalg.det(a)) < 1e-3:
            continue
        b = rng.normal(0, 1, 3)
        assert np.allclose(sk._solve3(a, b), np.linalg.solve(a, b), rtol=1e-9, atol=1e-12)


def reference_scores(grid: np.ndarray, origin: np.ndarray, res: float, pts: np.ndarray,
                     offsets: np.ndarray) -> np.ndarray:
    """The correlative scores as they were written in NumPy (``_Field.score`` before it was
    compiled): one gather of offsets x points."""
    ij = np.floor((pts - origin) / res).astype(np.int64)
    h, w = grid.shape
    lo, hi = offsets.min(axis=0), offsets.max(axis=0)
    keep = ((ij[:, 0] + lo[0] >= 0) & (ij[:, 0] + hi[0] < w)
            & (ij[:, 1] + lo[1] >= 0) & (ij[:, 1] + hi[1] < h))
    base = ij[keep, 1] * w + ij[keep, 0]
    flat = base[None, :] + (offsets[:, 1] * w + offsets[:, 0])[:, None]
    return np.asarray(grid.ravel().take(flat).sum(axis=1) / max(1, len(pts)))


@pytest.mark.parametrize("seed", range(3))
def test_field_scores_are_the_numpy_gathers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = rng.uniform(0, 1, (rng.integers(20, 80), rng.integers(20, 80)))
    origin = rng.uniform(-5, 5, 2)
    h, w = grid.shape
    # Points inside, near the border (dropped for every offset when one takes them off) and outside.
    pts = origin + rng.uniform(-0.5, 1.1, (300, 2)) * np.array([w, h]) * 0.1
    ax = np.arange(-4, 5) * rng.integers(1, 4)
    offsets = np.stack(np.meshgrid(ax, ax, indexing="xy"), axis=-1).reshape(-1, 2)
    got = sk.field_scores(grid, origin, 0.1, pts, offsets)
    assert np.allclose(got, reference_scores(grid, origin, 0.1, pts, offsets), rtol=1e-12, atol=1e-15)


def test_the_loop_search_finds_the_same_pose_with_the_compiled_scores() -> None:
    """The loop search end to end with the NumPy scores and the compiled ones: the same match."""
    from mapping import lidar_slam

    truth = Pose(2.0, 8.0, -1.2)
    sub = submap_of([Pose(1.0, 9.0, -1.0), Pose(2.5, 7.0, -1.4), Pose(1.5, 4.0, 1.0)])
    guess = np.array([truth.x + 1.2, truth.y - 0.9, truth.theta + math.radians(12.0)])
    args = (points_at(truth), sub, guess, 2.0, math.radians(20.0), SlamConfig())
    got = lidar_slam.search_loop(*args)
    original = lidar_slam._Field.score
    try:
        lidar_slam._Field.score = lambda self, grid, pts, offs: reference_scores(  # type: ignore[method-assign]
            grid, self.origin, self.res, pts, offs)
        want = lidar_slam.search_loop(*args)
    finally:
        lidar_slam._Field.score = original  # type: ignore[method-assign]
    assert got is not None and want is not None
    assert np.abs(got.pose - want.pose).max() < 1e-9 and got.inliers == want.inliers


@pytest.mark.fleet  # (a subprocess)
def test_the_kernels_import_and_run_where_no_cache_can_be_written(tmp_path: Path) -> None:
    """A read-only install under a read-only home (a robot container): numba finds no place for
    its cache and would refuse the module at import; the kernels compile without it."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    shutil.copy(Path(sk.__file__), pkg / "kernels_copy.py")
    (pkg / "__pycache__").write_text("a file where numba's cache folder would go")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "XDG_"))}
    env.update(HOME="/dev/null", XDG_CACHE_HOME="/dev/null/cache", PYTHONPATH=str(pkg))
    code = ("import numpy as np, kernels_copy as k; "
            "g = k.PointGrid.build(np.array([[0.0, 0.0], [1.0, 0.0]])); "
            "print(k.nearest(g, np.array([[0.9, 0.1]]), 0.5).tolist())")
    out = subprocess.run([sys.executable, "-W", "error", "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[1]"


def test_ties_go_to_the_lower_index_whatever_the_cells() -> None:
    """Samples of a two-sided wall lie at the same places: among equal distances the lower
    index, in any grid (a k-d tree's choice depends on its shape)."""
    rng = np.random.default_rng(9)
    pts = rng.uniform(-3, 3, (60, 2))
    pts = np.vstack([pts, pts[::-1]])  # every point twice, the copies in reverse order
    q = rng.uniform(-3, 3, (300, 2))
    d2 = ((q[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
    want4 = np.lexsort((np.broadcast_to(np.arange(len(pts)), d2.shape), d2), axis=1)[:, :4]
    want = want4[:, :3]
    for cell in (0.05, 0.15, 1.0):
        grid = sk.PointGrid.build(pts, cell)
        assert sk.nearest(grid, q, 10.0).tolist() == want[:, 0].tolist()
        up = np.array([[1.0, 0.0]] * len(pts))
        # With every direction accepted, the match is the nearest, lowest index first.
        got = sk.directed_matches(grid, up, q, np.tile([1.0, 0.0], (len(q), 1)), 10.0, -2.0)
        assert got.tolist() == want[:, 0].tolist()
        # With only the second copies' direction accepted: the first of the three nearest that is one.
        dirs = np.vstack([np.tile([0.0, 1.0], (60, 1)), np.tile([1.0, 0.0], (60, 1))])
        for k in (1, 3, 4):  # the k nearest: the registration's match takes 3, its displaced test 4
            got = sk.directed_matches(grid, dirs, q, np.tile([1.0, 0.0], (len(q), 1)), 10.0, 0.5, k=k)
            expect = [next((int(i) for i in row[:k] if i >= 60), -1) for row in want4]
            assert got.tolist() == expect


def reference_crossings(o: np.ndarray, n: np.ndarray, seg: np.ndarray, sn: np.ndarray,
                        reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The free probes' ray cast as it was written in NumPy (``registration._facing_probes``
    before it was compiled), all rays against all segments at once."""
    p0 = seg[:, 0]
    e = seg[:, 1] - p0
    den = n[:, 0:1] * e[None, :, 1] - n[:, 1:2] * e[None, :, 0]
    wx = p0[None, :, 0] - o[:, 0:1]
    wy = p0[None, :, 1] - o[:, 1:2]
    ok = np.abs(den) > 1e-9
    dd = np.where(ok, den, 1.0)
    t = (wx * e[None, :, 1] - wy * e[None, :, 0]) / dd
    s = (wx * n[:, 1:2] - wy * n[:, 0:1]) / dd
    t = np.where(ok & (t > 1e-6) & (t <= reach) & (s >= 0.0) & (s <= 1.0), t, np.inf)
    j = np.argmin(t, axis=1)
    first = t[np.arange(len(o)), j]
    return first, np.einsum("ij,ij->i", sn[j], n) < 0.0


@pytest.mark.parametrize("chunk", [1, 7, 128])
def test_first_crossings_are_the_numpy_ray_cast(chunk: int) -> None:
    """Wall samples' normals against a map's walls (a room with a pillar and random walls, rays
    from on the walls, parallel to some, through shared corners): the same crossings bit for
    bit, whatever the chunks."""
    rng = np.random.default_rng(chunk)
    seg = np.vstack([room_segments(), rng.uniform(0, 12, (40, 2, 2))])
    d = seg[:, 1] - seg[:, 0]
    sn = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.hypot(d[:, 0], d[:, 1])[:, None]
    t = rng.uniform(0, 1, (500, 1))
    pick = rng.integers(0, len(seg), 500)
    o = seg[pick, 0] + t * d[pick]
    o[:20] = seg[pick[:20], 0]  # from corners
    n = np.vstack([sn[pick[:400]] * rng.choice([-1.0, 1.0], (400, 1)), d[pick[400:]] / np.hypot(
        d[pick[400:], 0], d[pick[400:], 1])[:, None]])  # the last 100 along their own wall
    first, facing = sk.first_crossings(o, n, seg, sn, 6.0, chunk)
    want_first, want_facing = reference_crossings(o, n, seg, sn, 6.0)
    assert np.array_equal(first, want_first)
    hit = np.isfinite(want_first)
    assert np.array_equal(facing[hit], want_facing[hit]) and 100 < hit.sum() < 500
