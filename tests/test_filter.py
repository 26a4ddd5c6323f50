"""The wireframe particle filter (paper Fig. 7), on small hand-made worlds in tests/worlds/."""

import math
from pathlib import Path

import numpy as np
import pytest

from agents.mapping_run import SimOptions, filter_config_for, seeds_for, simulate
from agents.sim.world import load_world
from mapping import Label, Pose, Wireframe
from mapping.filter import (
    MAX_LIKELIHOOD,
    FilterConfig,
    WireframeFilter,
    budget_map,
    budget_scan,
    contradiction_update,
    drop_fragments,
    drop_line_of_sight,
    edge_log_odds,
)
from mapping.metrics import wall_precision_recall

WORLDS = Path(__file__).parent / "worlds"


def run(world_name: str, steps: int, seed: int = 0, particles: int = 5, faults: dict | None = None):
    world = load_world(WORLDS / f"{world_name}.geojson")
    inputs = list(simulate(world, SimOptions(steps=steps), seed))
    f = WireframeFilter(filter_config_for(particles, 0.2, 8.0), seeds_for(seed)["filter"], inputs[0].true_pose)
    trace = []
    for k, inp in enumerate(inputs):
        info = f.step(inp.odometry, inp.scan, fault=(faults or {}).get(k))
        p, r = wall_precision_recall(world.truth, f.best, 0.4) if f.best.n_edges else (math.nan, 0.0)
        trace.append((info, p, r, f.pose.distance(inp.true_pose)))
    return world, f, trace


@pytest.mark.parametrize(
    "kwargs",
    [
        {"particles": 0},
        {"max_range": -1.0},
        {"fov": 7.0},
        {"keep_threshold": 1.5},
        {"merge_threshold": 0.0},
        {"temperature": math.nan},
        {"max_vertices": 2},
        {"min_fragment_length": -0.1},
        {"min_line_distance": math.inf},
    ],
)
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        FilterConfig(**kwargs)


def test_maps_a_small_room_accurately():
    _world, f, trace = run("tiny", 40)
    info, precision, recall, _ = trace[-1]
    assert precision >= 0.95 and recall >= 0.95
    assert max(t[3] for t in trace) < 0.1  # pose error, metres
    assert f.memory_bytes() == sum(p.paper_storage_bytes() for p in f.particles)
    assert f.steps == len(trace) == info.step >= 20
    assert 1 <= info.distinct <= 5


def test_is_deterministic_given_the_seed():
    _, a, _ = run("tiny", 15, seed=3)
    _, b, _ = run("tiny", 15, seed=3)
    assert a.best.almost_equal(b.best, tol=0.0, likelihood_tol=0.0)
    assert a.pose == b.pose


def test_identical_particles_share_one_object():
    # The first scan goes into the empty map of every particle: one merge, one shared object.
    world = load_world(WORLDS / "tiny.geojson")
    inp = next(simulate(world, SimOptions(steps=1), 0))
    f = WireframeFilter(filter_config_for(8, 0.2, 8.0), np.random.default_rng(0), inp.true_pose)
    info = f.step(inp.odometry, inp.scan)
    assert info.distinct == 1
    assert all(p is f.particles[0] for p in f.particles)
    assert f.memory_bytes() == 8 * f.best.paper_storage_bytes()


def test_recovers_from_a_scan_matching_failure():
    """Paper Fig. 8: one scan is placed with a large wrong shift (0.9 m, -0.6 m, 0.15 rad). The
    best particle's wall precision must come back to its level before the fault within 5 steps
    (measured: 1 step on this world and seed) while the pose estimate is unaffected."""
    fault_at = 30
    _, _f, trace = run("lshape", fault_at + 12, seed=0, particles=10, faults={fault_at: Pose(0.9, -0.6, 0.15)})
    before = trace[fault_at - 1][1]
    assert trace[fault_at][1] < before - 0.1  # the fault did corrupt the map
    recovered = [k for k in range(fault_at + 1, fault_at + 6) if trace[k][1] >= before - 0.01]
    assert recovered, [round(t[1], 3) for t in trace[fault_at:]]
    assert min(t[1] for t in trace[recovered[0] : fault_at + 12]) >= before - 0.02
    assert max(t[3] for t in trace) < 0.1


