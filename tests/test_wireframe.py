import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import Label, Pose, Wireframe, paper_storage_bytes


def square(size: float = 2.0) -> Wireframe:
    return Wireframe.from_polylines([[(0, 0), (size, 0), (size, size), (0, size)]])


def test_square_is_ccw_ring():
    wf = square()
    assert wf.n_vertices == 4 and wf.n_edges == 4
    assert wf.edges.tolist() == [[0, 1], [1, 2], [2, 3], [3, 0]]
    assert wf.total_length() == pytest.approx(8.0)


@pytest.mark.parametrize(
    "kwargs, reason",
    [
        ({"points": [[0, 0], [1, 0]], "edges": [[0, 2]]}, "outside"),
        ({"points": [[0, 0], [1, 0]], "edges": [[1, 1]]}, "self-loop"),
        ({"points": [[0, 0], [np.nan, 0]], "edges": []}, "non-finite"),
        ({"points": [[0, 0], [1, 0]], "edges": [[0, 1]], "labels": [0]}, "labels"),
        ({"points": [[0, 0], [1, 0]], "edges": [[0, 1]], "labels": [0, 7]}, "labels"),
        ({"points": [[0, 0], [1, 0]], "edges": [[0, 1]], "likelihood": [1.5]}, "likelihood"),
        ({"points": [[0, 0], [1, 0]], "edges": [[0, 1]], "likelihood": [1, 1]}, "likelihood"),
        ({"points": [0, 0, 1], "edges": []}, "points"),
    ],
)
def test_constructor_rejects_with_reason(kwargs, reason):
    with pytest.raises(ValueError, match=reason):
        Wireframe.build(**kwargs)


def test_arrays_are_read_only():
    wf = square()
    with pytest.raises(ValueError):
        wf.points[0, 0] = 5.0


def test_paper_storage_accounting():
    assert paper_storage_bytes(42, 42) == 840
    assert paper_storage_bytes(293, 298) == 5910
    assert 6 * paper_storage_bytes(293, 298) == 35460
    assert square().paper_storage_bytes() == 80


def test_transform_and_inverse():
    wf = square()
    pose = Pose(3.0, -1.0, 0.7)
    back = wf.transformed(pose).transformed(pose.inverse())
    assert back.almost_equal(wf, tol=1e-12)
    assert not wf.transformed(Pose(0.01, 0, 0)).almost_equal(wf, tol=1e-3)


def test_pose_algebra():
    a, b = Pose(1, 2, 0.5), Pose(-3, 0.5, -2.0)
    pts = np.array([[0.3, -0.2], [5, 5]])
    assert np.allclose(a.compose(b).apply(pts), a.apply(b.apply(pts)))
    assert a.compose(a.inverse()).almost_equal(Pose.identity(), tol=1e-12, angle_tol=1e-12)
    assert np.allclose(a.apply_inverse(a.apply(pts)), pts)
    assert a.between(a.compose(b)).almost_equal(b, tol=1e-12, angle_tol=1e-12)
    assert Pose(0, 0, 3 * math.pi).theta == pytest.approx(-math.pi)
    assert Pose.parse("1,2,0.5") == Pose(1, 2, 0.5)
    with pytest.raises(ValueError):
        Pose.parse("1,2")


def test_almost_equal_ignores_order_but_not_direction():
    wf = square()
    perm = np.array([2, 0, 3, 1])
    inv = np.argsort(perm)
    shuffled = Wireframe.build(wf.points[perm], inv[wf.edges][::-1])
    assert shuffled.almost_equal(wf)
    reversed_edges = Wireframe.build(wf.points, wf.edges[:, ::-1])
    assert not reversed_edges.almost_equal(wf)


def test_subgraph_and_compaction():
    wf = Wireframe.build([[0, 0], [1, 0], [2, 0], [5, 5]], [[0, 1], [1, 2]])
    sub = wf.subgraph_edges(np.array([True, False]))
    assert sub.n_vertices == 2 and sub.edges.tolist() == [[0, 1]]
    assert wf.compacted().n_vertices == 3


def test_geojson_shape():
    wf = Wireframe.build(
        [[0, 0], [1, 0], [1, 1]], [[0, 1], [1, 2]], labels=[0, 1, 2], likelihood=[0.5, 0.25]
    )
    doc = wf.to_geojson()
    kinds = [(f["geometry"]["type"], f["properties"]["kind"]) for f in doc["features"]]
    assert kinds.count(("Point", "corner")) == 3 and kinds.count(("LineString", "wall")) == 2
    labels = [f["properties"]["label"] for f in doc["features"] if f["properties"]["kind"] == "corner"]
    assert labels == ["nominal", "occlusion", "frontier"]
    wall = next(f for f in doc["features"] if f["properties"]["kind"] == "wall")
    assert wall["geometry"]["coordinates"] == [[0.0, 0.0], [1.0, 0.0]]
    assert wall["properties"]["likelihood"] == 0.5


