"""The wireframe particle filter (paper Sec. III-B, Fig. 7, Sec. IV-B to IV-F).

Each particle is a candidate map, a :class:`~mapping.wireframe.Wireframe` in the world frame.
One :meth:`WireframeFilter.step` takes an odometry increment and a scan (robot frame) and

1. **predicts the pose** ``x_pred = x (+) odometry`` (Sec. IV-A);
2. **matches** the scan against the best particle's predicted scan at ``x_pred`` with the
   wireframe ICP (Sec. IV-C, :func:`mapping.icp.icp`) and, when the match is accepted,
   corrects the pose ``x = x_pred (+) correction``; otherwise keeps ``x_pred``;
3. for every distinct particle, **predicts the scan** at ``x`` (Sec. IV-B,
   :func:`mapping.visibility.visible_view`), computes ``log p(S | W_i)`` and the per-edge
   likelihoods (Sec. IV-D, :func:`mapping.likelihood.scan_likelihood`) and updates the weight
   ``w_i <- eta w_i p(S | W_i)``;
4. lowers the stored likelihood of every in-sight edge the scan contradicts (see below);
   edges in view that the prediction does not report (back-facing ones, paper Fig. 5) count
   as contradicted, in the weight and in the bookkeeping, when the scan saw through them
   (:func:`mapping.likelihood.seen_through`);
5. **resamples with mutation** (Sec. IV-F, :func:`mapping.resample.resample_with_mutation`);
6. **merges** the scan, placed at ``x``, into every resulting particle (Sec. IV-E,
   :func:`mapping.merge.merge`); scan edges carry their per-edge likelihoods into the merge.

Choices where the paper is silent or that differ from it
--------------------------------------------------------
* **One pose estimate**, not one per particle: odometry predicts it and ICP against the best
  particle corrects it. The scan is placed at that pose in every particle. A scalar pose
  uncertainty (grown by an odometry noise model, reset by an accepted match) sets the ICP
  prior and the largest correction accepted.
* **Edge likelihood bookkeeping.** A scan edge enters the map with its per-edge likelihood
  (Sec. IV-D: Gaussian factors of its two vertices times ``1 - p_fn`` when the particle
  predicted it, ``p_fp`` when it is new); merging combines it with the map edge as
  ``1 - (1 - L1)(1 - L2)`` (Sec. IV-E), so walls seen again climb above the keep threshold. A
  map edge in sight that the scan *contradicts* (it sees through it, see
  :mod:`mapping.likelihood`) and does not observe anywhere gets the Bayes update
  ``L <- L p_fn / (L p_fn + (1 - L)(1 - p_fp))``. This is how a wrong wall falls below the keep
  threshold "verified through multiple scans" (Sec. IV-F).
* **Static world.** A new scan edge that lies where a particle is sure there is free space
  (its prediction sees past it onto confirmed walls) is not merged into that particle
  (:attr:`FilterConfig.reject_in_free_space`): a false positive or a passer-by.
* Stored likelihoods are capped at :data:`MAX_LIKELIHOOD` before a contradiction update, so a
  wall merged often enough to round to 1.0 can still be taken down.
* **Copies.** Particles that the current scan cannot tell apart (the same predicted scan with
  the same in-sight likelihoods) count as copies of one particle at resampling: the first draw
  of the group is kept, every further draw is mutated (see :mod:`mapping.resample`).
* **Order.** Resampling with mutation runs *before* the merge (the paper merges first). The
  candidates for dropping are the in-sight edges below the keep threshold that the current scan
  does *not* observe: an edge the scan observes would be merged straight back. The outcome is
  the same; the cost is one merge per distinct particle instead of one per particle. "In
  sight" is the view's ``in_view``: within range and field of view, reported, hidden or
  back-facing (a wrong wall placed behind a real one can never be seen again, but it is in
  predicted sight; below the keep threshold it may be dropped).
* **Weights** are reset to uniform after resampling, which happens every step. The best
  particle is the highest-weight one of the step (its unmutated copy after resampling); among
  particles of equal weight, the one whose edge set is most plausible (:func:`edge_log_odds`).
* **Locality.** Prediction (:func:`mapping.visibility.visible_view`) and merging
  (:func:`mapping.merge.merge`) both cull the map to the edges near the robot with one
  vectorised bounding-box test before any Python-level work, so the time per step does not
  grow with the map.
* **Scan clean-up** before anything else: short frontier fragments and walls along a line of
  sight are dropped (:attr:`FilterConfig.min_fragment_length`,
  :attr:`FilterConfig.min_line_distance`).
* **Budgets.** A scan keeps at most ``max_scan_vertices`` vertices (longest walls first); a
  particle at most ``max_vertices`` (lowest-likelihood edges are dropped first).
* Distinct particles are found by object identity; unmutated copies share one object, and
  particles whose merge results are equal (same arrays) are made to share one, so the
  prediction, likelihood and merge of identical particles run once.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mapping.icp import ICPConfig, ICPResult, icp
from mapping.likelihood import (
    CONTRADICTED,
    OBSERVED,
    LikelihoodConfig,
    ScanLikelihood,
    in_known_free_space,
    scan_likelihood,
    seen_through,
)
from mapping.resample import resample_with_mutation
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["FilterConfig", "StepInfo", "WireframeFilter", "budget_map", "budget_scan", "contradiction_update", "drop_fragments", "drop_line_of_sight", "edge_log_odds", "particle_bytes"]


class ViewLike(Protocol):
    """What :func:`mapping.visibility.visible_view` returns (the attributes used here)."""

    @property
    def scan(self) -> Wireframe: ...

    @property
    def edge_source(self) -> Any: ...


ViewFn = Callable[[Wireframe, Pose, float, float], ViewLike]
MergeFn = Callable[[Wireframe, Wireframe, float], Wireframe]


@dataclass(frozen=True)
class FilterConfig:
    """Configuration of :class:`WireframeFilter`.

    Parameters
    ----------
    particles : int
        Number of particles ``M`` (default 10, as in the paper's small simulation).
    max_range : float
        Sensing range (metres) used for the predicted scan; match the sensor's.
    fov : float
        Field of view (radians, centred on the heading) of the predicted scan.
    merge_threshold : float
        Distance (metres) below which vertices are merged (Sec. IV-E; 0.2 m in the paper's
        small world, 0.4 m in the large one).
    keep_threshold : float
        Edges with likelihood at or above this are never dropped by mutation (Sec. IV-F).
    mutate : bool
        Mutate further copies at resampling (False with ``particles=1`` is the single-hypothesis
        baseline).
    use_icp : bool
        Correct the pose by ICP (False: dead reckoning).
    temperature : float
        Log-likelihoods are divided by this before the weight update (1: the paper's update).
    tie_tolerance : float
        Particles whose log-weight is within this of the best one are tied; the tie goes to
        the largest :func:`edge_log_odds` (the paper does not say how to pick among equals).
    reject_in_free_space : bool
        Do not merge into a particle the new scan edges (matched by none of its predicted
        edges) that lie where it is sure there is free space: its predicted scan sees past
        them onto walls at or above the keep threshold (the paper assumes a static world, so
        such an edge is a false positive or a passer-by; merging it could also swallow real
        walls, see the merge's collinear grouping). Walls behind that are themselves doubtful
        do not count, so a wall misplaced behind the true one (a scan-matching failure) does
        not lock the true one out.
    max_vertices : int
        Vertex budget of one particle.
    max_scan_vertices : int
        Vertex budget of one scan.
    min_fragment_length : float
        Scan edges shorter than this (metres) with a frontier end are dropped before anything
        else: a short piece of a wall glimpsed past an occluder has a direction dominated by
        corner noise (a 2 cm error on a 0.2 m piece tilts it by 11 degrees), so it would not
        merge into its wall and would linger as clutter. Complete short walls (no frontier end)
        are kept.
    min_line_distance : float
        Scan edges whose supporting line passes within this (metres) of the robot are dropped:
        a wall along a line of sight cannot be seen (a real scanner sees it edge-on), and an
        occlusion joined to its frontier by a corner extractor lies exactly on a line of sight
        (paper Sec. IV-A: such a pair is "colinear along the same line of sight").
    odometry_trans_per_m, odometry_rot_per_rad, odometry_rot_per_m : float
        Assumed odometry noise (std per metre driven, per radian turned, radians per metre).
        The pose's standard deviation grows by these while no scan match is accepted and
        shrinks back after one; the ICP prior and its largest accepted correction (three
        standard deviations, within the ICP config's own limits) follow it, so a scan step
        cannot "correct" the pose by more than the odometry can plausibly be off.
    likelihood : LikelihoodConfig
    icp : ICPConfig

    Raises
    ------
    ValueError
        On a value out of range.
    """

    particles: int = 10
    max_range: float = 8.0
    fov: float = 2.0 * math.pi
    merge_threshold: float = 0.2
    keep_threshold: float = 0.5
    mutate: bool = True
    use_icp: bool = True
    temperature: float = 1.0
    tie_tolerance: float = 1e-6
    max_vertices: int = 5000
    max_scan_vertices: int = 200
    min_fragment_length: float = 0.4
    min_line_distance: float = 0.15
    reject_in_free_space: bool = True
    odometry_trans_per_m: float = 0.05
    odometry_rot_per_rad: float = 0.05
    odometry_rot_per_m: float = 0.005
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)

    def __post_init__(self) -> None:
        if isinstance(self.particles, bool) or not isinstance(self.particles, (int, np.integer)) or self.particles < 1:
            raise ValueError(f"particles must be an integer >= 1, got {self.particles!r}")
        for name in ("max_range", "merge_threshold", "temperature"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in ("odometry_trans_per_m", "odometry_rot_per_rad", "odometry_rot_per_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {v!r}")
        if not (0 < self.fov <= 2 * math.pi + 1e-12):
            raise ValueError(f"fov must be in (0, 2 pi], got {self.fov!r}")
        if not (0.0 <= self.keep_threshold <= 1.0):
            raise ValueError(f"keep_threshold must be within [0, 1], got {self.keep_threshold!r}")
        if not (math.isfinite(self.min_line_distance) and self.min_line_distance >= 0):
            raise ValueError(f"min_line_distance must be >= 0, got {self.min_line_distance!r}")
        if not (math.isfinite(self.min_fragment_length) and self.min_fragment_length >= 0):
            raise ValueError(f"min_fragment_length must be >= 0, got {self.min_fragment_length!r}")
        if self.max_vertices < 3 or self.max_scan_vertices < 2:
            raise ValueError("max_vertices must be >= 3 and max_scan_vertices >= 2")


@dataclass(frozen=True)
class StepInfo:
    """What one :meth:`WireframeFilter.step` did.

    Attributes
    ----------
    step : int
        1-based index of the step.
    pose, predicted_pose : Pose
        The corrected pose estimate and the odometry prediction.
    icp : ICPResult or None
        The scan match (None when there was nothing to match against).
    log_likelihoods : (M,) float64
        ``log p(S | W_i)`` of each particle before resampling.
    best : int
        Index of the best particle after resampling.
    distinct : int
        Number of distinct particle objects after the step.
    mutated : int
        Number of mutated copies made at resampling.
    """

    step: int
    pose: Pose
    predicted_pose: Pose
    icp: ICPResult | None
    log_likelihoods: FloatArray
    best: int
    distinct: int
    mutated: int


# ------------------------------------------------------------------------------ pure helpers
def drop_fragments(scan: Wireframe, min_length: float) -> Wireframe:
    """Drop scan edges shorter than ``min_length`` that have a frontier end (see
    :attr:`FilterConfig.min_fragment_length`)."""
    if scan.n_edges == 0 or min_length <= 0:
        return scan
    fr = scan.labels[scan.edges] == Label.FRONTIER
    bad = (scan.edge_lengths() < min_length) & fr.any(axis=1)
    return scan.subgraph_edges(~bad) if bad.any() else scan


def drop_line_of_sight(scan: Wireframe, min_distance: float) -> Wireframe:
    """Drop scan edges (robot frame) whose supporting line passes within ``min_distance`` of the
    robot at the origin (see :attr:`FilterConfig.min_line_distance`)."""
    if scan.n_edges == 0 or min_distance <= 0:
        return scan
    s = scan.segments()
    d = s[:, 1] - s[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    cross = np.abs(s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0])
    bad = cross < min_distance * np.maximum(length, 1e-12)
    return scan.subgraph_edges(~bad) if bad.any() else scan


def budget_scan(scan: Wireframe, max_vertices: int) -> Wireframe:
    """Keep whole walls, longest first, while the scan has at most ``max_vertices`` vertices."""
    if scan.n_vertices <= max_vertices:
        return scan
    order = np.argsort(-scan.edge_lengths(), kind="stable")
    used = np.zeros(scan.n_vertices, dtype=bool)
    keep = np.zeros(scan.n_edges, dtype=bool)
    count = 0
    for e in order.tolist():
        a, b = (int(v) for v in scan.edges[e])
        extra = int(not used[a]) + int(not used[b])
        if count + extra > max_vertices:
            continue
        used[a] = used[b] = True
        count += extra
        keep[e] = True
    return scan.subgraph_edges(keep)


def budget_map(wf: Wireframe, max_vertices: int) -> Wireframe:
    """Drop the lowest-likelihood edges until ``wf`` has at most ``max_vertices`` vertices."""
    while wf.n_vertices > max_vertices and wf.n_edges:
        excess = wf.n_vertices - max_vertices
        order = np.argsort(wf.likelihood, kind="stable")
        keep = np.ones(wf.n_edges, dtype=bool)
        keep[order[: max(1, excess // 2)]] = False
        wf = wf.subgraph_edges(keep)
    return wf


def edge_log_odds(wf: Wireframe, floor: float = 1e-3) -> float:
    """``sum_e log(L_e / (1 - L_e))`` over the edges of ``wf`` (likelihoods clipped to
    ``[floor, 1 - floor]``): how plausible its edge set is under independent edge likelihoods.
    Adding an edge with likelihood below 1/2 lowers it."""
    if wf.n_edges == 0:
        return 0.0
    L = np.clip(wf.likelihood, floor, 1.0 - floor)
    return float(np.sum(np.log(L) - np.log1p(-L)))


# Pose standard deviation right after an accepted scan match (metres, radians).
_SIGMA_XY_MIN = 0.03
_SIGMA_TH_MIN = 0.01

#: Edge likelihoods are capped here before a contradiction update: merging combines them as
#: ``1 - (1 - L1)(1 - L2)``, which rounds to exactly 1.0 after a few dozen sightings, and a
#: likelihood of exactly 1 could never be lowered again. At 0.999, four contradicting scans
#: take a wall below a keep threshold of 0.5.
MAX_LIKELIHOOD = 0.999


def contradiction_update(likelihood: FloatArray, p_fp: float, p_fn: float) -> FloatArray:
    """Bayes update of an edge's existence likelihood after a scan that saw through it:
    ``L p_fn / (L p_fn + (1 - L)(1 - p_fp))``, with ``L`` first capped at
    :data:`MAX_LIKELIHOOD`."""
    L = np.minimum(np.asarray(likelihood, dtype=np.float64), MAX_LIKELIHOOD)
    num = L * p_fn
    den = num + (1.0 - L) * (1.0 - p_fp)
    return np.asarray(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), dtype=np.float64)


def _edge_states(n_edges: int, edge_source: IntArray, state: NDArray[np.int8]) -> tuple[BoolArray, BoolArray, BoolArray]:
    """Per source edge: in sight, observed (any piece), contradicted (some piece, none observed)."""
    in_sight = np.zeros(n_edges, dtype=bool)
    observed = np.zeros(n_edges, dtype=bool)
    contra = np.zeros(n_edges, dtype=bool)
    src = np.asarray(edge_source, dtype=np.int64)
    ok = src >= 0
    in_sight[src[ok]] = True
    observed[src[ok & (state == OBSERVED)]] = True
    contra[src[ok & (state == CONTRADICTED)]] = True
    return in_sight, observed, contra & ~observed


def _default_view(wf: Wireframe, pose: Pose, max_range: float, fov: float) -> ViewLike:
    from mapping.visibility import visible_view

    return visible_view(wf, pose, max_range, fov)


def _default_merge(base: Wireframe, new: Wireframe, threshold: float) -> Wireframe:
    from mapping.merge import MergeConfig, merge

    return merge(base, new, MergeConfig(threshold=threshold))


# ------------------------------------------------------------------------------ the filter
@dataclass
class _Eval:
    """Per distinct particle: its prediction, likelihood and likelihood-updated map."""

    lik: ScanLikelihood
    updated: Wireframe
    in_sight: BoolArray
    candidates_mask: BoolArray
    scan_edge_likelihood: FloatArray
    group: bytes
    merge_mask: BoolArray


class WireframeFilter:
    """The wireframe particle filter (paper Fig. 7).

    Parameters
    ----------
    config : FilterConfig
    rng : numpy.random.Generator
        The only source of randomness (resampling and mutation).
    initial_pose : Pose, optional
        The robot's pose at the first scan (identity by default: the map frame is the frame of
        the first pose).
    view_fn, merge_fn : callable, optional
        Replace the predicted-scan and merge steps (tests); default
        :func:`mapping.visibility.visible_view` and :func:`mapping.merge.merge`.
    """

    def __init__(
        self,
        config: FilterConfig,
        rng: np.random.Generator,
        initial_pose: Pose | None = None,
        view_fn: ViewFn | None = None,
        merge_fn: MergeFn | None = None,
    ) -> None:
        if not isinstance(config, FilterConfig):
            raise ValueError("config must be a FilterConfig")
        self.config = config
        self.rng = rng
        self._pose = initial_pose or Pose.identity()
        empty = Wireframe.empty()
        self._particles: list[Wireframe] = [empty] * config.particles
        self._weights = np.full(config.particles, 1.0 / config.particles)
        self._best = 0
        self._steps = 0
        self._sigma_xy = _SIGMA_XY_MIN
        self._sigma_th = _SIGMA_TH_MIN
        self._view_fn: ViewFn = view_fn or _default_view
        self._merge_fn: MergeFn = merge_fn or _default_merge

    # ------------------------------------------------------------------ state
    @property
    def pose(self) -> Pose:
        """The current pose estimate (map frame)."""
        return self._pose

    @property
    def particles(self) -> tuple[Wireframe, ...]:
        return tuple(self._particles)

    @property
    def weights(self) -> FloatArray:
        w = self._weights.copy()
        w.setflags(write=False)
        return w

    @property
    def best_index(self) -> int:
        return self._best

    @property
    def best(self) -> Wireframe:
        """The best particle's map."""
        return self._particles[self._best]

    @property
    def steps(self) -> int:
        return self._steps

    def memory_bytes(self) -> int:
        """Particle-set storage by the paper's accounting (Sec. IV-G), every particle counted."""
        return sum(p.paper_storage_bytes() for p in self._particles)

    def distinct_particles(self) -> int:
        return len({id(p) for p in self._particles})

    # ------------------------------------------------------------------ helpers
    def predicted_view(self, wf: Wireframe, pose: Pose) -> tuple[Wireframe, IntArray, BoolArray]:
        """The predicted scan of ``wf`` at ``pose`` (robot frame, Sec. IV-B), the index of the
        source edge in ``wf`` of each of its edges, and which edges of ``wf`` are in view but
        not reported (hidden or back-facing). The view function culls the edges out of range
        itself (vectorised), so the sweep only sees the edges near the robot."""
        cfg = self.config
        if wf.n_edges == 0:
            return Wireframe.empty(), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
        view = self._view_fn(wf, pose, cfg.max_range, cfg.fov)
        src = np.asarray(view.edge_source, dtype=np.int64).reshape(-1)
        in_view = getattr(view, "in_view", None)
        visible = getattr(view, "visible", None)
        if in_view is None or visible is None:
            unreported = np.zeros(wf.n_edges, dtype=bool)
        else:
            unreported = np.asarray(in_view, dtype=bool) & ~np.asarray(visible, dtype=bool)
        return view.scan, src, unreported

    # ------------------------------------------------------------------ the step
    def step(self, odometry: Pose, scan: Wireframe, *, fault: Pose | None = None) -> StepInfo:
        """One filter iteration (paper Fig. 7).

        Parameters
        ----------
        odometry : Pose
            Motion since the previous scan, in the previous robot frame.
        scan : Wireframe
            The scan in the robot frame (vertices counterclockwise, labelled).
        fault : Pose, optional
            Fault injection (paper Fig. 8): place this scan at ``pose (+) fault`` instead of the
            estimated pose for this step's likelihood and merge, as a scan-matching failure
            would. The pose estimate itself is not changed.

        Returns
        -------
        StepInfo
        """
        cfg = self.config
        self._steps += 1
        scan = drop_line_of_sight(drop_fragments(scan, cfg.min_fragment_length), cfg.min_line_distance)
        scan = budget_scan(scan, cfg.max_scan_vertices)
        predicted = self._pose.compose(odometry)
        pose = predicted
        icp_res: ICPResult | None = None
        best = self._particles[self._best]
        d = math.hypot(odometry.x, odometry.y)
        self._sigma_xy = math.hypot(self._sigma_xy, cfg.odometry_trans_per_m * d)
        self._sigma_th = math.hypot(
            self._sigma_th, cfg.odometry_rot_per_rad * abs(odometry.theta) + cfg.odometry_rot_per_m * d
        )
        if cfg.use_icp and best.n_edges and scan.n_edges:
            ref, _, _ = self.predicted_view(best, predicted)
            if ref.n_vertices:
                icfg = dataclasses.replace(
                    cfg.icp,
                    prior_sigma_xy=min(cfg.icp.prior_sigma_xy, max(self._sigma_xy, _SIGMA_XY_MIN)),
                    prior_sigma_theta=min(cfg.icp.prior_sigma_theta, max(self._sigma_th, _SIGMA_TH_MIN)),
                    max_translation=min(cfg.icp.max_translation, max(3.0 * self._sigma_xy, 0.15)),
                    max_rotation=min(cfg.icp.max_rotation, max(3.0 * self._sigma_th, 0.05)),
                )
                icp_res = icp(scan, ref, icfg)
                if icp_res.accepted:
                    pose = predicted.compose(icp_res.correction)
                    self._sigma_xy = _SIGMA_XY_MIN
                    self._sigma_th = _SIGMA_TH_MIN
        self._pose = pose
        place = pose if fault is None else pose.compose(fault)

        lcfg = cfg.likelihood
        evals: dict[int, _Eval] = {}
        for p in self._particles:
            if id(p) in evals:
                continue
            view, src, unreported = self.predicted_view(p, place)
            lik = scan_likelihood(scan, view, lcfg)
            in_sight, observed, contra = _edge_states(p.n_edges, src, lik.predicted_edge_state)
            # Edges in view that the prediction does not report (back-facing, or hidden behind
            # another map edge): contradicted when the scan saw through them.
            through = np.zeros(p.n_edges, dtype=bool)
            cand_hidden = np.flatnonzero(unreported & ~observed)
            if len(cand_hidden) and scan.n_edges:
                segs = place.apply_inverse(p.points[p.edges[cand_hidden]].reshape(-1, 2)).reshape(-1, 2, 2)
                through[cand_hidden] = seen_through(scan, segs, lcfg.occlusion_margin, cfg.max_range)
            if through.any():
                contra |= through
                in_sight |= through
                lik = dataclasses.replace(
                    lik,
                    log_likelihood=lik.log_likelihood + math.log(lcfg.p_fn) * int(through.sum()),
                    edge_log=lik.edge_log + math.log(lcfg.p_fn) * int(through.sum()),
                )
            updated = p
            if contra.any():
                L = p.likelihood.copy()
                L[contra] = contradiction_update(L[contra], lcfg.p_fp, lcfg.p_fn)
                updated = p.replace(likelihood=L)
            group = b"".join(
                (
                    np.round(view.points, 6).tobytes(),
                    view.edges.tobytes(),
                    view.labels.tobytes(),
                    np.round(updated.likelihood[src[src >= 0]], 6).tobytes(),
                    np.round(p.points[p.edges[through]], 6).tobytes(),
                )
            )
            # New scan edges where this particle is sure there is free space are not merged into
            # it (static world: a false positive or a passer-by).
            merge_mask = np.ones(scan.n_edges, dtype=bool)
            if cfg.reject_in_free_space and scan.n_edges and view.n_edges:
                unm = np.flatnonzero(~lik.scan_edge_matched)
                if len(unm):
                    free = in_known_free_space(
                        view, scan.segments()[unm], lcfg.occlusion_margin, cfg.keep_threshold
                    )
                    merge_mask[unm[free]] = False
            # Candidates for mutation (Sec. IV-F, "within sight (or predicted sight)"): every edge
            # in view, reported or not, that this scan does not observe.
            cands = (in_sight | unreported) & ~observed
            evals[id(p)] = _Eval(lik, updated, in_sight, cands, lik.scan_edge_likelihood, group, merge_mask)

        loglik = np.array([evals[id(p)].lik.log_likelihood for p in self._particles])
        logw = np.log(np.maximum(self._weights, 1e-300)) + loglik / cfg.temperature
        logw -= logw.max()
        w = np.exp(logw)
        w /= w.sum()
        # The best particle: the highest weight; ties (common: particles that differ only in
        # edges this scan says nothing about) go to the most plausible edge set.
        tied = np.flatnonzero(logw >= -cfg.tie_tolerance)
        if len(tied) > 1:
            score = np.array([edge_log_odds(evals[id(self._particles[i])].updated) for i in tied.tolist()])
            best_parent = int(tied[int(np.argmax(score))])
        else:
            best_parent = int(np.argmax(w))

        updated_list = [evals[id(p)].updated for p in self._particles]
        sight_list = [evals[id(p)].candidates_mask for p in self._particles]
        groups = [evals[id(p)].group for p in self._particles]
        res = resample_with_mutation(
            updated_list, w, sight_list, cfg.keep_threshold, self.rng, cfg.mutate, groups=groups
        )

        # Merge the scan into every distinct resulting particle (identical ones share the result).
        merged: dict[tuple[int, int], Wireframe] = {}
        by_content: dict[bytes, Wireframe] = {}
        new: list[Wireframe] = []
        for k, q in enumerate(res.particles):
            parent = self._particles[int(res.indexes[k])]
            key = (id(q), id(parent))
            if key not in merged:
                ev = evals[id(parent)]
                scan_world = scan.replace(likelihood=ev.scan_edge_likelihood).transformed(place)
                if not ev.merge_mask.all():
                    scan_world = scan_world.subgraph_edges(ev.merge_mask)
                m = budget_map(self._merge_fn(q, scan_world, cfg.merge_threshold), cfg.max_vertices)
                # Particles that came out equal share one object (their next steps run once).
                merged[key] = by_content.setdefault(_content_key(m), m)
            new.append(merged[key])
        best_obj = updated_list[best_parent]
        self._best = next(
            (k for k, q in enumerate(res.particles) if q is best_obj and not res.mutated[k]),
            int(np.flatnonzero(res.indexes == best_parent)[0]) if np.any(res.indexes == best_parent) else 0,
        )
        self._particles = new
        self._weights = np.full(len(new), 1.0 / len(new))
        return StepInfo(
            step=self._steps,
            pose=pose,
            predicted_pose=predicted,
            icp=icp_res,
            log_likelihoods=loglik,
            best=self._best,
            distinct=self.distinct_particles(),
            mutated=int(res.mutated.sum()),
        )


def _content_key(wf: Wireframe) -> bytes:
    return b"".join(
        (wf.points.tobytes(), wf.labels.tobytes(), wf.edges.tobytes(), wf.likelihood.tobytes(), wf.sources.tobytes())
    )


def particle_bytes(particles: Sequence[Wireframe]) -> int:
    """``sum(p.paper_storage_bytes() for p in particles)`` (paper Sec. IV-G)."""
    return sum(p.paper_storage_bytes() for p in particles)
