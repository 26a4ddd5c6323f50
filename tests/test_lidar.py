"""Tests of the simulated lidar (agents.sim.lidar)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.sim.lidar import LidarConfig, raycast
from mapping.se2 import Pose
from mapping.wireframe import Wireframe

SQUARE = Wireframe.from_polylines([[(0.0, 0.0), (4.0, 0.0), (4.0, 4.0), (0.0, 4.0)]])


def _reference(segments: np.ndarray, pose: Pose, config: LidarConfig) -> np.ndarray:
    """Slow per-beam, per-wall ray casting, written independently of the implementation."""
    out = np.full(config.beams, np.inf)
    for b, ang in enumerate(config.angles()):
        th = pose.theta + ang
        d = np.array([math.cos(th), math.sin(th)])
        best = math.inf
        for (ax, ay), (bx, by) in segments:
            # Solve pose + s d = a + u (b - a) with Cramer's rule.
            m = np.array([[d[0], ax - bx], [d[1], ay - by]])
            det = np.linalg.det(m)
            if abs(det) < 1e-12:
                continue
            s, u = np.linalg.solve(m, np.array([ax - pose.x, ay - pose.y]))
            if s > 0 and -1e-9 <= u <= 1 + 1e-9:
                best = min(best, s)
        if best <= config.max_range:
            out[b] = best
    return out


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    "kwargs",
    [
        {"beams": 1},
        {"beams": 10.0},
        {"beams": True},
        {"fov": 0.0},
        {"fov": 7.0},
        {"fov": math.nan},
        {"max_range": 0.0},
        {"max_range": math.inf},
        {"sigma": -0.1},
        {"sigma": math.nan},
    ],
)
def test_config_rejects_bad_values(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        LidarConfig(**kwargs)  # type: ignore[arg-type]


def test_angles_half_turn_include_both_edges() -> None:
    a = LidarConfig().angles()
    assert a.shape == (361,)
    assert a[0] == pytest.approx(-math.pi / 2) and a[-1] == pytest.approx(math.pi / 2)
    assert np.allclose(np.diff(a), math.pi / 360)
    assert a[180] == pytest.approx(0.0, abs=1e-12)


def test_angles_full_turn_do_not_repeat_the_first_beam() -> None:
    cfg = LidarConfig(beams=360, fov=2 * math.pi)
    a = cfg.angles()
    assert cfg.full_circle
    assert a[0] == pytest.approx(-math.pi)
    assert np.allclose(np.diff(a), 2 * math.pi / 360)
    assert a[-1] < math.pi - 1e-6


# ---------------------------------------------------------------- geometry
def test_square_room_from_the_centre_known_ranges() -> None:
    cfg = LidarConfig(beams=361, fov=math.pi, sigma=0.0)
    r = raycast(SQUARE.segments(), Pose(2.0, 2.0, 0.0), cfg)
    a = cfg.angles()
    # Facing +x: straight ahead 2 m, the side walls 2 m, the corners 2 sqrt(2).
    assert r[180] == pytest.approx(2.0)
    assert r[0] == pytest.approx(2.0) and r[-1] == pytest.approx(2.0)
    assert r[90] == pytest.approx(2.0 * math.sqrt(2.0))
    expected = np.minimum(2.0 / np.abs(np.cos(a)).clip(1e-12), 2.0 / np.abs(np.sin(a)).clip(1e-12))
    assert np.allclose(r, expected)


def test_heading_rotates_the_beams() -> None:
    cfg = LidarConfig(sigma=0.0)
    # Off-centre robot: 1 m from the top wall, 3 m from the right one.
    up = raycast(SQUARE.segments(), Pose(1.0, 3.0, math.pi / 2), cfg)
    right = raycast(SQUARE.segments(), Pose(1.0, 3.0, 0.0), cfg)
    assert up[180] == pytest.approx(1.0)
    assert right[180] == pytest.approx(3.0)


def test_walls_are_opaque_from_both_sides() -> None:
    cfg = LidarConfig(sigma=0.0)
    segs = SQUARE.segments()
    pose = Pose(1.3, 2.2, 0.4)
    assert np.array_equal(raycast(segs, pose, cfg), raycast(segs[:, ::-1], pose, cfg))


def test_no_return_beyond_range_and_without_walls() -> None:
    cfg = LidarConfig(max_range=3.0, sigma=0.0)
    r = raycast(SQUARE.segments(), Pose(0.5, 2.0, 0.0), cfg)
    assert np.isinf(r[180])  # the far wall is 3.5 m away
    assert r[0] == pytest.approx(2.0)
    assert np.all(np.isinf(raycast(np.zeros((0, 2, 2)), Pose(), cfg)))


def test_rays_through_a_shared_corner_do_not_leak() -> None:
    cfg = LidarConfig(beams=8, fov=2 * math.pi, sigma=0.0)
    # Beams at multiples of 45 degrees from the centre pass exactly through the corners.
    r = raycast(SQUARE.segments(), Pose(2.0, 2.0, 0.0), cfg)
    assert np.all(np.isfinite(r))
    assert r[1] == pytest.approx(2.0 * math.sqrt(2.0))


def test_bad_segments_shape_raises() -> None:
    with pytest.raises(ValueError):
        raycast(np.zeros((3, 2)), Pose(), LidarConfig())
    with pytest.raises(ValueError):
        raycast(np.full((1, 2, 2), np.nan), Pose(), LidarConfig())


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    x=st.floats(-3, 3),
    y=st.floats(-3, 3),
    theta=st.floats(-math.pi, math.pi),
    full=st.booleans(),
)
def test_matches_a_slow_reference(seed: int, x: float, y: float, theta: float, full: bool) -> None:
    rng = np.random.default_rng(seed)
    a = rng.uniform(-6, 6, (25, 2))
    segs = np.stack([a, a + rng.uniform(-2, 2, (25, 2))], axis=1)
    cfg = LidarConfig(beams=37, fov=2 * math.pi if full else 2.0, max_range=5.0, sigma=0.0)
    pose = Pose(x, y, theta)
    got = raycast(segs, pose, cfg)
    want = _reference(segs, pose, cfg)
    assert np.array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    assert np.allclose(got[fin], want[fin], atol=1e-9)


# ---------------------------------------------------------------- noise
def test_noise_is_seeded_and_has_the_configured_spread() -> None:
    cfg = LidarConfig(beams=361, fov=2 * math.pi, sigma=0.01)
    segs, pose = SQUARE.segments(), Pose(2.0, 2.0, 0.0)
    exact = raycast(segs, pose, cfg, None)
    a = raycast(segs, pose, cfg, np.random.default_rng(7))
    b = raycast(segs, pose, cfg, np.random.default_rng(7))
    assert np.array_equal(a, b)
    errs = np.concatenate([raycast(segs, pose, cfg, np.random.default_rng(s)) - exact for s in range(20)])
    assert abs(errs.mean()) < 0.001
    assert errs.std() == pytest.approx(0.01, rel=0.05)


def test_zero_sigma_or_no_rng_is_exact() -> None:
    segs, pose = SQUARE.segments(), Pose(1.0, 1.0, 1.0)
    exact = raycast(segs, pose, LidarConfig(sigma=0.0), np.random.default_rng(1))
    assert np.array_equal(exact, raycast(segs, pose, LidarConfig(sigma=0.5), None))


def test_noisy_readings_never_negative_and_saturate_to_no_return() -> None:
    cfg = LidarConfig(max_range=2.05, sigma=0.2)
    r = raycast(SQUARE.segments(), Pose(2.0, 0.02, math.pi / 2), cfg, np.random.default_rng(3))
    fin = r[np.isfinite(r)]
    assert np.all(fin >= 0.0) and np.all(fin < cfg.max_range)
    assert np.isinf(r).any()  # the 2 m walls sometimes read beyond 2.05 m


# How fast a scan is cast (361 beams, 100 walls) is a benchmark figure, not a test:
# `wiremap bench speed --pieces` (raycast_ms).
