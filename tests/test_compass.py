"""The wall-direction heading measurement (mapping.compass) and its use in the filter."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.compass import CompassConfig, Directions, compass_heading, direction_clusters, wall_directions
from mapping.filter import FilterConfig, WireframeFilter
from mapping.loops import LoopConfig
from mapping.se2 import Pose
from mapping.visibility import visible_view
from mapping.wireframe import Wireframe
from tests.filter_util import set_state

D = math.radians


def _map_dirs() -> tuple[np.ndarray, np.ndarray]:
    """A rectilinear map: 60 m of walls along 0 degrees and 40 m along 90, a little spread."""
    return np.array([0.0, D(0.1), D(-0.1), D(90.0), D(90.05)]), np.array([30.0, 20.0, 10.0, 25.0, 15.0])


def test_offset_is_the_heading_error():
    md, ml = _map_dirs()
    # The heading estimate is 0.8 degrees too large: scan walls look turned by +0.8.
    sd = np.mod(np.array([0.0, D(90.0), D(180.0)]) + D(0.8), math.pi)
    h = compass_heading(sd, np.array([5.0, 6.0, 4.0]), md, ml, D(2.0))
    assert h is not None and h.walls == 3 and h.length == pytest.approx(15.0)
    assert math.degrees(h.offset) == pytest.approx(-0.8, abs=0.06)
    assert h.variance > D(0.15) ** 2  # the common (model) error does not average out


def test_no_measurement_without_support_or_outside_the_gate():
    md, ml = _map_dirs()
    sd, sl = np.array([D(1.0)]), np.array([5.0])
    assert compass_heading(sd, sl, md, ml, D(2.0)) is not None
    assert compass_heading(sd, sl, md, ml, D(2.0), min_support=100.0) is None
    # A wall 10 degrees off every map direction is a new direction at a 1-degree uncertainty.
    assert compass_heading(np.array([D(10.0)]), sl, md, ml, D(1.0)) is None
    # ... and stays one even at a large uncertainty: the gate is capped (max_gate).
    assert compass_heading(np.array([D(10.0)]), sl, md, ml, D(20.0)) is None
    assert compass_heading(np.zeros(0), np.zeros(0), md, ml, D(1.0)) is None
    assert compass_heading(sd, sl, np.zeros(0), np.zeros(0), D(1.0)) is None


def test_a_wall_off_the_others_is_dropped():
    md, ml = _map_dirs()
    sd = np.mod(np.array([D(0.5), D(90.5), D(0.5), D(4.5)]), math.pi)
    h = compass_heading(sd, np.array([6.0, 6.0, 6.0, 6.0]), md, ml, D(3.0))
    assert h is not None and h.walls == 3
    assert math.degrees(h.offset) == pytest.approx(-0.5, abs=0.05)


@settings(max_examples=60, deadline=None)
@given(err=st.floats(-3.0, 3.0), turn=st.floats(0.0, 180.0))
def test_offset_property(err, turn):
    """Whatever the walls' own directions and a heading error inside the gate, the measured
    offset undoes the error (to the directions' spread in the map)."""
    base = D(turn)
    md = np.mod(np.array([base, base + D(0.05), base + D(90.0)]), math.pi)
    ml = np.array([20.0, 20.0, 20.0])
    sd = np.mod(np.array([base, base + D(90.0)]) + D(err), math.pi)
    h = compass_heading(sd, np.array([4.0, 4.0]), md, ml, D(2.0))
    assert h is not None
    assert math.degrees(h.offset) == pytest.approx(-err, abs=0.06)


def test_wall_directions_filters_and_folds():
    wf = Wireframe.build([(0, 0), (5, 0), (5, -3), (5, -4)], [(1, 0), (1, 2), (2, 3)],
                         likelihood=[0.9, 0.2, 0.9])
    d, ln = wall_directions(wf, 2.0)
    assert np.allclose(d, [0.0, math.pi / 2]) and np.allclose(ln, [5.0, 3.0])
    d, ln = wall_directions(wf, 2.0, min_likelihood=0.5)
    assert np.allclose(d, [0.0]) and np.allclose(ln, [5.0])


def _world_map() -> Wireframe:
    """Established walls far from the robot (out of its 8 m range): 0 and 90 degrees."""
    pts = [(-60, 40), (60, 40), (60, -40), (-60, -40)]
    return Wireframe.build(pts, [(0, 1), (1, 2), (2, 3), (3, 0)], likelihood=[0.99] * 4)


@pytest.mark.parametrize("err_deg", [1.5, -2.0])
def test_filter_fixes_the_heading_from_new_walls(err_deg):
    """After a turn in open space the heading is 1.5-2 degrees off (its standard deviation is
    2.5 degrees) and the robot sees walls the map does not hold yet. With the compass the
    heading comes back to within 0.2 degrees and the new walls enter the map parallel to the
    old ones; without it they enter turned by the error."""
    truth = Wireframe.build([(-4, 5), (6, 5), (6, -3)], [(1, 0), (2, 1)])
    true_pose = Pose(1.0, 0.5, 0.3)
    scan = visible_view(truth, true_pose, 8.0, 2 * math.pi).scan
    est = Pose(1.0, 0.5, 0.3 + D(err_deg))
    out = {}
    for on in (True, False):
        cfg = FilterConfig(particles=1, mutate=False, compass=CompassConfig(enabled=on),
                           loops=LoopConfig(enabled=False))
        f = WireframeFilter(cfg, np.random.default_rng(0), initial_pose=est)
        set_state(f, [_world_map()], np.diag([0.05**2, 0.05**2, D(2.5) ** 2]))
        info = f.step(Pose.identity(), scan)
        dth = math.degrees(f.pose.theta - true_pose.theta)
        new = f.best.subgraph_edges(f.best.edge_lengths() < 20.0)
        d, _ = wall_directions(new, 2.0)
        worst = max(math.degrees(abs((a + math.pi / 4) % (math.pi / 2) - math.pi / 4)) for a in d)
        out[on] = (dth, worst, info.compass, math.degrees(math.sqrt(f.pose_covariance[2, 2])))
    dth, worst, h, sig = out[True]
    assert h is not None and h.walls == 2
    assert abs(dth) < 0.2 and worst < 0.3 and sig < 0.5
    dth_off, worst_off, h_off, sig_off = out[False]
    assert sig_off > 2.0
    assert h_off is None and abs(dth_off - err_deg) < 0.05 and worst_off > abs(err_deg) - 0.3


def test_filter_covariance_shrinks_with_the_measurement():
    truth = Wireframe.build([(-4, 5), (6, 5), (6, -3)], [(1, 0), (2, 1)])
    scan = visible_view(truth, Pose.identity(), 8.0, 2 * math.pi).scan
    cfg = FilterConfig(particles=1, mutate=False, loops=LoopConfig(enabled=False))
    f = WireframeFilter(cfg, np.random.default_rng(0), initial_pose=Pose(0, 0, D(1.0)))
    set_state(f, [_world_map()], np.diag([0.05**2, 0.05**2, D(2.5) ** 2]))
    f.step(Pose.identity(), scan)
    assert math.degrees(math.sqrt(f.pose_covariance[2, 2])) < 0.5
    # Below compass.min_sigma the match is the better reference: the compass does not run at
    # full weight. The map here has no birth stamps (as young as can be), so only the slow
    # young-map pull runs (compass_young_weight), moving the heading by at most that fraction
    # of the measured offset; with the weight 0 nothing runs.
    poses, infos = {}, {}
    for w in (0.0, 0.05):
        f2 = WireframeFilter(dataclasses.replace(cfg, compass=CompassConfig(young_weight=w)),
                             np.random.default_rng(0),
                             initial_pose=Pose(0, 0, D(0.3)))  # within the gate of a 0.1-degree sigma
        set_state(f2, [_world_map()], np.diag([0.05**2, 0.05**2, D(0.1) ** 2]))
        infos[w] = f2.step(Pose.identity(), scan)
        poses[w] = f2.pose
    assert infos[0.0].compass is None
    h = infos[0.05].compass
    assert h is not None and h.walls >= 1
    moved = poses[0.05].theta - poses[0.0].theta
    assert abs(moved) <= 0.05 * abs(h.offset) + 1e-12
    assert moved == 0.0 or np.sign(moved) == np.sign(h.offset)
    # The pull is only for young walls: a map holding the walls in view too (the scan is
    # matched against them), stamped at the start, the robot having driven 20 m (young) or
    # 30 m (older than compass_young_travel, 25 m) since.
    w = _world_map()
    seen = Wireframe.build([(-4, 5), (6, 5), (6, -3)], [(1, 0), (2, 1)], likelihood=[0.99] * 2)
    both = Wireframe.build(np.vstack([w.points, seen.points]),
                           np.vstack([w.edges, seen.edges + w.n_vertices]), likelihood=[0.99] * 6)
    for driven, runs in ((20.0, True), (30.0, False)):
        f3 = WireframeFilter(cfg, np.random.default_rng(0), initial_pose=Pose(0, 0, D(0.3)))
        set_state(f3, [both], np.diag([0.05**2, 0.05**2, D(0.1) ** 2]))
        f3.loops.stamp(f3.particles)
        f3.loops.distance = driven
        assert (f3.step(Pose.identity(), scan).compass is not None) == runs, driven


@pytest.mark.parametrize(
    "bad",
    [
        {"max_gate": 0.0},
        {"min_support": -1.0},
        {"anchor": -1.0},
        {"right_angle": -D(1.0)},
        {"right_angle": D(50.0)},
        {"young_weight": 1.5},
        {"young_weight": -0.1},
        {"young_travel": -1.0},
    ],
)
def test_config_rejects_bad_compass_values(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        CompassConfig(**bad)
    assert CompassConfig(young_weight=0.0).young_weight == 0.0
    assert CompassConfig(anchor=None).anchor is None


def test_direction_clusters_wrap_around_the_half_circle():
    d = np.radians([0.1, 179.9, 90.0, 90.2, 45.0])
    dirs, sup = direction_clusters(d, np.array([1.0, 1.0, 2.0, 2.0, 1.0]), D(1.0))
    assert np.allclose(sup, [4.0, 2.0, 1.0])
    assert np.allclose(np.degrees(dirs), [90.1, 0.0, 45.0], atol=1e-9)
    # one chain all around: one cluster
    ring = np.radians(np.arange(0.0, 180.0, 0.5))
    assert len(direction_clusters(ring, np.ones(len(ring)), D(1.0))[0]) == 1
    assert len(direction_clusters(np.zeros(0), np.zeros(0), D(1.0))[0]) == 0


def test_directions_freeze_after_the_anchor():
    """The reference is the map's clusters while anchoring, then frozen: a map turned later by
    half a degree does not turn it; a new direction joins once it has the support."""
    ref = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0))
    ref.update(np.radians([0.0, 90.0]), np.array([12.0, 11.0]), 5.0)
    assert np.allclose(np.degrees(ref.reference()[0]), [0.0, 90.0]) and not ref.settled
    ref.update(np.radians([0.0, 90.0]), np.array([12.0, 11.0]), 10.0)  # anchor reached: frozen
    assert ref.settled and len(ref.frozen) == 2
    ref.update(np.radians([0.5, 90.5, 30.0]), np.array([40.0, 40.0, 5.0]), 50.0)
    assert np.allclose(np.degrees(ref.reference()[0]), [0.0, 90.0])
    ref.update(np.radians([0.5, 90.5, 30.0, 30.2]), np.array([40.0, 40.0, 5.0, 6.0]), 60.0)
    dirs, sup = ref.reference()
    assert np.allclose(np.degrees(dirs), [0.0, 90.0, 30.0 + 0.2 * 6 / 11]) and sup[2] == pytest.approx(11.0)
    # before any direction is frozen, too short clusters give no measurement
    young = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0))
    young.update(np.radians([0.0]), np.array([3.0]), 1.0)
    d, s = young.reference()
    assert compass_heading(np.radians([1.0]), np.array([3.0]), d, s, D(2.0)) is None


