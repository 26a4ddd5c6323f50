"""Point-to-line matching of raw scan points against map walls (mapping.scan_match)."""

import math

import numpy as np
import pytest

from mapping.icp import Correspondences, ICPResult
from mapping.scan_match import PointMatchConfig, assign, match_points, point_normals, refine_match
from mapping.se2 import Pose

# A room seen from the origin: back wall at x = 6, side walls at y = -3 and y = 4, and a pillar face.
ROOM = np.array(
    [
        [[6.0, -3.0], [6.0, 4.0]],
        [[-1.0, 4.0], [6.0, 4.0]],
        [[-1.0, -3.0], [6.0, -3.0]],
        [[3.0, 1.0], [3.0, 2.0]],
    ]
)
CORRIDOR = np.array([[[-10.0, -1.5], [10.0, -1.5]], [[-10.0, 1.5], [10.0, 1.5]]])


def ray_cast(segs: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Ranges from the origin to the nearest segment along each bearing (inf: none)."""
    out = np.full(len(angles), np.inf)
    for k, a in enumerate(angles):
        d = np.array([math.cos(a), math.sin(a)])
        for p, q in segs:
            e = q - p
            den = d[0] * -e[1] + d[1] * e[0]
            if abs(den) < 1e-12:
                continue
            t = (p[0] * -e[1] + p[1] * e[0]) / den
            s = (d[0] * p[1] - d[1] * p[0]) / den
            if t > 0 and 0 <= s <= 1:
                out[k] = min(out[k], t)
    return out


def scan_of(segs: np.ndarray, pose: Pose, n: int = 181, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Robot-frame points of a 180-degree scan of ``segs`` (map frame) taken at ``pose``."""
    local = pose.apply_inverse(segs.reshape(-1, 2)).reshape(-1, 2, 2)
    a = np.linspace(-math.pi / 2, math.pi / 2, n)
    r = ray_cast(local, a)
    r = r + np.random.default_rng(seed).normal(0.0, noise, n)
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)


def test_recovers_an_offset_in_a_room() -> None:
    truth = Pose(0.15, -0.1, math.radians(2.0))
    pts = scan_of(ROOM, truth, noise=0.01)
    prior = np.diag([0.3**2, 0.3**2, math.radians(5) ** 2])
    res = match_points(pts, ROOM, prior, gate_start=1.0)
    assert res.accepted, res.reason
    assert res.constrained == 3
    assert abs(res.correction.x - truth.x) < 0.01
    assert abs(res.correction.y - truth.y) < 0.01
    assert abs(res.correction.theta - truth.theta) < math.radians(0.2)
    assert res.covariance[0, 0] < prior[0, 0]


def test_clutter_does_not_pull() -> None:
    truth = Pose(0.1, 0.05, math.radians(-1.5))
    pts = scan_of(ROOM, truth, noise=0.01)
    rng = np.random.default_rng(3)
    clutter = rng.uniform([1.0, -2.0], [4.0, 2.0], size=(40, 2))  # chairs and people in the room
    pts = np.concatenate([pts[:60], clutter, pts[60:]])
    res = match_points(pts, ROOM, np.diag([0.3**2, 0.3**2, math.radians(5) ** 2]), gate_start=1.0)
    assert res.accepted, res.reason
    assert math.hypot(res.correction.x - truth.x, res.correction.y - truth.y) < 0.02
    assert abs(res.correction.theta - truth.theta) < math.radians(0.3)


def test_corridor_keeps_the_prior_along_its_axis() -> None:
    truth = Pose(0.4, 0.1, math.radians(1.0))
    pts = scan_of(CORRIDOR, truth)
    prior = np.diag([0.5**2, 0.5**2, math.radians(5) ** 2])
    res = match_points(pts, CORRIDOR, prior, gate_start=1.0)
    assert res.constrained == 2
    assert abs(res.correction.y - truth.y) < 0.01
    assert abs(res.correction.x) < 0.05  # along the corridor: the prediction, not the truth
    assert res.covariance[0, 0] > 0.5 * prior[0, 0]


def test_rejects_a_scan_of_another_place() -> None:
    pts = scan_of(CORRIDOR, Pose.identity())
    res = match_points(pts, ROOM, np.diag([0.1**2, 0.1**2, 0.01]), gate_start=0.5)
    assert not res.accepted
    assert match_points(pts, np.zeros((0, 2, 2)), np.eye(3)).reason == "nothing to match"


def test_point_normals_and_assign() -> None:
    xs = np.linspace(0.0, 2.0, 21)
    pts = np.stack([xs, np.full_like(xs, 1.0)], axis=1)
    nrm = point_normals(pts, 2)
    assert np.isnan(nrm[0, 0]) and np.isnan(nrm[-1, 0])
    assert np.allclose(np.abs(nrm[2:-2, 1]), 1.0)
    segs = np.array([[[0.0, 1.02], [2.0, 1.02]], [[1.0, 0.0], [1.0, 2.0]]])
    j = assign(pts, nrm, segs, 0.3, math.radians(30), 0.1)
    # Points near x = 1 are nearer the vertical wall but have the horizontal one's normal.
    assert (j[2:-2] == 0).all()
    assert (assign(pts + np.array([0.0, 1.0]), nrm, segs, 0.3, math.radians(30), 0.1)[2:-2] == -1).all()


def test_refine_match_replaces_a_rejected_correction() -> None:
    truth = Pose(0.2, 0.0, math.radians(1.0))
    pts = scan_of(ROOM, truth)
    empty = Correspondences(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, 2), np.int64), np.zeros(0))
    rejected = ICPResult(Pose.identity(), False, empty, math.inf, 0, 1, reason="too few")
    out = refine_match(rejected, pts, ROOM, np.diag([0.3**2, 0.3**2, 0.005]), None, PointMatchConfig(), 8.0)
    assert out.accepted and out.consistent and out.constrained == 3
    assert abs(out.correction.x - 0.2) < 0.01
    far = scan_of(CORRIDOR, Pose.identity())
    assert refine_match(rejected, far, ROOM, np.diag([0.01, 0.01, 1e-4]), None, PointMatchConfig(), 8.0) is rejected


def test_config_checks() -> None:
    with pytest.raises(ValueError):
        PointMatchConfig(kernel=0.0)
    with pytest.raises(ValueError):
        PointMatchConfig(min_inlier_fraction=1.5)
