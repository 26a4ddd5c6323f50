"""Tests of agents.sim.sensor: the simulated corner sensor (paper Sec. IV-A)."""

import math

import numpy as np
import pytest

from agents.sim.sensor import CornerSensor, CornerSensorConfig, LabelStats, label_accuracy, label_stats
from mapping import Label, Pose, Wireframe

NOM, OCC, FRO = Label.NOMINAL, Label.OCCLUSION, Label.FRONTIER

# A 10 x 10 room with a box: from (2, 5) the scan has 8 corners (2 occlusions, 2 frontiers).
ROOM = Wireframe.from_polylines([[(0, 0), (10, 0), (10, 10), (0, 10)], [(4, 4), (4, 6), (6, 6), (6, 4)]])
POSE = Pose(2.0, 5.0, 0.3)


def sensor(**kw) -> CornerSensor:
    base = {"max_range": 20.0, "sigma": 0.0, "p_fp": 0.0, "p_fn": 0.0}
    base.update(kw)
    return CornerSensor(ROOM, CornerSensorConfig(**base))


def test_true_scan_is_the_visible_view():
    t = sensor().true_scan(POSE)
    assert t.n_vertices == 8 and t.n_edges == 6
    assert sorted(t.labels.tolist()) == [NOM, NOM, NOM, NOM, OCC, OCC, FRO, FRO]
    assert np.all(t.likelihood == 1.0) and np.all(t.sources == 0)
    want = Wireframe.build(
        [(0, 0), (10, 0), (10, 1), (4, 4), (4, 6), (10, 9), (10, 10), (0, 10)],
        [(0, 1), (1, 2), (3, 4), (5, 6), (6, 7), (7, 0)],
        labels=[NOM, NOM, FRO, OCC, OCC, FRO, NOM, NOM],
    )
    assert t.transformed(POSE).almost_equal(want, tol=1e-9)


def test_noise_free_scan_equals_true_scan():
    s = sensor()
    scan = s.scan(POSE, np.random.default_rng(3))
    truth = s.true_scan(POSE)
    assert scan.almost_equal(truth, tol=0.0)
    assert np.array_equal(scan.points, truth.points)


def test_seeded_scans_are_reproducible():
    s = CornerSensor(ROOM, CornerSensorConfig(max_range=20.0, sigma=0.05, p_fp=0.3, p_fn=0.3))
    a = s.scan(POSE, np.random.default_rng(42))
    b = s.scan(POSE, np.random.default_rng(42))
    c = s.scan(POSE, np.random.default_rng(43))
    for f in ("points", "labels", "edges", "likelihood", "sources"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.points, c.points) or a.n_vertices != c.n_vertices


def test_all_walls_missed_gives_empty_scan():
    scan = sensor(p_fn=1.0).scan(POSE, np.random.default_rng(0))
    assert scan.n_edges == 0 and scan.n_vertices == 0


def test_missed_wall_drops_only_orphan_corners():
    s = sensor(p_fn=0.5)
    truth = s.true_scan(POSE)
    rng = np.random.default_rng(11)
    seen_partial = False
    for _ in range(50):
        scan = s.scan(POSE, rng)
        # Every reported corner ends a reported wall, at its true place with its true label.
        deg_in, deg_out = scan.degree()
        assert np.all(deg_in + deg_out > 0)
        for p, lab in zip(scan.points, scan.labels):
            k = int(np.argmin(np.hypot(*(truth.points - p).T)))
            assert np.allclose(truth.points[k], p) and truth.labels[k] == lab
        # Every reported wall is a true wall (no false positives here).
        assert scan.n_edges <= truth.n_edges
        seen_partial |= 0 < scan.n_edges < truth.n_edges
    assert seen_partial


def test_false_positive_joins_unjoined_consecutive_corners():
    s = sensor(p_fp=1.0)
    truth = s.true_scan(POSE)
    scan = s.scan(POSE, np.random.default_rng(0))
    # 8 corners on a full turn = 8 consecutive pairs, 6 of them already walls.
    assert scan.n_edges == truth.n_edges + 2
    assert scan.n_vertices == truth.n_vertices
    pts = scan.points
    new = [tuple(e) for e in scan.edges.tolist()]
    lab = scan.labels
    # The two spurious walls join an occlusion to its frontier, counterclockwise (along a ray).
    extra = [e for e in new if {lab[e[0]], lab[e[1]]} == {OCC, FRO}]
    assert len(extra) == 2
    for i, j in extra:
        cross = pts[i, 0] * pts[j, 1] - pts[i, 1] * pts[j, 0]
        assert abs(cross) < 1e-9  # on one line of sight


