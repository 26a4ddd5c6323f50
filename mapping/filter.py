"""The wireframe particle filter (paper Sec. III-B, Fig. 7, Sec. IV-B to IV-F).

Each particle is a candidate map, a :class:`~mapping.wireframe.Wireframe` in the world frame.
One :meth:`WireframeFilter.step` takes an odometry increment and a scan (robot frame), cleans
the scan up (:mod:`mapping.scan_cleanup`) and runs these phases, each a method:

1. **predict** the pose ``x_pred = x (+) odometry`` and its covariance (Sec. IV-A,
   :meth:`WireframeFilter._predict`);
2. **match** the scan against the best particle's predicted scan at ``x_pred`` with the
   wireframe ICP (Sec. IV-C, :func:`mapping.icp.icp`) and, when the match is accepted,
   correct the pose ``x = x_pred (+) correction``; otherwise keep ``x_pred``
   (:meth:`WireframeFilter._match_scan`);
3. fuse the wall-direction **compass** (:mod:`mapping.compass`,
   :meth:`WireframeFilter._fuse_compass`);
4. for every distinct particle, **predict the scan** at ``x`` (Sec. IV-B,
   :func:`mapping.visibility.visible_view`), compute ``log p(S | W_i)`` and the per-edge
   likelihoods (Sec. IV-D, :func:`mapping.likelihood.scan_likelihood`) and lower the stored
   likelihood of every in-sight edge the scan contradicts (:mod:`mapping.evidence`); edges in
   view that the prediction does not report (back-facing ones, paper Fig. 5) count as
   contradicted, in the weight and in the bookkeeping, when the scan saw through them
   (:meth:`WireframeFilter._evaluate`);
5. **reweight** ``w_i <- eta w_i p(S | W_i)`` (:meth:`WireframeFilter._reweight`);
6. **resample with mutation** (Sec. IV-F, :func:`mapping.resample.resample_with_mutation`,
   :meth:`WireframeFilter._resample`);
7. **merge** the scan, placed at ``x``, into every resulting particle (Sec. IV-E,
   :func:`mapping.merge.merge`); scan edges carry their per-edge likelihoods into the merge
   (:meth:`WireframeFilter._merge_scan`);
8. **close loops** (:mod:`mapping.loops`, :meth:`WireframeFilter._loop_closure`).

The configuration (:class:`FilterConfig`) groups its settings by concern, each group next to
the code it tunes; the measurements behind the defaults are in docs/experiments.md.

Choices where the paper is silent or that differ from it
--------------------------------------------------------
* **One pose estimate**, not one per particle: odometry predicts it and ICP against the best
  particle corrects it. The scan is placed at that pose in every particle. The pose carries a
  full 3 x 3 covariance of its error in the robot frame (an extended Kalman filter on SE(2)
  relative to the map): the odometry noise model grows it (:meth:`WireframeFilter.predict_covariance`),
  it is the ICP's prior (:func:`mapping.icp.icp`: the scan corrects only the directions it
  constrains better than the odometry, within a Mahalanobis gate), and an accepted match
  replaces it by the ICP's posterior covariance, floored at :attr:`OdometryConfig.pose_floor_xy`
  and :attr:`OdometryConfig.pose_floor_theta` (the map itself is not more accurate than that).
  The ICP's first correspondence gate follows it too (three standard deviations, the rotation
  taken at half the range, within the ICP config's ``gate_end``..``gate_start``).
* **Re-anchoring.** That covariance is the pose's uncertainty relative to the map *around it*,
  which the robot has just built. A part of the map built long ago can be off from it by the
  drift accumulated in between, more than the gate allows; a rejected match is therefore tried
  once more with the drift (:attr:`GatingConfig.drift_xy`, :attr:`GatingConfig.drift_theta`,
  growing with the square root of the distance driven) added to the prior, and accepted only if
  it constrains all three directions with half the usual residual. The pose then rejoins the
  older map instead of building a second copy beside it (the map's own drift stays: no past
  scan is moved).
* **Gating the map.** A scan that cannot be placed does not touch the map: when a map is in
  view and, after matching, the heading is uncertain by more than
  :attr:`GatingConfig.max_sigma_theta` (a sharp turn the scan could not fix), or the match
  failed while the position is uncertain by more than :attr:`GatingConfig.max_sigma_xy`
  (lost track), the step only predicts (``StepInfo.mapped`` is False). Nor, with
  :attr:`GatingConfig.update_distance` / :attr:`GatingConfig.update_angle` set, does a scan
  taken before the robot has driven or turned that much since the last one that did
  (GMapping's ``linearUpdate`` / ``angularUpdate``): no match, no likelihood, no merge.
* **Frontiers continue established walls** (:func:`mapping.snapping.snap_frontiers`): before
  the merge, a scan frontier that extends a longer map wall is moved onto that wall's line; a
  wall growing at its frontier would otherwise follow the pose's error and the pose would
  follow the wall.
* **Walls continue across doorways** (:func:`mapping.snapping.snap_collinear`): a new scan
  wall in the line of an established map wall, past its end, is put onto that line; door by
  door a corridor would otherwise bend by the pose's heading error at each new wall.
* **Corners are averaged** (:mod:`mapping.refine`): a scan whose match fixed the whole pose
  moves every map corner it observes to the running mean of its observations, until the corner
  has had ``refine.max_count`` of them, before the merge (the merge itself
  keeps the map's position); otherwise the first sighting's pose error stays in the corner for
  good and the pose inherits it.
* **Carving** (:func:`mapping.evidence.seen_through_spans`, :func:`mapping.evidence.carve`):
  stretches of a map wall that a scan saw through while it saw the rest of the wall are cut
  out (a false-positive edge that the merge joined to a real collinear wall cannot be removed
  by mutation, whose unit is the edge).
* **Evidence and merge scans.** Likelihoods and contradictions use the whole scan (short
  frontier fragments included: a fragment is evidence that the wall is there, and dropping it
  would make the wall look seen through); ICP and the merge use the scan without them.
* **Edge likelihood bookkeeping.** A scan edge enters the map with its per-edge likelihood
  (Sec. IV-D: Gaussian factors of its two vertices times ``1 - p_fn`` when the particle
  predicted it, ``p_fp`` when it is new); merging combines it with the map edge as
  ``1 - (1 - L1)(1 - L2)`` (Sec. IV-E), so walls seen again climb above the keep threshold. A
  map edge in sight that the scan *contradicts* (it sees through it, see
  :mod:`mapping.likelihood`) and does not observe anywhere gets the Bayes update
  ``L <- L p_fn / (L p_fn + (1 - L)(1 - p_fp))``, in proportion to the part of the edge in
  view (``evidence.partial_contradiction``). This is how a wrong wall falls below the
  keep threshold "verified through multiple scans" (Sec. IV-F).
* **Wall-direction compass** (:mod:`mapping.compass`, :class:`mapping.compass.CompassConfig`): while the
  match leaves the heading uncertain, the directions of the scan's long walls against the
  building's wall directions (learnt from the first metres driven, then frozen) are fused as a
  heading measurement; the loop closer keeps them as heading factors on its keyframes. While
  the match pins the heading against a map young enough to carry the current drift, the
  measurement still pulls, at a twentieth of its weight (``compass.young_weight``).
* **Static world.** A new scan edge that lies where a particle is sure there is free space
  (its prediction sees past it onto confirmed walls) is not merged into that particle
  (``evidence.reject_in_free_space``): a false positive or a passer-by.
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
  particles of equal weight, the one whose edge set is most plausible
  (:func:`mapping.evidence.edge_log_odds`).
* **Locality.** Prediction (:func:`mapping.visibility.visible_view`) and merging
  (:func:`mapping.merge.merge`) both cull the map to the edges near the robot with one
  vectorised bounding-box test before any Python-level work, so the time per step does not
  grow with the map.
* **Scan clean-up** before anything else: edges that close a gap between two walls' loose
  ends (frontier or occlusion vertices) are dropped (``cleanup.drop_gap_bridges``),
  so are walls along a line of sight (``cleanup.min_line_distance``); short frontier fragments
  (``cleanup.min_fragment_length``) are kept as evidence only (above;
  :mod:`mapping.scan_cleanup`).
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

from mapping.compass import CompassConfig, Directions, Heading, compass_heading, wall_directions
from mapping.config import check_number
from mapping.evidence import (
    EvidenceConfig,
    carve,
    contradiction_update,
    edge_log_odds,
    edge_states,
    seen_fraction,
    seen_through_spans,
)
from mapping.icp import ICPConfig, ICPResult, icp
from mapping.likelihood import (
    LikelihoodConfig,
    ScanLikelihood,
    in_known_free_space,
    scan_likelihood,
    seen_through,
)
from mapping.loops import Closure, LoopCloser, LoopConfig
from mapping.refine import RefineConfig, refine_corners
from mapping.resample import ResampleResult, resample_with_mutation
from mapping.scan_cleanup import CleanScan, CleanupConfig, clean_scan
from mapping.scan_match import PointMatchConfig, refine_match
from mapping.se2 import Pose
from mapping.snapping import SnappingConfig, snap_collinear, snap_frontiers
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["FilterConfig", "GatingConfig", "OdometryConfig", "StepInfo", "WireframeFilter", "budget_map",
           "particle_bytes"]


class ViewLike(Protocol):
    """What :func:`mapping.visibility.visible_view` returns (the attributes used here)."""

    @property
    def scan(self) -> Wireframe: ...

    @property
    def edge_source(self) -> Any: ...


ViewFn = Callable[[Wireframe, Pose, float, float], ViewLike]
MergeFn = Callable[[Wireframe, Wireframe, float], Wireframe]


@dataclass(frozen=True)
class OdometryConfig:
    """The odometry noise model and the pose's least uncertainty (``odometry.*`` settings).

    The pose covariance grows by the noise while no match is accepted
    (:meth:`WireframeFilter.predict_covariance`); it is the ICP's prior, so a scan cannot move
    the pose further than the odometry can plausibly be off.

    Parameters
    ----------
    trans_per_m : float
        Translation noise std per metre driven, on each axis (0.03: 1.5 times the simulator's
        :class:`agents.sim.motion.OdometryNoise`; a filter should not trust its odometry more
        than it deserves).
    rot_per_rad : float
        Heading noise std per radian turned (0.03, likewise 1.5 times the simulator's).
    rot_per_m : float
        Heading noise std (radians) per metre driven (0.003, likewise).
    pose_floor_xy, pose_floor_theta : float
        Least std (metres, radians) of the pose after an accepted match (0.01 m, 0.002 rad): the
        map's own corners are that uncertain.

    Raises
    ------
    ValueError
        On a negative or non-finite value.
    """

    trans_per_m: float = 0.03
    rot_per_rad: float = 0.03
    rot_per_m: float = 0.003
    pose_floor_xy: float = 0.01
    pose_floor_theta: float = 0.002

    def __post_init__(self) -> None:
        for name in ("trans_per_m", "rot_per_rad", "rot_per_m", "pose_floor_xy", "pose_floor_theta"):
            check_number(name, getattr(self, name), 0.0)


@dataclass(frozen=True)
class GatingConfig:
    """When a scan may touch the map, and re-anchoring to an older map (``gating.*`` settings).

    Parameters
    ----------
    max_sigma_theta : float
        A scan whose heading std after matching exceeds this (radians; 1 degree) does not touch
        the map when a map was in view: after a sharp turn it would be written in rotated.
    max_sigma_xy : float
        Nor does a scan whose match was rejected while the position std exceeds this (metres;
        0.5): the robot has lost track and would duplicate walls beside themselves.
    reanchor : bool
        Retry a rejected match with the map's drift added to the prior, accepting it only fully
        constrained at half the usual residual: otherwise the pose never rejoins an older map.
    drift_xy, drift_theta : float
        The map's drift relative to itself per square-root metre driven (0.02 m, 0.0008 rad:
        0.5 m and 1 degree after 500 m).
    anchored_evidence : bool
        Lower no likelihood and carve nothing from a scan whose match with the map in view was
        rejected: its pose is the odometry's, and a wall that looks seen through may only be
        misplaced relative to it.
    update_distance, update_angle : float
        A scan touches the map only once the robot has driven ``update_distance`` metres or
        turned ``update_angle`` radians (sums of the odometry's increments) since the last scan
        that did -- GMapping's ``linearUpdate`` / ``angularUpdate``; the first scan always does.
        The steps in between only predict the pose. 0 and 0 (the defaults): every scan.

    Raises
    ------
    ValueError
        On a negative (or, for the sigmas, zero) value.
    """

    max_sigma_theta: float = math.radians(1.0)
    max_sigma_xy: float = 0.5
    reanchor: bool = True
    drift_xy: float = 0.02
    drift_theta: float = 0.0008
    anchored_evidence: bool = True
    update_distance: float = 0.0
    update_angle: float = 0.0

    def __post_init__(self) -> None:
        for name in ("max_sigma_theta", "max_sigma_xy"):
            check_number(name, getattr(self, name), 0.0, open_low=True)
        for name in ("drift_xy", "drift_theta", "update_distance", "update_angle"):
            check_number(name, getattr(self, name), 0.0)


@dataclass(frozen=True)
class FilterConfig:
    """Configuration of :class:`WireframeFilter`: the paper's parameters, then groups by concern.

    Each setting has a dotted name (``compass.young_weight``; :func:`mapping.config.config_items`,
    :func:`mapping.config.with_overrides`). The measurements behind the defaults are in
    docs/experiments.md, each with the command that reproduces it.

    Parameters
    ----------
    particles : int
        Number of particles ``M`` (10, as in the paper's small simulation).
    max_range : float
        Sensing range (metres) of the predicted scan; the sensor's.
    fov : float
        Field of view (radians, centred on the heading) of the predicted scan; the sensor's.
    merge_threshold : float
        Distance (metres) below which vertices merge (Sec. IV-E: 0.2 m in the paper's small
        world, 0.4 m in the large one).
    keep_threshold : float
        Edges at or above this likelihood are never dropped by mutation (Sec. IV-F; 0.5).
    mutate : bool
        Mutate further copies at resampling (False with one particle: the single-hypothesis
        baseline).
    use_icp : bool
        Correct the pose by ICP (False: dead reckoning).
    temperature : float
        Log-likelihoods are divided by this before the weight update (1: the paper's update).
    tie_tolerance : float
        Log-weights within this of the best are tied; the tie goes to the largest
        :func:`mapping.evidence.edge_log_odds` (the paper does not say how to pick).
    max_vertices : int
        Vertex budget of one particle (5000: bounds memory and time; never reached in the test
        worlds).
    max_scan_vertices : int
        Vertex budget of one scan (200, longest walls kept first).
    odometry : OdometryConfig
        Odometry noise and pose floors.
    gating : GatingConfig
        When a scan may touch the map; re-anchoring.
    cleanup : mapping.scan_cleanup.CleanupConfig
        What a scan loses before use.
    snapping : mapping.snapping.SnappingConfig
        Snapping scan walls onto established ones before the merge.
    compass : mapping.compass.CompassConfig
        The wall-direction heading measurement.
    evidence : mapping.evidence.EvidenceConfig
        Contradictions, carving, free-space rejection.
    refine : mapping.refine.RefineConfig
        Corner refinement.
    likelihood : mapping.likelihood.LikelihoodConfig
        The scan likelihood (Sec. IV-D).
    icp : mapping.icp.ICPConfig
        The scan matcher (Sec. IV-C).
    loops : mapping.loops.LoopConfig
        Loop closure (not in the paper; ``enabled=False`` is the paper's filter).
    point_match : mapping.scan_match.PointMatchConfig
        Real lidar (not in the paper): with ``enabled`` and a step given the scan's raw points,
        every point is matched against the walls in view (:meth:`WireframeFilter._match_points`).
        Off by default (the simulator's corner sensor has no points).

    Raises
    ------
    ValueError
        On a value out of range (the message names the field).
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
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    gating: GatingConfig = field(default_factory=GatingConfig)
    cleanup: CleanupConfig = field(default_factory=CleanupConfig)
    snapping: SnappingConfig = field(default_factory=SnappingConfig)
    compass: CompassConfig = field(default_factory=CompassConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)
    point_match: PointMatchConfig = field(default_factory=PointMatchConfig)

    def __post_init__(self) -> None:
        check_number("particles", self.particles, 1, integer=True)
        for name in ("max_range", "merge_threshold", "temperature"):
            check_number(name, getattr(self, name), 0.0, open_low=True)
        check_number("fov", self.fov, 0.0, 2 * math.pi + 1e-12, open_low=True)
        check_number("keep_threshold", self.keep_threshold, 0.0, 1.0)
        check_number("tie_tolerance", self.tie_tolerance, 0.0)
        check_number("max_vertices", self.max_vertices, 3, integer=True)
        check_number("max_scan_vertices", self.max_scan_vertices, 2, integer=True)
        groups = {"odometry": OdometryConfig, "gating": GatingConfig, "cleanup": CleanupConfig,
                  "snapping": SnappingConfig, "compass": CompassConfig, "evidence": EvidenceConfig,
                  "refine": RefineConfig, "likelihood": LikelihoodConfig, "icp": ICPConfig,
                  "loops": LoopConfig, "point_match": PointMatchConfig}
        for name, kind in groups.items():
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")


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
    mapped : bool
        Whether the scan updated the particles (False when its pose was too uncertain, see
        :class:`GatingConfig`).
    loop : Closure or None
        The loop closure this step made (:mod:`mapping.loops`; ``pose`` is then the pose after it).
    compass : Heading or None
        The wall-direction heading measurement fused this step (:mod:`mapping.compass`).
    """

    step: int
    pose: Pose
    predicted_pose: Pose
    icp: ICPResult | None
    log_likelihoods: FloatArray
    best: int
    distinct: int
    mutated: int
    mapped: bool = True
    loop: Closure | None = None
    compass: Heading | None = None


# ------------------------------------------------------------------------------ pure helpers
def budget_map(wf: Wireframe, max_vertices: int) -> Wireframe:
    """Drop the lowest-likelihood edges until ``wf`` has at most ``max_vertices`` vertices."""
    while wf.n_vertices > max_vertices and wf.n_edges:
        excess = wf.n_vertices - max_vertices
        order = np.argsort(wf.likelihood, kind="stable")
        keep = np.ones(wf.n_edges, dtype=bool)
        keep[order[: max(1, excess // 2)]] = False
        wf = wf.subgraph_edges(keep)
    return wf




def _default_view(wf: Wireframe, pose: Pose, max_range: float, fov: float) -> ViewLike:
    from mapping.visibility import visible_view

    return visible_view(wf, pose, max_range, fov)


class _CachedMerge:
    """The default merge (:func:`mapping.merge.merge`) with two caches, cleared at every step
    (:meth:`clear`), the same results as without them.

    * Whole merges by the content of their inputs (:meth:`Wireframe.content_digest` of the
      base and of the scan, and the threshold): a merge is a pure function of them, and about
      40 % of a step's merges on the real logs repeat one already made (particles whose maps
      and scan likelihoods came out byte for byte equal, as different objects).
    * A :class:`mapping.merge.MergeCache`: the particles a scan is merged into often have the
      same part near it (they differ where old mutations dropped edges), and the merge's work
      on that part is then done once per step.
    """

    def __init__(self) -> None:
        from mapping.merge import MergeCache

        self.cache = MergeCache()
        self.results: dict[tuple[bytes, bytes, float], Wireframe] = {}

    def clear(self) -> None:
        """Forget everything (keyed by content: only the same step's scan can hit)."""
        self.cache.clear()
        self.results.clear()

    def __call__(self, base: Wireframe, new: Wireframe, threshold: float) -> Wireframe:
        from mapping.merge import MergeConfig, merge

        key = (base.content_digest(), new.content_digest(), threshold)
        out = self.results.get(key)
        if out is None:
            out = self.results[key] = merge(base, new, MergeConfig(threshold=threshold), cache=self.cache)
        return out


# ------------------------------------------------------------------------------ the filter
@dataclass
class _StepContext:
    """What the phases of one :meth:`WireframeFilter.step` pass on to each other.

    Attributes
    ----------
    evidence : Wireframe
        The cleaned-up scan (robot frame): what the likelihood and the contradictions use.
    scan : Wireframe
        ``evidence`` without short fragments, snapped after the match: what is merged.
    matched_scan : Wireframe
        ``scan`` before snapping: what the loop closure matches.
    kept : (m,) int64
        The edge of ``evidence`` of each edge of ``scan``.
    predicted, pose : Pose
        The odometry's prediction and the current estimate (after the match and the compass).
    best : Wireframe
        The best particle at the start of the step (the match's reference).
    fault : Pose or None
        Fault injection (:meth:`WireframeFilter.step`).
    icp : ICPResult or None
        The scan match (None: nothing to match against).
    matched_edges : (k,) int64
        Edges of ``best`` in the predicted scan the scan was matched against.
    heading : Heading or None
        The compass measurement fused.
    points : (n, 2) float64 or None
        The scan's raw points (robot frame, bearing order) when the point match is on.
    """

    evidence: Wireframe
    scan: Wireframe
    matched_scan: Wireframe
    kept: IntArray
    predicted: Pose
    pose: Pose
    best: Wireframe
    fault: Pose | None
    icp: ICPResult | None = None
    matched_edges: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    heading: Heading | None = None
    points: FloatArray | None = None

    @property
    def place(self) -> Pose:
        """Where the scan is placed for the likelihood and the merge (the pose, or the fault)."""
        return self.pose if self.fault is None else self.pose.compose(self.fault)


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
        self.origin = self._pose  # the map frame's pose of the first scan
        empty = Wireframe.empty()
        self._particles: list[Wireframe] = [empty] * config.particles
        self._weights = np.full(config.particles, 1.0 / config.particles)
        self._best = 0
        self._steps = 0
        odo = config.odometry
        self._cov = np.diag([odo.pose_floor_xy**2, odo.pose_floor_xy**2, odo.pose_floor_theta**2])
        self._drift = np.zeros((3, 3))
        # Distance and turn since the last step that updated the map (_update_due): infinite
        # until one has.
        self._since_update = (math.inf, 0.0)
        self._pending_spans = np.zeros((0, 2, 2))
        self._view_fn: ViewFn = view_fn or _default_view
        self._cached_merge: _CachedMerge | None = None
        if merge_fn is None:
            merge_fn = self._cached_merge = _CachedMerge()
        self._merge_fn: MergeFn = merge_fn
        self._through: dict[bytes, bool] = {}  # _seen_through_unreported's answers this step
        self._spans: dict[Any, list[tuple[float, float, bool]]] = {}  # seen_through_spans' memo
        self._loops = LoopCloser(config.loops, self._pose)
        self._directions = Directions(
            config.compass.anchor or 0.0, config.compass.min_support, config.compass.max_gate,
            right_angle=config.compass.right_angle,
        )

    # ------------------------------------------------------------------ state
    @property
    def pose(self) -> Pose:
        """The current pose estimate (map frame)."""
        return self._pose

    @property
    def pose_covariance(self) -> FloatArray:
        """Covariance (3 x 3) of the pose estimate's error ``(x, y, theta)`` in the robot frame."""
        c = self._cov.copy()
        c.setflags(write=False)
        return c

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

    def warp(self, fn: Callable[[FloatArray], FloatArray]) -> None:
        """Move every particle's vertices by ``fn`` (``(n, 2)`` map-frame points to new ones,
        row for row: labels, edges and likelihoods stay), the spans seen through at the last
        step with them, and the corners' births and counts to their new coordinates
        (:meth:`mapping.loops.LoopCloser.warped`; its keyframes stay). For a pose graph that
        reshapes the trajectory the map was built on (:func:`mapping.lidar_slam.graph_warp`);
        the pose is the caller's (the next step's odometry carries the graph's move of the
        current pose)."""
        moved: dict[int, Wireframe] = {}
        pairs: list[tuple[FloatArray, FloatArray]] = []
        for p in self._particles:
            if id(p) not in moved and len(p):
                pts = np.ascontiguousarray(fn(p.points), dtype=np.float64)
                moved[id(p)] = p.moved_to(pts)
                pairs.append((p.points, pts))
        self._particles = [moved.get(id(p), p) for p in self._particles]
        self._loops.warped(pairs)
        if len(self._pending_spans):
            self._pending_spans = fn(self._pending_spans.reshape(-1, 2)).reshape(-1, 2, 2)
        self._spans.clear()
        self._through.clear()

    def memory_bytes(self) -> int:
        """Particle-set storage by the paper's accounting (Sec. IV-G), every particle counted
        (:func:`particle_bytes` of :attr:`particles`)."""
        return particle_bytes(self._particles)

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

    def predict_covariance(self, cov: FloatArray, odometry: Pose) -> FloatArray:
        """The pose covariance after driving ``odometry`` (robot frame before and after).

        The error ``e`` of the old pose (robot frame) becomes ``Ad(u^-1) e`` in the new robot
        frame, ``Ad(u^-1) = [[R(-th_u), R(-th_u) (-u_y, u_x)^T], [0, 1]]``, and the odometry
        noise adds ``diag(s_t^2, s_t^2, s_r^2)`` with ``s_t = trans_per_m d`` and
        ``s_r = rot_per_rad |th_u| + rot_per_m d`` (``d`` the distance driven), the noise model
        of :class:`agents.sim.motion.OdometryNoise` with the filter's own parameters.
        """
        c, s_ = math.cos(odometry.theta), math.sin(odometry.theta)
        A = np.array(
            [
                [c, s_, c * -odometry.y + s_ * odometry.x],
                [-s_, c, -s_ * -odometry.y + c * odometry.x],
                [0.0, 0.0, 1.0],
            ]
        )
        out = A @ cov @ A.T + self._odometry_noise(odometry)
        return np.asarray(0.5 * (out + out.T), dtype=np.float64)

    def _odometry_noise(self, odometry: Pose) -> FloatArray:
        """``diag(s_t^2, s_t^2, s_r^2)`` of :meth:`predict_covariance` for one increment."""
        cfg = self.config
        d = math.hypot(odometry.x, odometry.y)
        st = cfg.odometry.trans_per_m * d
        sr = cfg.odometry.rot_per_rad * abs(odometry.theta) + cfg.odometry.rot_per_m * d
        return np.diag([st * st, st * st, sr * sr])

    def motion_increment(self, odometry: Pose, match: ICPResult | None) -> FloatArray:
        """What one step adds to the uncertainty of the robot's motion (robot frame): the
        odometry noise ``Q`` of :meth:`predict_covariance`, fused with the information ``H`` of
        the step's scan match when it was accepted, ``(Q^-1 + H)^-1``. Directions the scan
        pinned down add next to nothing; a turn with nothing in view adds the odometry's
        whole heading noise (:class:`mapping.loops.LoopConfig`, ``motion_cov``)."""
        Q = self._odometry_noise(odometry) + 1e-12 * np.eye(3)
        if match is None or not match.accepted:
            return Q
        H = np.asarray(match.information, dtype=np.float64)
        return np.asarray(np.linalg.inv(np.linalg.inv(Q) + 0.5 * (H + H.T)), dtype=np.float64)

    def _confirmed(
        self, wf: Wireframe, found: dict[int, list[tuple[float, float]]], seen: list[FloatArray]
    ) -> dict[int, list[tuple[float, float]]]:
        """The seen-through spans of ``found`` (on edges of ``wf``) that the previous step's scan
        also saw through (a span of the previous step within :attr:`FilterConfig.merge_threshold`
        of the span's middle); all of ``found`` is recorded in ``seen`` for the next step. One
        scan in which the corner sensor missed a wall (``p_fn``) must not carve it."""
        out: dict[int, list[tuple[float, float]]] = {}
        prev = self._pending_spans
        for e, ivs in found.items():
            a, b = wf.points[wf.edges[e, 0]], wf.points[wf.edges[e, 1]]
            u = (b - a) / max(float(np.hypot(*(b - a))), 1e-12)
            for t0, t1 in ivs:
                seg = np.stack([a + t0 * u, a + t1 * u])
                seen.append(seg[None])
                if len(prev) == 0:
                    continue
                mid = 0.5 * (seg[0] + seg[1])
                d = prev[:, 1] - prev[:, 0]
                dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
                tt = np.clip(np.einsum("ij,ij->i", mid - prev[:, 0], d) / dd, 0.0, 1.0)
                gap = np.hypot(*(prev[:, 0] + tt[:, None] * d - mid).T)
                if float(gap.min()) <= self.config.merge_threshold:
                    out.setdefault(e, []).append((t0, t1))
        return out

    def _compass(
        self, scan: Wireframe, pose: Pose, best: Wireframe, matched: IntArray, weight: float = 1.0
    ) -> tuple[Pose, Heading | None]:
        """The wall-direction heading measurement (:mod:`mapping.compass`) of ``scan`` at
        ``pose`` against the reference directions (:class:`mapping.compass.Directions`; with
        ``compass.anchor=None``, the established walls of ``best`` but the edges ``matched``,
        those the scan match already used), fused into the pose and its covariance as a Kalman
        update of the heading with the measurement's variance divided by ``weight`` (the
        position moves with it through the covariance's cross terms); the part of the
        measurement the update did not apply goes to the loop closer as a heading factor, at
        the measurement's own variance. Returns the pose and the measurement (None: none)."""
        cfg = self.config
        ccfg = cfg.compass
        sd, sl = wall_directions(scan, ccfg.min_length)
        if len(sd) == 0:
            return pose, None
        if ccfg.anchor is not None:
            md, ml = self._directions.reference()
        else:
            ref = best
            if len(matched):
                keep = np.ones(best.n_edges, dtype=bool)
                keep[matched] = False
                ref = best.subgraph_edges(keep)
            md, ml = wall_directions(ref, ccfg.min_length, cfg.keep_threshold)
        h = compass_heading(
            np.mod(sd + pose.theta, math.pi), sl, md, ml, math.sqrt(self._cov[2, 2]),
            corner_sigma=ccfg.corner_sigma, model_sigma=ccfg.model_sigma,
            min_support=ccfg.min_support, max_gate=ccfg.max_gate,
        )
        if h is None:
            return pose, None
        P = self._cov
        gain = P[:, 2] / (P[2, 2] + h.variance / weight)
        dx = gain * h.offset
        self._loops.heading(float(h.offset - dx[2]), h.variance)
        C = P - np.outer(gain, P[2, :])
        self._cov = np.asarray(0.5 * (C + C.T), dtype=np.float64)
        return pose.compose(Pose(float(dx[0]), float(dx[1]), float(dx[2]))), h

    def _icp(self, scan: Wireframe, ref: Wireframe, prior: FloatArray) -> ICPResult:
        """ICP of ``scan`` on ``ref`` with ``prior`` as the correction's prior; the first
        correspondence gate is three standard deviations (the rotation's taken at half the
        range), within the ICP config's ``gate_end``..``gate_start``."""
        cfg = self.config
        reach = 3.0 * (
            math.sqrt(max(prior[0, 0], prior[1, 1])) + math.sqrt(prior[2, 2]) * 0.5 * cfg.max_range
        )
        icfg = dataclasses.replace(cfg.icp, gate_start=min(cfg.icp.gate_start, max(cfg.icp.gate_end, reach)))
        return icp(scan, ref, icfg, prior_covariance=prior)

    # ------------------------------------------------------------------ the step
    @property
    def loops(self) -> LoopCloser:
        """The loop-closure back end (keyframes, closures so far)."""
        return self._loops

    def step(
        self, odometry: Pose, scan: Wireframe, *, fault: Pose | None = None, points: FloatArray | None = None
    ) -> StepInfo:
        """One filter iteration (paper Fig. 7), then the loop-closure check (:mod:`mapping.loops`).

        The phases, each a method: clean the scan up (:func:`mapping.scan_cleanup.clean_scan`),
        predict the pose (:meth:`_predict`), match the scan (:meth:`_match_scan`), fuse the
        compass (:meth:`_fuse_compass`); then, when the scan may touch the map
        (:meth:`_may_map`), evaluate every distinct particle (:meth:`_evaluate`), reweight
        (:meth:`_reweight`), resample with mutation (:meth:`_resample`) and merge the scan
        (:meth:`_merge_scan`); last, the loop closure (:meth:`_loop_closure`).

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
        points : (n, 2) float64, optional
            The raw scan's points (robot frame, bearing order), for the point match
            (:attr:`FilterConfig.point_match`); ignored while that is off.

        Returns
        -------
        StepInfo
        """
        cfg = self.config
        self._steps += 1
        if self._cached_merge is not None:
            self._cached_merge.clear()  # keyed by content: only this step's scan can hit
        self._through.clear()  # answers for this step's scan and pose only
        self._spans.clear()  # (the same)
        ctx = self._predict(odometry, clean_scan(scan, cfg.cleanup, cfg.max_scan_vertices), fault)
        # A scan taken before the robot has moved enough only predicts (_update_due): no match.
        due = self._update_due(odometry)
        if due:
            if cfg.point_match.enabled and points is not None:
                ctx.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
            self._match_scan(ctx)
            self._fuse_compass(ctx)
        self._pose = ctx.pose
        if due and self._may_map(ctx):
            evals = self._evaluate(ctx)
            weights, best_parent, loglik = self._reweight(evals)
            resampled, best = self._resample(evals, weights, best_parent)
            self._merge_scan(ctx, evals, resampled, best)
            info = self._info(ctx, loglik, int(resampled.mutated.sum()), mapped=True)
            self._since_update = (0.0, 0.0)
        else:
            info = self._info(ctx, np.zeros(len(self._particles)), 0, mapped=False)
        return self._loop_closure(odometry, info, ctx.matched_scan, ctx.points)

    def _update_due(self, odometry: Pose) -> bool:
        """Whether this step's scan may update the map by the distance and turn since the last
        step that did (:attr:`GatingConfig.update_distance`, :attr:`GatingConfig.update_angle`;
        a threshold at 0 never triggers, both at 0 let every scan through). The first step, and
        every step until one has mapped, is due."""
        g = self.config.gating
        if g.update_distance <= 0 and g.update_angle <= 0:
            return True
        dist, turn = self._since_update
        dist += math.hypot(odometry.x, odometry.y)
        turn += abs(odometry.theta)
        self._since_update = (dist, turn)
        return (dist == math.inf or (g.update_distance > 0 and dist >= g.update_distance)
                or (g.update_angle > 0 and turn >= g.update_angle))

    def _info(self, ctx: _StepContext, loglik: FloatArray, mutated: int, mapped: bool) -> StepInfo:
        """The step's :class:`StepInfo`, after its last phase."""
        return StepInfo(
            step=self._steps,
            pose=ctx.pose,
            predicted_pose=ctx.predicted,
            icp=ctx.icp,
            log_likelihoods=loglik,
            best=self._best,
            distinct=self.distinct_particles(),
            mutated=mutated,
            mapped=mapped,
            compass=ctx.heading,
        )

    def _predict(self, odometry: Pose, cleaned: CleanScan, fault: Pose | None) -> _StepContext:
        """Predict the pose and its uncertainty from the odometry (paper Sec. IV-A).

        ``x_pred = x (+) u``; the covariance grows by the odometry noise model
        (:meth:`predict_covariance`), and the map's drift relative to the pose (the prior of a
        re-anchoring match, :class:`GatingConfig`) by ``diag(drift_xy^2, drift_xy^2,
        drift_theta^2) d`` for ``d`` metres driven.

        Parameters
        ----------
        odometry : Pose
            The increment since the previous scan (previous robot frame).
        cleaned : mapping.scan_cleanup.CleanScan
            This step's scan after clean-up.
        fault : Pose or None
            The fault to inject at placing (:meth:`step`).

        Returns
        -------
        _StepContext
            The step's state, the pose set to the prediction.
        """
        cfg = self.config
        predicted = self._pose.compose(odometry)
        best = self._particles[self._best]
        self._cov = self.predict_covariance(self._cov, odometry)
        d = math.hypot(odometry.x, odometry.y)
        self._drift = self._drift + np.diag(
            [cfg.gating.drift_xy**2 * d, cfg.gating.drift_xy**2 * d, cfg.gating.drift_theta**2 * d]
        )
        return _StepContext(cleaned.evidence, cleaned.scan, cleaned.scan, cleaned.kept, predicted, predicted,
                            best, fault)

    def _match_scan(self, ctx: _StepContext) -> None:
        """Match the scan against the best particle's predicted scan (paper Sec. IV-C).

        The wireframe ICP (:func:`mapping.icp.icp`) with the pose covariance as its prior; a
        rejected match is retried once with the map's drift added to the prior
        (:attr:`GatingConfig.reanchor`). After a consistent match the scan's frontiers, and
        after an accepted one its walls continuing established ones, are snapped onto the map
        (:mod:`mapping.snapping`). An accepted match corrects the pose,
        ``x = x_pred (+) correction``, and its covariance becomes the ICP's posterior, floored at
        :attr:`OdometryConfig.pose_floor_xy` and :attr:`OdometryConfig.pose_floor_theta`.

        Parameters
        ----------
        ctx : _StepContext
            Updated in place: ``icp``, ``matched_edges``, ``scan`` (snapped) and ``pose``.
        """
        cfg = self.config
        best, scan, predicted = ctx.best, ctx.scan, ctx.predicted
        if not (cfg.use_icp and best.n_edges and scan.n_edges):
            return
        ref, ref_src, _ = self.predicted_view(best, predicted)
        ctx.matched_edges = ref_src[ref_src >= 0]
        if not ref.n_vertices:
            return
        icp_res = self._icp(scan, ref, self._cov)
        if not icp_res.accepted and cfg.gating.reanchor and scan.n_edges >= 2:
            # The map in view may be older than the pose's uncertainty says (module
            # docstring, "re-anchoring"): try again with the drift added to the prior.
            again = self._icp(scan, ref, self._cov + self._drift)
            if again.accepted and again.constrained == 3 and again.rmse <= 0.5 * cfg.icp.max_rmse:
                icp_res = again
        if ctx.points is not None and cfg.point_match.local:
            icp_res = self._match_points(icp_res, ctx.points, ref, self._cov, reanchor=cfg.gating.reanchor)
        ctx.icp = icp_res
        if icp_res.consistent and cfg.snapping.frontiers:
            # Also a scan that only confirms the prediction (ICPResult.consistent): its
            # frontiers must not drag an established wall's line either.
            corr = icp_res.correction if icp_res.accepted else Pose.identity()
            support = best.edge_lengths()[np.maximum(ref_src, 0)] * (ref_src >= 0)
            sp = snap_frontiers(
                corr.apply(scan.points), scan, ref, icp_res.correspondences.edge_pairs,
                support, cfg.icp.gate_end,
            )
            snap = cfg.snapping
            if snap.collinear and icp_res.accepted:
                sp = snap_collinear(
                    sp, scan, ref, icp_res.correspondences.edge_pairs, support,
                    snap.collinear_min_support, snap.collinear_max_offset, snap.collinear_max_angle,
                )
            ctx.scan = scan.replace(points=corr.inverse().apply(sp))
        if icp_res.accepted:
            ctx.pose = predicted.compose(icp_res.correction)
            C = np.array(icp_res.covariance, dtype=np.float64)
            odo = cfg.odometry
            floor = np.array([odo.pose_floor_xy, odo.pose_floor_xy, odo.pose_floor_theta]) ** 2
            C[np.diag_indices(3)] = np.maximum(np.diag(C), floor)
            self._cov = C

    def _fuse_compass(self, ctx: _StepContext) -> None:
        """Fuse the wall-direction heading measurement (:mod:`mapping.compass`; not in the paper).

        While the reference directions are being learnt (the first ``compass.anchor`` metres)
        or are needed, they are updated from the best particle's established walls. At full
        weight while the heading's std after the match exceeds ``compass.min_sigma``; below it,
        at ``compass.young_weight``, only while the walls the scan was matched against are at
        most ``compass.young_travel`` metres of driving old (a map that young carries the
        present drift). See :meth:`_compass` for the update itself.

        Parameters
        ----------
        ctx : _StepContext
            Updated in place: ``pose`` and ``heading``.
        """
        cfg = self.config
        ccfg = cfg.compass
        best, scan = ctx.best, ctx.scan
        if not (ccfg.enabled and best.n_edges):
            return
        need = scan.n_edges > 0 and math.sqrt(self._cov[2, 2]) > ccfg.min_sigma
        if ccfg.anchor is not None:
            anchoring = self._loops.distance < ccfg.anchor
            if anchoring or need or not self._directions.settled:
                md, ml = wall_directions(best, ccfg.min_length, cfg.keep_threshold)
                self._directions.update(md, ml, self._loops.distance)
        if need:
            ctx.pose, ctx.heading = self._compass(scan, ctx.pose, best, ctx.matched_edges)
        elif (ccfg.young_weight > 0 and scan.n_edges
                and self._loops.age(best.points[np.unique(best.edges[ctx.matched_edges])])
                <= ccfg.young_travel):
            # The match pinned the heading down, but against walls as young as the drift
            # they carry: the compass still pulls, slowly (CompassConfig.young_weight).
            # No wall matched, or none stamped yet, is age 0: nothing says the map is old.
            ctx.pose, ctx.heading = self._compass(scan, ctx.pose, best, ctx.matched_edges, ccfg.young_weight)

    def _may_map(self, ctx: _StepContext) -> bool:
        """Whether the scan is placed well enough to touch the map (module docstring, "gating").

        Not when a map was in view and the heading's std after matching exceeds
        ``gating.max_sigma_theta``, nor when the match was rejected while the position's std
        exceeds ``gating.max_sigma_xy``; the step then only predicts.
        """
        g = self.config.gating
        icp_res = ctx.icp
        lost = (
            icp_res is not None
            and not icp_res.accepted
            and math.sqrt(max(self._cov[0, 0], self._cov[1, 1])) > g.max_sigma_xy
        )
        return not (lost or (icp_res is not None and math.sqrt(self._cov[2, 2]) > g.max_sigma_theta))

    def _evaluate(self, ctx: _StepContext) -> dict[int, _Eval]:
        """Predict the scan and score it for every distinct particle (Sec. IV-B, IV-D).

        Negative evidence (contradictions, carving) needs the scan placed against the map: not
        from a scan whose match with a map in view was rejected (``gating.anchored_evidence``).
        The seen-through spans found are kept for the next step's confirmation.

        Parameters
        ----------
        ctx : _StepContext

        Returns
        -------
        dict
            ``id(particle) -> _Eval``, one per distinct particle object.
        """
        icp_res = ctx.icp
        anchored = icp_res is None or icp_res.consistent or not self.config.gating.anchored_evidence
        evals: dict[int, _Eval] = {}
        seen_spans: list[FloatArray] = []
        by_view: dict[bytes, tuple[ScanLikelihood, BoolArray]] = {}
        for p in self._particles:
            if id(p) not in evals:
                evals[id(p)] = self._evaluate_particle(p, ctx, anchored, seen_spans, by_view)
        self._pending_spans = np.concatenate(seen_spans) if seen_spans else np.zeros((0, 2, 2))
        return evals

    def _evaluate_particle(
        self,
        p: Wireframe,
        ctx: _StepContext,
        anchored: bool,
        seen_spans: list[FloatArray],
        by_view: dict[bytes, tuple[ScanLikelihood, BoolArray]],
    ) -> _Eval:
        """One particle's predicted scan, likelihood and evidence-updated map (Sec. IV-B, IV-D).

        ``log p(S | W)`` of the evidence scan against the prediction at the placed pose
        (:func:`mapping.likelihood.scan_likelihood`); edges in view that the prediction does not
        report (back-facing or hidden, paper Fig. 5) count as contradicted when the scan saw
        through them. Contradicted edges get the Bayes update
        (:func:`mapping.evidence.contradiction_update`), seen-through stretches confirmed by
        the previous scan are carved (:func:`mapping.evidence.carve`), new scan edges in known
        free space are kept out of this particle's merge, and the in-sight edges the scan does
        not observe are the candidates for mutation (Sec. IV-F).

        Parameters
        ----------
        p : Wireframe
            The particle.
        ctx : _StepContext
        anchored : bool
            Whether negative evidence may be applied (:meth:`_evaluate`).
        seen_spans : list
            Collects this step's seen-through spans (map frame segments).
        by_view : dict
            This step's likelihoods and free-space verdicts by predicted scan
            (:meth:`Wireframe.content_digest`): both depend on nothing else, and distinct
            particles often predict the same scan (they differ out of sight).

        Returns
        -------
        _Eval
        """
        cfg = self.config
        lcfg = cfg.likelihood
        evidence, place = ctx.evidence, ctx.place
        view, src, unreported = self.predicted_view(p, place)
        key = view.content_digest()
        known = by_view.get(key)
        if known is None:
            lik = scan_likelihood(evidence, view, lcfg, max_range=cfg.max_range)
            merge_mask = self._free_space_mask(ctx, view, lik)
            by_view[key] = (lik, merge_mask)
        else:
            lik, merge_mask = known  # (shared between particles: read, never written)
        in_sight, observed, contra = edge_states(p.n_edges, src, lik.predicted_edge_state)
        through = self._seen_through_unreported(p, place, evidence, unreported & ~observed)
        if through.any():
            contra |= through
            in_sight |= through
            lik = dataclasses.replace(
                lik,
                log_likelihood=lik.log_likelihood + math.log(lcfg.p_fn) * int(through.sum()),
                edge_log=lik.edge_log + math.log(lcfg.p_fn) * int(through.sum()),
            )
        updated = p
        if not anchored:
            contra = np.zeros_like(contra)
        if contra.any():
            L = p.likelihood.copy()
            weight = seen_fraction(p, view, src)[contra] if cfg.evidence.partial_contradiction else 1.0
            L[contra] = contradiction_update(L[contra], lcfg.p_fp, lcfg.p_fn, weight)
            updated = p.replace(likelihood=L)
        spans: dict[int, list[tuple[float, float]]] = {}
        if cfg.evidence.carve and anchored:
            found = seen_through_spans(
                p, place, view, src, lik.correspondences.edge_pairs, evidence,
                2.5 * cfg.merge_threshold, cfg.merge_threshold, lcfg.occlusion_margin, cfg.max_range,
                memo=self._spans,
            )
            spans = self._confirmed(p, found, seen_spans)
        group = b"".join(
            (
                np.round(view.points, 6).tobytes(),
                view.edges.tobytes(),
                view.labels.tobytes(),
                np.round(updated.likelihood[src[src >= 0]], 6).tobytes(),
                np.round(p.points[p.edges[through]], 6).tobytes(),
            )
        )
        # Candidates for mutation (Sec. IV-F, "within sight (or predicted sight)"): every edge
        # in view, reported or not, that this scan does not observe.
        cands = (in_sight | unreported) & ~observed
        if spans:
            group += repr(sorted(spans.items())).encode()
            updated, origin = carve(updated, spans)
            in_sight, cands = in_sight[origin], cands[origin]
        return _Eval(lik, updated, in_sight, cands, lik.scan_edge_likelihood[ctx.kept], group, merge_mask)

    def _free_space_mask(self, ctx: _StepContext, view: Wireframe, lik: ScanLikelihood) -> BoolArray:
        """Which edges of the merge scan may be merged into a particle whose predicted scan is
        ``view`` (likelihood ``lik``): not the new ones (unmatched) where the particle is sure
        there is free space (``evidence.reject_in_free_space``; static world: a false
        positive or a passer-by)."""
        cfg = self.config
        scan = ctx.scan
        merge_mask = np.ones(scan.n_edges, dtype=bool)
        if cfg.evidence.reject_in_free_space and scan.n_edges and view.n_edges:
            unm = np.flatnonzero(~lik.scan_edge_matched[ctx.kept])
            if len(unm):
                free = in_known_free_space(
                    view, scan.segments().take(unm, axis=0), cfg.likelihood.occlusion_margin,
                    cfg.keep_threshold,
                )
                merge_mask[unm[free]] = False
        return merge_mask

    def _seen_through_unreported(
        self, p: Wireframe, place: Pose, evidence: Wireframe, candidates: BoolArray
    ) -> BoolArray:
        """Which edges of ``p`` in view but not reported by the prediction (back-facing, or
        hidden behind another map edge; ``candidates``) the scan ``evidence`` saw through
        (:func:`mapping.likelihood.seen_through`): they count as contradicted (paper Fig. 5)."""
        lcfg = self.config.likelihood
        through = np.zeros(p.n_edges, dtype=bool)
        cand_hidden = np.flatnonzero(candidates)
        if len(cand_hidden) and evidence.n_edges:
            # seen_through answers each segment on its own, and the step's particles share most
            # of their hidden walls: answers are kept for the step by the wall's map-frame
            # coordinates (``place`` and ``evidence`` are the step's), and only new walls are
            # moved to the robot frame (elementwise: the same numbers) and asked.
            world = p.points.take(p.edges.take(cand_hidden, axis=0).reshape(-1), axis=0).reshape(-1, 4)
            keys = [row.tobytes() for row in world]
            kept = self._through
            ask = [i for i, k in enumerate(keys) if k not in kept]
            if ask:
                segs = place.apply_inverse(world.take(ask, axis=0).reshape(-1, 2)).reshape(-1, 2, 2)
                found = seen_through(evidence, segs, lcfg.occlusion_margin, self.config.max_range,
                                     min_incidence=lcfg.min_incidence)
                for i, f in zip(ask, found.tolist()):
                    kept[keys[i]] = f
            through[cand_hidden] = [kept[k] for k in keys]
        return through

    def _reweight(self, evals: dict[int, _Eval]) -> tuple[FloatArray, int, FloatArray]:
        """The weight update ``w_i <- eta w_i p(S | W_i)^(1 / temperature)`` (Sec. III-B, IV-D).

        Returns
        -------
        weights : (M,) float64
            Normalised.
        best_parent : int
            The highest-weight particle; ties (particles that differ only in edges this scan
            says nothing about) go to the most plausible edge set
            (:func:`mapping.evidence.edge_log_odds`).
        log_likelihoods : (M,) float64
            ``log p(S | W_i)``.
        """
        cfg = self.config
        loglik = np.array([evals[id(p)].lik.log_likelihood for p in self._particles])
        logw = np.log(np.maximum(self._weights, 1e-300)) + loglik / cfg.temperature
        logw -= logw.max()
        w = np.exp(logw)
        w /= w.sum()
        tied = np.flatnonzero(logw >= -cfg.tie_tolerance)
        if len(tied) > 1:
            score = np.array([edge_log_odds(evals[id(self._particles[i])].updated) for i in tied.tolist()])
            best_parent = int(tied[int(np.argmax(score))])
        else:
            best_parent = int(np.argmax(w))
        return w, best_parent, loglik

    def _resample(
        self, evals: dict[int, _Eval], weights: FloatArray, best_parent: int
    ) -> tuple[ResampleResult, int]:
        """Resample with mutation (Sec. IV-F, :func:`mapping.resample.resample_with_mutation`).

        Particles the scan cannot tell apart (equal ``_Eval.group``) count as copies of one;
        further draws of a group are mutated: in-sight edges below the keep threshold that the
        scan does not observe may be dropped.

        Returns
        -------
        resampled : mapping.resample.ResampleResult
        best : int
            Index of the best particle after resampling: the unmutated copy of ``best_parent``.
        """
        cfg = self.config
        updated_list = [evals[id(p)].updated for p in self._particles]
        sight_list = [evals[id(p)].candidates_mask for p in self._particles]
        groups = [evals[id(p)].group for p in self._particles]
        res = resample_with_mutation(
            updated_list, weights, sight_list, cfg.keep_threshold, self.rng, cfg.mutate, groups=groups
        )
        best_obj = updated_list[best_parent]
        best = next(
            (k for k, q in enumerate(res.particles) if q is best_obj and not res.mutated[k]),
            int(np.flatnonzero(res.indexes == best_parent)[0]) if np.any(res.indexes == best_parent) else 0,
        )
        return res, best

    def _merge_scan(self, ctx: _StepContext, evals: dict[int, _Eval], res: ResampleResult, best: int) -> None:
        """Merge the placed scan into every resulting particle (Sec. IV-E, :func:`mapping.merge.merge`).

        Scan edges carry the parent's per-edge likelihoods into the merge, less those the parent
        rejected in free space. Corners are refined first (:mod:`mapping.refine`), only from a
        scan whose match fixed all three directions of the pose. Each merged map is budgeted
        (:func:`budget_map`); identical resulting particles share one object, so their next
        steps run once. Weights are reset to uniform.

        Parameters
        ----------
        ctx : _StepContext
        evals : dict
            From :meth:`_evaluate`.
        res : mapping.resample.ResampleResult
        best : int
            The best particle's index after resampling.
        """
        cfg = self.config
        icp_res = ctx.icp
        merged: dict[tuple[int, int], Wireframe] = {}
        by_content: dict[bytes, Wireframe] = {}
        refined: dict[int, Wireframe] = {}
        new: list[Wireframe] = []
        # Corner refinement (mapping.refine) only from a scan whose match fixed all three
        # directions of the pose: along a degenerate direction (a corridor's axis) the pose is
        # the odometry's, and averaging it in would drag the corners along with its error.
        refine = cfg.refine.enabled and (icp_res is None or (icp_res.accepted and icp_res.constrained == 3))
        placed = ctx.scan.transformed(ctx.place)  # the scan in the map frame, for every merge below
        # The scan as merged into a parent's offspring depends on the parent alone: one object
        # per parent, so that its mutated copies' merges do not build it (and digest it for
        # the merge cache, _CachedMerge) again.
        scans: dict[int, Wireframe] = {}
        for k, q in enumerate(res.particles):
            parent = self._particles[int(res.indexes[k])]
            key = (id(q), id(parent))
            if key not in merged:
                scan_world = scans.get(id(parent))
                if scan_world is None:
                    scan_world = scans[id(parent)] = self._scan_for(placed, evals[id(parent)])
                if refine and q.n_vertices:
                    if id(q) not in refined:
                        rq, moved = refine_corners(
                            q, placed, cfg.merge_threshold, self._loops.counts(q.points), cfg.refine.max_count
                        )
                        self._loops.moved(moved.old, moved.new, moved.counts)
                        refined[id(q)] = rq
                    q = refined[id(q)]
                m = budget_map(self._merge_fn(q, scan_world, cfg.merge_threshold), cfg.max_vertices)
                # Particles that came out equal share one object (their next steps run once).
                merged[key] = by_content.setdefault(_content_key(m), m)
            new.append(merged[key])
        self._best = best
        self._particles = new
        self._weights = np.full(len(new), 1.0 / len(new))

    @staticmethod
    def _scan_for(placed: Wireframe, ev: _Eval) -> Wireframe:
        """The placed scan as merged into a particle evaluated as ``ev``: with its per-edge
        likelihoods, less the edges it rejected in free space."""
        scan_world = placed.replace(likelihood=ev.scan_edge_likelihood)
        return scan_world if ev.merge_mask.all() else scan_world.subgraph_edges(ev.merge_mask)

    def _match_points(
        self, res: ICPResult, points: FloatArray, ref: Wireframe, prior: FloatArray, *, reanchor: bool
    ) -> ICPResult:
        """The point match (:func:`mapping.scan_match.refine_match`; real lidar, not in the
        paper): every raw point of the scan against the walls of ``ref`` (the predicted scan),
        starting from the wireframe ICP's correction in ``res`` when accepted. Its correction,
        covariance and verdict replace the ICP's; a failed point match leaves ``res`` as it was.
        With ``reanchor`` a failure is retried with the map's drift added to the prior."""
        drift = self._drift if reanchor else None
        return refine_match(res, points, ref.segments(), prior, drift, self.config.point_match,
                            self.config.max_range)

    def _loop_closure(
        self, odometry: Pose, info: StepInfo, scan: Wireframe, points: FloatArray | None = None
    ) -> StepInfo:
        """Loop-closure bookkeeping and check after the filter step (:mod:`mapping.loops`).

        Keyframes, births and observation counts advance with the step; with ``loops.enabled``
        the matched scan is checked against the old part of the best map
        (:meth:`_close_loops`), and a closure moves the pose (``info.pose``, ``info.loop``).
        """
        lc = self._loops
        inc = self.motion_increment(odometry, info.icp) if lc.config.motion_cov else None
        lc.advance(self._pose, math.hypot(odometry.x, odometry.y) + 0.5 * abs(odometry.theta), inc)
        lc.stamp(self._particles)
        if self._steps % 500 == 0:
            lc.prune(self._particles)
        if self.config.loops.enabled:
            closed = self._close_loops(scan, points)
            if closed is not None:
                info = dataclasses.replace(info, pose=self._pose, loop=closed)
        return info

    def _close_loops(self, scan: Wireframe, points: FloatArray | None = None) -> Closure | None:
        """After a step: every ``check_every`` metres, the scan matched against the old part of
        the best map, and a closure when it is off. With the raw ``points`` (the point match
        on) the match against the old map is refined by them (:meth:`_match_points`)."""
        lc = self._loops
        lcfg = lc.config
        if not lc.due() or scan.n_edges < 2:
            return None
        old, young, _ = lc.split(self.best)
        if old.n_edges < lcfg.min_old_edges:
            return None
        ref, ref_src, _ = self.predicted_view(old, self._pose)
        if ref.n_edges < lcfg.min_old_edges:
            return None
        used = np.unique(old.edges[ref_src[ref_src >= 0]])
        born = lc.births(old.points[used])
        born = born[born >= 0]
        if len(born) == 0:
            return None
        born_kf = int(np.median(born))
        prior = lc.prior(born_kf)

        def good(r: ICPResult) -> bool:
            return bool(r.accepted and r.constrained >= lcfg.min_constrained
                        and r.n_constraints >= lcfg.min_constraints and r.rmse <= lcfg.max_rmse)

        res = self._icp(scan, ref, prior)
        if points is not None:
            res = self._match_points(res, points, ref, prior, reanchor=False)
        if not good(res):
            return None
        here = self._pose  # where the young chain puts the robot
        yref = self.predicted_view(young, self._pose)[0] if young.n_edges else Wireframe.empty()
        if yref.n_edges >= lcfg.min_old_edges:
            yres = self._icp(scan, yref, prior)
            if good(yres):
                here = self._pose.compose(yres.correction)
        corrected = self._pose.compose(res.correction)
        c = here.inverse().compose(corrected)
        if math.hypot(c.x, c.y) < lcfg.min_correction and abs(c.theta) < lcfg.min_rotation:
            return None
        merge_fn = self._merge_fn
        thr = self.config.merge_threshold
        pose, parts = lc.close(here, corrected, born_kf, res.covariance, self._particles,
                               lambda a, b: merge_fn(a, b, thr))
        # The young chain's pose was `here`; the estimate moves with it.
        pose = pose.compose(here.inverse().compose(self._pose))
        self._pose = pose
        budgeted: dict[int, Wireframe] = {}
        for p in parts:  # particles sharing one object share its budgeted map (computed once)
            if id(p) not in budgeted:
                budgeted[id(p)] = budget_map(p, self.config.max_vertices)
        self._particles = [budgeted[id(p)] for p in parts]
        self._drift = np.zeros((3, 3))
        lc.stamp(self._particles)
        return lc.closures[-1]



def _content_key(wf: Wireframe) -> bytes:
    """Equal for particles whose arrays are byte for byte equal (:meth:`Wireframe.content_digest`)."""
    return wf.content_digest()


def particle_bytes(particles: Sequence[Wireframe]) -> int:
    """``sum(p.paper_storage_bytes() for p in particles)`` (paper Sec. IV-G)."""
    return sum(p.paper_storage_bytes() for p in particles)
