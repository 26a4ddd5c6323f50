"""The cheaper fuse of issue 21, part 3 (branch fusespeed), gives the same maps bit for bit: the
frontier closing tests blocks of frontiers at once, the merge's thick-wall veto looks only at
the walls at candidate corners. Each is checked here against the former formulation (one
frontier at a time; dense base-wall x new-wall matrices), kept in this file as the reference.
The whole fuse is checked by ``python -m tests.fused_fingerprint`` and
``tests/service_fingerprint.py`` (same output as before the change)."""

from __future__ import annotations

import importlib
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.fleet import EdgeFrame, apply_closings, close_frontiers
from mapping.wireframe import Label, Wireframe

merge_module = importlib.import_module("mapping.merge")  # (``mapping.merge`` is also the function)
NAMES = ("points", "labels", "edges", "likelihood", "sources")


def same_arrays(a: Wireframe, b: Wireframe) -> None:
    for name in NAMES:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


# ---------------------------------------------------------------------- frontier closing
def close_frontiers_one_by_one(wf: Wireframe, threshold: float,
                               max_angle: float = math.radians(20.0)) -> Wireframe:
    """The former :func:`close_frontiers`: each frontier's distances to every edge in turn (the
    decisions made from them, :func:`apply_closings`, were not rewritten: shared)."""
    fr = np.flatnonzero(wf.labels == Label.FRONTIER)
    if len(fr) == 0 or wf.n_edges == 0:
        return wf
    geo = EdgeFrame.of(wf)
    P, E = wf.points, wf.edges
    closings = []
    for v in fr.tolist():
        touches = (E[:, 0] == v) | (E[:, 1] == v)
        rel = P[v] - geo.A
        t = rel[:, 0] * geo.dirs[:, 0] + rel[:, 1] * geo.dirs[:, 1]
        d = np.abs(geo.dirs[:, 0] * rel[:, 1] - geo.dirs[:, 1] * rel[:, 0])
        closing = np.flatnonzero(geo.ok & ~touches & (d <= threshold) & (t > threshold)
                                 & (t < geo.L - threshold))
        if len(closing):
            closings.append((v, touches, closing))
    return apply_closings(wf, geo, closings, threshold, max_angle)


def random_walls(rng: np.random.Generator, n: int, span: float, frontier_p: float) -> Wireframe:
    """``n`` walls, mostly axis-aligned and on shared lines (so that frontiers get closed, at
    angles and along), some ends frontiers."""
    a = np.round(rng.uniform(0.0, span, (n, 2)) * 4) / 4
    horizontal = rng.random(n) < 0.5
    length = rng.uniform(0.3, 3.0, n) * rng.choice([-1.0, 1.0], n)
    along = np.stack([length, np.zeros(n)], 1)
    b = a + np.where(horizontal[:, None], along, along[:, ::-1])
    b += rng.normal(0.0, 0.02, b.shape) * (rng.random((n, 1)) < 0.3)
    labels = np.where(rng.random(2 * n) < frontier_p, Label.FRONTIER, Label.NOMINAL)
    return Wireframe.build(np.concatenate([a, b]), np.stack([np.arange(n), np.arange(n, 2 * n)], 1), labels,
                           rng.uniform(0.1, 1.0, n), rng.integers(1, 1 << 20, n))


@settings(max_examples=120, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.sampled_from([0.1, 0.2, 0.4]))
def test_close_frontiers_is_the_one_by_one_closing(seed, n, thr):
    wf = random_walls(np.random.default_rng(seed), n, 8.0, 0.4)
    got, ref = close_frontiers(wf, thr), close_frontiers_one_by_one(wf, thr)
    assert (got is wf) == (ref is wf)
    same_arrays(got, ref)


