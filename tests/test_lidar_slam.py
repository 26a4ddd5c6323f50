"""Lidar SLAM under the filter (mapping.lidar_slam): normals, the point-to-line match, the
correlative loop search, the pose graph, and the whole SLAM on simulated and real scans."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from agents.sim.lidar import LidarConfig, raycast
from mapping.lidar_slam import (
    Edge,
    LidarSlam,
    SlamConfig,
    Submap,
    graph_warp,
    match_scan,
    optimize,
    scan_normals,
    scan_sides,
    search_loop,
)
from mapping.se2 import Pose

LIDAR = LidarConfig(beams=181, fov=math.pi, max_range=20.0, sigma=0.0)
DATA = Path(__file__).parent / "data"


def room_segments() -> np.ndarray:
    """An L-shaped hall with a pillar and a few doorways: enough structure to fix a pose."""
    outline = [(0, 0), (12, 0), (12, 5), (5, 5), (5, 12), (0, 12)]
    segs = [(outline[i], outline[(i + 1) % len(outline)]) for i in range(len(outline))]
    segs += [((2, 2), (3, 2)), ((3, 2), (3, 3)), ((3, 3), (2, 3)), ((2, 3), (2, 2))]
    segs += [((8, 1), (9.5, 2.5))]  # a wall at an odd angle
    return np.array(segs, dtype=np.float64)


def points_at(pose: Pose, rng: np.random.Generator | None = None, sigma: float = 0.0) -> np.ndarray:
    cfg = LidarConfig(beams=LIDAR.beams, fov=LIDAR.fov, max_range=LIDAR.max_range, sigma=sigma)
    r = raycast(room_segments(), pose, cfg, rng)
    a = cfg.angles()
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)


def submap_of(poses: list[Pose]) -> Submap:
    clouds = []
    for p in poses:
        pts = points_at(p)
        n = scan_normals(pts)
        clouds.append((p.apply(pts), n @ np.array([[math.cos(p.theta), -math.sin(p.theta)],
                                                   [math.sin(p.theta), math.cos(p.theta)]]).T))
    return Submap.build(clouds, 0.05)


def test_normals_are_perpendicular_to_a_wall_and_missing_at_a_gap() -> None:
    x = np.linspace(0.0, 2.0, 21)
    pts = np.stack([x, np.full_like(x, 3.0)], axis=1)
    pts = np.vstack([pts, [[5.0, 3.0], [5.1, 3.0]]])  # a jump of 2.9 m: no neighbour there
    n = scan_normals(pts, gap=0.3)
    assert np.allclose(n[1:20, 1], -1.0) and np.allclose(n[1:20, 0], 0.0)  # towards the scanner
    assert np.isnan(n[0]).all() and np.isnan(n[20]).all() and np.isnan(n[21]).all()
    assert np.allclose(scan_normals(pts[20::-1], gap=0.3)[1:20], n[19:0:-1])  # whatever the order


def test_a_short_range_scanner_is_not_paired_with_the_far_face_of_a_wall() -> None:
    """A wall 0.2 m thick, both faces in the submap, each seen from its own side (normals
    towards it). A scan of the near face, guessed 0.15 m towards the far one: the plain match
    slides onto the far face (the nearer points); with a short-range scanner
    (``scanner_range`` under ``facing_range``) a point pairs only with a face that looks the
    way it does, and the match lands on the near face."""
    y = np.linspace(-3.0, 3.0, 121)
    near = np.stack([np.full_like(y, 1.0), y], axis=1)
    far = np.stack([np.full_like(y, 1.2), y], axis=1)
    corner = np.stack([np.linspace(0.0, 0.95, 20), np.full(20, 3.0)], axis=1)  # a cross wall fixes y
    sub = Submap.build([(near, np.tile([-1.0, 0.0], (len(y), 1))), (far, np.tile([1.0, 0.0], (len(y), 1))),
                        (corner, np.tile([0.0, -1.0], (20, 1)))], 0.02)
    pts = np.vstack([near[10:111:2], corner])
    nrm = scan_sides(pts, np.vstack([scan_normals(near[10:111:2], gap=0.3), scan_normals(corner, gap=0.3)]))
    guess = np.array([0.15, 0.0, 0.0])
    plain = match_scan(pts, sub, guess, SlamConfig(), sides=nrm)  # a long-range scanner: no check
    assert plain.pose[0] == pytest.approx(0.2, abs=0.02)
    short = match_scan(pts, sub, guess, SlamConfig(scanner_range=3.5), sides=nrm)
    assert abs(short.pose[0]) < 0.01 and abs(short.pose[1]) < 0.01
    assert match_scan(pts, sub, guess, SlamConfig(scanner_range=3.5, facing_range=3.0),
                      sides=nrm).pose[0] == pytest.approx(plain.pose[0])


def test_match_recovers_a_pose_from_a_wrong_guess() -> None:
    truth = Pose(3.5, 1.5, 0.6)
    sub = submap_of([Pose(1.5, 1.0, 0.4), Pose(2.5, 1.2, 0.5)])
    guess = np.array([truth.x + 0.15, truth.y - 0.1, truth.theta + math.radians(3.0)])
    m = match_scan(points_at(truth), sub, guess, SlamConfig())
    assert math.hypot(m.pose[0] - truth.x, m.pose[1] - truth.y) < 0.01
    assert abs(m.pose[2] - truth.theta) < math.radians(0.2)
    assert m.inliers > 0.5  # the scan sees more than the two old scans did


def test_the_prior_holds_what_a_corridor_does_not_fix() -> None:
    """Two parallel walls fix the pose across the corridor, not along it: the prior's centre
    stays along it and the data term's Hessian says so."""
    x = np.linspace(-10.0, 10.0, 401)
    walls = [np.stack([x, np.full_like(x, y)], axis=1) for y in (-1.0, 1.0)]
    normals = [np.tile([0.0, 1.0], (len(x), 1)) for _ in walls]
    sub = Submap.build(list(zip(walls, normals)), 0.05)
    pts = np.vstack([w[::10] for w in walls])
    guess = np.array([0.3, 0.05, 0.0])
    prior = np.diag([1 / 0.1**2, 1 / 0.1**2, 1 / 0.05**2])
    m = match_scan(pts, sub, guess, SlamConfig(), prior_information=prior)
    assert abs(m.pose[1]) < 0.01  # across: the walls
    assert abs(m.pose[0] - 0.3) < 0.01  # along: the prior
    w = np.linalg.eigvalsh(m.hessian[:2, :2])
    assert w[0] < 1e-6 * w[1]


