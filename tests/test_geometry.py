import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.geometry import (
    cross2,
    dot2,
    orient2d,
    pairwise_distances,
    parallel,
    point_segment_distance,
    projection_parameter,
    segments_intersect,
    signed_line_offset,
    unit_vectors,
)

coord = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
point = st.tuples(coord, coord)


def test_cross_and_dot_known_values():
    assert cross2([1, 0], [0, 1]) == 1.0  # counterclockwise turn is positive
    assert cross2([0, 1], [1, 0]) == -1.0
    assert dot2([1, 2], [3, 4]) == 11.0
    np.testing.assert_array_equal(cross2([[1, 0], [2, 0]], [0, 3]), [3.0, 6.0])


def test_unit_vectors_zero_safe():
    u, n = unit_vectors([[3.0, 4.0], [0.0, 0.0]])
    np.testing.assert_allclose(u, [[0.6, 0.8], [0.0, 0.0]])
    np.testing.assert_allclose(n, [5.0, 0.0])


def test_projection_parameter_and_distance_known():
    a, b = np.array([0.0, 0.0]), np.array([4.0, 0.0])
    pts = np.array([[2.0, 3.0], [-1.0, 1.0], [6.0, 0.0], [4.0, -2.0]])
    np.testing.assert_allclose(projection_parameter(pts, a, b), [0.5, -0.25, 1.5, 1.0])
    np.testing.assert_allclose(point_segment_distance(pts, a, b), [3.0, math.sqrt(2.0), 2.0, 2.0])
    # degenerate segment: distance to the point, parameter 0
    assert projection_parameter([1.0, 1.0], a, a) == 0.0
    assert point_segment_distance([3.0, 4.0], a, a) == pytest.approx(5.0)


def test_signed_offset_left_is_positive():
    off = signed_line_offset([[1.0, 2.0], [1.0, -0.5]], [0.0, 0.0], [1.0, 0.0])
    np.testing.assert_allclose(off, [2.0, -0.5])


def test_parallel_same_and_opposite():
    tol = math.radians(10)
    assert parallel([1, 0], [math.cos(0.1), math.sin(0.1)], tol)
    assert not parallel([1, 0], [math.cos(0.2), math.sin(0.2)], tol)
    assert not parallel([1, 0], [-1, 0.01], tol)
    assert parallel([1, 0], [-1, 0.01], tol, same_direction=False)
    assert not parallel([0, 0], [1, 0], tol)


@pytest.mark.parametrize(
    "seg1, seg2, any_, proper",
    [
        (((0, 0), (2, 2)), ((0, 2), (2, 0)), True, True),  # X crossing
        (((0, 0), (1, 0)), ((1, 0), (1, 1)), True, False),  # shared end point
        (((0, 0), (2, 0)), ((1, 0), (3, 0)), True, False),  # collinear overlap
        (((0, 0), (1, 0)), ((2, 0), (3, 0)), False, False),  # collinear apart
        (((0, 0), (1, 0)), ((0, 1), (1, 1)), False, False),  # parallel
        (((0, 0), (2, 0)), ((1, 0), (1, 5)), True, False),  # T
    ],
)
def test_segments_intersect_cases(seg1, seg2, any_, proper):
    (a1, b1), (a2, b2) = seg1, seg2
    assert bool(segments_intersect(a1, b1, a2, b2)) is any_
    assert bool(segments_intersect(a1, b1, a2, b2, proper=True)) is proper
    assert bool(segments_intersect(a2, b2, a1, b1)) is any_


def test_pairwise_distances_shape_and_values():
    d = pairwise_distances([[0, 0], [1, 0]], [[0, 0], [0, 1], [3, 4]])
    assert d.shape == (2, 3)
    np.testing.assert_allclose(d[0], [0.0, 1.0, 5.0])


@settings(max_examples=200, deadline=None)
@given(point, point, point)
def test_distance_matches_brute_force(p, a, b):
    """The closed-form distance equals the minimum over a fine sampling of the segment."""
    s = np.linspace(0.0, 1.0, 2001)
    pa, pb, pp = np.array(a), np.array(b), np.array(p)
    samples = pa[None] + s[:, None] * (pb - pa)[None]
    brute = np.min(np.hypot(*(samples - pp).T))
    d = float(point_segment_distance(pp, pa, pb))
    assert d <= brute + 1e-9
    assert brute - d <= np.hypot(*(pb - pa)) / 2000 + 1e-9


@settings(max_examples=200, deadline=None)
@given(point, point, point, point)
def test_intersection_symmetric_and_proper_implies_any(a1, b1, a2, b2):
    x = bool(segments_intersect(a1, b1, a2, b2))
    assert x == bool(segments_intersect(b2, a2, b1, a1))
    if segments_intersect(a1, b1, a2, b2, proper=True):
        assert x


def test_orient2d_exact_sign_where_floating_point_cancels():
    # regression (hypothesis): with a point 2e-88 from the origin, cross((1 + 2e-88, -1), (1, -1))
    # rounds to 0 while the exact value is -2e-88; the sign must not depend on the base point
    a, b, c = (-1.0, 1.0), (2.14630177107482e-88, 0.0), (0.0, 0.0)
    signs = {float(np.sign(orient2d(*t))) for t in [(a, b, c), (b, c, a), (c, a, b)]}
    assert signs == {-1.0}
    assert {float(np.sign(orient2d(*t))) for t in [(b, a, c), (a, c, b), (c, b, a)]} == {1.0}
    assert not segments_intersect(a, b, c, c) and not segments_intersect(b, a, c, c)
    # nearly collinear points far from the origin: the float product loses the sign
    p, q, r = (1e16, 1e16), (1e16 + 2, 1e16 + 2), (1e16 + 4, 1e16 + 4 + 2)
    assert orient2d(p, q, r) > 0 and orient2d(q, r, p) > 0
    np.testing.assert_array_equal(orient2d([[0, 0], [0, 0]], [1, 0], [[0, 1], [0, -1]]), [1.0, -1.0])


@settings(max_examples=300, deadline=None)
@given(point, point, point)
def test_orient2d_sign_is_invariant_under_rotation_of_the_points(a, b, c):
    s = np.sign(orient2d(a, b, c))
    assert s == np.sign(orient2d(b, c, a)) == np.sign(orient2d(c, a, b)) == -np.sign(orient2d(b, a, c))