def test_geojson_without_indices_joins_by_coordinates():
    doc = {
        "type": "FeatureCollection",
        "features": [
            {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 0]]},
             "properties": {}},
            {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[1, 0], [1, 1]]},
             "properties": {}},
        ],
    }
    wf = Wireframe.from_geojson(doc)
    assert wf.n_vertices == 3 and wf.n_edges == 2


def test_geojson_errors_name_the_feature():
    with pytest.raises(ValueError, match="feature 0"):
        Wireframe.from_geojson({"type": "FeatureCollection", "features": [{"geometry": {"type": "Polygon"}}]})
    with pytest.raises(ValueError, match="FeatureCollection"):
        Wireframe.from_geojson({"type": "Feature"})


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@st.composite
def wireframes(draw, max_vertices: int = 12):
    n = draw(st.integers(0, max_vertices))
    pts = draw(st.lists(st.tuples(finite, finite), min_size=n, max_size=n))
    labels = draw(st.lists(st.sampled_from(list(Label)), min_size=n, max_size=n))
    edges = []
    if n >= 2:
        pairs = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=2 * n))
        edges = [(a, b) for a, b in pairs if a != b]
    lik = draw(st.lists(st.floats(0, 1), min_size=len(edges), max_size=len(edges)))
    return Wireframe.build(np.array(pts, dtype=float).reshape(-1, 2), edges, [int(x) for x in labels], lik)


@settings(max_examples=150, deadline=None)
@given(wireframes())
def test_geojson_round_trip_is_exact(wf):
    back = Wireframe.from_geojson(json.loads(json.dumps(wf.to_geojson())))
    assert np.array_equal(back.points, wf.points)
    assert np.array_equal(back.labels, wf.labels)
    assert np.array_equal(back.edges, wf.edges)
    assert np.array_equal(back.likelihood, wf.likelihood)


def test_almost_equal_finds_a_matching_within_tolerance_when_one_exists():
    # a0 = b0; a1 and b1 lie 0.2 m from the origin, 0.3 m apart. Both a0 and a1 have b0 as their
    # nearest neighbour, and the matching of least summed distance (a0-b0, a1-b1: 0 + 0.3) breaks
    # tol = 0.25 while a0-b1, a1-b0 (0.2 + 0.2) keeps every pair within it.
    ang = 2 * math.asin(0.15 / 0.2)
    a = Wireframe.build([[0.0, 0.0], [0.2, 0.0]])
    b = Wireframe.build([[0.0, 0.0], [0.2 * math.cos(ang), 0.2 * math.sin(ang)]])
    assert a.almost_equal(b, tol=0.25)
    assert not a.almost_equal(b, tol=0.15)


def test_masks_of_any_width_are_canonical():
    """uint64 while every mask fits (so maps of at most 64 robots are as they always were),
    Python ints in an object array once a mask has bit 64 or above."""
    from mapping.wireframe import as_masks, mask_array, mask_bytes, mask_or

    assert as_masks([1, 2, (1 << 64) - 1]).dtype == np.uint64
    assert as_masks(np.array([3, 4], dtype=object)).dtype == np.uint64
    wide = as_masks([1, 1 << 64, 1 << 199])
    assert wide.dtype == object and wide.tolist() == [1, 1 << 64, 1 << 199]
    assert all(type(v) is int for v in wide.tolist())
    for bad in ([-1, 1 << 70], [1.5, 1 << 70], [True, 1 << 70]):
        with pytest.raises(ValueError):
            as_masks(bad)
    assert mask_array(2, 1 << 5).dtype == np.uint64 and mask_array(2, 1 << 80).tolist() == [1 << 80] * 2
    assert mask_or(wide) == 1 | (1 << 64) | (1 << 199) and mask_or(as_masks([1, 6])) == 7
    small = as_masks([1, 2])
    assert mask_bytes(small) == small.tobytes()
    wf = Wireframe.build([(0, 0), (1, 0), (1, 1)], [(0, 1), (1, 2)], sources=[1 << 70, 3])
    assert wf.sources.dtype == object and not wf.sources.flags.writeable
    other = wf.replace(sources=[1 << 71, 3])
    assert wf.content_digest() != other.content_digest()
    assert wf.content_digest() == wf.replace(sources=[1 << 70, 3]).content_digest()
    assert not wf.almost_equal(other) and wf.almost_equal(wf.replace(sources=[1 << 70, 3]))
    back = Wireframe.from_geojson(json.loads(json.dumps(wf.to_geojson())))
    assert back.sources.tolist() == [1 << 70, 3]
    with pytest.raises(ValueError, match="contributor mask"):
        Wireframe.build([(0, 0), (1, 0)], [(0, 1)], sources=[-(1 << 70)])
    with pytest.raises(ValueError, match="sources: a contributor mask"):
        Wireframe(wf.points, wf.labels, wf.edges, wf.likelihood, np.array([-(1 << 70), 1], dtype=object))