def test_close_frontiers_in_several_blocks_is_the_one_by_one_closing():
    """Over 2**18 frontier x edge entries: the frontiers are taken in several blocks."""
    wf = random_walls(np.random.default_rng(7), 1200, 60.0, 0.5)
    assert np.count_nonzero(wf.labels == Label.FRONTIER) * wf.n_edges > 3 * (1 << 18)
    got, ref = close_frontiers(wf, 0.2), close_frontiers_one_by_one(wf, 0.2)
    assert got is not wf
    same_arrays(got, ref)


# ---------------------------------------------------------------------- the thick-wall veto
def not_other_face_dense(edges, raw_a, raw_d, raw_n, mbl, nlb, thr, cos_tol, r, c):  # type: ignore[no-untyped-def]
    """The former veto: every (base wall, new wall) pair as dense matrices, counted through
    incidence matrices."""
    if mbl == 0 or mbl == len(edges):
        return np.ones(len(r), dtype=bool)
    u = raw_d / np.where(raw_n > 0.0, raw_n, 1.0)[:, None]
    ub, un = u[:mbl, None, :], u[None, mbl:, :]
    anti = ub[..., 0] * un[..., 0] + ub[..., 1] * un[..., 1] <= -cos_tol
    rel = raw_a[None, mbl:, :] - raw_a[:mbl, None, :]
    veto = anti & (np.abs(ub[..., 0] * rel[..., 1] - ub[..., 1] * rel[..., 0]) > 0.25 * thr)
    eb, en = edges[:mbl], edges[mbl:] - nlb
    inc_b = np.zeros((nlb, mbl))
    inc_b[eb[:, 0], np.arange(mbl)] = 1.0
    inc_b[eb[:, 1], np.arange(mbl)] = 1.0
    inc_n = np.zeros((len(en), int(max(en.max(), c.max())) + 1))
    inc_n[np.arange(len(en)), en[:, 0]] = 1.0
    inc_n[np.arange(len(en)), en[:, 1]] = 1.0
    hits = (inc_b[r] @ veto.astype(np.float64)) * inc_n.T[c]
    return hits.sum(axis=1) == 0.0


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 14), st.integers(1, 14), st.integers(1, 30),
       st.sampled_from([0.05, 0.2, 1.0]))
def test_thick_wall_veto_is_the_dense_one(seed, nlb, nn, n_cand, thr):
    """Random local walls between a few corners (many walls per corner, directions often
    opposite, offsets around thr / 4) and random candidate pairs: the same verdicts, with
    few candidates (tested one by one) and many (after the test for any opposite pair)."""
    rng = np.random.default_rng(seed)
    mbl = int(rng.integers(1, 3 * nlb + 1))
    mn = int(rng.integers(1, 3 * nn + 1))
    eb = np.stack([rng.integers(0, nlb, mbl), rng.integers(0, nlb, mbl)], 1)
    en = np.stack([rng.integers(0, nn, mn), rng.integers(0, nn, mn)], 1) + nlb
    edges = np.concatenate([eb, en]).astype(np.int64)
    angles = rng.choice([0.0, math.pi, 0.5 * math.pi, -0.5 * math.pi], len(edges))
    angles += rng.normal(0, 0.05, len(edges))
    raw_n = rng.uniform(0.0, 2.0, len(edges)) * (rng.random(len(edges)) > 0.05)
    raw_d = np.stack([np.cos(angles), np.sin(angles)], 1) * raw_n[:, None]
    raw_a = rng.uniform(-0.3, 0.3, (len(edges), 2)) * thr
    r = rng.integers(0, nlb, n_cand).astype(np.intp)
    c = rng.integers(0, nn, n_cand).astype(np.intp)
    cos_tol = math.cos(math.radians(10.0))
    got = merge_module._not_other_face(edges, raw_a, raw_d, raw_n, mbl, nlb, thr, cos_tol)(r, c)
    ref = not_other_face_dense(edges, raw_a, raw_d, raw_n, mbl, nlb, thr, cos_tol, r, c)
    assert got.dtype == bool and np.array_equal(got, ref)