@pytest.mark.parametrize("first", [0.0, 179.7, 45.0])
def test_right_angle_prior_squares_a_late_direction(first):
    """A corridor's first 10 m show one direction; the perpendicular one, met after the first
    corner, comes with that turn's heading error (0.6 degrees here). Within ``right_angle`` of
    perpendicular it is frozen at exactly perpendicular (across the 0/180 wrap too); a direction
    further off, or with the prior off, is frozen as the map has it."""
    def grown(right_angle: float, later: float) -> np.ndarray:
        ref = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0), right_angle=right_angle)
        ref.update(np.radians([first]), np.array([12.0]), 10.0)
        ref.update(np.radians([first, first + later]), np.array([30.0, 12.0]), 40.0)
        return np.degrees(ref.reference()[0])

    def off(a: float, b: float) -> float:  # difference of two directions (degrees, mod 180)
        return abs((a - b + 90.0) % 180.0 - 90.0)

    on = grown(D(1.0), 90.6)
    assert len(on) == 2 and off(on[0], first) < 1e-9 and off(on[1], first + 90.0) < 1e-9
    assert 0.0 <= on[1] < 180.0
    assert off(grown(0.0, 90.6)[1], first + 90.6) < 1e-9  # prior off: as mapped
    assert off(grown(D(1.0), 91.5)[1], first + 91.5) < 1e-9  # 1.5 degrees off: not squared
    assert off(grown(D(1.0), 89.2)[1], first + 90.0) < 1e-9  # the other side of 90