# ------------------------------------------- replace / subgraph_edges / compacted fast paths
def _full(wf: Wireframe) -> Wireframe:
    """The same arrays through the checking constructor."""
    return Wireframe(wf.points, wf.labels, wf.edges, wf.likelihood, wf.sources)


def _same_arrays(a: Wireframe, b: Wireframe) -> None:
    for f in ("points", "labels", "edges", "likelihood", "sources"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape and not x.flags.writeable
        np.testing.assert_array_equal(x, y)


@st.composite
def random_wireframe(draw, wide: bool = False):
    n = draw(st.integers(0, 12))
    pts = draw(st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=n, max_size=n))
    edges = []
    if n >= 2:
        pair = st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)).filter(lambda e: e[0] != e[1])
        edges = draw(st.lists(pair, max_size=2 * n))
    m = len(edges)
    top = 2**70 if wide else 2**64 - 1
    return Wireframe.build(
        np.array(pts, dtype=float).reshape(-1, 2), edges,
        draw(st.lists(st.integers(0, 2), min_size=n, max_size=n)),
        draw(st.lists(st.floats(0.0, 1.0), min_size=m, max_size=m)),
        draw(st.lists(st.integers(0, top), min_size=m, max_size=m)),
    )


@settings(max_examples=80, deadline=None)
@given(st.one_of(random_wireframe(), random_wireframe(wide=True)), st.integers(0, 2**32 - 1))
def test_fast_paths_give_the_checking_constructors_arrays(wf, seed):
    """replace, subgraph_edges and compacted skip the checks of arrays that cannot have become
    invalid; their results are the arrays Wireframe(...) makes of the same input."""
    rng = np.random.default_rng(seed)
    keep = rng.random(wf.n_edges) < 0.6
    sub = wf.subgraph_edges(keep)
    expected = Wireframe(wf.points, wf.labels, wf.edges[keep], wf.likelihood[keep],
                         wf.sources[keep]).compacted()
    _same_arrays(sub, _full(expected))
    _same_arrays(sub, _full(sub))
    moved = wf.replace(points=wf.points + 1.0)
    _same_arrays(moved, Wireframe(wf.points + 1.0, wf.labels, wf.edges, wf.likelihood, wf.sources))
    lik = rng.random(wf.n_edges)
    _same_arrays(wf.replace(likelihood=lik), Wireframe(wf.points, wf.labels, wf.edges, lik, wf.sources))
    _same_arrays(wf.replace(), _full(wf))


def test_replace_still_rejects_what_the_constructor_rejects():
    wf = square()
    with pytest.raises(ValueError, match="non-finite"):
        wf.replace(points=np.array([[0, 0], [1, 0], [1, 1], [np.nan, 1]]))
    with pytest.raises(ValueError, match="outside"):  # fewer vertices: the old edges are checked again
        wf.replace(points=np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), labels=np.zeros(3, np.uint8))
    with pytest.raises(ValueError, match="labels"):
        wf.replace(points=np.zeros((5, 2)))
    with pytest.raises(ValueError, match="likelihood"):  # fewer edges: the old likelihoods no longer fit
        wf.replace(edges=np.array([[0, 1]]))
    with pytest.raises(ValueError, match="within"):
        wf.replace(likelihood=np.full(4, 2.0))
    with pytest.raises(TypeError):
        wf.replace(colour=1)
    with pytest.raises(ValueError, match="edge mask"):
        wf.subgraph_edges(np.ones(3, dtype=bool))


def test_replace_copies_what_it_is_given():
    wf = square()
    pts = wf.points.copy()
    moved = wf.replace(points=pts)
    pts[0, 0] = 9.0
    assert moved.points[0, 0] == 0.0 and not moved.points.flags.writeable
