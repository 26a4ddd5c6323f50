"""Resampling with mutation (paper Sec. IV-F).

Particles are drawn by weight with the low-variance (systematic) sampler. The first copy of a
drawn particle is kept unchanged; every further copy is *mutated*: each edge that is in sight of
the robot and whose likelihood is below the keep threshold is kept with probability equal to its
likelihood and dropped otherwise. Edges out of sight and edges at or above the threshold are
always kept. This replaces the noisy motion model of a classic particle filter as the source of
diversity between wireframe particles.

Following FilterPy, the sampler returns indexes and the caller moves the particles.

Choices where the paper is silent
---------------------------------
* "Copies" are counted per group of particles, by default by object identity: particles that
  are the same :class:`~mapping.wireframe.Wireframe` object (unmutated copies share the
  object) are one particle drawn several times. The filter passes coarser groups: particles
  the current scan cannot tell apart (same predicted scan, same in-sight likelihoods). Without
  this, a set of particles that differ only out of sight, with equal weights, would each be
  drawn once by the low-variance sampler and never try dropping a doubtful wall in sight.
* The likelihood used for keep/drop is the edge's stored likelihood (updated by the filter from
  the per-edge likelihoods of Sec. IV-D before resampling).
* A mutated copy that happens to keep every candidate is the same object as its parent.
* Vertices left without an edge by a mutation are dropped.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["ResampleResult", "low_variance_indexes", "mutate", "mutation_candidates",
           "resample_with_mutation"]


def _normalised(weights: ArrayLike) -> FloatArray:
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.size == 0:
        raise ValueError("weights must not be empty")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and non-negative")
    total = w.sum()
    if total <= 0:
        raise ValueError("weights must not all be zero")
    return np.asarray(w / total, dtype=np.float64)


def low_variance_indexes(weights: ArrayLike, rng: np.random.Generator, n: int | None = None) -> IntArray:
    """Low-variance (systematic) resampling: ``n`` indexes drawn in proportion to ``weights``.

    One uniform offset ``u ~ U[0, 1/n)``; index ``k`` is the particle whose cumulative weight
    interval contains ``u + k/n``. A particle of weight ``w`` is drawn ``floor(n w)`` or
    ``ceil(n w)`` times.

    Parameters
    ----------
    weights : (c,) array_like
        Non-negative, not all zero; normalised here.
    rng : numpy.random.Generator
    n : int, optional
        How many to draw (default ``len(weights)``).

    Returns
    -------
    (n,) int64, non-decreasing.

    References
    ----------
    S. Thrun, W. Burgard, D. Fox, *Probabilistic Robotics*, Table 4.4.
    """
    w = _normalised(weights)
    count = len(w) if n is None else int(n)
    if count < 1:
        raise ValueError("n must be >= 1")
    positions = (rng.random() + np.arange(count)) / count
    cum = np.cumsum(w)
    cum[-1] = 1.0  # guard against round-off
    return np.asarray(np.searchsorted(cum, positions, side="right"), dtype=np.int64).clip(0, len(w) - 1)


def mutation_candidates(wf: Wireframe, in_sight: ArrayLike, keep_threshold: float) -> BoolArray:
    """Edges that a further copy may drop: in sight and with likelihood below ``keep_threshold``.

    ``in_sight`` is a boolean mask over the edges or an array of edge indexes.
    """
    mask = np.zeros(wf.n_edges, dtype=bool)
    s = np.asarray(in_sight)
    if s.dtype == bool:
        if s.shape != (wf.n_edges,):
            raise ValueError(f"in-sight mask must have shape ({wf.n_edges},), got {s.shape}")
        mask |= s
    elif s.size:
        mask[s.astype(np.int64).reshape(-1)] = True
    return mask & (wf.likelihood < keep_threshold)


def mutate(wf: Wireframe, candidates: BoolArray, rng: np.random.Generator) -> Wireframe:
    """Keep each candidate edge with probability equal to its likelihood, drop it otherwise.

    Returns ``wf`` itself when nothing is dropped (so identical copies stay shared).
    """
    cand = np.asarray(candidates, dtype=bool)
    if cand.shape != (wf.n_edges,):
        raise ValueError(f"candidate mask must have shape ({wf.n_edges},), got {cand.shape}")
    idx = np.flatnonzero(cand)
    if idx.size == 0:
        return wf
    drop = rng.random(idx.size) >= wf.likelihood[idx]
    if not drop.any():
        return wf
    keep = np.ones(wf.n_edges, dtype=bool)
    keep[idx[drop]] = False
    return wf.subgraph_edges(keep)


@dataclass(frozen=True)
class ResampleResult:
    """Outcome of :func:`resample_with_mutation`.

    Attributes
    ----------
    particles : tuple of Wireframe
        The new particle set.
    indexes : (n,) int64
        Parent of each new particle.
    mutated : (n,) bool
        Whether each new particle is a further (mutated) copy.
    """

    particles: tuple[Wireframe, ...]
    indexes: IntArray
    mutated: BoolArray

    def first_copy_of(self, parent: int) -> int | None:
        """Slot of the unmutated copy of ``parent`` (None when it was not drawn or when its
        object's first copy came from another parent index)."""
        for k, (i, m) in enumerate(zip(self.indexes.tolist(), self.mutated.tolist())):
            if i == parent and not m:
                return k
        return None


def resample_with_mutation(
    particles: Sequence[Wireframe],
    weights: ArrayLike,
    in_sight: Sequence[ArrayLike],
    keep_threshold: float,
    rng: np.random.Generator,
    mutate_copies: bool = True,
    groups: Sequence[Hashable] | None = None,
) -> ResampleResult:
    """Resampling with mutation (paper Sec. IV-F).

    Parameters
    ----------
    particles : sequence of Wireframe
    weights : (c,) array_like
        Particle weights (normalised here).
    in_sight : sequence of masks or index arrays
        For each particle, its edges in sight of the robot (see :func:`mutation_candidates`).
    keep_threshold : float
        Edges with likelihood at or above this are never dropped.
    rng : numpy.random.Generator
    mutate_copies : bool
        False gives plain resampling (every copy unchanged).
    groups : sequence of hashable, optional
        A key per particle: particles with equal keys count as copies of one particle (the
        first draw of the group is kept, every further draw is mutated). Default: object
        identity.

    Returns
    -------
    ResampleResult
    """
    if len(particles) != len(in_sight):
        raise ValueError("particles and in_sight must have the same length")
    if groups is not None and len(groups) != len(particles):
        raise ValueError("groups must have one key per particle")
    if not 0.0 <= keep_threshold <= 1.0:
        raise ValueError("keep_threshold must be within [0, 1]")
    idx = low_variance_indexes(weights, rng, len(particles))
    seen: set[Hashable] = set()
    cand_cache: dict[int, BoolArray] = {}
    out: list[Wireframe] = []
    mutated = np.zeros(len(idx), dtype=bool)
    for k, i in enumerate(idx.tolist()):
        parent = particles[i]
        group: Hashable = id(parent) if groups is None else groups[i]
        if group not in seen or not mutate_copies:
            seen.add(group)
            out.append(parent)
            continue
        mutated[k] = True
        if id(parent) not in cand_cache:
            cand_cache[id(parent)] = mutation_candidates(parent, in_sight[i], keep_threshold)
        out.append(mutate(parent, cand_cache[id(parent)], rng))
    return ResampleResult(tuple(out), idx, mutated)