def test_loop_search_finds_a_far_pose_and_refuses_a_foreign_scan() -> None:
    truth = Pose(2.0, 8.0, -1.2)
    sub = submap_of([Pose(1.0, 9.0, -1.0), Pose(2.5, 7.0, -1.4), Pose(1.5, 4.0, 1.0)])
    guess = np.array([truth.x + 1.2, truth.y - 0.9, truth.theta + math.radians(12.0)])
    m = search_loop(points_at(truth), sub, guess, radius=2.0, angle=math.radians(20.0), config=SlamConfig())
    assert m is not None
    assert math.hypot(m.pose[0] - truth.x, m.pose[1] - truth.y) < 0.05
    assert abs(m.pose[2] - truth.theta) < math.radians(0.5)
    # A scan of another building (a plain 3 x 3 m room) is nowhere in this submap.
    room = np.array([((0, 0), (3, 0)), ((3, 0), (3, 3)), ((3, 3), (0, 3)), ((0, 3), (0, 0))], dtype=float)
    r = raycast(room, Pose(1.5, 1.5, 0.0), LIDAR)
    a = LIDAR.angles()
    foreign = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)[np.isfinite(r)]
    assert search_loop(foreign, sub, guess, radius=2.0, angle=math.radians(20.0), config=SlamConfig()) is None


def _square(n_side: int, step: float) -> list[np.ndarray]:
    poses, p = [], np.zeros(3)
    for side in range(4):
        for _ in range(n_side):
            poses.append(p.copy())
            p = p + np.array([step * math.cos(p[2]), step * math.sin(p[2]), 0.0])
        p[2] += math.pi / 2 if side < 3 else 0.0
    return poses


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array(Pose(*a).between(Pose(*b)).as_tuple())