def test_single_hypothesis_baseline_runs():
    world = load_world(WORLDS / "tiny.geojson")
    inputs = list(simulate(world, SimOptions(steps=10), 1))
    f = WireframeFilter(filter_config_for(1, 0.2, 8.0), np.random.default_rng(0), inputs[0].true_pose)
    for inp in inputs:
        info = f.step(inp.odometry, inp.scan)
        assert info.mutated == 0 and info.distinct == 1
    assert f.best.n_edges >= 4


def test_dead_reckoning_without_icp_still_maps():
    world = load_world(WORLDS / "tiny.geojson")
    inputs = list(simulate(world, SimOptions(steps=5), 2))
    cfg = filter_config_for(3, 0.2, 8.0, use_icp=False)
    f = WireframeFilter(cfg, np.random.default_rng(0), inputs[0].true_pose)
    for inp in inputs:
        assert f.step(inp.odometry, inp.scan).icp is None
    assert f.best.n_edges >= 4


def test_contradiction_update_is_bayes_and_leaves_certainty_capped():
    out = contradiction_update(np.array([0.0, 0.5, 1.0]), p_fp=0.1, p_fn=0.1)
    assert out[0] == 0.0
    assert out[1] == pytest.approx(0.05 / (0.05 + 0.45))
    # An edge at likelihood 1 (merging saturates) can still be brought down.
    c = MAX_LIKELIHOOD
    assert out[2] == pytest.approx(c * 0.1 / (c * 0.1 + (1 - c) * 0.9))
    lik = np.array([1.0])
    for _ in range(4):
        lik = contradiction_update(lik, 0.1, 0.1)
    assert lik[0] < 0.5


def test_edge_log_odds_penalises_doubtful_edges():
    strong = Wireframe.build([(0, 0), (1, 0)], [(0, 1)], likelihood=[0.9])
    doubtful = Wireframe.build([(0, 0), (1, 0), (2, 0), (3, 0)], [(0, 1), (2, 3)], likelihood=[0.9, 0.1])
    assert edge_log_odds(doubtful) < edge_log_odds(strong)
    assert edge_log_odds(Wireframe.empty()) == 0.0


def test_scan_clean_up():
    # A frontier fragment 0.2 m long goes; a complete 0.2 m wall stays; a wall along a line of
    # sight (through the robot's position, extended) goes.
    scan = Wireframe.build(
        [(2, -1), (2, -0.8), (3, 1), (3, 1.2), (1, 1), (4, 4)],
        [(0, 1), (2, 3), (4, 5)],
        labels=[Label.NOMINAL, Label.FRONTIER, Label.NOMINAL, Label.NOMINAL, Label.OCCLUSION, Label.FRONTIER],
    )
    a = drop_fragments(scan, 0.4)
    assert a.n_edges == 2
    b = drop_line_of_sight(a, 0.15)
    assert b.n_edges == 1 and np.allclose(b.points, [(3, 1), (3, 1.2)])


def test_budgets():
    rng = np.random.default_rng(0)
    rings = [rng.uniform(0, 10, size=(2, 2)) for _ in range(30)]
    wf = Wireframe.from_polylines(rings, closed=False, likelihood=1.0)
    wf = wf.replace(likelihood=rng.uniform(0, 1, wf.n_edges))
    s = budget_scan(wf, 20)
    assert s.n_vertices <= 20
    # the longest walls are the ones kept
    assert s.edge_lengths().min() >= np.sort(wf.edge_lengths())[-10] - 1e-12
    m = budget_map(wf, 21)
    assert m.n_vertices <= 21
    assert m.likelihood.min() >= np.median(wf.likelihood) - 0.2
