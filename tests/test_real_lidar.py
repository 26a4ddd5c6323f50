"""Tests of the realistic simulated lidar (agents.sim.real_lidar) and of turned worlds (NAME@DEG).

Each effect on its own, seeded: range noise growing with range, dropouts, max-range bursts,
glass, clutter, people; the same seeds give the same scans; the clean lidar is unchanged; and a
short run of the filter on a small world with the realistic sensor keeps a quality floor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from agents import mapping_run as mr
from agents.sim.lidar import LidarConfig, cast_ranges, raycast
from agents.sim.real_lidar import (
    RangeNoise,
    RealLidarConfig,
    SceneConfig,
    apply_noise,
    build_scene,
    realistic_scan,
)
from agents.sim.world import WorldError, load_world
from mapping.metrics import evaluate
from mapping.se2 import Pose

WORLDS = "tests/worlds"
QUIET = RangeNoise(sigma0=0.0, sigma_per_m=0.0, resolution=0.0, p_dropout=0.0, p_burst=0.0)
EMPTY = SceneConfig(glass_share=0.0, clutter_per_100m2=0.0, people_per_100m2=0.0)
FULL_TURN = LidarConfig(beams=720, fov=2 * math.pi, max_range=8.0)


def _wall(y: float = 3.0) -> np.ndarray:
    return np.array([[[-20.0, y], [20.0, y]]])


# ---------------------------------------------------------------- per-beam noise
def test_range_noise_grows_with_range_by_the_expected_ratio() -> None:
    noise = RangeNoise(sigma0=0.005, sigma_per_m=0.002, resolution=0.0, p_dropout=0.0, p_burst=0.0)
    rng = np.random.default_rng(11)
    near = apply_noise(np.full(20000, 1.0), noise, 10.0, rng) - 1.0
    far = apply_noise(np.full(20000, 8.0), noise, 10.0, rng) - 8.0
    assert abs(near.mean()) < 2e-4 and abs(far.mean()) < 5e-4
    assert near.std() == pytest.approx(0.007, rel=0.03)
    assert far.std() / near.std() == pytest.approx((0.005 + 8 * 0.002) / (0.005 + 0.002), rel=0.05)


def test_readings_are_rounded_to_the_resolution_and_never_negative() -> None:
    noise = RangeNoise(sigma0=0.2, sigma_per_m=0.0, resolution=0.01, p_dropout=0.0, p_burst=0.0)
    out = apply_noise(np.full(5000, 0.1), noise, 10.0, np.random.default_rng(2))
    assert np.all(out >= 0.0)
    assert np.allclose(out * 100, np.round(out * 100), atol=1e-9)


def test_dropouts_share_is_p() -> None:
    noise = RangeNoise(sigma0=0.0, sigma_per_m=0.0, resolution=0.0, p_dropout=0.05, p_burst=0.0)
    out = apply_noise(np.full(100_000, 3.0), noise, 10.0, np.random.default_rng(3))
    assert np.isinf(out).mean() == pytest.approx(0.05, abs=0.003)
    assert np.all(out[np.isfinite(out)] == 3.0)


def test_max_range_bursts_come_in_runs_of_the_mean_length() -> None:
    noise = RangeNoise(sigma0=0.0, sigma_per_m=0.0, resolution=0.0, p_dropout=0.0, p_burst=0.002,
                       burst_beams=4.0)
    out = apply_noise(np.full(200_000, 3.0), noise, 10.0, np.random.default_rng(4))
    lost = np.isinf(out).astype(np.int8)
    starts = np.flatnonzero(np.diff(np.concatenate([[0], lost])) == 1)
    ends = np.flatnonzero(np.diff(np.concatenate([lost, [0]])) == -1)
    runs = ends - starts + 1
    assert len(runs) == pytest.approx(400, rel=0.15)
    assert runs.mean() == pytest.approx(4.0, rel=0.15)  # a few bursts overlap


def test_readings_beyond_the_range_are_no_return() -> None:
    out = apply_noise(np.array([9.99, 10.0, 12.0, np.inf]), QUIET, 10.0, np.random.default_rng(0))
    assert out[0] == 9.99 and np.all(np.isinf(out[1:]))


# ---------------------------------------------------------------- glass
def test_glass_returns_only_near_normal_incidence_and_shows_what_is_behind() -> None:
    pane = np.array([[[-20.0, 2.0], [20.0, 2.0]]])
    segs = np.concatenate([pane, _wall(5.0)])
    glass = np.array([True, False])
    cfg = LidarConfig(beams=181, fov=math.pi, max_range=20.0)  # beam k at bearing (k - 90) degrees
    r = cast_ranges(segs, Pose(0.0, 0.0, math.pi / 2), cfg, glass=glass,
                    glass_min_sin=math.cos(math.radians(10.0)))
    bearing = np.radians(np.arange(181) - 90.0)  # from the heading (the pane's normal)
    near_normal = np.abs(bearing) < math.radians(9.5)
    oblique = (np.abs(bearing) > math.radians(10.5)) & (np.abs(bearing) < math.radians(60))
    assert np.allclose(r[near_normal], 2.0 / np.cos(bearing[near_normal]))
    assert np.allclose(r[oblique], 5.0 / np.cos(bearing[oblique]))  # through the pane to the wall
    alone = cast_ranges(pane, Pose(0.0, 0.0, math.pi / 2), cfg, glass=np.array([True]),
                        glass_min_sin=math.cos(math.radians(10.0)))
    assert np.all(np.isinf(alone[oblique])) and np.all(np.isfinite(alone[near_normal]))


def test_scene_panes_are_cut_out_of_walls_with_nothing_solid_behind() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(glass_share=1.0), 0)
    panes = scene.walls[scene.glass]
    assert len(panes)
    lengths = np.hypot(*(panes[:, 1] - panes[:, 0]).T)
    assert np.all((lengths >= 1.0 - 1e-9) & (lengths <= 4.0 + 1e-9))
    # the walls and panes together are the truth's walls: same total length
    total = np.hypot(*(scene.walls[:, 1] - scene.walls[:, 0]).T).sum()
    truth = world.truth.segments()
    assert total == pytest.approx(np.hypot(*(truth[:, 1] - truth[:, 0]).T).sum())
    # paper-small's solid walls are 0.4 m thick: only the outer walls may hold windows
    xy = panes.reshape(-1, 2)
    assert np.all((np.isclose(xy, 0.0) | np.isclose(xy, 15.0)).any(axis=1))


def test_a_glass_window_returns_nothing_where_a_clean_lidar_sees_a_wall() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(glass_share=1.0, clutter_per_100m2=0.0, people_per_100m2=0.0), 0)
    (a, b), *_ = scene.walls[scene.glass]
    mid = 0.5 * (a + b)
    along = (b - a) / np.hypot(*(b - a))
    inward = np.array([-along[1], along[0]])  # walls have free space on their left
    eye = mid + 1.0 * inward + math.tan(math.radians(30)) * along  # the pane's middle, 30 deg off normal
    pose = Pose(float(eye[0]), float(eye[1]), math.atan2(*(mid - eye)[::-1]))
    cfg = LidarConfig(beams=3, fov=math.radians(2.0), max_range=20.0)  # beams 29-31 degrees off normal
    clean = raycast(world.truth.segments(), pose, cfg)
    real = realistic_scan(scene, pose, 0.0, cfg, QUIET, np.random.default_rng(0))
    assert np.all(np.isfinite(clean)) and np.all(clean < 2.0)
    assert np.all(np.isinf(real))  # outside the building: nothing


# ---------------------------------------------------------------- clutter and people
def test_clutter_is_seen_by_the_lidar_but_is_not_in_the_truth() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(clutter_per_100m2=5.0, people_per_100m2=0.0, glass_share=0.0), 1)
    assert len(scene.objects) >= 5 and set(scene.kinds) <= {"chair", "table", "box", "round"}
    truth = world.truth.segments()
    assert world.truth.n_edges == 42  # the truth stays the walls
    hit = 0
    for (x, y, radius), kind in zip(scene.objects, scene.kinds):
        if kind not in ("box", "round"):
            continue  # legs can fall between beams
        # look at the object from 1.5 m away, from the side with free space
        for ang in np.linspace(0, 2 * math.pi, 8, endpoint=False):
            eye = np.array([x, y]) + (radius + 1.5) * np.array([math.cos(ang), math.sin(ang)])
            if world.is_free(eye):
                break
        pose = Pose(float(eye[0]), float(eye[1]), math.atan2(y - eye[1], x - eye[0]))
        cfg = LidarConfig(beams=3, fov=math.radians(1.0), max_range=8.0)
        real = realistic_scan(scene, pose, 0.0, cfg, QUIET, np.random.default_rng(0))
        clean = raycast(truth, pose, cfg)
        # the beam at the object's centre meets its outline (within its enclosing disc), in
        # front of the walls the clean lidar sees there
        assert 1.5 - 1e-6 <= real[1] <= 1.5 + radius and real[1] < clean[1]
        hit += 1
    assert hit >= 1
    # no truth wall near any object: clutter is not structure
    from shapely.geometry import MultiLineString, Point

    walls = MultiLineString([tuple(map(tuple, s)) for s in truth])
    assert all(walls.distance(Point(x, y)) > r for x, y, r in scene.objects)


def test_clutter_on_the_route_is_left_out() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(clutter_per_100m2=8.0), 2)
    x, y, r = scene.objects[0]
    route = np.array([[x - 3.0, y], [x + 3.0, y]])
    kept = scene.clear_of(route, 0.35)
    assert len(kept.objects) < len(scene.objects)
    assert not np.any(np.all(np.isclose(kept.objects, [x, y, r]), axis=1))
    still = np.array([np.any(np.all(kept.objects == o, axis=1)) for o in scene.objects])
    assert len(kept.clutter) == int(still[scene.clutter_object].sum())
    assert np.array_equal(np.unique(kept.clutter_object), np.arange(len(kept.objects)))


def test_a_person_blocks_a_beam_at_one_time_and_not_at_another() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(people_per_100m2=1.0, clutter_per_100m2=0.0, glass_share=0.0), 3)
    assert len(scene.paths)
    (a, b), speed = scene.paths[0], float(scene.speed[0])
    length = float(np.hypot(*(b - a)))
    # the time the first person is at the middle of its path, then half a round later (an end)
    t_mid = ((0.5 * length - scene.phase[0]) % (2 * length)) / speed
    t_end = t_mid + 0.5 * length / speed
    centre = scene.people_at(t_mid)[0]
    assert np.allclose(centre, 0.5 * (a + b))
    normal = np.array([a[1] - b[1], b[0] - a[0]]) / length
    for side in (1.0, -1.0):
        eye = centre + side * 1.0 * normal
        if world.is_free(eye) and world.is_free(centre + side * 0.5 * normal):
            break
    pose = Pose(float(eye[0]), float(eye[1]), math.atan2(centre[1] - eye[1], centre[0] - eye[0]))
    cfg = LidarConfig(beams=3, fov=math.radians(1.0), max_range=20.0)
    at_mid = realistic_scan(scene, pose, t_mid, cfg, QUIET, np.random.default_rng(0))
    at_end = realistic_scan(scene, pose, t_end, cfg, QUIET, np.random.default_rng(0))
    assert at_mid[1] == pytest.approx(1.0 - scene.person_radius, abs=0.02)
    assert at_end[1] > 1.5


def test_a_person_next_to_the_robot_steps_aside() -> None:
    world = load_world("paper-small")
    scene = build_scene(world, SceneConfig(people_per_100m2=1.0), 3)
    c = scene.people_at(7.0)[0]
    assert len(scene.people_segments(7.0, Pose(float(c[0]) + 0.2, float(c[1]), 0.0), 8.0)) == 0
    assert len(scene.people_segments(7.0, Pose(float(c[0]) + 2.0, float(c[1]), 0.0), 8.0)) == 12


# ---------------------------------------------------------------- seeds and the clean lidar
def test_same_seeds_same_scans_other_scene_seed_other_scene() -> None:
    world = load_world("tests/worlds/lshape.geojson")

    def scans(seed: int, scene_seed: int | None) -> list[np.ndarray]:
        opts = mr.SimOptions(sensor="lidar-real", steps=6, scene_seed=scene_seed)
        return [np.vstack([s.scan.points, s.points]) for s in mr.simulate(world, opts, seed)]

    one, two = scans(4, None), scans(4, None)
    assert all(np.array_equal(x, y) for x, y in zip(one, two))
    a, b = build_scene(world, SceneConfig(), 5), build_scene(world, SceneConfig(), 5)
    assert np.array_equal(a.clutter, b.clutter) and np.array_equal(a.paths, b.paths)
    assert np.array_equal(a.walls, b.walls) and np.array_equal(a.glass, b.glass)
    c = build_scene(world, SceneConfig(), 6)
    assert not np.array_equal(a.objects, c.objects)
    assert not all(np.array_equal(x, y) for x, y in zip(one, scans(4, 99)))


def test_clean_lidar_defaults_and_output_are_unchanged() -> None:
    """The clean sensor is what it was: the same defaults, ranges = exact cast + N(0, sigma)
    drawn in beam order from the rng, and the simulator's clean lidar has no points."""
    assert LidarConfig() == LidarConfig(beams=361, fov=math.pi, max_range=10.0, sigma=0.01)
    opts = mr.SimOptions()
    assert (opts.sensor, opts.lidar_beams, opts.lidar_sigma, opts.max_range) == ("corners", 720, 0.01, 8.0)
    segs = load_world("paper-small").truth.segments()
    pose = Pose(3.0, 4.0, 0.3)
    exact = cast_ranges(segs, pose, FULL_TURN)
    got = raycast(segs, pose, FULL_TURN, np.random.default_rng(9))
    seen = np.isfinite(exact)
    want = exact.copy()
    want[seen] = np.maximum(exact[seen] + np.random.default_rng(9).normal(0.0, 0.01, int(seen.sum())), 0.0)
    want[want >= FULL_TURN.max_range] = np.inf
    assert np.array_equal(got, want)
    inp = next(mr.simulate(load_world("tests/worlds/tiny.geojson"), mr.SimOptions(sensor="lidar"), 0))
    assert inp.points is None