def test_pose_graph_fixed_point_and_a_closed_loop() -> None:
    truth = _square(5, 1.0)
    omega = np.diag([100.0, 100.0, 400.0])
    exact = [Edge(i, i + 1, _rel(truth[i], truth[i + 1]), omega) for i in range(len(truth) - 1)]
    fixed = optimize(np.array(truth), exact)
    assert np.allclose(fixed[:, :2], np.array(truth)[:, :2], atol=1e-9)
    assert np.allclose(np.cos(fixed[:, 2] - np.array(truth)[:, 2]), 1.0, atol=1e-12)
    # Odometry that turns 2 degrees too far at every node; a loop edge from the last node back
    # to the first, as a loop search would measure it.
    bent = [Edge(e.i, e.j, e.z + np.array([0.0, 0.0, math.radians(2.0)]), e.omega) for e in exact]
    chain = [np.zeros(3)]
    for e in bent:
        chain.append(np.array(Pose(*chain[-1]).compose(Pose(*e.z)).as_tuple()))
    loop = Edge(0, len(truth) - 1, _rel(truth[0], truth[-1]), np.diag([1e4, 1e4, 1e5]), robust=True)
    before = np.hypot(*(np.array(chain)[:, :2] - np.array(truth)[:, :2]).T).max()
    after_x = optimize(np.array(chain), [*bent, loop])
    after = np.hypot(*(after_x[:, :2] - np.array(truth)[:, :2]).T).max()
    assert np.allclose(after_x[0], 0.0, atol=1e-9)  # node 0 is the frame
    assert after < 0.25 * before


def _hall_drive() -> tuple[list[Pose], list[Pose], list[np.ndarray]]:
    """Around the L-shaped hall and along its first wall again: the true poses, odometry that
    drifts 2 degrees per metre, and the scans."""
    route = [Pose(1.0, 1.0, 0.0)]
    waypoints = [(10.5, 1.0), (10.5, 3.8), (3.8, 3.8), (3.8, 10.5), (1.0, 10.5), (1.0, 1.0), (10.5, 1.0)]
    for wx, wy in waypoints:
        while True:
            p = route[-1]
            d = math.hypot(wx - p.x, wy - p.y)
            if d < 1e-6:
                break
            step = min(0.8, d)
            th = math.atan2(wy - p.y, wx - p.x)
            route.append(Pose(p.x + step * math.cos(th), p.y + step * math.sin(th), th))
    rng = np.random.default_rng(4)
    odo = [Pose.identity()]
    for a, b in itertools.pairwise(route):
        inc = a.between(b)
        d = math.hypot(inc.x, inc.y)
        odo.append(Pose(inc.x * (1 + 0.05 * rng.standard_normal()), inc.y,
                        inc.theta + math.radians(2.0) * d + 0.01 * rng.standard_normal()))
    scans = [points_at(p, rng, sigma=0.01) for p in route]
    return route, odo, scans


def test_slam_closes_a_loop_in_a_simulated_hall_and_is_deterministic() -> None:
    """Around the L-shaped hall and along its first wall again, with odometry that drifts 2
    degrees per metre: a loop closes, the SLAM's trajectory stays within 0.15 m RMS of the truth
    (the odometry's goes past 1 m), and the same scans give the same poses. (The drift is a
    bias of one prior sigma per metre at ``odo_rot_per_m`` 0.035, the logs' noise: 0.121 m RMS,
    0.264 m at worst; 0.073 / 0.137 m at the former 0.07.)"""
    route, odo, scans = _hall_drive()

    def run() -> LidarSlam:
        slam = LidarSlam(SlamConfig(), start=np.array(route[0].as_tuple()))
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        return slam

    slam = run()
    truth = np.array([p.as_tuple() for p in route])
    dead = [np.array(route[0].as_tuple())]
    for o in odo[1:]:
        dead.append(np.array(Pose(*dead[-1]).compose(o).as_tuple()))
    err = np.hypot(*(slam.poses[:, :2] - truth[:, :2]).T)
    odo_err = np.hypot(*(np.array(dead)[:, :2] - truth[:, :2]).T)
    assert odo_err.max() > 1.0
    assert slam.loops, "no loop closed"
    assert err.max() < 0.35 and float(np.sqrt(np.mean(err**2))) < 0.15, (err.max(), np.sqrt(np.mean(err**2)))
    assert np.array_equal(run().poses, slam.poses)


