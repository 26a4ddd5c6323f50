"""Fleet-level map algorithms (mapping/fleet.py): frontier closing across robots, map-to-map
alignment, the fold tree's shape; and the content digest of a wireframe."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.fleet import align_maps, close_frontiers, fold_split
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

N, F = Label.NOMINAL, Label.FRONTIER


def edge_set(wf: Wireframe, nd: int = 1) -> set[tuple[tuple[float, float], tuple[float, float]]]:
    s = wf.segments()
    return {(tuple(np.round(a, nd)), tuple(np.round(b, nd))) for a, b in s}


# ---------------------------------------------------------------------- close_frontiers
def test_frontier_closed_by_a_longer_wall_reattaches():
    # A: (0,0) -> (3,0) ending in a frontier; B: (2,0) -> (6,0) covers the frontier.
    wf = Wireframe.build([(0, 0), (3, 0), (2, 0), (6, 0)], [(0, 1), (2, 3)], [N, F, N, N])
    out = close_frontiers(wf, 0.2)
    assert edge_set(out) == {((0.0, 0.0), (2.0, 0.0)), ((2.0, 0.0), (6.0, 0.0))}
    assert not np.any(out.labels == F)


def test_frontier_edge_entirely_covered_is_dropped():
    wf = Wireframe.build([(2.5, 0), (3, 0), (0, 0), (6, 0)], [(0, 1), (2, 3)], [N, F, N, N], sources=[1, 2])
    out = close_frontiers(wf, 0.2)
    assert edge_set(out) == {((0.0, 0.0), (6.0, 0.0))}
    assert out.n_vertices == 2 and int(out.sources[0]) == 2


def test_frontier_meeting_a_wall_at_an_angle_becomes_a_corner():
    # a wall coming down to a frontier that sits on another robot's wall: a T junction
    wf = Wireframe.build([(3, 2), (3, 0.05), (0, 0), (6, 0)], [(0, 1), (2, 3)], [N, F, N, N])
    out = close_frontiers(wf, 0.2)
    assert out.n_edges == 2 and out.labels[1] == N


def test_frontier_not_closed_by_the_back_of_a_thin_wall_or_far_walls():
    back = Wireframe.build([(0, 0), (3, 0), (6, 0), (1, 0)], [(0, 1), (2, 3)], [N, F, N, N])
    assert close_frontiers(back, 0.2) is back  # opposite direction: the other side
    far = Wireframe.build([(0, 0), (3, 0), (2, 1), (6, 1)], [(0, 1), (2, 3)], [N, F, N, N])
    assert close_frontiers(far, 0.2) is far
    near_end = Wireframe.build([(0, 0), (3, 0), (3.1, 0), (6, 0)], [(0, 1), (2, 3)], [N, F, N, N])
    assert close_frontiers(near_end, 0.2) is near_end  # at an end, not the interior: merge's job


@given(st.floats(0.3, 2.7), st.floats(-0.15, 0.15), st.floats(0.05, 0.3))
@settings(max_examples=60, deadline=None)
def test_close_frontiers_never_loses_covered_length(fx, fy, thr):
    """Whatever it does, the union of walls still covers the truth [0, 6] on y = 0."""
    wf = Wireframe.build([(-1, 0), (fx, fy), (0, 0), (6, 0)], [(0, 1), (2, 3)], [N, F, N, N])
    out = close_frontiers(wf, thr)
    xs = np.linspace(-0.9, 5.9, 69)
    segs = out.segments()
    for x in xs:
        covered = any(min(a[0], b[0]) - 1e-9 <= x <= max(a[0], b[0]) + 1e-9 for a, b in segs)
        assert covered, (x, segs)
    assert out.n_edges <= wf.n_edges


# ---------------------------------------------------------------------- align_maps
def _room() -> Wireframe:
    """A 12 x 5 m room with a 2 x 1 m alcove: corners pin it in x, y and rotation."""
    pts = [(12, 5), (7, 5), (7, 6), (5, 6), (5, 5), (0, 5), (0, 0), (12, 0), (12, 5)]
    return Wireframe.build(pts, [(i, i + 1) for i in range(len(pts) - 1)], [N] * len(pts))


def test_align_maps_undoes_a_small_error_in_the_fleet_frame():
    room = _room()
    err = Pose(0.15, -0.1, math.radians(1.5))
    moved = room.transformed(err)
    corr = align_maps(moved, room, 0.6, math.radians(6.0))
    assert corr is not None
    back = moved.transformed(corr)
    assert float(np.max(np.hypot(*(back.points - room.points).T))) < 0.02


def test_align_maps_refuses_large_negligible_and_empty_cases():
    room = _room()
    far = room.transformed(Pose(0.5, 0.0, 0.0))
    assert align_maps(far, room, 0.2, math.radians(6.0)) is None  # beyond max_shift
    assert align_maps(room, room, 0.6, math.radians(6.0)) is None  # nothing to correct
    assert align_maps(Wireframe.empty(), room, 0.6, 0.1) is None
    assert align_maps(room, Wireframe.empty(), 0.6, 0.1) is None


# ---------------------------------------------------------------------- fold_split
def test_fold_split_is_the_left_fold_up_to_three_and_balanced_at_sixteen():
    assert fold_split(0, 2) == 1
    assert fold_split(0, 3) == 2  # ((r1, r2), r3)
    assert fold_split(0, 16) == 8
    assert fold_split(8, 16) == 12
    assert fold_split(4, 9) == 8  # after the largest power of two below 5
    with pytest.raises(ValueError):
        fold_split(3, 4)


@given(st.integers(0, 100), st.integers(2, 200))
def test_fold_split_cuts_a_power_of_two_off_the_left(lo, n):
    mid = fold_split(lo, lo + n)
    left = mid - lo
    assert lo < mid < lo + n
    assert left & (left - 1) == 0 and left < n <= 2 * left


# ---------------------------------------------------------------------- content digest
def test_content_digest_is_equal_for_equal_arrays_only():
    room = _room()
    again = Wireframe(room.points.copy(), room.labels, room.edges, room.likelihood, room.sources)
    assert room.content_digest() == again.content_digest()
    assert len(room.content_digest()) == 16
    changed = [
        room.replace(likelihood=np.full(room.n_edges, 0.5)),
        room.replace(sources=np.ones(room.n_edges, dtype=np.uint64)),
        room.transformed(Pose(1e-9, 0.0, 0.0)),
        Wireframe(room.points, room.labels, room.edges[::-1], room.likelihood, room.sources),
        room.subgraph_edges(np.arange(room.n_edges) > 0),
        Wireframe.empty(),
    ]
    assert len({w.content_digest() for w in [room, *changed]}) == len(changed) + 1