@pytest.mark.parametrize(
    "kwargs",
    [{"sigma0": -0.1}, {"p_dropout": 1.5}, {"burst_beams": 0.5}, {"resolution": math.nan}],
)
def test_noise_rejects_bad_values(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        RangeNoise(**kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [{"glass_share": 2.0}, {"glass_return_deg": 95.0}, {"person_radius": 0.0},
     {"person_speed": (1.0, 0.5)}, {"glass_length": (0.0, 1.0)}, {"clutter_per_100m2": -1.0}],
)
def test_scene_rejects_bad_values(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        SceneConfig(**kwargs)  # type: ignore[arg-type]


# ---------------------------------------------------------------- walls at odd angles
def test_a_turned_world_has_the_same_walls_at_odd_angles() -> None:
    base = load_world("paper-small")
    turned = load_world("paper-small@23")
    assert turned.name == "paper-small@23"
    assert turned.truth.n_edges == base.truth.n_edges and turned.truth.n_vertices == base.truth.n_vertices
    xmin, ymin, _, _ = turned.bounds()
    assert xmin == pytest.approx(0.0) and ymin == pytest.approx(0.0)
    seg = turned.truth.segments()
    ang = np.degrees(np.arctan2(*(seg[:, 1] - seg[:, 0]).T[::-1])) % 90.0
    assert np.all(np.isclose(ang, 23.0, atol=1e-6) | np.isclose(ang, 67.0, atol=1e-6))
    lengths = np.sort(np.hypot(*(seg[:, 1] - seg[:, 0]).T))
    base_seg = base.truth.segments()
    assert np.allclose(lengths, np.sort(np.hypot(*(base_seg[:, 1] - base_seg[:, 0]).T)))
    assert float(turned.free_space.area) == pytest.approx(float(base.free_space.area))


@pytest.mark.parametrize("spec", ["paper-small@x", "paper-small@nan", "no-such-world@10"])
def test_a_bad_turned_world_is_a_world_error(spec: str) -> None:
    with pytest.raises(WorldError):
        load_world(spec)


# ---------------------------------------------------------------- the filter on realistic scans
def test_filter_maps_a_small_world_from_realistic_scans() -> None:
    """The L-shaped floor plan with the realistic lidar as it ships (panes, clutter, a person,
    noise, dropouts, bursts): the map still holds the walls within 0.2 m (the floor plans'
    95 % target)."""
    from mapping.filter import WireframeFilter

    world = load_world(f"{WORLDS}/lshape.geojson")
    scene = build_scene(world, RealLidarConfig().scene, 0)
    assert scene.glass.any() and len(scene.objects) and len(scene.paths)  # every effect is there
    inputs = list(mr.simulate(world, mr.SimOptions(sensor="lidar-real"), 0))
    assert all(s.points is not None and len(s.points) for s in inputs)
    cfg = mr.filter_config_for(10, 0.2, 8.0)
    filt = WireframeFilter(cfg, mr.seeds_for(0)["filter"], initial_pose=inputs[0].true_pose)
    for _ in mr.run_filter(inputs, filt):
        pass
    m = evaluate(world.truth, filt.best, 0.2, 0.2)
    assert m["wall_precision"] >= 0.95 and m["wall_recall"] >= 0.95, m
    assert m["mean_dist_m"] <= 0.03, m


# ---------------------------------------------------------------- scans that take time
def _turning_scans(time_increment: float) -> list:
    """Three scans of a 360-degree lidar at 10 Hz on a robot turning on the spot at 1 rad/s."""
    from agents.files.carmen import LaserScan
    from mapping.se2 import Pose

    n = 100
    angles = -math.pi + 2 * math.pi * np.arange(n) / n
    return [LaserScan(0.1 * k, np.full(n, 2.0), angles, 10.0, Pose(0.0, 0.0, 0.1 * k),
                      time_increment=time_increment) for k in range(3)]


def test_deskewed_turns_a_scans_beams_back_at_the_wheels_velocity() -> None:
    from mapping.lidar_frontend import FrontendConfig

    scans = _turning_scans(0.1 / 100)
    out = mr.deskewed(scans, FrontendConfig())
    mid = out[1]  # 1 rad/s from the scan before to the one after
    assert mid.angles[10] - scans[1].angles[10] == pytest.approx(1.0 * 10 * 0.001)
    assert len(mid.angles) < 100 and mid.angles[-1] - mid.angles[0] < 2 * math.pi
    assert mr.wheel_velocity(scans[0], scans[1], scans[2]) == pytest.approx((0.0, 0.0, 1.0))
    assert mr.wheel_velocity(scans[1], scans[1], scans[1]) == (0.0, 0.0, 0.0)
    off = mr.deskewed(scans, FrontendConfig(deskew=False))
    assert all(np.array_equal(a.angles, b.angles) for a, b in zip(off, scans, strict=True))
    still = _turning_scans(0.0)  # simultaneous beams: as they are
    kept = mr.deskewed(still, FrontendConfig())
    assert all(np.array_equal(a.angles, b.angles) for a, b in zip(kept, still, strict=True))


def test_deskewed_takes_the_motion_after_the_scans_time() -> None:
    """A scan's time is its first beam's: its sweep is the motion to the next scan. A robot that
    stands, then turns: the scan it turns during is de-skewed by the whole turn (a velocity
    centred on the scan's time would give half), the one before by none."""
    from dataclasses import replace

    from mapping.lidar_frontend import FrontendConfig
    from mapping.se2 import Pose

    scans = _turning_scans(0.1 / 100)
    scans = [replace(s, odom=Pose(0.0, 0.0, turn)) for s, turn in zip(scans, (0.0, 0.0, 0.1), strict=True)]
    stood, turned, last = mr.deskewed(scans, FrontendConfig())
    assert np.array_equal(stood.angles, scans[0].angles)
    assert turned.angles[10] - scans[1].angles[10] == pytest.approx(1.0 * 10 * 0.001)
    assert last.angles[10] - scans[2].angles[10] == pytest.approx(1.0 * 10 * 0.001)  # from the one before

    # the odometry over its own sweep, when the reader had it, before its neighbours'
    swept = replace(scans[0], odom_end=Pose(0.0, 0.0, 0.5 * 0.099))
    assert mr.sweep_velocity(swept) == pytest.approx((0.0, 0.0, 0.5))
    first = mr.deskewed([swept, *scans[1:]], FrontendConfig())[0]
    assert first.angles[10] - scans[0].angles[10] == pytest.approx(0.5 * 10 * 0.001)
    # beams that came the other way round (the LDS-01 driver's default order): turned back the other way
    against = mr.deskewed(scans, FrontendConfig(sweep_reversed=True))[1]
    assert against.angles[10] - scans[1].angles[10] == pytest.approx(1.0 * (99 - 10) * 0.001)


# ---------------------------------------------------------------- the scanner's range
def test_a_short_range_scanner_turns_the_slams_facing_check_on() -> None:
    """The front end gives the SLAM the scanner's own range (the scans' median ``max_range``):
    under ``slam.facing_range`` (8 m) the match checks the side of a wall a point was seen from;
    a long-range scanner's SLAM is the profile's, unchanged; the report says the range."""
    from dataclasses import replace

    from mapping.lidar_frontend import FrontendConfig

    fc = FrontendConfig()
    short = [replace(s, max_range=3.5) for s in _turning_scans(0.0)]
    got = mr.for_scanner(fc, short)
    assert got.slam.scanner_range == 3.5 and got.slam.scanner_range < got.slam.facing_range
    assert mr.for_scanner(got, short) is got  # the same scans: the same front end
    far = mr.for_scanner(fc, _turning_scans(0.0))
    assert far.slam.scanner_range == 10.0 and far.slam.scanner_range >= far.slam.facing_range
    assert mr.for_scanner(fc, []) is fc
    given = replace(fc, slam=replace(fc.slam, scanner_range=30.0))  # the settings' own range stays
    assert mr.for_scanner(given, short) is given
    cal = mr.calibrate_log(short, fc)
    assert cal.scanner_range == 3.5 and mr.yaw_report(cal)["scanner_range_m"] == 3.5