def test_false_positive_rate_statistics():
    s = sensor(p_fp=0.25)
    rng = np.random.default_rng(5)
    extra = [s.scan(POSE, rng).n_edges - 6 for _ in range(800)]
    # 2 candidate pairs per scan: mean 0.5 extra walls, binomial std of the mean ~ 0.0153.
    assert abs(np.mean(extra) - 0.5) < 0.05


def test_missed_wall_rate_statistics():
    s = sensor(p_fn=0.2)
    rng = np.random.default_rng(6)
    kept = np.mean([s.scan(POSE, rng).n_edges for _ in range(800)]) / 6
    assert abs(kept - 0.8) < 0.02  # std of the mean ~ 0.0058


def test_noise_std():
    sigma = 0.05
    s = sensor(sigma=sigma)
    truth = s.true_scan(POSE)
    rng = np.random.default_rng(9)
    res = np.concatenate([s.scan(POSE, rng).points - truth.points for _ in range(500)])
    # 4000 residuals per axis: the sample std is within ~1.1 % (1 sigma) of the truth.
    assert abs(res.mean()) < 0.005
    assert np.allclose(res.std(axis=0), sigma, rtol=0.05)
    assert abs(np.corrcoef(res.T)[0, 1]) < 0.05  # isotropic: axes independent


def test_fov_and_range_of_sensor():
    s = CornerSensor(ROOM, CornerSensorConfig(max_range=3.0, fov=math.pi / 2, sigma=0.0, p_fp=0, p_fn=0))
    t = s.true_scan(Pose(2.0, 5.0, 0.0))
    # Ahead: only the box face 2 m away, both ends silhouettes.
    assert np.allclose(t.points, [(2, -1), (2, 1)])
    assert t.labels.tolist() == [OCC, OCC]


@pytest.mark.parametrize(
    "kw",
    [
        {"max_range": 0.0},
        {"max_range": math.inf},
        {"fov": 0.0},
        {"fov": 7.0},
        {"sigma": -0.1},
        {"sigma": math.nan},
        {"p_fp": 1.5},
        {"p_fn": -0.1},
        {"min_piece": -1.0},
    ],
)
def test_config_rejects_with_reason(kw):
    name = next(iter(kw))
    with pytest.raises(ValueError, match=name):
        CornerSensorConfig(**kw)


def test_label_accuracy():
    truth = sensor().true_scan(POSE)
    assert label_accuracy(truth, truth, tol=0.1) == 1.0
    flipped = truth.labels.copy()
    flipped[[0, 3]] = (flipped[[0, 3]] + 1) % 3
    wrong = truth.replace(labels=flipped)
    assert label_accuracy(wrong, truth, tol=0.1) == pytest.approx(6 / 8)
    # A missing corner does not count against the labels, only against detection.
    fewer = truth.subgraph_edges(np.arange(truth.n_edges) != 0)
    st = label_stats(fewer, truth, tol=0.1)
    assert (st.n_true, st.n_matched, st.n_same) == (
        8,
        8 - (truth.n_vertices - fewer.n_vertices),
        st.n_matched,
    )
    assert st.accuracy == 1.0
    total = st + LabelStats(2, 2, 1)
    assert total == LabelStats(10, st.n_matched + 2, st.n_matched + 1)
    assert math.isnan(label_accuracy(Wireframe.empty(), truth, tol=0.1))


def test_label_accuracy_of_noisy_scans_is_high():
    s = CornerSensor(ROOM, CornerSensorConfig(max_range=20.0))  # default noise and error rates
    rng = np.random.default_rng(1)
    total = LabelStats()
    for k in range(100):
        pose = Pose(1.0 + 0.02 * k, 5.0 + 0.03 * (k % 7), 0.1 * k)
        total += label_stats(s.scan(pose, rng), s.true_scan(pose), tol=0.1)
    assert total.accuracy >= 0.99
    assert total.detection >= 0.95