def test_the_facing_check_keeps_a_hall_seen_from_one_side_as_it_is() -> None:
    """The hall's walls are each seen from one side only: with the facing check on (a 3.5 m
    scanner's setting) every match, loop search (its query's sides turned into the newest scan's
    frame) and refinement pairs what it paired without, up to the points that lose their pair
    at a corner: the same loops close and every pose stays within 3 cm."""
    route, odo, scans = _hall_drive()
    runs = []
    for cfg in (SlamConfig(), SlamConfig(scanner_range=3.5)):
        slam = LidarSlam(cfg, start=np.array(route[0].as_tuple()))
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        slam.refine()
        runs.append(slam)
    plain, checked = runs
    assert checked.config.facing and not plain.config.facing
    assert checked.loops == plain.loops and len(plain.loops) >= 3
    assert np.hypot(*(checked.poses[:, :2] - plain.poses[:, :2]).T).max() < 0.03


def _laps(cfg: SlamConfig, laps: int = 2) -> tuple[LidarSlam, np.ndarray, int]:
    """The hall drive ``laps`` times over (each lap's odometry the first's again): the SLAM, the
    truth and how many times the graph was optimised."""
    import mapping.lidar_slam as ls

    route, odo, scans = _hall_drive()
    back = route[-1].between(route[0])  # from the drive's end to its start, one step
    route_all = route * laps
    odo_all = [*odo] + [*[back, *odo[1:]]] * (laps - 1)
    scans_all = scans * laps
    calls = [0]
    plain = ls.optimize

    def counted(*a: object, **k: object) -> np.ndarray:
        calls[0] += 1
        return plain(*a, **k)  # type: ignore[arg-type]

    ls.optimize = counted  # type: ignore[assignment]
    try:
        slam = LidarSlam(cfg, start=np.array(route_all[0].as_tuple()))
        for k, (pts, o) in enumerate(zip(scans_all, odo_all, strict=True)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
    finally:
        ls.optimize = plain  # type: ignore[assignment]
    return slam, np.array([p.as_tuple() for p in route_all]), calls[0]


def test_a_settled_loop_keeps_its_edge_and_optimises_nothing() -> None:
    """Two laps of the hall: with ``loop_settled_xy`` / ``loop_settled_theta``, a loop that
    agrees with the estimate adds its edge without a Gauss-Newton over the graph (one
    optimisation per unsettled loop tried, none per settled one); the trajectory stays as good;
    settling off optimises for every loop. (The drive's odometry turns 2 degrees a metre, so
    most of its loops move the estimate by more than 0.2 degree: only a few settle here.)"""
    on, truth, calls_on = _laps(SlamConfig(loop_settled_xy=0.02, loop_settled_theta=math.radians(0.2)))
    off, _, calls_off = _laps(SlamConfig())
    assert off.settled == 0 and calls_off == len(off.loops) + len(off.rejected)
    assert 0 < on.settled < len(on.loops), (on.settled, len(on.loops))
    assert calls_on == len(on.loops) - on.settled + len(on.rejected)
    loop_edges = [e for e in on.edges if e.j != e.i + 1]
    assert [(e.i, e.j) for e in loop_edges] == on.loops  # every loop's edge is in the graph, settled or not

    def rms(slam: LidarSlam) -> float:
        return float(np.sqrt(np.mean(np.sum((slam.poses[:, :2] - truth[:, :2]) ** 2, axis=1))))

    assert rms(on) < 0.2 and rms(on) < rms(off) + 0.02, (rms(on), rms(off))


@pytest.mark.parametrize("visits", [1, 2])
def test_a_revisit_reuses_the_old_nodes(visits: int) -> None:
    """Four laps of the hall with ``revisit_xy``: once a loop has tied the path to the first
    lap, a scan matched near ``visits`` earlier visits of its place (and located on the nearest
    one's walls) is no node of its own. The graph after four laps holds about ``visits`` laps'
    nodes; every scan still has a pose (:meth:`LidarSlam.scan_poses`), as good as when every
    scan is a node (the lap's drift is held on the old walls, not on the wheels); the chain
    stays connected (a link into each node but the first); no scan before the first loop is
    left out. Off, nothing is left out and ``scan_poses`` is ``poses``."""
    settled = {"loop_settled_xy": 0.02, "loop_settled_theta": math.radians(0.2)}
    cfg = SlamConfig(revisit_xy=0.5, revisit_theta=0.35, revisit_visits=visits, **settled)
    on, truth, _ = _laps(cfg, laps=4)
    off, _, _ = _laps(SlamConfig(**settled), laps=4)
    lap = len(truth) // 4
    assert off.skipped == 0 and np.array_equal(off.scan_poses(), off.poses)
    assert len(on.poses) + on.skipped == len(truth) == len(on.online)
    assert visits * lap * 0.8 < len(on.poses) < visits * lap + 10, (len(on.poses), lap)
    chain = sorted(e.j for e in on.edges if not e.robust)
    assert chain == list(range(1, len(on.poses)))
    # each node's chain edge comes from the node the scan before it is, or was posed on
    into = {e.j: e.i for e in on.edges if not e.robust}
    after_skip = [(node, prev[0]) for prev, (node, rel) in itertools.pairwise(on._scans)
                  if rel is None and prev[1] is not None]
    assert after_skip and all(into[node] == twin != node - 1 for node, twin in after_skip), after_skip
    assert all(into[node] == prev[0] for prev, (node, rel) in itertools.pairwise(on._scans)
               if rel is None and prev[1] is None)
    first_loop = on.loops[0][1]
    assert all(rel is None for _, rel in on._scans[: first_loop + 1])

    def rms(poses: np.ndarray, part: slice = slice(None)) -> float:
        return float(np.sqrt(np.mean(np.sum((poses[part, :2] - truth[part, :2]) ** 2, axis=1))))

    assert rms(on.scan_poses()) < 0.2 and rms(on.scan_poses()) < rms(off.poses) + 0.01, (
        rms(on.scan_poses()), rms(off.poses))
    assert rms(on.scan_poses(), slice(-lap, None)) < 0.2  # the last lap held, not drifting on the wheels


def test_the_cloud_cache_bound_changes_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """The SLAM keeps the world-frame clouds of at most ``CLOUD_CACHE`` scans; one evicted and
    needed again is computed again, the same arrays: a cache of 4 gives the same poses bit for
    bit as the default."""
    import mapping.lidar_slam as ls

    route, odo, scans = _hall_drive()

    def run() -> np.ndarray:
        slam = LidarSlam(SlamConfig(), start=np.array(route[0].as_tuple()))
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        assert len(slam._clouds) <= ls.CLOUD_CACHE
        return slam.poses

    full = run()
    monkeypatch.setattr(ls, "CLOUD_CACHE", 4)
    assert np.array_equal(run(), full)


def test_the_travel_array_grows_and_refine_recomputes_evicted_clouds(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop search's travel array starts at one entry and doubles as scans come (the same
    loops and poses as one that never grows), and the offline refinement, which visits every
    scan's neighbours, gives the same poses with 3 clouds cached as with the default cache."""
    import mapping.lidar_slam as ls

    route, odo, scans = _hall_drive()

    def run(**fields: object) -> LidarSlam:
        slam = LidarSlam(SlamConfig(), start=np.array(route[0].as_tuple()), **fields)  # type: ignore[arg-type]
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        return slam

    big, small = run(), run(_travel=np.zeros(1))
    assert len(small._travel) >= len(scans) and np.array_equal(small.poses, big.poses)
    assert small.loops == big.loops and small.rejected == big.rejected
    big.refine()
    monkeypatch.setattr(ls, "CLOUD_CACHE", 3)
    small.refine()
    assert np.array_equal(small.poses, big.poses)


def test_refine_ties_a_revisit_the_loop_search_never_tried() -> None:
    """With the online loop search off, the drive's end (along the first wall again) has drifted
    by the odometry's heading error; the offline refinement matches each scan against the other
    visit of its place and pulls the whole trajectory in: RMS error less than half, max error
    below 0.25 m; deterministic."""
    route, odo, scans = _hall_drive()
    truth = np.array([p.as_tuple() for p in route])

    def run(passes: int) -> LidarSlam:
        slam = LidarSlam(SlamConfig(loop_every=10**6, refine_passes=passes), start=truth[0].copy())
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        for _ in range(passes):
            slam.refine()
        return slam

    def rms(slam: LidarSlam) -> float:
        return float(np.sqrt(np.mean(np.sum((slam.poses[:, :2] - truth[:, :2]) ** 2, axis=1))))

    before, after = run(0), run(2)
    assert not before.loops and not after.loops
    assert rms(before) > 0.08, rms(before)
    assert rms(after) < 0.5 * rms(before), (rms(before), rms(after))
    assert np.hypot(*(after.poses[:, :2] - truth[:, :2]).T).max() < 0.25
    assert np.array_equal(run(2).poses, after.poses)


def test_the_online_refinement_ties_a_revisit_while_driving_and_then_rests() -> None:
    """``refine_online_nodes``: the refinement's matches made a few nodes a scan while the robot
    drives. With the loop search off, the drive's end (along the first wall again) is pulled in
    as the offline refinement pulls it: RMS error less than half, deterministic. Once the
    graph has settled, a sweep matches nothing again (each node's visits sit where they sat at
    its last match) and optimises nothing: it costs a robot that stands in a mapped place no
    matches. Off, no sweep state is touched."""
    route, odo, scans = _hall_drive()
    truth = np.array([p.as_tuple() for p in route])

    def run(nodes: int) -> LidarSlam:
        slam = LidarSlam(SlamConfig(loop_every=10**6, refine_online_nodes=nodes, refine_online_batch=5),
                         start=truth[0].copy())
        for k, (pts, o) in enumerate(zip(scans, odo)):
            slam.add(pts, np.zeros(3) if k == 0 else np.array(o.as_tuple()))
        return slam

    def rms(poses: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))

    off, on = run(0), run(8)
    assert not off.loops and not on.loops
    assert off._sweep.matched == 0 and not off._sweep.edges
    assert on._sweep.matched > 0 and on._sweep.optimised > 0 and on.reshaped == on._sweep.optimised
    assert on._sweep.refused == 0
    assert rms(on.poses) < 0.5 * rms(off.poses), (rms(off.poses), rms(on.poses))
    assert np.array_equal(run(8).poses, on.poses)
    # standing in the mapped place: sweeps go round until one matches nothing again
    n = len(on.poses)
    for _ in range(20 * n):
        before = on._sweep.matched
        for _ in range(n):
            on._refine_online()
        if on._sweep.matched == before:
            break
    else:
        raise AssertionError("the sweep never settled")
    poses, solved = on.poses, on._sweep.optimised
    for _ in range(2 * n):
        on._refine_online()
    assert on._sweep.matched == before and on._sweep.optimised == solved and on.poses is poses


