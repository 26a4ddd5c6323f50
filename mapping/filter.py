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
  particle corrects it. The scan is placed at that pose in every particle. The pose carries a
  full 3 x 3 covariance of its error in the robot frame (an extended Kalman filter on SE(2)
  relative to the map): the odometry noise model grows it (:meth:`WireframeFilter.predict_covariance`),
  it is the ICP's prior (:func:`mapping.icp.icp`: the scan corrects only the directions it
  constrains better than the odometry, within a Mahalanobis gate), and an accepted match
  replaces it by the ICP's posterior covariance, floored at :attr:`FilterConfig.pose_floor_xy`
  and :attr:`FilterConfig.pose_floor_theta` (the map itself is not more accurate than that).
  The ICP's first correspondence gate follows it too (three standard deviations, the rotation
  taken at half the range, within the ICP config's ``gate_end``..``gate_start``).
* **Re-anchoring.** That covariance is the pose's uncertainty relative to the map *around it*,
  which the robot has just built. A part of the map built long ago can be off from it by the
  drift accumulated in between, more than the gate allows; a rejected match is therefore tried
  once more with the drift (:attr:`FilterConfig.drift_xy`, :attr:`FilterConfig.drift_theta`,
  growing with the square root of the distance driven) added to the prior, and accepted only if
  it constrains all three directions with half the usual residual. The pose then rejoins the
  older map instead of building a second copy beside it (the map's own drift stays: no past
  scan is moved).
* **Gating the map.** A scan that cannot be placed does not touch the map: when a map is in
  view and, after matching, the heading is uncertain by more than
  :attr:`FilterConfig.max_map_sigma_theta` (a sharp turn the scan could not fix), or the match
  failed while the position is uncertain by more than :attr:`FilterConfig.max_map_sigma_xy`
  (lost track), the step only predicts (``StepInfo.mapped`` is False).
* **Frontiers continue established walls** (:func:`snap_frontiers`): before the merge, a scan
  frontier that extends a longer map wall is moved onto that wall's line; a wall growing at its
  frontier would otherwise follow the pose's error and the pose would follow the wall.
* **Walls continue across doorways** (:func:`snap_collinear`): a new scan wall in the line of an
  established map wall, past its end, is put onto that line; door by door a corridor would
  otherwise bend by the pose's heading error at each new wall.
