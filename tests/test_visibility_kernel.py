"""The compiled visibility sweep (:func:`mapping.kernels.visibility_sweep`) against the Python
sweep it replaced (``tests/visibility_reference.py``): the same views bit for bit, on the
simulated worlds, on noisy particle-like maps with crossing and degenerate walls, at full and
partial fields of view, limited and unlimited range."""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from agents.sim.world import builtin_names, load_world
from mapping import Label, Pose, Wireframe
from mapping.visibility import View, visible_view
from tests.visibility_reference import reference_view


def assert_same(got: View, want: View) -> None:
    """Every array of the two views equal, bit for bit (dtype, shape and bytes)."""
    pairs = {
        "points": (got.scan.points, want.scan.points),
        "labels": (got.scan.labels, want.scan.labels),
        "edges": (got.scan.edges, want.scan.edges),
        "likelihood": (got.scan.likelihood, want.scan.likelihood),
        "sources": (got.scan.sources, want.scan.sources),
        "edge_source": (got.edge_source, want.edge_source),
        "vertex_source": (got.vertex_source, want.vertex_source),
        "edge_t": (got.edge_t, want.edge_t),
        "visible": (got.visible, want.visible),
        "in_view": (got.in_view, want.in_view),
    }
    for name, (a, b) in pairs.items():
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, (name, a.dtype, b.dtype, a.shape, b.shape)
        assert a.tobytes() == b.tobytes(), (name, a, b)


def noisy_map(rng: np.random.Generator, n: int, spread: float) -> Wireframe:
    """A particle-like map: jittered room corners, random walls (some crossing, some tiny, some
    sharing vertices), random labels and likelihoods."""
    pts = rng.uniform(-spread, spread, (n, 2))
    if n > 4:  # a few exact repeats and near-repeats: shared corners, zero-length walls
        pts[1] = pts[0]
        pts[3] = pts[2] + 1e-13
    edges = []
    for i in range(n - 1):
        edges.append((i, i + 1))
    for _ in range(n // 2):
        a, b = rng.integers(0, n, 2)
        if a != b:
            edges.append((int(a), int(b)))
    labels = rng.integers(0, 3, n)
    wf = Wireframe.build(pts, edges, labels=[Label(int(v)) for v in labels])
    return wf.replace(likelihood=rng.uniform(0.05, 1.0, wf.n_edges))


@pytest.mark.parametrize("name", builtin_names())
def test_worlds_from_their_free_space(name: str) -> None:
    world = load_world(name)
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    free = world.free_space
    minx, miny, maxx, maxy = free.bounds
    poses = 0
    import shapely

    while poses < 25:
        x, y = rng.uniform(minx, maxx), rng.uniform(miny, maxy)
        if not free.contains(shapely.Point(x, y)):
            continue
        pose = Pose(float(x), float(y), float(rng.uniform(-math.pi, math.pi)))
        for fov, reach in ((2 * math.pi, 8.0), (math.radians(240.0), 20.0), (math.radians(90.0), math.inf)):
            truth = world.truth
            assert_same(visible_view(truth, pose, reach, fov), reference_view(truth, pose, reach, fov))
        poses += 1


@pytest.mark.parametrize("seed", range(12))
def test_noisy_maps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for n in (2, 5, 12, 40, 120):
        wf = noisy_map(rng, n, float(rng.uniform(1.0, 15.0)))
        for _ in range(6):
            pose = Pose(*rng.uniform(-5, 5, 2).tolist(), float(rng.uniform(-4, 4)))
            fov = float(rng.choice([2 * math.pi, math.radians(270.0), math.radians(180.0), 0.3]))
            max_range = float(rng.choice([3.0, 8.0, math.inf]))
            min_piece = float(rng.choice([0.0, 1e-3, 0.5]))
            assert_same(visible_view(wf, pose, max_range, fov, min_piece=min_piece),
                        reference_view(wf, pose, max_range, fov, min_piece=min_piece))


def test_robot_on_a_corner_and_on_a_wall_line() -> None:
    """Degenerate viewpoints: a wall through the robot (edge-on), a corner at the robot, a
    corner straight ahead on the field of view's boundary ray."""
    pts = [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0),
           (0.0, 0.0), (1.0, 0.0), (0.0, -1.0), (1.0, 1.0)]
    wf = Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (6, 7)])
    extra = Wireframe.build(pts[4:], [(0, 1), (2, 3)])
    for pose in (Pose(0.0, 0.0, 0.0), Pose(0.5, 0.0, 0.0), Pose(1.0, 1.0, math.pi / 4), Pose(-2.0, 0.0, 0.0)):
        for fov in (2 * math.pi, math.pi / 2, math.pi):
            for w in (wf, extra):
                assert_same(visible_view(w, pose, 8.0, fov), reference_view(w, pose, 8.0, fov))


def test_bearings_within_angle_tol_are_one_event() -> None:
    """Ends closer in bearing than ``ANGLE_TOL`` are one event of the sweep, grouped from the
    first of a run (not chained): walls whose starts are k * 1e-12 rad apart, a star of walls
    on shared bearings, at fields of view of a few ANGLE_TOL."""
    from mapping.visibility import ANGLE_TOL

    pts, edges = [], []
    for k in range(6):  # six walls at 5 m whose start bearings are k * 1e-12 apart
        a = -0.3 + k * 1e-12
        b = a + 0.4 + k * 0.05
        pts += [(5.0 * math.cos(a), 5.0 * math.sin(a)), (5.0 * math.cos(b), 5.0 * math.sin(b))]
        edges.append((2 * k, 2 * k + 1))
    fan = Wireframe.build(pts, edges)
    rings = [[(r * math.cos(t), r * math.sin(t)) for t in (0.0, math.pi / 2, math.pi, 3 * math.pi / 2)]
             for r in (1.0, 2.0, 3.0)]
    star = Wireframe.from_polylines(rings, closed=True)
    for wf in (fan, star):
        for fov in (2 * math.pi, math.pi, 1e-12, 2e-12, 0.5 * ANGLE_TOL + 1e-13):
            for theta in (0.0, -0.3, 1e-12, math.pi / 4):
                pose = Pose(0.0, 0.0, theta)
                assert_same(visible_view(wf, pose, 8.0, fov), reference_view(wf, pose, 8.0, fov))
    f32 = np.float32(1.0)  # a numpy float32 field of view is taken as the float it is
    assert_same(visible_view(star, Pose(0.0, 0.0, 0.1), 8.0, f32),  # type: ignore[arg-type]
                reference_view(star, Pose(0.0, 0.0, 0.1), 8.0, float(f32)))