def test_slam_on_the_real_excerpt_beats_its_odometry() -> None:
    """The committed freiburg-101 excerpt (60 real scans): the SLAM's trajectory is closer to
    the truth than the drifting odometry, and the filter fed with it maps the walls."""
    from agents import mapping_run as mr
    from agents.files.carmen import read_carmen_log, scan_truth
    from mapping.lidar_frontend import FrontendConfig, scan_points, slam_increments
    from mapping.lidar_metrics import ate

    log = read_carmen_log(DATA / "freiburg-101-head.log.gz")
    truth = scan_truth(log)
    assert truth is not None
    fcfg = FrontendConfig()
    pts = [scan_points(np.where(s.ranges >= s.max_range, np.inf, s.ranges), s.angles, fcfg)
           for s in log.scans]
    wheel = [Pose.identity(), *(a.odom.between(b.odom) for a, b in zip(log.scans, log.scans[1:]))]
    inc, _slam = slam_increments(pts, wheel, SlamConfig(enabled=True))
    est = [truth[0]]
    for i in inc[1:]:
        est.append(est[-1].compose(i))
    odo = [truth[0]]
    for w in wheel[1:]:
        odo.append(odo[-1].compose(w))
    t = np.array([p.as_tuple() for p in truth])
    slam_ate = ate(np.array([p.as_tuple() for p in est]), t)[0]
    odo_ate = ate(np.array([p.as_tuple() for p in odo]), t)[0]
    assert slam_ate < 0.5 * odo_ate
    # carmen_inputs with the SLAM on hands the filter these increments.
    _fo, ecfg, fc = mr.split_profile({"slam.enabled": True})
    inputs = list(mr.carmen_inputs(log.scans, max_range=20.0, extract=ecfg, frontend=fc))
    assert all(a.odometry.almost_equal(b, 1e-12, 1e-12) for a, b in zip(inputs, inc))