* **Corners are averaged** (:mod:`mapping.refine`): a scan whose match fixed the whole pose
  moves every map corner it observes to the running mean of its observations, until the corner
  has had :attr:`FilterConfig.refine_max_count` of them, before the merge (the merge itself
  keeps the map's position); otherwise the first sighting's pose error stays in the corner for
  good and the pose inherits it.
* **Carving** (:func:`seen_through_spans`, :func:`carve`): stretches of a map wall that a scan
  saw through while it saw the rest of the wall are cut out (a false-positive edge that the
  merge joined to a real collinear wall cannot be removed by mutation, whose unit is the edge).
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
  view (:attr:`FilterConfig.partial_contradiction`). This is how a wrong wall falls below the
  keep threshold "verified through multiple scans" (Sec. IV-F).
* **Wall-direction compass** (:mod:`mapping.compass`, :attr:`FilterConfig.compass`): while the
  match leaves the heading uncertain, the directions of the scan's long walls against the
  building's wall directions (learnt from the first metres driven, then frozen) are fused as a
  heading measurement; the loop closer keeps them as heading factors on its keyframes. While
  the match pins the heading against a map young enough to carry the current drift, the
  measurement still pulls, at a twentieth of its weight (:attr:`FilterConfig.compass_young_weight`).
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
* **Scan clean-up** before anything else: edges that close a gap between two walls' loose
  ends (frontier or occlusion vertices) are dropped (:attr:`FilterConfig.drop_gap_bridges`),
  so are walls along a line of sight (:attr:`FilterConfig.min_line_distance`); short frontier fragments
  (:attr:`FilterConfig.min_fragment_length`) are kept as evidence only (above).
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

from mapping.compass import Directions, Heading, compass_heading, wall_directions
from mapping.icp import ICPConfig, ICPResult, icp
from mapping.likelihood import (
    CONTRADICTED,
    OBSERVED,
    LikelihoodConfig,
    ScanLikelihood,
    in_known_free_space,
    ray_ranges,
    scan_likelihood,
    seen_through,
)
from mapping.loops import Closure, LoopCloser, LoopConfig
from mapping.refine import refine_corners
from mapping.resample import resample_with_mutation
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["FilterConfig", "StepInfo", "WireframeFilter", "budget_map", "budget_scan", "carve", "contradiction_update", "drop_fragments", "drop_line_of_sight", "edge_log_odds", "fragment_mask", "particle_bytes", "seen_fraction", "seen_through_spans"]


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
    carve : bool
        Cut out of a map wall the stretches that a scan saw through while it saw the rest of
        the wall (:func:`seen_through_spans`, :func:`carve`): stretches at least 2.5 merge
        thresholds long, more than one merge threshold from the observed parts, and seen
        through by two consecutive scans (a single scan in which the sensor missed part of a
        wall must not carve it). (Walls the
        prediction does not report, seen from behind or hidden, are not carved: when the corner
        sensor misses the wall in front, p_fn, the one behind looks seen through.) A wall extended
        too far (a false-positive edge that the merge joined to a real collinear wall, across a
        doorway or between aligned pillars) would otherwise stay forever: its likelihood is the
        real wall's, so mutation never drops it. Only partly observed walls are carved; a wall
        the scan misses entirely is a matter for its likelihood (``p_fn``).
    anchored_evidence : bool
        Lower no edge likelihood and carve nothing from a scan whose match against the map in
        view was rejected (and did not even confirm the prediction): its pose is the odometry's, and a wall that looks seen through may
        only be misplaced relative to it (its weight update, resampling and merge still run).
    reanchor : bool
        When a scan match is rejected, try it once more with the prior widened by the map's
        drift (below) and accept it only if it constrains all three directions with half the
        usual residual: a robot coming back to a part of the map built long ago finds it
        where the map put it, which differs from where its recent, locally consistent pose says
        by the drift accumulated in between. Without this the pose could never rejoin the older
        map (its gate is the local uncertainty), and the map would grow a second copy of it.
    drift_xy, drift_theta : float
        Drift of the map relative to itself per square-root metre driven (metres, radians): the
        covariance ``diag(drift_xy^2, drift_xy^2, drift_theta^2) * distance`` is added to the
        prior of the second match; it only grows (defaults: 0.5 m and 1 degree after 500 m).
    max_map_sigma_theta : float
        A scan whose heading standard deviation after matching exceeds this (radians) does not
        touch the map (no likelihood, carving, resampling or merge), when there was a map in view
        to match it against: after a sharp turn (the odometry's heading error grows with the
        angle turned) a scan that could not be matched would be written into the map rotated,
        and the map would then agree with the wrong heading. Position errors are not gated:
        they shift walls by a bounded amount, and a long featureless corridor leaves the
        position along it uncertain for good reasons. Without a map in view (new territory)
        the scan is always used.
    max_map_sigma_xy : float
        Likewise a scan that could not be matched (a map in view, the match rejected) while the
        position's standard deviation exceeds this (metres) does not touch the map: the robot
        has lost track, and what it writes would duplicate walls beside themselves.
    snap_frontiers : bool
        Before merging, move the scan's frontier vertices onto the line of the longer map wall
        they continue (:func:`snap_frontiers`), so that a wall growing at its frontier keeps
        its established line instead of following the pose's error. Also after a match that
        only confirmed the prediction (:attr:`mapping.icp.ICPResult.consistent`: in a corridor,
        right after an accepted match, the scan knows no direction better than the tight
        prior): snapping only after accepted matches let every other scan drag the wall's far
        end by the odometry's heading error, and a museum wall turned by 0.4 degrees over
        40 m.
    snap_collinear : bool
        Before merging, put a new scan wall that continues a map wall at least
        ``collinear_min_support`` long past its end (a corridor wall behind a doorway) onto
        that wall's line, when both its ends are within ``collinear_max_offset`` of the line
        and it runs within ``collinear_max_angle`` of the same direction (:func:`snap_collinear`;
        after accepted matches only). Not in the paper. Measured on the museum, seed 1: mean
        wall error 0.45 -> 0.29 m, recall 0.80 -> 0.89.
    collinear_min_support, collinear_max_offset, collinear_max_angle : float
        Defaults 2 m, 0.08 m, 1.5 degrees.
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
    drop_gap_bridges : bool
        Drop, before anything else, scan edges that join two frontier or occlusion vertices
        each of which also ends another scan edge (not in the paper). Such a vertex is where a
        wall leaves the sensor's range or view; it ends that one wall, so an edge from it to
        another such vertex closes a gap between two walls' loose ends: a false positive
        (the corner sensor's ``p_fp``, Sec. IV-A). Traced on a long corridor (tests/worlds/
        bigring): the false edge across the corridor between the two walls' frontiers at the
        range limit goes into the map, the next scan's own false edge 0.25 m further on matches
        it, and the scan match moves the pose 0.2-0.5 m back along the corridor, where nothing
        else constrains it; the filter's likelihoods only drop the edge a scan later. A real
        wall cut by the range at both ends has frontiers that end only it, and an extracted
        lidar scan (:mod:`mapping.extract`) gives every non-nominal end its own vertex, so
        neither loses anything. Museum seeds 0-7 (with
        the compass's right-angle prior), mean wall distance / recall: 0.144/1.0, 0.134/1.0,
        0.114/1.0, 0.125/1.0, 0.126/1.0, 0.123/1.0, 0.257/0.997, 0.215/1.0 (median 0.130 m),
        particle sets 34,080-35,340 B, precision 0.994-1.0; without: 0.075/1.0, 0.198/1.0,
        0.113/1.0, 0.314/0.994, 0.165/0.990, 0.153/1.0, 0.268/0.997, 0.197/1.0 (median
        0.181 m), 34,380-36,450 B, precision 0.990-0.999. The one-particle baseline gains as
        much (8 seeds: 0.182 m, precision 0.974; 0.90 m, 0.64 before). Ring
        corridor seeds 0-7, precision/recall: 0.991/0.991, 0.993/1.0, 0.653/0.654,
        0.306/0.308, 0.993/1.0, 0.803/0.803, 0.833/0.833, 0.496/0.500 (no false walls any
        more: precision = recall; what is left is along-track drift that no closure
        removes). tests/worlds/slanted seed 0: 1.0/1.0 (was 0.924/1.0: its two false walls
        from a pillar to the room's wall were such bridges).
    odometry_trans_per_m, odometry_rot_per_rad, odometry_rot_per_m : float
        Assumed odometry noise (std per metre driven on each axis, per radian turned, radians
        per metre driven). The pose covariance grows by these while no scan match is accepted
        and shrinks after one; it is the ICP's prior, so a scan step cannot "correct" the pose by
        more than the odometry can plausibly be off (defaults: 1.5 times the simulator's
        :class:`agents.sim.motion.OdometryNoise`, a filter should not trust its odometry more
        than it deserves).
    pose_floor_xy, pose_floor_theta : float
        Least standard deviation (metres, radians) of the pose after an accepted match: the
        pose is relative to a map whose own corners are that uncertain.
    refine_corners : bool
        Move each map corner a scan observes to the mean of its observations before the merge
        (:mod:`mapping.refine`; not in the paper, whose merge keeps one position). Only scans
        whose match was accepted with all three directions constrained refine (measured on the
        museum, seed 1: refining from every consistent scan, degenerate ones included, gave a
        mean wall error of 0.83 m, from fully constrained ones 0.45 m, without 0.48 m).
    refine_max_count : int
        Observations (>= 1) after which a corner is settled and no longer refined (default 10).
    partial_contradiction : bool
        A scan that contradicts a wall it sees only a part of counts for that part: the Bayes
        update of the wall's likelihood (:func:`contradiction_update`) is weighted by the
        length of the wall in view over its length (:func:`seen_fraction`). The paper's edge is
        the unit of evidence; its museum's outer walls are single 200 m edges, 8 m of which are
        in range at a time. Mapped a few tenths of a degree off (the drift of the poses that
        built them), a stretch of such a wall stands in front of the real one, the scans there
        see through it, and with whole updates a few of them took the whole 200 m wall below the
        keep threshold, and mutation dropped it from every particle (museum, seeds 0-4, wall
        recall 0.959/0.889/0.926/0.837/0.752 with whole updates; 0.927/0.925/0.975/0.998/0.842
        weighted, with ``LoopConfig.motion_cov``). Weighted, the wall has to be seen through
        along a good part of its length before it goes. Over seeds 0-7 the gain is smaller than
        those five suggest: median recall 0.926 against 0.908, worst seed 0.79 against 0.75,
        mean distance unchanged (0.308 against 0.305 m); a museum run is chaotic (a 0.008 m
        difference at one loop closure grew into 0.33 against 1.06 m), so judge a change on
        eight seeds, not three. (Tried and not kept:
        cutting the seen-through stretch out, or exempting long walls from contradiction and
        mutation: recall up on most seeds, but a wall cut or kept on a wrong pose's evidence
        then pulled the pose away, 1-2 seeds in 5 collapsed to 0.4-0.7 recall; mutated copies
        that cut the stretch in view of an old long wall instead of dropping all of it: seeds
        0-4 recall 0.905/0.944/0.975/0.983/0.698 against 0.927/0.925/0.975/0.998/0.842.)
    compass : bool
        Fuse a heading measurement from wall directions (:mod:`mapping.compass`, not in the
        paper) whenever the heading's standard deviation after the scan match is above
        ``compass_min_sigma`` (below it, see ``compass_young_weight``): the scan's walls at
        least ``compass_min_length`` long against the building's wall directions as the map
        learnt them (``compass_anchor``), each supported by ``compass_min_support`` metres of
        established walls. After a turn in a hall wider than the range, or when new territory
        comes into view, the ICP has no mapped wall to fix the heading on, and the odometry's
        error of the turn went into every new wall.
    compass_min_sigma, compass_min_length, compass_min_support : float
        Defaults 0.0026 rad (0.15 degrees, just above ``pose_floor_theta``: the compass runs whenever the
        match did not pin the heading down), 2 m, 10 m.
    compass_corner_sigma, compass_model_sigma, compass_max_gate : float
        The measurement's noise model and its largest gate (:func:`mapping.compass.compass_heading`;
        defaults 0.03 m, 0.15 degrees, 6 degrees).
    compass_anchor : float or None
        The reference directions (:class:`mapping.compass.Directions`) are those of the walls
        mapped in the first ``compass_anchor`` metres driven (default 10), frozen then;
        directions met later join when established. ``None``: the reference is the whole map's
        walls at every step, but those the scan match used (counted twice, they made the heading
        look better known than it was, and a 120 m corridor, all of whose map the scan matched,
        came out at 0.36/0.21 wall precision instead of 1.0). Museum seeds 0-7, mean wall distance
        / recall: without the compass 0.311/0.927, 0.260/0.925, 0.270/0.975, 0.198/0.998,
        0.428/0.842, 0.440/0.793, 0.304/0.933, 0.337/0.911 (median 0.308 m, 0.926); whole map
        (``None``) 0.266/0.990, 0.212/0.994, 0.326/0.994, 0.244/0.985, 0.467/0.770, 0.183/0.999,
        0.263/0.986, 0.484/0.765 (median 0.265 m, 0.988: seeds 4 and 7 kept a 0.5-degree error of
        their first 30 m all run long, the map's consensus had it); anchored 0.262/0.976,
        0.200/0.999, 0.276/0.996, 0.188/0.966, 0.152/0.987, 0.217/0.995, 0.183/0.964,
        0.309/0.942 (median 0.208 m, 0.982).
    compass_right_angle : float
        A reference direction within this angle (radians, default 1 degree; 0 turns the prior
        off) of perpendicular to one frozen before it is frozen at exactly perpendicular
        (:class:`mapping.compass.Directions`). Ring corridor (tests/worlds/bigring,
        10 particles, seeds 0-7, wall precision/recall at 0.2 m): without the prior
        0.844/0.890, 0.871/0.916, 0.546/0.571, 0.607/0.654, 0.956/1.0, 0.545/0.563,
        0.685/0.739, 0.956/1.0; with it (squaring to the longest direction, before the
        first-established order) 0.934/0.985, 0.950/1.0, 0.607/0.634, 0.831/0.887, 0.956/1.0,
        0.703/0.742, 0.804/0.852, 0.956/1.0. Museum seeds 0-7, mean wall distance: without
        0.077, 0.151, 0.131, 0.250, 0.197, 0.151, 0.192, 0.263 m (median 0.172), with 0.075,
        0.198, 0.106, 0.314, 0.165, 0.153, 0.268, 0.197 m (median 0.181): a wash there. With
        ``drop_gap_bridges`` as well, see that option.
    compass_young_weight, compass_young_travel : float
        The compass also runs when the scan match pinned the heading down (its standard
        deviation at most ``compass_min_sigma``), provided the map walls the scan was matched
        against were first mapped at most ``compass_young_travel`` metres of driving ago
        (default 25; the median over their corners' birth keyframes), with its variance
        divided by ``compass_young_weight`` (default 0.05: the heading moves by about 5 % of the
        measured offset per scan; 0 turns this off). Why: a map that young carries the drift
        the robot has now, so the match is confident about a heading relative to a map that
        turns with it -- in a long corridor mapped as it is driven, the first metres' error of
        a few tenths of a degree stays for good (ring seed 3: -0.3 degrees over its first side,
        0.74 m off at the end; -0.04 degrees and 0.30 m with it). The small weight lets
        the compass correct the drift over tens of scans without fighting the match on any one
        of them (a pull at the full weight walked museum seed 5's heading 2 degrees off in five
        scans, with the match at every step). Against older walls the match is the better
        reference: they were mapped before the present drift, while the compass's reference
        carries a small bias of its own (museum seed 6: 0.29 degrees, the heading's drift over
        its first 10 m, written into the one 17.8 m wall the reference is frozen from; with an
        exact reference that seed maps at 0.145 m instead of 0.358 m). The part of each
        measurement not applied still goes to the loop closer as a heading factor at the
        measurement's own variance, so a closure can turn the young chain to the walls'
        heading. Ring corridor (tests/worlds/bigring, 10 particles,
        seeds 0-7, precision/recall at 0.2 m): without 0.991/0.991, 0.993/1.0, 0.653/0.654,
        0.306/0.308, 0.993/1.0, 0.803/0.803, 0.833/0.833, 0.496/0.500 (3 pass 95 %); with
        1.0/1.0, 0.967/0.973, 0.993/0.992, 0.954/0.954, 0.993/1.0, 0.666/0.666, 1.0/1.0,
        0.496/0.500 (6 pass; seed 7's route ends before anything fixes its along-track drift,
        seed 5's before it comes back to its first corridor). Museum seeds 0-7, mean wall
        distance: without 0.144, 0.134, 0.114, 0.125, 0.126, 0.123, 0.257, 0.215 m (median
        0.130), with 0.093, 0.122, 0.082, 0.097, 0.160, 0.141, 0.358, 0.196 m (median 0.132;
        seed 6 is the biased reference), recall 0.989-1.0 both: a wash there. Tried: the pull
        whatever the map's age (weight 0.05): ring 6 of 8 as well, museum median 0.139 with seed 4 at
        0.285 m; weight 0.2 without the heading factors: ring 5 of 8, museum median 0.172;
        0.05 without them: ring 4 of 8; the reference frozen after 20 m instead of 10: ring 6
        of 8, museum median 0.142.
    likelihood : LikelihoodConfig
    icp : ICPConfig
    loops : LoopConfig
        Loop closure (:mod:`mapping.loops`): keyframes, birth stamps of the map corners, loop
        detection against the old part of the map, pose-graph optimisation and deformation of
        the particles. Not in the paper; ``LoopConfig(enabled=False)`` is the paper's filter.

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
    drop_gap_bridges: bool = True
    reject_in_free_space: bool = True
    carve: bool = True
    anchored_evidence: bool = True
    reanchor: bool = True
    drift_xy: float = 0.02
    drift_theta: float = 0.0008
    max_map_sigma_theta: float = math.radians(1.0)
    max_map_sigma_xy: float = 0.5
    snap_frontiers: bool = True
    snap_collinear: bool = True
    collinear_min_support: float = 2.0
    collinear_max_offset: float = 0.08
    collinear_max_angle: float = math.radians(1.5)
    odometry_trans_per_m: float = 0.03
    odometry_rot_per_rad: float = 0.03
    odometry_rot_per_m: float = 0.003
    pose_floor_xy: float = 0.01
    pose_floor_theta: float = 0.002
    refine_corners: bool = True
    refine_max_count: int = 10
    partial_contradiction: bool = True
    compass: bool = True
    compass_min_sigma: float = 0.0026
    compass_min_length: float = 2.0
    compass_min_support: float = 10.0
    compass_corner_sigma: float = 0.03
    compass_model_sigma: float = math.radians(0.15)
    compass_max_gate: float = math.radians(6.0)
    compass_anchor: float | None = 10.0
    compass_right_angle: float = math.radians(1.0)
    compass_young_weight: float = 0.05
    compass_young_travel: float = 25.0
    likelihood: LikelihoodConfig = field(default_factory=LikelihoodConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)

    def __post_init__(self) -> None:
        if isinstance(self.particles, bool) or not isinstance(self.particles, (int, np.integer)) or self.particles < 1:
            raise ValueError(f"particles must be an integer >= 1, got {self.particles!r}")
        for name in ("max_range", "merge_threshold", "temperature"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in ("odometry_trans_per_m", "odometry_rot_per_rad", "odometry_rot_per_m", "pose_floor_xy",
                     "pose_floor_theta"):
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
        for name in ("drift_xy", "drift_theta", "collinear_min_support", "collinear_max_offset", "compass_min_sigma",
                     "compass_min_length", "compass_min_support", "compass_corner_sigma", "compass_model_sigma"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {v!r}")
        for name in ("max_map_sigma_theta", "max_map_sigma_xy"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if self.compass_anchor is not None and not (
            isinstance(self.compass_anchor, (int, float)) and math.isfinite(self.compass_anchor) and self.compass_anchor >= 0
        ):
            raise ValueError(f"compass_anchor must be None or a number >= 0, got {self.compass_anchor!r}")
        if not (0.0 <= self.compass_right_angle <= math.pi / 4):
            raise ValueError(f"compass_right_angle must be within [0, pi/4], got {self.compass_right_angle!r}")
        if not (0.0 <= self.compass_young_weight <= 1.0):
            raise ValueError(f"compass_young_weight must be within [0, 1], got {self.compass_young_weight!r}")
        if not (isinstance(self.compass_young_travel, (int, float)) and self.compass_young_travel >= 0):
            raise ValueError(f"compass_young_travel must be a number >= 0, got {self.compass_young_travel!r}")
        if not (0.0 < self.compass_max_gate <= math.pi / 4):
            raise ValueError(f"compass_max_gate must be within (0, pi/4], got {self.compass_max_gate!r}")
        if not (0.0 <= self.collinear_max_angle <= math.pi / 2):
            raise ValueError(f"collinear_max_angle must be within [0, pi/2], got {self.collinear_max_angle!r}")
        if isinstance(self.refine_max_count, bool) or not isinstance(self.refine_max_count, (int, np.integer)) \
                or self.refine_max_count < 1:
            raise ValueError(f"refine_max_count must be an integer >= 1, got {self.refine_max_count!r}")
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
    mapped : bool
        Whether the scan updated the particles (False when its pose was too uncertain, see
        :attr:`FilterConfig.max_map_sigma_theta`).
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
def fragment_mask(scan: Wireframe, min_length: float) -> BoolArray:
    """The scan edges to keep: all but those shorter than ``min_length`` with a frontier end
    (see :attr:`FilterConfig.min_fragment_length`)."""
    if scan.n_edges == 0 or min_length <= 0:
        return np.ones(scan.n_edges, dtype=bool)
    fr = scan.labels[scan.edges] == Label.FRONTIER
    return np.asarray(~((scan.edge_lengths() < min_length) & fr.any(axis=1)))


def drop_fragments(scan: Wireframe, min_length: float) -> Wireframe:
    """Drop scan edges shorter than ``min_length`` that have a frontier end (see
    :attr:`FilterConfig.min_fragment_length`)."""
    keep = fragment_mask(scan, min_length)
    return scan if keep.all() else scan.subgraph_edges(keep)


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


def drop_gap_bridges(scan: Wireframe) -> Wireframe:
    """Drop scan edges that join two non-nominal vertices each of which also ends another edge
    (see :attr:`FilterConfig.drop_gap_bridges`)."""
    if scan.n_edges == 0:
        return scan
    din, dout = scan.degree()
    loose = (scan.labels != Label.NOMINAL) & (din + dout >= 2)
    bad = loose[scan.edges[:, 0]] & loose[scan.edges[:, 1]]
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


#: Edge likelihoods are capped here before a contradiction update: merging combines them as
#: ``1 - (1 - L1)(1 - L2)``, which rounds to exactly 1.0 after a few dozen sightings, and a
#: likelihood of exactly 1 could never be lowered again. At 0.999, four contradicting scans
#: take a wall below a keep threshold of 0.5.
MAX_LIKELIHOOD = 0.999


def contradiction_update(
    likelihood: FloatArray, p_fp: float, p_fn: float, weight: float | FloatArray = 1.0
) -> FloatArray:
    """Bayes update of an edge's existence likelihood after a scan that saw through it:
    ``L p_fn / (L p_fn + (1 - L)(1 - p_fp))``, with ``L`` first capped at
    :data:`MAX_LIKELIHOOD`. With ``weight`` ``w`` (per edge, in [0, 1]) the update counts for
    that fraction of a whole one: the odds are multiplied by ``(p_fn / (1 - p_fp)) ** w``
    (``w = 1`` is the formula above, ``w = 0`` leaves ``L``)."""
    L = np.minimum(np.asarray(likelihood, dtype=np.float64), MAX_LIKELIHOOD)
    ratio = np.power(p_fn / (1.0 - p_fp), np.asarray(weight, dtype=np.float64))
    num = L * ratio
    den = num + (1.0 - L)
    return np.asarray(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), dtype=np.float64)


def seen_fraction(wf: Wireframe, view: Wireframe, edge_source: IntArray) -> FloatArray:
    """Per edge of ``wf``: the length of its pieces in the predicted scan ``view``
    (``edge_source``: the map edge of each view edge) over its own length, in [0, 1]; 1 for an
    edge with no piece in the view (hidden or back-facing: see the filter's step 4)."""
    src = np.asarray(edge_source, dtype=np.int64)
    ok = src >= 0
    seen = np.bincount(src[ok], weights=view.edge_lengths()[ok], minlength=wf.n_edges)
    frac = np.clip(seen / np.maximum(wf.edge_lengths(), 1e-12), 0.0, 1.0)
    return np.asarray(np.where(seen > 0, frac, 1.0), dtype=np.float64)


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


def seen_through_spans(
    wf: Wireframe,
    pose: Pose,
    view: Wireframe,
    edge_source: IntArray,
    edge_pairs: IntArray,
    evidence: Wireframe,
    min_span: float,
    cover_margin: float,
    margin: float,
    max_range: float,
) -> dict[int, list[tuple[float, float]]]:
    """Parts of map edges that this scan observed in part and saw through elsewhere.

    For every predicted edge (a visible piece of map edge ``e``) that some scan edges match
    (``edge_pairs``: ``(scan edge, predicted edge)``), the matched scan edges are projected on
    ``e``'s line and their union, grown by ``cover_margin`` at both ends, is *covered*. Each
    uncovered stretch of the visible piece at least ``min_span`` long whose three sample points
    (a quarter, half and three quarters along) the scan saw through -- its ray at that bearing
    meets no scan wall before the point plus ``margin``, and the point is within ``max_range``
    minus ``margin`` (no wall within range is seen-through too: a corner sensor reports every
    wall in range) -- is returned, as arc-length intervals along ``e`` from its start.

    This is the evidence that carves a wall that was extended too far (a false-positive edge
    joined to a real collinear wall by the merge, e.g. across a doorway or between aligned
    pillars): the scan sees the real part and sees through the rest.

    Parameters
    ----------
    wf : Wireframe
        The particle's map (world frame).
    pose : Pose
        Where the scan was taken.
    view : Wireframe
        The predicted scan (robot frame) and ``edge_source``, the map edge of each of its edges.
    edge_pairs : (k, 2) int
        Edge correspondences between ``evidence`` and ``view``.
    evidence : Wireframe
        The scan (robot frame).

    Returns
    -------
    dict
        Map edge index -> list of ``(t0, t1)`` intervals (metres along the edge), disjoint.
    """
    out: dict[int, list[tuple[float, float]]] = {}
    if len(edge_pairs) == 0 or view.n_edges == 0:
        return out
    src = np.asarray(edge_source, dtype=np.int64)
    ends = pose.apply_inverse(wf.points[wf.edges].reshape(-1, 2)).reshape(-1, 2, 2)
    vseg = view.segments()
    sseg = evidence.segments()
    by_pred: dict[int, list[int]] = {}
    for si, pj in edge_pairs.tolist():
        by_pred.setdefault(int(pj), []).append(int(si))
    samples: list[FloatArray] = []
    meta: list[tuple[int, float, float]] = []
    for pj, scan_edges in by_pred.items():
        e = int(src[pj])
        if e < 0:
            continue
        a, b = ends[e]
        d = b - a
        length = float(math.hypot(d[0], d[1]))
        if length < min_span:
            continue
        u = d / length
        v0, v1 = sorted(float((q - a) @ u) for q in vseg[pj])
        v0, v1 = max(v0, 0.0), min(v1, length)
        if v1 - v0 < min_span:
            continue
        cov = sorted(
            (min(t0, t1) - cover_margin, max(t0, t1) + cover_margin)
            for t0, t1 in (((sseg[i, 0] - a) @ u, (sseg[i, 1] - a) @ u) for i in scan_edges)
        )
        gaps: list[tuple[float, float]] = []
        cur = v0
        for c0, c1 in cov:
            if c0 > cur:
                gaps.append((cur, min(c0, v1)))
            cur = max(cur, c1)
            if cur >= v1:
                break
        if cur < v1:
            gaps.append((cur, v1))
        for g0, g1 in gaps:
            if g1 - g0 >= min_span:
                t = g0 + (g1 - g0) * np.array([0.25, 0.5, 0.75])
                samples.append(a + t[:, None] * u)
                meta.append((e, float(g0), float(g1)))
    if not samples:
        return out
    pts = np.concatenate(samples)
    dist = np.hypot(pts[:, 0], pts[:, 1])
    rng_scan = ray_ranges(evidence, np.arctan2(pts[:, 1], pts[:, 0]))
    seen = np.asarray((rng_scan > dist + margin) & (dist <= max_range - margin), dtype=bool)
    all_seen: list[bool] = np.asarray(seen.reshape(-1, 3).all(axis=1), dtype=bool).tolist()
    for (e, g0, g1), good in zip(meta, all_seen):
        if good:
            out.setdefault(e, []).append((g0, g1))
    for e in out:
        out[e].sort()
    return out


def snap_frontiers(
    scan_points: FloatArray,
    scan: Wireframe,
    ref: Wireframe,
    edge_pairs: IntArray,
    support: FloatArray,
    max_offset: float,
) -> FloatArray:
    """Frontier vertices of the scan moved onto the line of the map wall they continue.

    A frontier vertex is where sight of a wall ended, not a corner: its position *along* the
    wall says how far the wall was seen, its position *across* it is only as good as the pose.
    When the scan edge that ends in it corresponds (``edge_pairs``: ``(scan edge, ref edge)``)
    to a reference edge whose map wall (``support``: length of the map wall behind each
    reference edge) is longer than the scan edge, the established wall knows its line better:
    the vertex is projected onto that line if that moves it by at most ``max_offset``.
    Otherwise a wall growing scan by scan at its frontier would follow the pose's error (its
    newest end is placed by the newest pose), and matching the next scan against it could not
    see that error: the map and the pose would drift together.

    Parameters
    ----------
    scan_points : (n, 2)
        The scan's vertices, in the reference's frame (moved by the ICP correction).
    scan, ref : Wireframe
        The scan and the reference (predicted scan).
    edge_pairs : (k, 2) int
    support : (ref.n_edges,) float
    max_offset : float

    Returns
    -------
    (n, 2) float64
        The vertices, frontiers snapped where the rule applies.
    """
    out = np.array(scan_points, dtype=np.float64, copy=True)
    if len(edge_pairs) == 0:
        return out
    s_len = np.hypot(*(scan_points[scan.edges[:, 1]] - scan_points[scan.edges[:, 0]]).T)
    best: dict[int, tuple[float, int]] = {}
    for si, rj in edge_pairs.tolist():
        sup = float(support[rj])
        if sup <= s_len[si]:
            continue
        for v in scan.edges[si].tolist():
            if scan.labels[v] == Label.FRONTIER and sup > best.get(v, (-1.0, -1))[0]:
                best[v] = (sup, rj)
    for v, (_, rj) in best.items():
        a, b = ref.points[ref.edges[rj, 0]], ref.points[ref.edges[rj, 1]]
        d = b - a
        ln = float(math.hypot(d[0], d[1]))
        if ln <= 0:
            continue
        n = np.array([-d[1], d[0]]) / ln
        off = float((out[v] - a) @ n)
        if abs(off) <= max_offset:
            out[v] = out[v] - off * n
    return out


def snap_collinear(
    scan_points: FloatArray,
    scan: Wireframe,
    ref: Wireframe,
    edge_pairs: IntArray,
    support: FloatArray,
    min_support: float,
    max_offset: float,
    max_angle: float,
) -> FloatArray:
    """Scan walls that continue an established map wall across a gap put onto its line.

    A wall behind a doorway is new to the map, so nothing pins it: it enters at the pose's
    heading, a tenth of a degree off, and the next wall of the corridor continues *it*; door by
    door the corridor bends. Buildings are built along lines: a new scan wall (no reference edge
    corresponds to it) that runs in the same direction as a map wall at least ``min_support``
    long (within ``max_angle``, same free side) with both ends within ``max_offset`` of that
    wall's line, beyond its extent, is taken to continue it, and its ends are projected onto
    the line. A wall genuinely offset by less than ``max_offset`` is straightened by at most
    that much.

    Parameters
    ----------
    scan_points : (n, 2)
        The scan's vertices in the reference's frame.
    scan, ref : Wireframe
    edge_pairs : (k, 2) int
        ``(scan edge, ref edge)`` correspondences of the match.
    support : (ref.n_edges,) float
        Length of the map wall behind each reference edge (0 where none).
    min_support, max_offset, max_angle : float

    Returns
    -------
    (n, 2) float64
    """
    out = np.array(scan_points, dtype=np.float64, copy=True)
    if scan.n_edges == 0 or ref.n_edges == 0:
        return out
    new = np.ones(scan.n_edges, dtype=bool)
    if len(edge_pairs):
        new[edge_pairs[:, 0]] = False
    cand = np.flatnonzero(support >= min_support)
    if not new.any() or len(cand) == 0:
        return out
    ra, rb = ref.points[ref.edges[cand, 0]], ref.points[ref.edges[cand, 1]]
    rd = rb - ra
    rl = np.hypot(rd[:, 0], rd[:, 1])
    ru = rd / np.maximum(rl, 1e-12)[:, None]
    rn = np.stack([-ru[:, 1], ru[:, 0]], axis=1)
    cos_tol = math.cos(max_angle)
    moved: dict[int, FloatArray] = {}
    for si in np.flatnonzero(new).tolist():
        i, j = scan.edges[si].tolist()
        p, q = out[i], out[j]
        d = q - p
        ln = math.hypot(d[0], d[1])
        if ln <= 0:
            continue
        ok = (ru @ (d / ln)) >= cos_tol
        op = np.einsum("ij,ij->i", p - ra, rn)
        oq = np.einsum("ij,ij->i", q - ra, rn)
        ok &= (np.abs(op) <= max_offset) & (np.abs(oq) <= max_offset)
        tp = np.einsum("ij,ij->i", p - ra, ru)
        tq = np.einsum("ij,ij->i", q - ra, ru)
        ok &= (np.minimum(tp, tq) >= rl - 1e-9) | (np.maximum(tp, tq) <= 1e-9)  # beyond its extent
        if not ok.any():
            continue
        k = int(np.flatnonzero(ok)[np.argmax(rl[ok])])
        for v, off in ((i, op[k]), (j, oq[k])):
            if v not in moved:
                moved[v] = out[v] - off * rn[k]
    for v, pt in moved.items():
        out[v] = pt
    return out


def carve(wf: Wireframe, spans: dict[int, list[tuple[float, float]]]) -> tuple[Wireframe, IntArray]:
    """Remove the ``spans`` (arc-length intervals along edges, see :func:`seen_through_spans`)
    from the edges of ``wf``. The remaining pieces keep the edge's direction, likelihood and
    sources; a cut point is a new ``FRONTIER`` vertex (sight of the wall ends there).

    Returns
    -------
    Wireframe
        The kept edges of ``wf`` in order, then the new pieces.
    origin : (m',) int64
        For each edge of the result, the edge of ``wf`` it comes from.
    """
    if not spans:
        return wf, np.arange(wf.n_edges, dtype=np.int64)
    pts = [wf.points]
    labels = [wf.labels]
    n = wf.n_vertices
    new_edges: list[tuple[int, int]] = []
    origin_new: list[int] = []
    for e, ivs in sorted(spans.items()):
        i, j = (int(v) for v in wf.edges[e])
        a, b = wf.points[i], wf.points[j]
        d = b - a
        length = float(math.hypot(d[0], d[1]))
        u = d / length
        cur_v, cur_t = i, 0.0
        for t0, t1 in ivs:
            if t0 > cur_t + 1e-9:
                if t0 >= length - 1e-9:
                    end_v = j
                else:
                    pts.append((a + t0 * u)[None, :])
                    labels.append(np.array([Label.FRONTIER], dtype=np.uint8))
                    end_v = n
                    n += 1
                new_edges.append((cur_v, end_v))
                origin_new.append(e)
            if t1 >= length - 1e-9:
                cur_v, cur_t = -1, length
                break
            pts.append((a + t1 * u)[None, :])
            labels.append(np.array([Label.FRONTIER], dtype=np.uint8))
            cur_v, cur_t = n, t1
            n += 1
        if cur_v >= 0 and cur_t < length - 1e-9:
            new_edges.append((cur_v, j))
            origin_new.append(e)
    keep = np.ones(wf.n_edges, dtype=bool)
    keep[list(spans)] = False
    kept = np.flatnonzero(keep)
    org = np.asarray(origin_new, dtype=np.int64)
    edges = np.concatenate([wf.edges[kept], np.asarray(new_edges, dtype=np.int64).reshape(-1, 2)])
    out = Wireframe(
        np.concatenate(pts),
        np.concatenate(labels),
        edges,  # type: ignore[arg-type]
        np.concatenate([wf.likelihood[kept], wf.likelihood[org]]),
        np.concatenate([wf.sources[kept], wf.sources[org]]),
    ).compacted()
    return out, np.concatenate([kept, org]).astype(np.int64)


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
        self._cov = np.diag([config.pose_floor_xy**2, config.pose_floor_xy**2, config.pose_floor_theta**2])
        self._drift = np.zeros((3, 3))
        self._pending_spans = np.zeros((0, 2, 2))
        self._view_fn: ViewFn = view_fn or _default_view
        self._merge_fn: MergeFn = merge_fn or _default_merge
        self._loops = LoopCloser(config.loops, self._pose)
        self._directions = Directions(
            config.compass_anchor or 0.0, config.compass_min_support, config.compass_max_gate,
            right_angle=config.compass_right_angle,
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
        st = cfg.odometry_trans_per_m * d
        sr = cfg.odometry_rot_per_rad * abs(odometry.theta) + cfg.odometry_rot_per_m * d
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
        ``compass_anchor=None``, the established walls of ``best`` but the edges ``matched``,
        those the scan match already used), fused into the pose and its covariance as a Kalman
        update of the heading with the measurement's variance divided by ``weight`` (the
        position moves with it through the covariance's cross terms); the part of the
        measurement the update did not apply goes to the loop closer as a heading factor, at
        the measurement's own variance. Returns the pose and the measurement (None: none)."""
        cfg = self.config
        sd, sl = wall_directions(scan, cfg.compass_min_length)
        if len(sd) == 0:
            return pose, None
        if cfg.compass_anchor is not None:
            md, ml = self._directions.reference()
        else:
            ref = best
            if len(matched):
                keep = np.ones(best.n_edges, dtype=bool)
                keep[matched] = False
                ref = best.subgraph_edges(keep)
            md, ml = wall_directions(ref, cfg.compass_min_length, cfg.keep_threshold)
        h = compass_heading(
            np.mod(sd + pose.theta, math.pi), sl, md, ml, math.sqrt(self._cov[2, 2]),
            corner_sigma=cfg.compass_corner_sigma, model_sigma=cfg.compass_model_sigma,
            min_support=cfg.compass_min_support, max_gate=cfg.compass_max_gate,
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

    def _match(self, scan: Wireframe, ref: Wireframe, prior: FloatArray) -> ICPResult:
        """ICP of ``scan`` on ``ref`` with ``prior`` as the correction's prior; the first
        correspondence gate is three standard deviations (the rotation's taken at half the
        range), within the ICP config's ``gate_end``..``gate_start``."""
        cfg = self.config
        reach = 3.0 * (math.sqrt(max(prior[0, 0], prior[1, 1])) + math.sqrt(prior[2, 2]) * 0.5 * cfg.max_range)
        icfg = dataclasses.replace(cfg.icp, gate_start=min(cfg.icp.gate_start, max(cfg.icp.gate_end, reach)))
        return icp(scan, ref, icfg, prior_covariance=prior)

    # ------------------------------------------------------------------ the step
    @property
    def loops(self) -> LoopCloser:
        """The loop-closure back end (keyframes, closures so far)."""
        return self._loops

    def step(self, odometry: Pose, scan: Wireframe, *, fault: Pose | None = None) -> StepInfo:
        """One filter iteration (paper Fig. 7), then the loop-closure check (:mod:`mapping.loops`).

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
        info, matched_scan = self._step(odometry, scan, fault)
        # Keyframes, births and observation counts (mapping.loops, mapping.refine).
        lc = self._loops
        inc = self.motion_increment(odometry, info.icp) if lc.config.motion_cov else None
        lc.advance(self._pose, math.hypot(odometry.x, odometry.y) + 0.5 * abs(odometry.theta), inc)
        lc.stamp(self._particles)
        if self._steps % 500 == 0:
            lc.prune(self._particles)
        if self.config.loops.enabled:
            closed = self._close_loops(matched_scan)
            if closed is not None:
                info = dataclasses.replace(info, pose=self._pose, loop=closed)
        return info

    def _close_loops(self, scan: Wireframe) -> Closure | None:
        """After a step: every ``check_every`` metres, the scan matched against the old part of
        the best map, and a closure when it is off."""
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

        res = self._match(scan, ref, prior)
        if not good(res):
            return None
        here = self._pose  # where the young chain puts the robot
        yref = self.predicted_view(young, self._pose)[0] if young.n_edges else Wireframe.empty()
        if yref.n_edges >= lcfg.min_old_edges:
            yres = self._match(scan, yref, prior)
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

    def _step(self, odometry: Pose, scan: Wireframe, fault: Pose | None) -> tuple[StepInfo, Wireframe]:
        cfg = self.config
        self._steps += 1
        # The evidence (likelihood, contradictions) is the whole scan but for its gap bridges and
        # its walls along a line of sight; the scan that is matched and merged also loses its
        # short fragments.
        if cfg.drop_gap_bridges:
            scan = drop_gap_bridges(scan)
        evidence = budget_scan(drop_line_of_sight(scan, cfg.min_line_distance), cfg.max_scan_vertices)
        kept = fragment_mask(evidence, cfg.min_fragment_length)
        kept_idx = np.flatnonzero(kept)
        scan = evidence if kept.all() else evidence.subgraph_edges(kept)
        predicted = self._pose.compose(odometry)
        pose = predicted
        raw_scan = scan
        icp_res: ICPResult | None = None
        best = self._particles[self._best]
        self._cov = self.predict_covariance(self._cov, odometry)
        d = math.hypot(odometry.x, odometry.y)
        self._drift = self._drift + np.diag(
            [cfg.drift_xy**2 * d, cfg.drift_xy**2 * d, cfg.drift_theta**2 * d]
        )
        matched_edges = np.zeros(0, dtype=np.int64)  # the map edges the scan was matched against
        if cfg.use_icp and best.n_edges and scan.n_edges:
            ref, ref_src, _ = self.predicted_view(best, predicted)
            matched_edges = ref_src[ref_src >= 0]
            if ref.n_vertices:
                icp_res = self._match(scan, ref, self._cov)
                if not icp_res.accepted and cfg.reanchor and scan.n_edges >= 2:
                    # The map in view may be older than the pose's uncertainty says (module
                    # docstring, "re-anchoring"): try again with the drift added to the prior.
                    again = self._match(scan, ref, self._cov + self._drift)
                    if again.accepted and again.constrained == 3 and again.rmse <= 0.5 * cfg.icp.max_rmse:
                        icp_res = again
                if icp_res.consistent and cfg.snap_frontiers:
                    # Also a scan that only confirms the prediction (ICPResult.consistent): its
                    # frontiers must not drag an established wall's line either.
                    corr = icp_res.correction if icp_res.accepted else Pose.identity()
                    support = best.edge_lengths()[np.maximum(ref_src, 0)] * (ref_src >= 0)
                    sp = snap_frontiers(
                        corr.apply(scan.points), scan, ref, icp_res.correspondences.edge_pairs,
                        support, cfg.icp.gate_end,
                    )
                    if cfg.snap_collinear and icp_res.accepted:
                        sp = snap_collinear(
                            sp, scan, ref, icp_res.correspondences.edge_pairs, support,
                            cfg.collinear_min_support, cfg.collinear_max_offset, cfg.collinear_max_angle,
                        )
                    scan = scan.replace(points=corr.inverse().apply(sp))
                if icp_res.accepted:
                    pose = predicted.compose(icp_res.correction)
                    C = np.array(icp_res.covariance, dtype=np.float64)
                    floor = np.array([cfg.pose_floor_xy, cfg.pose_floor_xy, cfg.pose_floor_theta]) ** 2
                    C[np.diag_indices(3)] = np.maximum(np.diag(C), floor)
                    self._cov = C
        heading: Heading | None = None
        if cfg.compass and best.n_edges:
            need = scan.n_edges > 0 and math.sqrt(self._cov[2, 2]) > cfg.compass_min_sigma
            if cfg.compass_anchor is not None:
                anchoring = self._loops.distance < cfg.compass_anchor
                if anchoring or need or not self._directions.settled:
                    md, ml = wall_directions(best, cfg.compass_min_length, cfg.keep_threshold)
                    self._directions.update(md, ml, self._loops.distance)
            if need:
                pose, heading = self._compass(scan, pose, best, matched_edges)
            elif (cfg.compass_young_weight > 0 and scan.n_edges
                    and self._loops.age(best.points[np.unique(best.edges[matched_edges])])
                    <= cfg.compass_young_travel):
                # The match pinned the heading down, but against walls as young as the drift
                # they carry: the compass still pulls, slowly (FilterConfig.compass_young_weight).
                # No wall matched, or none stamped yet, is age 0: nothing says the map is old.
                pose, heading = self._compass(scan, pose, best, matched_edges, cfg.compass_young_weight)
        self._pose = pose
        place = pose if fault is None else pose.compose(fault)
        lost = (
            icp_res is not None
            and not icp_res.accepted
            and math.sqrt(max(self._cov[0, 0], self._cov[1, 1])) > cfg.max_map_sigma_xy
        )
        if lost or (icp_res is not None and math.sqrt(self._cov[2, 2]) > cfg.max_map_sigma_theta):
            # The scan cannot be placed well enough to touch the map (module docstring).
            return (StepInfo(
                step=self._steps,
                pose=pose,
                predicted_pose=predicted,
                icp=icp_res,
                log_likelihoods=np.zeros(len(self._particles)),
                best=self._best,
                distinct=self.distinct_particles(),
                mutated=0,
                mapped=False,
                compass=heading,
            ), raw_scan)

        lcfg = cfg.likelihood
        # Negative evidence (contradictions, carving) needs the scan placed against the map: not
        # from a scan whose match with a map in view was rejected.
        anchored = icp_res is None or icp_res.consistent or not cfg.anchored_evidence
        evals: dict[int, _Eval] = {}
        seen_spans: list[FloatArray] = []
        for p in self._particles:
            if id(p) in evals:
                continue
            view, src, unreported = self.predicted_view(p, place)
            lik = scan_likelihood(evidence, view, lcfg, max_range=cfg.max_range)
            in_sight, observed, contra = _edge_states(p.n_edges, src, lik.predicted_edge_state)
            # Edges in view that the prediction does not report (back-facing, or hidden behind
            # another map edge): contradicted when the scan saw through them.
            through = np.zeros(p.n_edges, dtype=bool)
            cand_hidden = np.flatnonzero(unreported & ~observed)
            if len(cand_hidden) and evidence.n_edges:
                segs = place.apply_inverse(p.points[p.edges[cand_hidden]].reshape(-1, 2)).reshape(-1, 2, 2)
                through[cand_hidden] = seen_through(
                    evidence, segs, lcfg.occlusion_margin, cfg.max_range, min_incidence=lcfg.min_incidence
                )
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
                weight = seen_fraction(p, view, src)[contra] if cfg.partial_contradiction else 1.0
                L[contra] = contradiction_update(L[contra], lcfg.p_fp, lcfg.p_fn, weight)
                updated = p.replace(likelihood=L)
            spans: dict[int, list[tuple[float, float]]] = {}
            if cfg.carve and anchored:
                found = seen_through_spans(
                    p, place, view, src, lik.correspondences.edge_pairs, evidence,
                    2.5 * cfg.merge_threshold, cfg.merge_threshold, lcfg.occlusion_margin, cfg.max_range,
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
            # New scan edges where this particle is sure there is free space are not merged into
            # it (static world: a false positive or a passer-by).
            merge_mask = np.ones(scan.n_edges, dtype=bool)
            if cfg.reject_in_free_space and scan.n_edges and view.n_edges:
                unm = np.flatnonzero(~lik.scan_edge_matched[kept_idx])
                if len(unm):
                    free = in_known_free_space(
                        view, scan.segments()[unm], lcfg.occlusion_margin, cfg.keep_threshold
                    )
                    merge_mask[unm[free]] = False
            # Candidates for mutation (Sec. IV-F, "within sight (or predicted sight)"): every edge
            # in view, reported or not, that this scan does not observe.
            cands = (in_sight | unreported) & ~observed
            if spans:
                group += repr(sorted(spans.items())).encode()
                updated, origin = carve(updated, spans)
                in_sight, cands = in_sight[origin], cands[origin]
            evals[id(p)] = _Eval(
                lik, updated, in_sight, cands, lik.scan_edge_likelihood[kept_idx], group, merge_mask
            )

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
        refined: dict[int, Wireframe] = {}
        new: list[Wireframe] = []
        # Corner refinement (mapping.refine) only from a scan whose match fixed all three
        # directions of the pose: along a degenerate direction (a corridor's axis) the pose is
        # the odometry's, and averaging it in would drag the corners along with its error.
        refine = cfg.refine_corners and (icp_res is None or (icp_res.accepted and icp_res.constrained == 3))
        placed = scan.transformed(place)  # the scan in the map frame, for every merge below
        for k, q in enumerate(res.particles):
            parent = self._particles[int(res.indexes[k])]
            key = (id(q), id(parent))
            if key not in merged:
                ev = evals[id(parent)]
                scan_world = placed.replace(likelihood=ev.scan_edge_likelihood)
                if not ev.merge_mask.all():
                    scan_world = scan_world.subgraph_edges(ev.merge_mask)
                if refine and q.n_vertices:
                    if id(q) not in refined:
                        rq, moved = refine_corners(
                            q, placed, cfg.merge_threshold, self._loops.counts(q.points), cfg.refine_max_count
                        )
                        self._loops.moved(moved.old, moved.new, moved.counts)
                        refined[id(q)] = rq
                    q = refined[id(q)]
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
        self._pending_spans = np.concatenate(seen_spans) if seen_spans else np.zeros((0, 2, 2))
        self._weights = np.full(len(new), 1.0 / len(new))
        return (StepInfo(
            step=self._steps,
            pose=pose,
            predicted_pose=predicted,
            icp=icp_res,
            log_likelihoods=loglik,
            best=self._best,
            distinct=self.distinct_particles(),
            mutated=int(res.mutated.sum()),
            compass=heading,
        ), raw_scan)


def _content_key(wf: Wireframe) -> bytes:
    return b"".join(
        (wf.points.tobytes(), wf.labels.tobytes(), wf.edges.tobytes(), wf.likelihood.tobytes(), wf.sources.tobytes())
    )


def particle_bytes(particles: Sequence[Wireframe]) -> int:
    """``sum(p.paper_storage_bytes() for p in particles)`` (paper Sec. IV-G)."""
    return sum(p.paper_storage_bytes() for p in particles)