def test_right_angle_prior_changes_what_the_compass_reads():
    """Without the prior the reference holds the 90-degree wing at the turn's error, so a scan
    of the (truly square) wing taken at the true heading reads as a 0.5-degree heading error;
    with the prior it reads as none."""
    out = {}
    for ra in (D(1.0), 0.0):
        ref = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0), right_angle=ra)
        ref.update(np.radians([0.0]), np.array([20.0]), 10.0)
        ref.update(np.radians([0.0, 90.5]), np.array([20.0, 15.0]), 30.0)
        d, s = ref.reference()
        h = compass_heading(np.radians([90.0, 90.0]), np.array([6.0, 6.0]), d, s, D(1.0))
        out[ra] = math.degrees(h.offset)
    assert abs(out[D(1.0)]) < 1e-9 and out[0.0] == pytest.approx(0.5, abs=1e-9)


def test_right_angle_prior_squares_to_the_first_direction_seen():
    """A robot starting next to a corner: the corridor it starts in (90 degrees, exact) is
    established first; after the turn, within the first 10 m, the next corridor's walls
    (mapped with the turn's 0.4-degree error) become the longer cluster. The reference squares
    the later one to the first, not the other way round."""
    ref = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0), right_angle=D(1.0))
    ref.update(np.radians([90.0]), np.array([12.0]), 3.0)
    ref.update(np.radians([90.0, 0.4]), np.array([12.0, 30.0]), 10.0)
    dirs = np.degrees(ref.reference()[0])
    assert np.allclose(dirs, [90.0, 0.0])
    # Without the order (both established at once) the longest cluster comes first.
    both = Directions(anchor=10.0, min_support=10.0, max_gate=D(6.0), right_angle=D(1.0))
    both.update(np.radians([90.0, 0.4]), np.array([12.0, 30.0]), 10.0)
    assert np.allclose(np.degrees(both.reference()[0]), [0.4, 90.4])
