"""Resampling with mutation (paper Sec. IV-F)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping import Wireframe
from mapping.resample import (
    low_variance_indexes,
    mutate,
    mutation_candidates,
    resample_with_mutation,
)


def strip(likelihoods) -> Wireframe:
    """Disjoint unit walls along x with the given likelihoods."""
    k = len(likelihoods)
    pts = [(2.0 * i + d, 0.0) for i in range(k) for d in (0.0, 1.0)]
    return Wireframe.build(pts, [(2 * i, 2 * i + 1) for i in range(k)], likelihood=likelihoods)


@settings(max_examples=60, deadline=None)
@given(
    w=st.lists(st.floats(0.0, 10.0), min_size=1, max_size=12).filter(lambda v: sum(v) > 1e-6),
    seed=st.integers(0, 2**31),
)
def test_low_variance_draws_floor_or_ceil_of_expected(w, seed):
    idx = low_variance_indexes(w, np.random.default_rng(seed))
    n = len(w)
    counts = np.bincount(idx, minlength=n)
    expected = n * np.asarray(w) / sum(w)
    assert counts.sum() == n
    assert np.all(counts >= np.floor(expected - 1e-9)) and np.all(counts <= np.ceil(expected + 1e-9))
    assert np.all(np.diff(idx) >= 0)


def test_low_variance_is_deterministic_given_the_generator():
    w = [0.1, 0.5, 0.2, 0.2]
    a = low_variance_indexes(w, np.random.default_rng(5), 20)
    b = low_variance_indexes(w, np.random.default_rng(5), 20)
    assert a.tolist() == b.tolist()
    assert np.bincount(a, minlength=4).tolist() == [2, 10, 4, 4]


@pytest.mark.parametrize("w", [[], [0.0, 0.0], [1.0, -1.0], [1.0, math.nan]])
def test_low_variance_rejects_bad_weights(w):
    with pytest.raises(ValueError):
        low_variance_indexes(w, np.random.default_rng(0))


def test_candidates_are_in_sight_and_below_threshold():
    wf = strip([0.1, 0.9, 0.3, 0.2])
    cand = mutation_candidates(wf, np.array([0, 1, 2]), keep_threshold=0.5)
    assert cand.tolist() == [True, False, True, False]
    cand = mutation_candidates(wf, np.array([True, True, False, True]), keep_threshold=0.5)
    assert cand.tolist() == [True, False, False, True]
    with pytest.raises(ValueError):
        mutation_candidates(wf, np.array([True]), 0.5)


def test_mutate_drops_by_likelihood_and_returns_same_object_when_nothing_dropped():
    wf = strip([0.0, 0.0, 0.7])
    rng = np.random.default_rng(0)
    # Zero-likelihood candidates are always dropped; non-candidates always kept.
    out = mutate(wf, np.array([True, False, False]), rng)
    assert out.n_edges == 2 and out.n_vertices == 4
    assert mutate(wf, np.zeros(3, bool), rng) is wf


def test_mutate_keeps_with_probability_equal_to_likelihood():
    wf = strip([0.3])
    rng = np.random.default_rng(123)
    kept = sum(mutate(wf, np.array([True]), rng).n_edges for _ in range(4000))
    assert abs(kept / 4000 - 0.3) < 0.03


def test_first_copy_is_kept_and_further_copies_mutate():
    a = strip([0.0, 0.0, 0.9])
    b = strip([0.5, 0.5, 0.5])
    sight = [np.ones(3, bool), np.ones(3, bool)]
    res = resample_with_mutation([a, b], [1.0, 0.0], sight, 0.5, np.random.default_rng(1))
    assert res.indexes.tolist() == [0, 0]
    assert res.particles[0] is a
    assert res.mutated.tolist() == [False, True]
    # The copy lost both zero-likelihood in-sight walls and kept the strong one.
    assert res.particles[1].n_edges == 1
    assert res.particles[1].likelihood.tolist() == [0.9]
    assert res.first_copy_of(0) == 0 and res.first_copy_of(1) is None


def test_identical_particles_count_as_one_particle_drawn_many_times():
    a = strip([0.0, 0.9])
    res = resample_with_mutation([a] * 4, np.ones(4), [np.ones(2, bool)] * 4, 0.5, np.random.default_rng(2))
    assert res.mutated.tolist() == [False, True, True, True]
    assert res.particles[0] is a
    assert all(p.n_edges == 1 for p in res.particles[1:])


def test_plain_resampling_without_mutation():
    a = strip([0.0, 0.0])
    res = resample_with_mutation([a, a], [1, 1], [np.ones(2, bool)] * 2, 0.5, np.random.default_rng(3), False)
    assert all(p is a for p in res.particles)
    assert not res.mutated.any()


def test_resample_rejects_mismatched_inputs():
    a = strip([0.5])
    with pytest.raises(ValueError):
        resample_with_mutation([a, a], [1, 1], [np.ones(1, bool)], 0.5, np.random.default_rng(0))
    with pytest.raises(ValueError):
        resample_with_mutation([a], [1], [np.ones(1, bool)], 1.5, np.random.default_rng(0))