@pytest.mark.parametrize("bad", [{"local_scans": 0}, {"gate_start": 0.1, "gate_end": 0.2},
                                 {"loop_min_inliers": 0.0}, {"refine_passes": -1},
                                 {"refine_visit_gap": 0}, {"loop_settled_xy": -0.01},
                                 {"loop_settled_theta": -0.01}, {"revisit_xy": -0.1},
                                 {"revisit_lock": -1.0}, {"revisit_visits": 0},
                                 {"refine_online_nodes": -1}, {"refine_online_batch": 0},
                                 {"refine_online_facing": -0.1}, {"facing_cos": 1.5},
                                 {"facing_range": -1.0}, {"scanner_range": 0.0}])
def test_bad_settings_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        SlamConfig(**bad)  # type: ignore[arg-type]


def test_map_with_the_slam_profile_on_the_real_excerpt(tmp_path: Path) -> None:
    """``wiremap map --carmen LOG --lidar-profile lidar-slam``: the report names the profile
    and the map is scored against the excerpt's truth."""
    import json

    from agents.cli import main

    out = tmp_path / "m"
    rc = main(["map", "--carmen", str(DATA / "freiburg-101-head.log.gz"), "--lidar-profile", "lidar-slam",
               "--out", str(out), "--seed", "1", "--quiet"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert report["lidar_profile"] == "lidar-slam"
    assert report["ate_rmse_m"] < 0.2


def test_bench_slam_on_the_real_excerpt(capsys: pytest.CaptureFixture[str]) -> None:
    """``wiremap bench slam LOG --starts 3 --json``: one ATE per start frame, each in the truth's
    frame (so all close to each other and well below the odometry's), their median reported;
    a bad flag is a one-line error."""
    import json

    from agents.cli import main

    log = str(DATA / "freiburg-101-head.log.gz")
    assert main(["bench", "slam", log, "--starts", "3", "--json"]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    r = last["logs"]["freiburg-101-head"]
    by = r["ate_rmse_m_by_start"]
    assert len(by) == 3 and last["starts"] == 3
    assert r["ate_rmse_m"] == pytest.approx(sorted(by)[1], abs=1e-6)
    assert max(by) < 0.5 * r["odometry_ate_rmse_m"], r
    assert max(by) - min(by) < 0.05, by
    assert last["settings"]["slam.enabled"] is True
    # The excerpt's prior as the calibration left it: never below the configured one.
    assert r["odo_rot_per_m"] >= SlamConfig().odo_rot_per_m
    assert main(["bench", "slam", log, "--starts", "0"]) == 2
    assert "--starts must be >= 1" in capsys.readouterr().err


@pytest.mark.parametrize("scale", [1, 10**6, 2**40])
def test_first_of_each_row_is_uniques_index(scale):
    """Submap thinning finds each voxel's row by one integer per row; the indices (and their
    order) are numpy.unique(axis=0)'s, also for spans too wide to number (its fallback)."""
    from mapping.lidar_slam import _first_of_each_row

    rng = np.random.default_rng(scale % 1000)
    for n in (1, 2, 50, 3000):
        keys = rng.integers(-20, 20, (n, 2)) * scale
        expected = np.unique(keys, axis=0, return_index=True)[1]
        np.testing.assert_array_equal(_first_of_each_row(keys), expected)
        np.testing.assert_array_equal(_first_of_each_row(keys[::-1]), np.unique(keys[::-1], axis=0,
                                                                                 return_index=True)[1])


def test_graph_warp_moves_points_with_their_nodes() -> None:
    """A map point follows the nodes nearest it: unchanged when the graph did not move; with
    one node, rigidly with it (a quarter turn about the node turns the point about it); with two
    nodes 20 m apart, a point by each moves with its own node only."""
    pts = np.array([[0.0, 1.0], [1.0, 0.0], [20.0, 1.5], [19.0, -0.5]])
    then = np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    assert np.allclose(graph_warp(then, then.copy(), pts), pts)
    assert graph_warp(then, then, np.zeros((0, 2))).shape == (0, 2)
    one = graph_warp(then[:1], np.array([[0.0, 0.0, math.pi / 2]]), pts[:2])
    assert np.allclose(one, [[-1.0, 0.0], [0.0, 1.0]])
    now = then + np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.0]])
    moved = graph_warp(then, now, pts)
    assert np.allclose(moved[:2], pts[:2], atol=1e-9)
    assert np.allclose(moved[2:], pts[2:] + np.array([1.0, -2.0]), atol=1e-9)
    # between two nodes that moved apart, a point moves part of the way (the Gaussian weights)
    pair = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    mid = graph_warp(pair, pair + np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[1.0, 0.0]]))
    assert np.allclose(mid, [[1.0, 0.5]])
