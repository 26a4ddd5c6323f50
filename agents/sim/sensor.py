"""The simulated corner sensor (paper Sec. IV-A).

The paper assumes a sensor preprocessing layer that reports "the relative positions of the
corners from the visible scene, with additive Gaussian noise", joined counterclockwise into a
labelled wireframe scan. :class:`CornerSensor` simulates that layer directly from the world's
ground-truth wireframe:

1. **Visible scene.** :func:`mapping.visibility.visible_view` of the truth from the true pose:
   the visible wall pieces in the robot frame, vertices counterclockwise, labelled nominal /
   occlusion / frontier (see that module for the exact rules). This noise-free scan is
   :meth:`CornerSensor.true_scan`, the ground truth for labels.
2. **Missed walls.** Each edge is dropped independently with probability ``p_fn``. A corner is
   reported only as the end of a reported wall: a vertex that no reported edge uses any more is
   dropped with it (the corner extractor finds corners as the ends of wall segments). Vertices
   keep their true labels.
3. **Spurious walls.** Each pair of consecutive scan vertices (counterclockwise; the last and
   the first are consecutive too for a full turn) that no true edge joins gets a false edge, in
   counterclockwise direction, with probability ``p_fp``. The classic case is an occlusion
   joined to its frontier, a "wall" along the line of sight that the filter must learn to drop.
4. **Noise.** Every reported corner moves by isotropic Gaussian noise of std ``sigma`` per axis.

Every edge of a measured scan has likelihood 1.0 and sources 0 (one measurement; the filter
assigns likelihoods). Random numbers come only from the ``rng`` argument, drawn in a fixed order
(corner noise for every true vertex, then one uniform per true edge, then one per consecutive
pair), so a seeded generator reproduces a scan exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mapping.se2 import Pose
from mapping.visibility import View, visible_view
from mapping.wireframe import Wireframe

__all__ = ["CornerSensor", "CornerSensorConfig", "LabelStats", "label_accuracy", "label_stats"]


@dataclass(frozen=True)
class CornerSensorConfig:
    """Parameters of the simulated corner sensor.

    Attributes
    ----------
    max_range : float
        Sensing range in metres (``> 0``).
    fov : float
        Field of view in radians, ``(0, 2 pi]``, centred on the heading.
    sigma : float
        Standard deviation of the corner position noise per axis, metres (``>= 0``).
    p_fp : float
        Probability that two consecutive corners not joined by a wall are joined anyway.
    p_fn : float
        Probability that a visible wall is missed.
    min_piece : float
        Visible wall pieces shorter than this (metres) are not reported.
    """

    max_range: float = 8.0
    fov: float = 2.0 * math.pi
    sigma: float = 0.02
    p_fp: float = 0.02
    p_fn: float = 0.02
    min_piece: float = 1e-3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_range) and self.max_range > 0.0):
            raise ValueError(f"max_range must be a finite distance > 0, got {self.max_range}")
        if not (0.0 < self.fov <= 2.0 * math.pi + 1e-12):
            raise ValueError(f"fov must be in (0, 2*pi] radians, got {self.fov}")
        if not (math.isfinite(self.sigma) and self.sigma >= 0.0):
            raise ValueError(f"sigma must be a finite std >= 0, got {self.sigma}")
        for name in ("p_fp", "p_fn"):
            p = getattr(self, name)
            if not (0.0 <= p <= 1.0):
                raise ValueError(f"{name} must be a probability in [0, 1], got {p}")
        if not (math.isfinite(self.min_piece) and self.min_piece >= 0.0):
            raise ValueError(f"min_piece must be a finite length >= 0, got {self.min_piece}")


class CornerSensor:
    """Simulated corner scans of a known world.

    Parameters
    ----------
    truth : Wireframe
        The world's ground-truth wireframe (all corners nominal, a thin wall two opposite edges).
    config : CornerSensorConfig
    """

    def __init__(self, truth: Wireframe, config: CornerSensorConfig | None = None) -> None:
        if not isinstance(truth, Wireframe):
            raise TypeError(f"truth must be a Wireframe, got {type(truth).__name__}")
        self.truth = truth
        self.config = config if config is not None else CornerSensorConfig()

    def view(self, pose: Pose) -> View:
        """The noise-free :class:`~mapping.visibility.View` from ``pose`` (with its sources)."""
        c = self.config
        return visible_view(self.truth, pose, c.max_range, c.fov, min_piece=c.min_piece)

    def true_scan(self, pose: Pose) -> Wireframe:
        """The noise-free scan from ``pose``, robot frame, counterclockwise: the true labels."""
        s = self.view(pose).scan
        return s.replace(likelihood=np.ones(s.n_edges), sources=np.zeros(s.n_edges, np.uint64))

    def scan(self, pose: Pose, rng: np.random.Generator) -> Wireframe:
        """A measured scan from the true ``pose``: robot frame, vertices counterclockwise.

        See the module docstring for the error model. Vertex order follows the true scan.
        """
        c = self.config
        truth = self.true_scan(pose)
        n, m = truth.n_vertices, truth.n_edges
        noise = rng.normal(0.0, 1.0, size=(n, 2)) * c.sigma
        kept = rng.random(m) >= c.p_fn
        full = c.fov >= 2.0 * math.pi - 1e-12
        a = np.arange(n - 1) if not (full and n > 2) else np.arange(n)
        pairs = np.stack([a, (a + 1) % max(n, 1)], axis=1) if n > 1 else np.zeros((0, 2), np.int64)
        spurious = rng.random(len(pairs)) < c.p_fp
        if len(pairs):
            joined = np.zeros((n, n), bool)
            joined[truth.edges[:, 0], truth.edges[:, 1]] = True
            joined |= joined.T
            spurious &= ~joined[pairs[:, 0], pairs[:, 1]]
        edges = np.concatenate([truth.edges[kept], pairs[spurious]]).astype(np.int64)
        if len(edges):
            order = np.lexsort((edges[:, 1], edges[:, 0]))
            edges = edges[order]
        k = len(edges)
        out = Wireframe.build(
            truth.points + noise, edges.reshape(-1, 2), truth.labels, np.ones(k), np.zeros(k, np.uint64)
        )
        return out.compacted()


@dataclass(frozen=True)
class LabelStats:
    """Counts behind :func:`label_accuracy`; add them up over many scans.

    Attributes
    ----------
    n_true : int
        Corners in the true scans.
    n_matched : int
        True corners with a measured corner within ``tol``.
    n_same : int
        Matched true corners whose nearest measured corner has the same label.
    """

    n_true: int = 0
    n_matched: int = 0
    n_same: int = 0

    def __add__(self, other: LabelStats) -> LabelStats:
        return LabelStats(
            self.n_true + other.n_true, self.n_matched + other.n_matched, self.n_same + other.n_same
        )

    @property
    def accuracy(self) -> float:
        """``n_same / n_matched`` (NaN when nothing matched)."""
        return self.n_same / self.n_matched if self.n_matched else math.nan

    @property
    def detection(self) -> float:
        """``n_matched / n_true`` (NaN for no true corners)."""
        return self.n_matched / self.n_true if self.n_true else math.nan


def label_stats(measured: Wireframe, truth_scan: Wireframe, tol: float) -> LabelStats:
    """Compare the labels of a measured scan with those of the true scan (same frame).

    Each true corner is matched to its nearest measured corner if that lies within ``tol``
    metres (several true corners may match the same measured one).
    """
    if not tol > 0.0:
        raise ValueError(f"tol must be > 0, got {tol}")
    n = truth_scan.n_vertices
    if n == 0 or measured.n_vertices == 0:
        return LabelStats(n, 0, 0)
    dist, j = cKDTree(measured.points).query(truth_scan.points, k=1)
    hit = dist <= tol
    same = hit & (measured.labels[np.minimum(j, measured.n_vertices - 1)] == truth_scan.labels)
    return LabelStats(n, int(hit.sum()), int(same.sum()))


def label_accuracy(measured: Wireframe, truth_scan: Wireframe, tol: float) -> float:
    """Share of the true scan's corners, among those with a measured corner within ``tol``, whose
    nearest measured corner has the same label.

    Corners the sensor missed do not count here (see :attr:`LabelStats.detection`); NaN when no
    true corner is matched. To aggregate over scans, sum :func:`label_stats` instead.
    """
    return label_stats(measured, truth_scan, tol).accuracy
