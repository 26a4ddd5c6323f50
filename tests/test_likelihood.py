"""The scan likelihood p(S | W) (paper Sec. IV-D), on hand-made wireframes."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import Label, Pose, Wireframe
from mapping.likelihood import (
    CONTRADICTED,
    OBSERVED,
    OCCLUDED,
    LikelihoodConfig,
    in_gap,
    ray_ranges,
    scan_likelihood,
)
from mapping.visibility import visible_view

CFG = LikelihoodConfig(sigma=0.1, p_fp=0.1, p_fn=0.1)
OUTER = [(0, 0), (6, 0), (6, 4), (3, 4), (3, 5), (0, 5)]
BOX = [(2, 1), (2, 2), (3, 2), (3, 1)]  # clockwise: an obstacle
POSE = Pose(1.0, 3.0, 0.3)


def view(*rings, pose=POSE, closed=True) -> Wireframe:
    return visible_view(Wireframe.from_polylines(rings, closed=closed), pose, 8.0).scan


def test_perfect_match_costs_only_the_true_positive_terms():
    s = view(OUTER, BOX)
    lk = scan_likelihood(s, s, CFG)
    assert lk.vertex_log == pytest.approx(0.0, abs=1e-12)
    assert lk.edge_log == pytest.approx(s.n_edges * math.log(0.9))
    assert np.all(lk.predicted_edge_state == OBSERVED)
    assert np.all(lk.scan_edge_matched)
    assert np.allclose(lk.scan_edge_likelihood, 0.9)


def test_per_edge_likelihood_is_gaussians_times_bernoulli():
    s = Wireframe.build([(2, -1), (2, 1)], [(0, 1)])
    shifted = s.replace(points=s.points + np.array([[0.05, 0.0], [0.0, 0.0]]))
    lk = scan_likelihood(shifted, s, CFG)
    g = math.exp(-(0.05**2) / (2 * 0.1**2))
    assert lk.scan_edge_likelihood[0] == pytest.approx(g * 1.0 * 0.9)
    assert lk.predicted_edge_likelihood[0] == pytest.approx(g * 0.9)
    eps = CFG.outlier_weight
    assert lk.vertex_log == pytest.approx(math.log((1 - eps) * g + eps))


def test_missing_obstacle_and_bogus_wall_score_lower():
    truth_scan = view(OUTER, BOX)
    rng = np.random.default_rng(1)
    scan = truth_scan.replace(points=truth_scan.points + rng.normal(0, 0.02, truth_scan.points.shape))
    good = scan_likelihood(scan, truth_scan, CFG).log_likelihood
    missing = scan_likelihood(scan, view(OUTER), CFG)
    bogus_map = Wireframe.from_polylines([OUTER, BOX, [(4, 2), (5, 2)]], closed=True)
    bogus = scan_likelihood(scan, visible_view(bogus_map, POSE, 8.0).scan, CFG)
    assert missing.log_likelihood < good - 5
    assert bogus.log_likelihood < good - 5
    assert np.count_nonzero(bogus.predicted_edge_state == CONTRADICTED) >= 1
    # The scan's obstacle edges are unknown to the "missing" particle: false positives.
    assert np.count_nonzero(~missing.scan_edge_matched) >= 2


def test_predicted_edge_factors_are_np_selects_bit_for_bit():
    # scan_likelihood gathers each predicted edge's factor from a table by its state; the former
    # code picked it with np.select. Same floats, every state present (the scan sees past the
    # far wall at x = 4, and a new wall at x = 2 hides the one at x = 3 behind it).
    particle = Wireframe.from_polylines([[(3, -0.5), (3, 0.5)], [(4, 1.5), (4, 3)], [(6, -1), (6, 1)]])
    scan = Wireframe.from_polylines([[(2, -1), (2, 1)], [(7, 1.4), (7, 3.2)], [(6.02, -1), (6.01, 1)]])
    for cfg in (CFG, LikelihoodConfig(sigma=0.07, p_fp=0.2, p_fn=0.15)):
        lk = scan_likelihood(scan, particle, cfg)
        state = lk.predicted_edge_state
        assert {OBSERVED, CONTRADICTED, OCCLUDED} <= set(state.tolist())
        g = np.exp(-(0.5 / cfg.sigma**2) * lk.predicted_vertex_dist**2)
        b = np.select([state == OBSERVED, state == CONTRADICTED], [1.0 - cfg.p_fn, cfg.p_fn], 1.0)
        former = np.clip(g[particle.edges[:, 0]] * g[particle.edges[:, 1]] * b, 0.0, 1.0)
        assert lk.predicted_edge_likelihood.tobytes() == former.tobytes()

def test_edge_behind_a_new_obstacle_is_occluded_not_contradicted():
    # The particle knows a wall at x = 4 only; the scan sees a new wall at x = 2 in front of it.
    particle = Wireframe.build([(4, -1), (4, 1)], [(0, 1)])
    scan = Wireframe.build([(2, -1.5), (2, 1.5)], [(0, 1)])
    lk = scan_likelihood(scan, particle, CFG)
    assert lk.predicted_edge_state.tolist() == [OCCLUDED]
    # ... whereas if the scan sees past it, it is contradicted.
    far = Wireframe.build([(6, -1.5), (6, 1.5)], [(0, 1)])
    lk2 = scan_likelihood(far, particle, CFG)
    assert lk2.predicted_edge_state.tolist() == [CONTRADICTED]
    assert lk2.edge_log == pytest.approx(math.log(0.1) + math.log(0.1))


def test_temporary_point_in_a_gap_costs_nothing():
    # The prediction has one wall ahead; the scan also sees a new wall behind the robot, where
    # the prediction has no wall at all (unexplored): its vertices get no Gaussian penalty.
    pred = Wireframe.build([(3, -1), (3, 1)], [(0, 1)])
    scan = Wireframe.build([(3, -1), (3, 1), (-3, 1), (-3, -1)], [(0, 1), (2, 3)])
    lk = scan_likelihood(scan, pred, CFG)
    assert np.allclose(lk.scan_vertex_dist, 0.0)
    assert lk.vertex_log == pytest.approx(0.0)
    assert lk.scan_edge_matched.tolist() == [True, False]
    assert lk.scan_edge_likelihood[1] == pytest.approx(CFG.p_fp)


def test_temporary_point_off_gap_is_projected_onto_nearest_edge():
    # Paper IV-D's example: the scan sees only half of a predicted wall (a frontier halfway);
    # the frontier has no match and is penalised only by its distance from the predicted wall.
    pred = Wireframe.build([(3, -2), (3, 2)], [(0, 1)])
    scan = Wireframe.build([(3, -2), (3.04, 0.0)], [(0, 1)], labels=[Label.NOMINAL, Label.FRONTIER])
    lk = scan_likelihood(scan, pred, CFG)
    assert lk.scan_vertex_dist[1] == pytest.approx(0.04)
    # The predicted end (3, 2) is unmatched and lies where the scan has no wall: no penalty.
    assert lk.predicted_vertex_dist[1] == pytest.approx(0.0)


def test_empty_prediction_and_empty_scan():
    s = view(OUTER)
    lk = scan_likelihood(s, Wireframe.empty(), CFG)
    assert lk.vertex_log == pytest.approx(0.0)
    assert lk.edge_log == pytest.approx(s.n_edges * math.log(CFG.p_fp))
    lk2 = scan_likelihood(Wireframe.empty(), Wireframe.empty(), CFG)
    assert lk2.log_likelihood == 0.0


def test_in_gap_and_ray_ranges():
    wall = Wireframe.build([(2, -1), (2, 1)], [(0, 1)])
    assert in_gap(wall, np.array([[5.0, 0.0], [-1.0, 0.0], [1.0, 3.0]])).tolist() == [False, True, True]
    r = ray_ranges(wall, np.array([0.0, math.pi, math.atan2(1, 2)]))
    assert r[0] == pytest.approx(2.0)
    assert math.isinf(r[1])
    assert r[2] == pytest.approx(math.hypot(2, 1))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), noise=st.floats(0.0, 0.2))
def test_likelihoods_are_probabilities_and_log_is_bounded(seed, noise):
    s = view(OUTER, BOX)
    rng = np.random.default_rng(seed)
    scan = s.replace(points=s.points + rng.normal(0.0, noise, s.points.shape))
    lk = scan_likelihood(scan, s, CFG)
    assert np.all((lk.scan_edge_likelihood >= 0) & (lk.scan_edge_likelihood <= 1))
    assert np.all((lk.predicted_edge_likelihood >= 0) & (lk.predicted_edge_likelihood <= 1))
    # Each vertex costs at most -log(eps); each edge at most -log(min(p_fp, p_fn)).
    bound = (s.n_vertices + scan.n_vertices) * math.log(1 / CFG.outlier_weight) + (
        s.n_edges + scan.n_edges
    ) * math.log(10)
    assert -bound <= lk.log_likelihood <= 0.0


@pytest.mark.parametrize("kwargs", [{"p_fp": 0.0}, {"p_fn": 1.0}, {"sigma": -1.0}, {"gap_margin": -0.1}])
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        LikelihoodConfig(**kwargs)
