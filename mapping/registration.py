"""Global registration of two wireframes in unrelated frames (robots that never met).

Given two maps ``A`` and ``B`` (each in the frame of its own robot's start pose), find the rigid
motion ``T`` such that ``B.transformed(T)`` lies on ``A`` -- or say that the evidence supports no
such motion. Nothing is assumed about the start poses: every step is invariant to a rigid motion
of either map.

Pipeline
--------
1. **Per-map features** (:func:`prepare`, once per map; the fusion service keeps them per robot
   and registers pairs with :func:`register_prepared`):

   * *wall samples*: every directed edge cut into pieces of about ``sample_spacing`` metres, each
     piece's midpoint, unit direction and length (a k-d tree over the midpoints);
   * *wall ends*: every end of an edge at a real corner (nominal or occlusion vertex, never a
     frontier: a frontier is where sight of a wall ended, not where the wall ends), with the
     edge's direction and whether the edge starts or ends there;
   * *free probes*: points ``free_depths`` metres to the left (the free side, see
     :mod:`mapping.wireframe`) of every wall sample that is at least ``probe_end_margin`` from
     the wall's ends, dropped when closer than ``free_clearance`` to any wall of the map, and
     deeper, every ``free_reach_step`` up to the wall in front, where that wall (within
     ``free_reach``) faces back. The robot saw the wall from its left, through that strip, and
     two walls that look at each other were seen across the space between them: it is space
     the map has *seen free*.
     This is the map's free space without a trajectory and without closed faces
     (:func:`mapping.metrics.free_space` needs closed rooms, which partial maps rarely have);
   * the *direction histogram*: wall length per directed direction (``direction_bins`` bins,
     Gaussian-smoothed by ``direction_smooth``).

2. **Rotation hypotheses.** The circular cross-correlation of the two direction histograms (FFT)
   peaks at the rotations that turn B's walls onto A's; up to ``max_rotations`` local maxima of at
   least ``rotation_peak_ratio`` times the highest are kept, each refined by a parabola through
   the peak and its neighbours. Directed walls make the histogram span 360 degrees, so a
   rectangular room gives four hypotheses, not two; the ambiguity that remains is resolved by
   the translation and verification steps.

3. **Translation voting** (a Hough transform over corner pairs). Under a rotation, a wall end of
   B and one of A with the same role (start or end of its edge) and directions within
   ``feature_angle_tol`` propose the translation that puts one on the other. Each proposal votes
   with the shorter of the two walls' lengths (capped at ``vote_weight_cap``: one long wall must
   not outvote many corners), split bilinearly over the four nearest cells of a ``vote_cell``
   grid; a nominal corner votes twice (once per wall), which favours full corners. The strongest
   cells, at least ``peak_separation`` apart, are the candidate translations
   (``peaks_per_rotation`` per rotation). Both maps are centred on their wall centroid first, so
   that a small rotation error spreads the votes as little as possible. With more than
   ``coarse_vote_pairs`` proposals (large maps), a vote on cells ``coarse_vote_factor`` times
   larger first picks the ``coarse_vote_cells`` strongest regions (and every region tied with the
   last of them); only their proposals vote on the fine grid.

4. **Verification.** The ``verify_candidates`` strongest candidates are scored: B's wall samples
   are moved by the candidate and matched to A's (within ``coarse_match_dist``, same direction
   within ``match_angle``): *support* is the matched wall length. *Conflict* is the wall length of
   each map that falls onto the other's free probes (within ``conflict_radius``), in both
   directions (B's walls on A's seen-free space and A's on B's): a wall where the other robot has
   seen free space, the false-merge guard. What a wall sample weighs in a conflict is made for
   filter-built maps: its edge's likelihood times its length, nothing for an edge shorter than
   ``conflict_min_wall`` (clutter, spurious slivers) or within ``frontier_margin`` of a frontier
   end (where sight of the wall ended, the wall runs on by the filter's drift), and
   ``displaced_weight`` of it when a wall of the other map of the same direction lies within
   ``displaced_dist`` (a drifted copy of that wall, not a foreign one). The score is ``support -
   conflict_weight * conflict``.

5. **Refinement.** The ``refine_candidates`` best are refined by iteratively re-matched
   point-to-line least squares on the wall samples (each matched B sample against the line of
   its A sample, Huber-weighted, gate shrinking to ``match_dist``) and re-scored at the final
   gate. The result is polished by the wireframe ICP :func:`mapping.icp.icp` on the two maps
   cropped to the overlap (used only when ICP accepts its correction and the score does not
   drop).

6. **Decision.** The best refined hypothesis is compared with the best *distinct* one (a
   translation more than ``distinct_translation`` or a rotation more than ``distinct_rotation``
   away, among every verified hypothesis): repeated structure (identical offices along a
   corridor) gives two similar scores and is refused rather than guessed. Accepted when all of

   * ``support >= min_support`` metres and ``support >= min_support_fraction`` of the smaller map;
   * ``conflict <= max_conflict + max_conflict_fraction * support``, and at most
     ``contested_max_conflict`` when the runner-up ratio exceeds ``conflict_runner_up_ratio``;
   * ``runner_up_ratio <= max_runner_up_ratio``. A distinct rival's ratio is the smaller of
     its *corner ratio* (B's wall ends it lands on A's wall ends of the same role and direction,
     over the best's count; the rivals of most support refined first) and the larger of its
     score ratio and, when it matches more wall than the best, its support ratio. Corners, not
     wall length, because a rival sliding along long walls keeps much of their length but not
     the corners around them; support beyond the best's counts whatever its conflict, because
     a filter's drift can put the true hypothesis's walls on seen-free space and leave a
     coincidence the best score -- unless it matches less than ``drift_support_ratio`` times
     the best's wall and has more conflict than acceptance allows it, when its score counts.
     When the best puts no wall on seen-free space (at most ``max_conflict``), a rival under
     that factor with ``clean_rival_conflict`` metres of conflict is no rival. The corner ratio
     is trusted only when the best matches at least ``rival_min_ends`` typed wall ends;
   * the matched walls constrain translation in every direction: the smaller eigenvalue of
     ``sum(length * n n^T)`` over matched samples (``n`` the wall normal) is at least
     ``min_cross_support`` metres (a corridor seen as two parallel walls does not say where
     along it the other map lies);
   * the RMS point-to-line residual of the matched samples is at most ``max_rmse``;
   * at least ``min_corners`` real corners of B land on real corners of A (one L of two walls
     looks like every other corner of its kind), or ``min_corners_unique`` when the hypothesis
     is unique (runner-up ratio at most ``unique_runner_up_ratio``, support at least twice
     ``min_support``; off by default, see :class:`RegistrationConfig`);
   * the overlap is not *self-similar*: the part of each map that the other matched, registered
     against its own map, has no hypothesis distinct from the identity that lands more than
     ``max_self_ratio`` of its corners on corners (or of its wall ends on wall ends of the same
     role and direction) without conflict. A robot that has itself seen
     the overlap's structure repeated (identical offices, pillar rows, the sides of a symmetric
     ring) is in a building where the other robot may have seen a *different* copy, which no
     agreement between the two maps can rule out. With a runner-up ratio above
     ``contested_runner_up_ratio`` the limit is ``contested_self_ratio``; recurring in both
     maps, the limit is ``mutual_self_ratio``. The part's features are the map's on its edges
     (its free probes the map's: the space the whole map saw free); a part of more than
     ``SELF_VOTE_ENDS`` wall ends votes with its walls' starts only, and a hypothesis that a
     cell-mask count shows cannot exceed the lowest of the three limits is not verified (so
     ``extra["self_a"]`` and ``["self_b"]`` are exact above that limit and may read 0 below).
     A fleet asks the same of every other robot's map before it joins two:
     :func:`recurrence_elsewhere`, the overlap placed in a third map at two distinct places.

Confidence
----------
:attr:`Registration.confidence` is ``(1 - runner_up_ratio) * support / (support + min_support)``
in [0, 1): 0 when a distinct hypothesis is as good, approaching 1 with a unique hypothesis and much
more supporting wall than the minimum. It is a ranking, not a probability; the accept decision
uses the individual gates above, all reported in :class:`Registration`.

Determinism: no randomness at all (exhaustive voting, not RANSAC); ties are broken by index.

Cost (CPU time of one process on a shared 2-core machine, ``time.process_time``): about 25-30 ms
(median) for the bench's map pairs; for two maps of about 300 corners (the whole museum twice,
281 corners and 2.5 km of wall each, or two halves of its coverage route, 200-270 corners) about
50 ms at a load of 2 on the two cores, against 65-70 ms for the code before
``docs/experiments.md``'s "Registration speed, part 3" and 115-145 ms before part 2. The sample match
and the free probes' ray cast are compiled (:mod:`mapping.kernels`): 43 ms in ``wiremap bench
register``'s 300-corner pairs. The time
goes to :func:`prepare` (the wall each free-probe ray meets, the clearance test; about 5 ms per
large map), the translation votes (every same-direction wall-end pair of a rectilinear map votes,
about 41,000 pairs per rotation for the museum; the coarse vote bounds the fine grid: 4 votes for
the pair and 4 for each self-similarity check), the scoring of the candidates (matched wall
first; the conflict only where the score can count), the refinement (large maps: every second
sample, half the iterations) and the runner-up's refinement. :func:`prepare` can be cached per
map; what it derives lazily (k-d trees, the cell masks) is kept with the features.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from mapping.icp import ICPConfig, icp
from mapping.kernels import PointGrid, directed_matches, first_crossings
from mapping.se2 import Pose
from mapping.wireframe import Label, Wireframe

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "Hypothesis",
    "MapFeatures",
    "Registration",
    "RegistrationConfig",
    "conflict_of",
    "prepare",
    "refine",
    "register",
    "register_prepared",
    "rotation_candidates",
]


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of :func:`register`. Lengths in metres, angles in radians.

    Parameters
    ----------
    sample_spacing : float
        Wall sample spacing (support, conflict and refinement resolution).
    max_samples : int
        Larger maps are sampled more coarsely, to about this many samples (cost bound: 2,000
        samples is 500 m of wall at the default spacing).
    min_wall : float
        Edges shorter than this are ignored (noise, corner slivers).
    free_depths : tuple of float
        Depths of the free probes in front of every wall sample.
    free_clearance : float
        Probes closer than this to a wall of their own map are dropped (corners, clutter).
    free_reach, free_reach_step : float
        A wall sample whose normal, on its free side, first meets a wall of the same map that
        faces it back (the two walls look at each other across open space: a room's opposite
        walls, a pillar seen from the room) within ``free_reach`` also gets probes every
        ``free_reach_step`` beyond the deepest of ``free_depths``, up to ``free_clearance``
        before that wall. Without it the seen-free space is a strip ``free_depths`` deep along
        the walls, and a copy of the map turned onto itself (a rotation-symmetric room whose
        pillar is what tells the two apart) puts the pillar in the middle of the room without
        conflict. 0 turns it off.
    probe_end_margin : float
        Probes only in front of the part of a wall at least this far from its ends.
    direction_bins : int
        Bins of the direction histogram over 360 degrees (720: half a degree).
    direction_smooth : float
        Standard deviation of the Gaussian that smooths the histogram (wall noise).
    max_rotations : int
        Rotation hypotheses kept (local maxima of the histogram correlation).
    rotation_peak_ratio : float
        A correlation peak is kept only if at least this times the highest.
    feature_angle_tol : float
        Two wall ends pair up when their rotated directions differ by at most this.
    vote_cell : float
        Translation vote grid cell.
    vote_weight_cap : float
        Largest vote of one wall-end pair (metres of wall).
    coarse_vote_pairs, coarse_vote_factor, coarse_vote_cells : int
        A rotation with more wall-end pairs than ``coarse_vote_pairs`` votes first on cells
        ``coarse_vote_factor`` times larger; only the proposals in the ``coarse_vote_cells``
        strongest coarse cells (with every cell tied with the last of them) and their neighbours
        vote on the fine grid (cost).
    peaks_per_rotation : int
        Candidate translations kept per rotation hypothesis.
    peak_separation : float
        Least distance between two candidate translations of one rotation.
    verify_candidates : int
        Candidates (by vote, over all rotations) that are scored.
    refine_candidates : int
        Scored candidates (by score) that are refined.
    coarse_match_dist, match_dist : float
        Largest distance of a matched wall sample before and after refinement.
    match_angle : float
        Largest direction difference of a matched wall sample.
    conflict_radius : float
        A wall sample this close to a free probe of the other map is in conflict.
    conflict_weight : float
        Weight of conflicting wall length in the score.
    conflict_min_wall : float
        Walls shorter than this never conflict (clutter and the filter's spurious slivers).
    frontier_margin : float
        Wall within this of a frontier end of its edge never conflicts: a frontier is where
        sight of the wall ended, and a filter-built map's wall runs on there by up to its drift.
    displaced_dist, displaced_weight : float
        A conflicting wall sample with a wall of the other map of its direction (within twice
        ``match_angle``) within ``displaced_dist`` is a *displaced* copy of that wall (the drift
        of a filter-built map), not a foreign wall: it counts ``displaced_weight`` of its length.
        Off by default (1.0): at 0.25 the benchmark merged a warehouse map with a CARMEN
        seattle map (cross-world) and two edmonton filter maps 0.9 m off, a corridor shifted
        along itself looks like drift.
    refine_iterations : int
        Point-to-line iterations of the refinement.
    huber : float
        Huber threshold of the refinement's residuals.
    use_icp : bool
        Polish the result with :func:`mapping.icp.icp` on the cropped overlap.
    max_icp_pairs : int
        ICP is skipped when the cropped maps' edge counts multiply to more than this (its edge
        correspondence test is quadratic; the point-to-line refinement already converged).
    distinct_translation, distinct_rotation : float
        Two hypotheses are distinct when their translations (at the centre of B's walls) differ
        by more than ``distinct_translation`` or their rotations by more than
        ``distinct_rotation``.
    min_support : float
        Least matched wall length for acceptance. With 8 m a single room wall pair cannot
        merge two maps; maps with less wall than this never merge.
    min_support_fraction : float
        Least matched wall length as a fraction of the smaller map's wall length.
    max_conflict, max_conflict_fraction : float
        Largest accepted conflict: ``max_conflict + max_conflict_fraction * support`` (the
        constant absorbs clutter and corner noise of real maps).
    max_runner_up_ratio : float
        Largest accepted runner-up ratio: over the distinct hypotheses, the smaller of its score
        ratio and its corner ratio (module docstring, step 6).
    rival_refine : int
        Distinct runner-ups (by score) refined before their corners are counted.
    rival_corner_dist : float
        Distance within which a runner-up's corners count as matched (looser than
        ``corner_match_dist``: an error here errs towards refusing).
    rival_min_ends : int
        The corner ratio of a runner-up is trusted only when the best hypothesis matches at least
        this many typed wall ends (four full corners): with fewer, one corner more or less swings
        the ratio, and the score ratio alone decides.
    clean_rival_conflict : float
        With a best hypothesis free of conflict (at most ``max_conflict``), a rival with at least
        this much conflict and less than ``drift_support_ratio`` times the best's support is not
        counted (step 6): the other robot saw that space empty. A building symmetric under a
        half turn but for a few walls (the office world) gives the half turn nearly the support
        of the truth, and only those walls tell them apart (four robots of unknown start, seed
        2, r4 onto r1 after 90 s: the truth matched 207.5 m with no conflict, the half turn
        191.4 m with 7.3 m, the half turn one office along 170.6 m with 2.2 m).
    drift_support_ratio : float
        A rival that matches more wall than the best counts by that wall whatever its conflict
        (drift puts a right transform's walls on seen-free space), but when it is within this
        factor of the best's wall and has more conflict than acceptance allows for its wall,
        it counts by its score (conflict included): 2-12 % more wall and 10-51 m of conflict
        against the truth's 0-4.5 m were the rivals in the office's fleets of four.
    min_cross_support : float
        Least wall length constraining the weaker translation direction.
    max_rmse : float
        Largest accepted RMS point-to-line residual of the matched samples.
    min_corners : int
        Least number of B's real corners that land within ``corner_match_dist`` of a real
        corner of A. One room corner (an L of two walls) looks like every other corner of
        its kind: four were needed to keep the corners of a symmetric ring apart, five to keep
        two museum maps of long walls apart (the benchmark merged them 22 m and 30 m off, four
        corners matched each time; the true overlap was wall without corners).
    min_corners_unique : int
        Least matched corners when the hypothesis is *unique*: its runner-up ratio (corner
        based, step 6) at most ``unique_runner_up_ratio`` and its support at least twice
        ``min_support``. Long-walled buildings (halls, museums) have few corners, but a long
        wall with a corner at each end fixes the translation once no rival keeps its corners.
        Off by default (equal to ``min_corners``): at 2 the benchmark merged two disjoint,
        congruent quarters of a symmetric ring (each robot saw one copy, so nothing in either
        map is ambiguous), the false merge that ``min_corners`` is there for.
    unique_runner_up_ratio : float
        See ``min_corners_unique``.
    corner_match_dist : float
        Distance within which two real corners match.
    max_self_ratio : float
        Largest accepted *self-similarity* of the overlap: the part of each map that the
        other matched is registered against its own map, and the best hypothesis distinct from
        the identity must score at most this fraction of the identity's score. A robot that
        has itself seen the overlap's structure twice (identical offices along a corridor, the
        sides of a symmetric ring) lives in a repetitive building, where the other robot may
        well have seen a *different* copy: no amount of agreement between the two maps can
        tell which (step 6 of the module docstring).
    contested_self_ratio, contested_runner_up_ratio : float
        When the runner-up ratio exceeds ``contested_runner_up_ratio`` (a rival half as good),
        the largest accepted self-similarity is ``contested_self_ratio`` instead: two
        half-strength signs of repetition together refuse (the benchmark's filter-built maps of
        two identical offices matched at 97 % of the smaller map, the rival at 58 %, the
        overlap recurring within each map at 59 %; at 0.55, a map of one office merged onto
        another office of a map that had seen several, 22 m off: rival at 53 %, recurring
        at 67 %).
    contested_max_conflict, conflict_runner_up_ratio : float
        When the runner-up ratio exceeds ``conflict_runner_up_ratio``, the largest accepted
        conflict is ``contested_max_conflict`` (no part proportional to the support): a rival
        of some strength and walls on seen-free space are two signs together (the benchmark
        merged maps of the corridor world one office apart, rivals at 47 % and 56 %, the other
        map's end wall across the corridor: 2.0 m of conflict, under the 2.6 m the
        proportional limit allowed).
    mutual_self_ratio : float
        Largest accepted self-similarity of the overlap in *both* maps at once: when each robot
        has itself seen the overlap's structure repeated, the building repeats by the evidence
        of both (the benchmark's filter-built maps merged turned 90 or 180 degrees and 6-18 m
        off, a warehouse's pillar grid recurring at 69 % and 73 %, offices alike on both sides
        of a corridor at 71-75 %, all under ``max_self_ratio``; at 0.6, two disjoint parts of
        the pillar grid merged 36 m off, recurring at 56 % and 67 %).

    Raises
    ------
    ValueError
        On a non-positive length, count or angle, or a ratio outside [0, 1].
    """

    sample_spacing: float = 0.25
    max_samples: int = 2000
    min_wall: float = 0.15
    free_depths: tuple[float, ...] = (0.35, 0.7, 1.05)
    free_clearance: float = 0.3
    free_reach: float = 6.0
    free_reach_step: float = 0.35
    probe_end_margin: float = 0.3
    direction_bins: int = 720
    direction_smooth: float = math.radians(1.0)
    max_rotations: int = 8
    rotation_peak_ratio: float = 0.3
    feature_angle_tol: float = math.radians(6.0)
    vote_cell: float = 0.3
    vote_weight_cap: float = 4.0
    coarse_vote_pairs: int = 4000
    coarse_vote_factor: int = 4
    coarse_vote_cells: int = 48
    peaks_per_rotation: int = 6
    peak_separation: float = 1.0
    verify_candidates: int = 16
    refine_candidates: int = 4
    coarse_match_dist: float = 0.35
    match_dist: float = 0.15
    match_angle: float = math.radians(15.0)
    conflict_radius: float = 0.2
    conflict_weight: float = 3.0
    conflict_min_wall: float = 0.5
    frontier_margin: float = 0.5
    displaced_dist: float = 0.6
    displaced_weight: float = 1.0
    refine_iterations: int = 6
    huber: float = 0.05
    use_icp: bool = True
    max_icp_pairs: int = 20_000
    distinct_translation: float = 1.0
    distinct_rotation: float = math.radians(5.0)
    min_support: float = 8.0
    min_support_fraction: float = 0.1
    max_conflict: float = 0.5
    max_conflict_fraction: float = 0.05
    max_runner_up_ratio: float = 0.7
    rival_refine: int = 3
    rival_corner_dist: float = 0.5
    rival_min_ends: int = 8
    clean_rival_conflict: float = 2.0
    drift_support_ratio: float = 1.25
    min_cross_support: float = 1.5
    max_rmse: float = 0.08
    min_corners: int = 5
    min_corners_unique: int = 5
    unique_runner_up_ratio: float = 0.5
    corner_match_dist: float = 0.25
    max_self_ratio: float = 0.75
    contested_self_ratio: float = 0.55
    contested_runner_up_ratio: float = 0.5
    mutual_self_ratio: float = 0.55
    contested_max_conflict: float = 0.5
    conflict_runner_up_ratio: float = 0.4

    def conflict_limit(self, support: float) -> float:
        """The largest conflict acceptance allows with ``support`` metres of matched wall."""
        return self.max_conflict + self.max_conflict_fraction * support

    def __post_init__(self) -> None:
        for name in ("sample_spacing", "free_clearance", "free_reach_step", "direction_smooth",
                     "feature_angle_tol",
                     "vote_cell", "vote_weight_cap", "peak_separation", "coarse_match_dist",
                     "match_dist", "match_angle", "conflict_radius", "huber", "distinct_translation",
                     "distinct_rotation", "max_rmse", "displaced_dist", "rival_corner_dist"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"RegistrationConfig.{name} must be a positive number, got {v!r}")
        for name in ("min_wall", "probe_end_margin", "conflict_weight", "free_reach",
                     "contested_max_conflict", "min_support", "max_conflict",
                     "max_conflict_fraction", "min_cross_support", "conflict_min_wall", "frontier_margin",
                     "clean_rival_conflict", "drift_support_ratio"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RegistrationConfig.{name} must be >= 0, got {v!r}")
        for name in ("coarse_vote_pairs", "coarse_vote_factor", "coarse_vote_cells", "max_samples",
                     "direction_bins", "max_rotations", "peaks_per_rotation", "verify_candidates",
                     "refine_candidates", "refine_iterations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"RegistrationConfig.{name} must be >= 1")
        if int(self.rival_refine) < 0 or int(self.rival_min_ends) < 0:
            raise ValueError("RegistrationConfig.rival_refine must be >= 0")
        for name in ("rotation_peak_ratio", "min_support_fraction", "max_runner_up_ratio", "displaced_weight",
                     "unique_runner_up_ratio", "contested_self_ratio", "contested_runner_up_ratio",
                     "mutual_self_ratio", "conflict_runner_up_ratio"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"RegistrationConfig.{name} must be within [0, 1], got {v!r}")
        if any(not (math.isfinite(d) and d > 0) for d in self.free_depths):
            raise ValueError("RegistrationConfig.free_depths must be positive")
        if self.match_dist > self.coarse_match_dist:
            raise ValueError("RegistrationConfig.match_dist must not exceed coarse_match_dist")


@dataclass(frozen=True, eq=False)
class CellMask:
    """Which cells of a square grid have one of a set of points within ``radius`` (a cheap
    superset test in front of a k-d tree query with ``distance_upper_bound=radius``).

    The cells are ``5 %`` wider than ``radius`` and each point marks its own cell and the eight
    around it, so a point that a bounded query would find is always in a marked cell, with room
    for the rounding of the division; a query point in an unmarked cell has nothing within
    ``radius`` and need not be asked. The mask has a border of unmarked cells all round, so a
    query's cell index is clipped into it instead of tested against each bound.

    Attributes
    ----------
    radius, cell : float
    origin : (2,) int64
        Cell index of ``mask[0, 0]``.
    mask : (nx, ny) bool
        C-contiguous; its first and last rows and columns are unmarked.
    """

    radius: float
    cell: float
    origin: IntArray
    mask: BoolArray

    def near(self, q: FloatArray) -> BoolArray:
        """Whether each of ``q`` (n, 2) lies in a marked cell."""
        return self.near_xy(q[:, 0], q[:, 1])

    def near_xy(self, x: FloatArray, y: FloatArray) -> BoolArray:
        """Whether each point ``(x, y)`` (arrays of one shape) lies in a marked cell."""
        nx, ny = self.mask.shape
        ix = np.floor(x / self.cell).astype(np.int64)
        iy = np.floor(y / self.cell).astype(np.int64)
        ix -= self.origin[0]
        iy -= self.origin[1]
        # Outside the grid: onto its unmarked border (ufuncs: ``np.clip`` costs ~25 us a call).
        np.maximum(ix, 0, out=ix)
        np.minimum(ix, nx - 1, out=ix)
        np.maximum(iy, 0, out=iy)
        np.minimum(iy, ny - 1, out=iy)
        ix *= ny
        ix += iy
        return np.asarray(self.mask.reshape(-1)[ix], dtype=bool)


MAX_MASK_CELLS = 4_000_000  # larger maps do without a cell mask (memory)
MIN_MASK_QUERY = 500  # fewer query points go straight to the tree (the mask's fixed cost)
SELF_VOTE_ENDS = 200  # a part with more wall ends votes with its walls' starts (self-similarity check)


def _cell_mask(points: FloatArray, radius: float) -> CellMask | None:
    """The :class:`CellMask` of ``points`` for queries within ``radius`` (None when there are no
    points or the grid would have more than ``MAX_MASK_CELLS`` cells)."""
    if len(points) == 0 or not radius > 0:
        return None
    cell = 1.05 * radius
    ix = np.floor(points[:, 0] / cell).astype(np.int64)
    iy = np.floor(points[:, 1] / cell).astype(np.int64)
    # A point's cell is two cells from every edge of the grid: its neighbours are marked and
    # the border beyond them stays unmarked (:meth:`CellMask.near`).
    lo = np.array([int(ix.min()) - 2, int(iy.min()) - 2], dtype=np.int64)
    nx, ny = int(ix.max()) - int(lo[0]) + 3, int(iy.max()) - int(lo[1]) + 3
    if nx * ny > MAX_MASK_CELLS:
        return None
    # Marked through the flat index (a quarter of the time of a 2-d scatter); the offsets of a
    # point's neighbours do not wrap, as its cell is not in the first or last row or column.
    mask = np.zeros(nx * ny, dtype=bool)
    flat = (ix - lo[0]) * ny + (iy - lo[1])
    for off in _around(ny).tolist():  # nine scatters: faster than one of nine times the points
        mask[flat + off] = True
    return CellMask(radius=radius, cell=cell, origin=lo, mask=mask.reshape(nx, ny))


def _around(ny: int) -> IntArray:
    """Flat-index offsets of a cell and of its eight neighbours in a C-ordered grid of ``ny``
    columns (they do not wrap for a cell outside the grid's first and last rows and columns)."""
    return np.array([-ny - 1, -ny, -ny + 1, -1, 0, 1, ny - 1, ny, ny + 1], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class MapFeatures:
    """What registration needs of one map (:func:`prepare`), in the map's own frame.

    Attributes
    ----------
    wireframe : Wireframe
    centre : (2,)
        Length-weighted centroid of the walls (votes are cast in centred coordinates).
    points, directions, normals : (k, 2)
        Wall samples: midpoints, unit directions, left (free-side) unit normals.
    weights : (k,)
        Wall length per sample.
    probes : (p, 2)
        Free probes (module docstring).
    end_points : (f, 2)
        Wall ends at real corners.
    end_angles : (f,)
        Direction of the wall at each end, radians in ``[-pi, pi)``.
    end_starts : (f,) bool
        Whether the wall starts (True) or ends there.
    end_weights : (f,)
        Length of the wall.
    histogram : (direction_bins,)
        Smoothed wall length per direction.
    length : float
        Total wall length (edges of at least ``min_wall``).
    owner : (k,) int64
        Index of each sample's edge in ``wireframe``.
    corner_points : (c, 2)
        Vertices at real corners (nominal or occlusion) that end an edge of at least ``min_wall``.
    conflict_weights : (k,)
        Wall length per sample as it counts in a conflict: times its edge's likelihood, 0 on
        edges shorter than ``conflict_min_wall`` and within ``frontier_margin`` of a frontier.
    config : RegistrationConfig
        The configuration it was prepared with.
    probe_owner : (p,) int64
        Index of each probe's wall sample (in ``points``).
    end_owner, end_vertex : (f,) int64
        Each wall end's edge and vertex in ``wireframe``.

    Derived data is built on first use and kept (once per map, not per hypothesis):
    :attr:`grid`, :attr:`probe_tree`, :attr:`end_tree`, :attr:`corner_tree`, :attr:`end_centred`,
    :attr:`end_cells`, :attr:`corner_cells`, :attr:`probe_cells`, :attr:`sample_cells`.
    """

    wireframe: Wireframe
    centre: FloatArray
    points: FloatArray
    directions: FloatArray
    normals: FloatArray
    weights: FloatArray
    probes: FloatArray
    end_points: FloatArray
    end_angles: FloatArray
    end_starts: BoolArray
    end_weights: FloatArray
    histogram: FloatArray
    length: float
    owner: IntArray
    corner_points: FloatArray
    conflict_weights: FloatArray
    config: RegistrationConfig
    probe_owner: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    end_owner: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    end_vertex: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))

    @cached_property
    def grid(self) -> PointGrid:
        """``points`` bucketed for the compiled sample queries (:func:`_match`, the displaced
        walls of :func:`_conflict_one`)."""
        return PointGrid.build(self.points)

    @cached_property
    def probe_tree(self) -> cKDTree | None:
        """k-d tree over ``probes`` (None when there are none). Only whether a probe lies within
        a radius is ever asked, which does not depend on the tree's shape: the sliding midpoint
        tree (``balanced_tree=False``) builds in half the time of the median one, and without
        shrinking its nodes to their points (``compact_nodes=False``) and with leaves of 32
        points in two thirds of that again, answering as fast."""
        if len(self.probes) == 0:
            return None
        return cKDTree(self.probes, leafsize=32, balanced_tree=False, compact_nodes=False)

    @cached_property
    def end_tree(self) -> cKDTree:
        """k-d tree over ``end_points``."""
        return cKDTree(self.end_points.reshape(-1, 2))

    @cached_property
    def corner_tree(self) -> cKDTree:
        """k-d tree over ``corner_points``."""
        return cKDTree(self.corner_points)

    @cached_property
    def end_centred(self) -> FloatArray:
        """``(end_points - centre).T``, ``(2, f)``: the vote's coordinates, one contiguous row
        per axis (a gather from a row is faster than a row gather of an ``(f, 2)`` array)."""
        return np.ascontiguousarray((self.end_points - self.centre).T, dtype=np.float64)

    @cached_property
    def end_cells(self) -> CellMask | None:
        """Cells near a wall end (``corner_match_dist``): an upper bound of :func:`_matched_ends`."""
        return _cell_mask(self.end_points, self.config.corner_match_dist)

    @cached_property
    def corner_cells(self) -> CellMask | None:
        """Cells near a corner (``corner_match_dist``): an upper bound of :func:`_matched_corners`."""
        return _cell_mask(self.corner_points, self.config.corner_match_dist)

    @cached_property
    def probe_cells(self) -> CellMask | None:
        """Cells near a free probe (``conflict_radius``): points elsewhere need no probe query."""
        return _cell_mask(self.probes, self.config.conflict_radius)

    @cached_property
    def sample_cells(self) -> CellMask | None:
        """Cells near a wall sample (``coarse_match_dist``, never below ``match_dist``: the
        config checks it)."""
        return _cell_mask(self.points, self.config.coarse_match_dist)


@dataclass(frozen=True)
class Hypothesis:
    """One scored transform of B onto A.

    Attributes
    ----------
    transform : Pose
        Maps B's points into A's frame.
    votes : float
        Its translation vote (metres of wall, step 3 of the module docstring); 0 if not voted.
    support : float
        Matched wall length of B (metres).
    conflict : float
        Wall length of either map on the other's seen-free space (metres).
    score : float
        ``support - conflict_weight * conflict``.
    rmse : float
        RMS point-to-line residual of the matched samples (metres).
    cross_support : float
        Smaller eigenvalue of the matched walls' normal scatter (metres of wall).
    refined : bool
        Whether it went through the refinement.
    matched : (ib, ia) int arrays or None
        The samples of B and of A it matched, when scored on every sample at ``match_dist``
        (kept for the ICP polish and the self-similarity check, which need the same matches;
        neither compared nor shown).
    """

    transform: Pose
    votes: float
    support: float
    conflict: float
    score: float
    rmse: float
    cross_support: float
    refined: bool = False
    matched: tuple[IntArray, IntArray] | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class Registration:
    """Outcome of :func:`register`.

    Attributes
    ----------
    accepted : bool
        Whether ``transform`` is supported by the evidence (all gates of the module docstring).
    transform : Pose or None
        The best hypothesis (B's frame into A's), also when refused; None when there was none.
    reason : str
        Why it was refused ("" when accepted).
    confidence : float
        ``(1 - runner_up_ratio) * support / (support + min_support)``, 0 without a hypothesis.
    support, support_fraction, conflict, rmse, cross_support : float
        Of the best hypothesis; ``support_fraction`` is over the smaller map's wall length.
    runner_up_ratio : float
        Score of the best distinct runner-up over the best score (0 when there is none).
    best, runner_up : Hypothesis or None
    hypotheses : int
        Candidate transforms voted for.
    """

    accepted: bool
    transform: Pose | None
    reason: str
    confidence: float = 0.0
    support: float = 0.0
    support_fraction: float = 0.0
    conflict: float = 0.0
    rmse: float = math.inf
    cross_support: float = 0.0
    runner_up_ratio: float = 0.0
    best: Hypothesis | None = None
    runner_up: Hypothesis | None = None
    hypotheses: int = 0
    extra: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------------------ features
def _wrap(a: FloatArray) -> FloatArray:
    return np.asarray((a + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


def prepare(wf: Wireframe, config: RegistrationConfig | None = None) -> MapFeatures:
    """The registration features of one map (module docstring, step 1).

    Parameters
    ----------
    wf : Wireframe
        The map, in its own frame. Every edge counts whatever its likelihood (drop unlikely
        edges first with :meth:`Wireframe.subgraph_edges` if wanted).
    config : RegistrationConfig, optional

    Returns
    -------
    MapFeatures
    """
    cfg = config or RegistrationConfig()
    seg = wf.segments()
    d = seg[:, 1] - seg[:, 0] if len(seg) else np.zeros((0, 2))
    ln = np.hypot(d[:, 0], d[:, 1])
    keep = ln >= max(cfg.min_wall, 1e-9)
    kept = np.flatnonzero(keep)
    seg, d, ln = seg[keep], d[keep], ln[keep]
    edges = wf.edges[keep]
    u = d / np.where(ln > 0, ln, 1.0)[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    # Samples: midpoints of equal pieces of each directed edge; the spacing grows on large maps
    # so that there are at most about ``max_samples`` (cost is linear in them).
    spacing = max(cfg.sample_spacing, float(ln.sum()) / cfg.max_samples)
    n = np.maximum(1, np.ceil(ln / spacing - 1e-9)).astype(np.int64)
    owner = np.repeat(np.arange(len(seg)), n)
    first = np.cumsum(n) - n
    j = np.arange(int(n.sum())) - np.repeat(first, n)
    t = (j + 0.5) / n[owner]
    pts = seg[owner, 0] + t[:, None] * d[owner]
    w = ln[owner] / n[owner]
    dirs = u[owner]
    nor = nrm[owner]
    total = float(ln.sum())
    centre = (pts * w[:, None]).sum(0) / total if total > 0 else np.zeros(2)
    tree = cKDTree(pts if len(pts) else np.zeros((0, 2)))
    # Free probes in front of the inner part of every wall.
    along = t * ln[owner]
    inner = (along >= cfg.probe_end_margin) & (ln[owner] - along >= cfg.probe_end_margin)
    inner_idx = np.flatnonzero(inner)
    p_in, n_in = pts[inner], nor[inner]
    probes = np.concatenate([p_in + dep * n_in for dep in cfg.free_depths]) if len(pts) else np.zeros((0, 2))
    probe_owner = np.tile(inner_idx, len(cfg.free_depths)) if len(pts) else np.zeros(0, np.int64)
    if len(pts):
        deep, deep_owner = _facing_probes(p_in, n_in, seg, nrm, cfg)
        probes = np.concatenate([probes, deep])
        probe_owner = np.concatenate([probe_owner, inner_idx[deep_owner]])
    if len(probes) and len(pts):
        # Only probes in a cell near a sample can be within the clearance (most are not).
        cells = _cell_mask(pts, cfg.free_clearance) if len(probes) >= MIN_MASK_QUERY else None
        clear = np.ones(len(probes), dtype=bool)
        ask = np.ones(len(probes), dtype=bool) if cells is None else cells.near(probes)
        if ask.any():
            dist, _ = tree.query(probes[ask], k=1, distance_upper_bound=cfg.free_clearance)
            clear[ask] = ~np.isfinite(dist)
        probes, probe_owner = probes[clear], probe_owner[clear]
    # Wall ends at real corners.
    real = np.zeros(len(Label), dtype=bool)
    real[[int(Label.NOMINAL), int(Label.OCCLUSION)]] = True
    ang = np.arctan2(u[:, 1], u[:, 0]) if len(u) else np.zeros(0)
    s_ok = real[wf.labels[edges[:, 0]]] if len(edges) else np.zeros(0, bool)
    e_ok = real[wf.labels[edges[:, 1]]] if len(edges) else np.zeros(0, bool)
    end_points = np.concatenate([seg[s_ok, 0], seg[e_ok, 1]])
    end_angles = np.concatenate([ang[s_ok], ang[e_ok]])
    end_starts = np.concatenate([np.ones(int(s_ok.sum()), bool), np.zeros(int(e_ok.sum()), bool)])
    end_weights = np.concatenate([ln[s_ok], ln[e_ok]])
    end_owner = np.concatenate([kept[s_ok], kept[e_ok]]).astype(np.int64)
    end_vertex = np.concatenate([edges[s_ok, 0], edges[e_ok, 1]]).astype(np.int64)
    # What a sample weighs in a conflict (likelihood, short walls, frontier ends).
    front = int(Label.FRONTIER)
    s_fr = wf.labels[edges[:, 0]] == front if len(edges) else np.zeros(0, bool)
    e_fr = wf.labels[edges[:, 1]] == front if len(edges) else np.zeros(0, bool)
    near_fr = (s_fr[owner] & (along < cfg.frontier_margin)) | (
        e_fr[owner] & (ln[owner] - along < cfg.frontier_margin)
    )
    cw = w * wf.likelihood[kept][owner] * (ln[owner] >= cfg.conflict_min_wall) * ~near_fr
    used = np.unique(end_vertex)
    corner_points = np.asarray(wf.points[used], dtype=np.float64).reshape(-1, 2)
    f = MapFeatures(
        wireframe=wf, centre=np.asarray(centre, dtype=np.float64), points=pts, directions=dirs, normals=nor,
        weights=w, probes=probes, end_points=end_points,
        end_angles=end_angles, end_starts=end_starts, end_weights=end_weights,
        histogram=_histogram(ang, ln, cfg), length=total,
        owner=kept[owner].astype(np.int64), corner_points=corner_points,
        conflict_weights=np.asarray(cw, dtype=np.float64), config=cfg,
        probe_owner=probe_owner.astype(np.int64), end_owner=end_owner, end_vertex=end_vertex,
    )
    f.__dict__["tree"] = tree  # built for the clearance test: kept (what ``cached_property`` stores)
    return f


def _histogram(ang: FloatArray, ln: FloatArray, cfg: RegistrationConfig) -> FloatArray:
    """Wall length ``ln`` per direction ``ang``, circularly smoothed (step 1)."""
    nb = cfg.direction_bins
    width = 2.0 * math.pi / nb
    # Linear binning (each wall split between its two nearest bins) keeps the sub-bin direction.
    pos = (ang + math.pi) / width - 0.5
    b0 = np.floor(pos).astype(np.int64)
    fr = pos - b0
    hist = np.bincount(np.concatenate([b0 % nb, (b0 + 1) % nb]),
                       weights=np.concatenate([ln * (1 - fr), ln * fr]), minlength=nb).astype(np.float64)
    k = np.fft.rfftfreq(nb, d=1.0 / nb)
    sig = cfg.direction_smooth / width
    return np.asarray(np.fft.irfft(np.fft.rfft(hist) * np.exp(-2.0 * (math.pi * sig * k / nb) ** 2), n=nb),
                      dtype=np.float64)


def _part(f: MapFeatures, edges: BoolArray) -> MapFeatures:
    """The features of the part of ``f``'s map made of the edges ``edges`` (a mask over
    ``f.wireframe``'s edges), taken from ``f`` instead of :func:`prepare` of the subgraph.

    Samples, wall ends and corners are ``f``'s on those edges (at ``f``'s sample spacing); the
    free probes are ``f``'s in front of those samples -- the space the whole map saw free, so a
    probe ray stops at the first wall of the *map*, not of the part (:func:`prepare` of the part
    alone would carry seen-free space through the walls left out).
    """
    cfg = f.config
    wf = f.wireframe.subgraph_edges(edges)
    smask = edges[f.owner]
    emask = edges[f.end_owner]
    pts = f.points[smask]
    w = f.weights[smask]
    total = float(w.sum())
    centre = (pts * w[:, None]).sum(0) / total if total > 0 else np.zeros(2)
    pmask = smask[f.probe_owner]
    probes = f.probes[pmask]
    # Sample indexes of the part (for the probes' owners).
    renum = np.cumsum(smask) - 1
    # Vertex numbering of the subgraph (``compacted`` keeps the order of the vertices left).
    used = np.zeros(f.wireframe.n_vertices, dtype=bool)
    used[f.wireframe.edges[edges].reshape(-1)] = True
    vmap = np.cumsum(used) - 1
    emap = np.cumsum(edges) - 1
    end_vertex = f.end_vertex[emask]
    corners = np.unique(end_vertex)
    seg = f.wireframe.segments()[edges]
    d = seg[:, 1] - seg[:, 0]
    ln = np.hypot(d[:, 0], d[:, 1])
    keep = ln >= max(cfg.min_wall, 1e-9)
    return MapFeatures(
        wireframe=wf, centre=np.asarray(centre, dtype=np.float64), points=pts, directions=f.directions[smask],
        normals=f.normals[smask], weights=w, probes=probes,
        end_points=f.end_points[emask], end_angles=f.end_angles[emask], end_starts=f.end_starts[emask],
        end_weights=f.end_weights[emask],
        histogram=_histogram(np.arctan2(d[keep, 1], d[keep, 0]), ln[keep], cfg), length=total,
        owner=emap[f.owner[smask]].astype(np.int64),
        corner_points=np.asarray(f.wireframe.points[corners], dtype=np.float64).reshape(-1, 2),
        conflict_weights=f.conflict_weights[smask], config=cfg,
        probe_owner=renum[f.probe_owner[pmask]].astype(np.int64),
        end_owner=emap[f.end_owner[emask]].astype(np.int64),
        end_vertex=vmap[end_vertex].astype(np.int64),
    )


def _facing_probes(
    origins: FloatArray, normals: FloatArray, seg: FloatArray, seg_normals: FloatArray,
    cfg: RegistrationConfig,
) -> tuple[FloatArray, IntArray]:
    """Probes deeper than ``free_depths`` in front of the wall samples ``origins`` whose normal
    first crosses a wall that faces back (``free_reach`` in :class:`RegistrationConfig`).

    The first crossing of each ray ``o + t n`` (``0 < t <= free_reach``) with the map's segments
    is found exactly, in chunks of consecutive samples (mostly along one wall) against the
    segments whose bounding box comes within ``free_reach`` of the chunk's; the probes are placed
    every ``free_reach_step`` from the deepest of ``free_depths`` to ``free_clearance`` before it.
    Returns the probes and the index in ``origins`` of each one's wall sample.
    """
    deep = np.arange(max(cfg.free_depths) + cfg.free_reach_step, cfg.free_reach, cfg.free_reach_step)
    none = (np.zeros((0, 2)), np.zeros(0, np.int64))
    if len(origins) == 0 or len(seg) == 0 or len(deep) == 0:
        return none
    # Chunks of rays near each other (origins in ``free_reach`` cells, in cell order), each
    # against the segments that meet the bounding box of its rays (origin to ``free_reach``
    # along the normal): a superset of those any of its rays can cross, so the result does not
    # depend on the chunks (compiled: mapping.kernels.first_crossings).
    cell = np.floor(origins / cfg.free_reach).astype(np.int64)
    order = np.lexsort((cell[:, 1], cell[:, 0]))
    first_r, facing_r = first_crossings(origins[order], normals[order], seg, seg_normals, cfg.free_reach)
    first = np.empty(len(origins))
    facing = np.empty(len(origins), dtype=bool)
    first[order], facing[order] = first_r, facing_r
    use = np.isfinite(first) & facing
    if not use.any():
        return none
    o, n, lim = origins[use], normals[use], first[use] - cfg.free_clearance
    keep = deep[None, :] <= lim[:, None]
    i, d = np.nonzero(keep)
    return np.asarray(o[i] + deep[d][:, None] * n[i], dtype=np.float64), np.flatnonzero(use)[i]


# ------------------------------------------------------------------------------ rotation
def rotation_candidates(
    fa: MapFeatures, fb: MapFeatures, config: RegistrationConfig | None = None
) -> FloatArray:
    """Rotations (radians) that turn B's wall directions onto A's, best first (step 2).

    The circular cross-correlation ``c[k] = sum_i hist_A[i + k] hist_B[i]`` is computed by FFT;
    its local maxima of at least ``rotation_peak_ratio`` of the highest, refined by a parabola
    through three bins, are returned (at most ``max_rotations``).
    """
    cfg = config or RegistrationConfig()
    nb = cfg.direction_bins
    c = np.fft.irfft(np.fft.rfft(fa.histogram) * np.conj(np.fft.rfft(fb.histogram)), n=nb)
    if not np.any(c > 0):
        return np.zeros(0)
    left, right = np.roll(c, 1), np.roll(c, -1)
    peak = (c >= left) & (c > right) & (c >= cfg.rotation_peak_ratio * c.max())
    idx = np.flatnonzero(peak)
    idx = idx[np.argsort(-c[idx], kind="stable")][: cfg.max_rotations]
    den = left[idx] - 2.0 * c[idx] + right[idx]
    off = np.where(den < 0, 0.5 * (left[idx] - right[idx]) / np.where(den < 0, den, -1.0), 0.0)
    return _wrap((idx + np.clip(off, -0.5, 0.5)) * (2.0 * math.pi / nb))


# ------------------------------------------------------------------------------ voting
def _angle_pairs(
    ang_a: FloatArray, key_a: IntArray, ang_b: FloatArray, key_b: IntArray, tol: float
) -> tuple[IntArray, IntArray]:
    """All ``(i, j)`` with ``key_a[i] == key_b[j]`` and ``|wrap(ang_a[i] - ang_b[j])| <= tol``
    (keys non-negative).

    Angles are binned by ``tol``; each B entry looks up its own and the two neighbouring bins
    (with the same key) through a sorted index, so the cost is the number of near pairs, not
    ``len(a) * len(b)``. Pairs come by shift of B's bin (-1, 0, +1), then by B entry, then in
    A's order.
    """
    nbin = max(3, int(2.0 * math.pi / tol))
    width = 2.0 * math.pi / nbin
    ba = ((ang_a + math.pi) / width).astype(np.int64) % nbin
    bb = ((ang_b + math.pi) / width).astype(np.int64) % nbin
    ka = key_a * nbin + ba
    order = np.argsort(ka, kind="stable")
    # Where each (key, bin) starts among A's entries sorted by it and how many it has (what a
    # search of the sorted keys finds), for B's entries in their bin and the two beside it.
    size = (max(int(key_a.max(initial=0)), int(key_b.max(initial=0))) + 1) * nbin
    count = np.bincount(ka, minlength=size)
    start = np.cumsum(count) - count
    kb = ((key_b * nbin)[None, :] + (bb[None, :] + np.array([[-1], [0], [1]])) % nbin).reshape(-1)
    cnt = count[kb]
    tot = int(cnt.sum())
    if tot == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ib = np.repeat(np.tile(np.arange(len(key_b)), 3), cnt)
    ia = order[np.arange(tot) + np.repeat(start[kb] - (np.cumsum(cnt) - cnt), cnt)]
    ok = _within(ang_a[ia] - ang_b[ib], tol)
    return ia[ok], ib[ok]


def _within(d: FloatArray, tol: float) -> BoolArray:
    """``|_wrap(d)| <= tol`` for differences ``d`` of two angles in ``[-pi, pi]``.

    ``_wrap`` (a float remainder, the costly part) changes a difference well inside (-pi, pi)
    by an ulp at most: only differences near ``tol`` or beyond 3 rad (across the wrap) need it
    for the same decision.
    """
    ad = np.abs(d)
    ok = ad <= tol
    unsure = (np.abs(ad - tol) <= 1e-9) | (ad >= 3.0)
    if unsure.any():
        ok[unsure] = np.abs(_wrap(d[unsure])) <= tol
    return np.asarray(ok, dtype=bool)


def _top_cells(grid: FloatArray, k: int) -> IntArray:
    """The indexes of the cells of ``grid`` whose vote is positive and at least the ``k``-th
    largest: the ``k`` strongest, and every cell tied with the ``k``-th.

    Cells with a vote are found first (a few thousand of hundreds of thousands) and ranked among
    themselves. A tie at the ``k``-th vote is common (votes are sums of capped weights, often
    whole multiples of ``vote_weight_cap``): all tied cells are kept rather than the ones
    ``np.argpartition`` happens to leave in front, which is independent of the grid's layout
    and cheaper (partitioning the whole grid, mostly zeros, costs 1-2 ms).
    """
    nz = np.flatnonzero(grid > 0.0)
    if len(nz) <= k:
        return np.asarray(nz, dtype=np.int64)
    vals = grid[nz]
    kth = float(-np.partition(-vals, k - 1)[k - 1])
    return np.asarray(nz[vals >= kth], dtype=np.int64)


def _sums_by_key(keys: IntArray, vals: FloatArray) -> tuple[IntArray, FloatArray]:
    """The sorted distinct ``keys`` and the sum of ``vals`` over each, added in array order:
    ``np.unique(keys, return_inverse=True)`` and a ``bincount`` over the inverse, in 60 % of
    the time on a large map's vote (a stable sort of the keys and the run starts, no more)."""
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    first = np.empty(len(sk), dtype=bool)
    first[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=first[1:])
    inv = np.empty(len(keys), dtype=np.int64)
    inv[order] = np.cumsum(first) - 1
    return np.asarray(sk[first], dtype=np.int64), np.asarray(np.bincount(inv, weights=vals), dtype=np.float64)


def _coarse_select(
    tx: FloatArray, ty: FloatArray, wv: FloatArray, cfg: RegistrationConfig
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The proposals in the strongest cells of a coarse vote (and their neighbours).

    Large maps propose tens of thousands of translations per rotation over a grid of millions of
    cells. A vote on cells ``coarse_vote_factor`` times larger (a grid that many squared times
    smaller, no bilinear split) finds where the peaks are: a fine peak's votes all fall in its
    coarse cell or a neighbour, so keeping the proposals of the ``coarse_vote_cells`` strongest
    coarse cells and their eight neighbours loses no peak that could be among the strongest.
    """
    size = cfg.vote_cell * cfg.coarse_vote_factor
    cx = np.floor(tx / size).astype(np.int64)
    cy = np.floor(ty / size).astype(np.int64)
    cx -= cx.min() - 1
    cy -= cy.min() - 1
    ny = int(cy.max()) + 2
    key = cx * ny + cy
    grid = np.asarray(np.bincount(key, weights=wv, minlength=(int(cx.max()) + 2) * ny), dtype=np.float64)
    k = min(cfg.coarse_vote_cells, len(grid) - 1)
    strong = _top_cells(grid, k)
    # Strong cells have votes, so they are inside the grid's border row and column: their
    # neighbours are cells of the grid.
    keep = np.zeros(len(grid), dtype=bool)
    keep[(strong[:, None] + _around(ny)).reshape(-1)] = True
    sel = keep[key]
    return tx[sel], ty[sel], wv[sel]


def _vote(
    fa: MapFeatures, fb: MapFeatures, theta: float, cfg: RegistrationConfig, sel: IntArray | None = None
) -> list[tuple[FloatArray, float]]:
    """Candidate translations (centred coordinates) under rotation ``theta``, strongest first;
    with ``sel``, only those of B's wall ends vote."""
    if len(fa.end_points) == 0 or len(fb.end_points) == 0:
        return []
    angles, starts = fb.end_angles, fb.end_starts
    if sel is not None:
        angles, starts = angles[sel], starts[sel]
    ia, ib = _angle_pairs(fa.end_angles, fa.end_starts.astype(np.int64), _wrap(angles + theta),
                          starts.astype(np.int64), cfg.feature_angle_tol)
    if sel is not None:
        ib = sel[ib]
    if len(ia) == 0:
        return []
    c, s = math.cos(theta), math.sin(theta)
    # B's ends turned (and the weights capped) once per end rather than once per pair: an
    # elementwise operation gives the same values before a gather as after it.
    bx, by = fb.end_centred
    tx = fa.end_centred[0][ia] - (c * bx - s * by)[ib]
    ty = fa.end_centred[1][ia] - (s * bx + c * by)[ib]
    cap = cfg.vote_weight_cap
    wv = np.minimum(np.minimum(fa.end_weights, cap)[ia], np.minimum(fb.end_weights, cap)[ib])
    if len(wv) > cfg.coarse_vote_pairs:
        tx, ty, wv = _coarse_select(tx, ty, wv, cfg)
    gx, gy = tx / cfg.vote_cell, ty / cfg.vote_cell
    x0, y0 = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
    fx, fy = gx - x0, gy - y0
    xmin, ymin = int(x0.min()), int(y0.min())
    ny = int(y0.max()) - ymin + 2
    base = (x0 - xmin) * ny + (y0 - ymin)
    keys = np.concatenate([base, base + ny, base + 1, base + ny + 1])
    vals = np.concatenate([wv * (1 - fx) * (1 - fy), wv * fx * (1 - fy), wv * (1 - fx) * fy, wv * fx * fy])
    nx = int(x0.max()) - xmin + 2
    top = 50 * cfg.peaks_per_rotation
    if nx * ny <= min(4_000_000, 16 * len(keys)):
        # Dense accumulation (a bincount is much cheaper than sorting the keys).
        grid = np.asarray(np.bincount(keys, weights=vals, minlength=nx * ny), dtype=np.float64)
        uk = np.asarray(np.flatnonzero(grid), dtype=np.int64)
        acc = grid[uk]
    else:  # sparse: only the cells that got votes
        uk, acc = _sums_by_key(keys, vals)
    if len(acc) > top:
        part = np.argpartition(-acc, top)[:top]
        uk, acc = uk[part], acc[part]
    order = np.lexsort((uk, -acc))  # strongest first, ties by cell
    out: list[tuple[FloatArray, float]] = []
    sep2 = cfg.peak_separation**2
    for o in order.tolist():
        cell = int(uk[o])  # Python ints: the same values as numpy scalars, without their cost
        cx = (cell // ny + xmin) * cfg.vote_cell
        cy = (cell % ny + ymin) * cfg.vote_cell
        if any((cx - p[0]) ** 2 + (cy - p[1]) ** 2 < sep2 for p, _ in out):
            continue
        # Sub-cell position: weighted mean of the proposals near the peak cell.
        near = (np.abs(tx - cx) <= cfg.vote_cell) & (np.abs(ty - cy) <= cfg.vote_cell)
        wn = wv[near]
        t = (
            np.array([np.dot(tx[near], wn), np.dot(ty[near], wn)]) / wn.sum()
            if wn.sum() > 0
            else np.array([cx, cy])
        )
        out.append((t, float(acc[o])))
        if len(out) >= cfg.peaks_per_rotation:
            break
    return out


# ------------------------------------------------------------------------------ scoring
def _rot(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def _match(
    fa: MapFeatures, fb: MapFeatures, T: Pose, gate: float, cfg: RegistrationConfig, stride: int = 1
) -> tuple[IntArray, IntArray]:
    """B samples (every ``stride``-th) moved by ``T`` matched to A samples: ``(ib, ia)``."""
    sel = np.arange(0, len(fb.points), stride)
    q = T.apply(fb.points[::stride])  # a view, not a gather
    cells = fa.sample_cells
    if cells is None or gate > cells.radius or len(q) < MIN_MASK_QUERY:
        rows = np.arange(len(q))
    else:  # only the points near a sample are asked; the others have no neighbour
        rows = np.flatnonzero(cells.near(q))
    none = np.zeros(0, np.int64)
    if len(rows) == 0:
        return none, none
    # Among the three nearest A samples within the gate, the nearest of the same direction
    # (compiled: mapping.kernels.directed_matches).
    db = fb.directions[sel[rows]] @ _rot(T.theta).T
    match = directed_matches(fa.grid, fa.directions, q[rows], db, gate, math.cos(cfg.match_angle))
    has = match >= 0
    return sel[rows[has]], match[has]


def _conflict_one(fp: MapFeatures, fw: MapFeatures, T: Pose, cfg: RegistrationConfig, stride: int) -> float:
    """Wall length of ``fw`` (moved by ``T`` into ``fp``'s frame) on ``fp``'s free probes."""
    if fp.probe_tree is None or len(fw.points) == 0:
        return 0.0
    sel = np.arange(0, len(fw.points), stride)
    sel = sel[fw.conflict_weights[sel] > 0]
    if len(sel) == 0:
        return 0.0
    q = T.apply(fw.points[sel])
    hit = (
        np.ones(len(q), dtype=bool)
        if fp.probe_cells is None or len(q) < MIN_MASK_QUERY
        else fp.probe_cells.near(q)
    )
    if hit.any():
        d, _ = fp.probe_tree.query(q[hit], k=1, distance_upper_bound=cfg.conflict_radius)
        hit[hit] = np.isfinite(d)
    if not hit.any():
        return 0.0
    sel, q = sel[hit], q[hit]
    w = fw.conflict_weights[sel].copy()
    # A displaced copy of one of fp's walls (same direction, one of the four nearest samples):
    # drift, not a foreign wall.
    dirs = fw.directions[sel] @ _rot(T.theta).T
    displaced = directed_matches(fp.grid, fp.directions, q, dirs, cfg.displaced_dist,
                                 math.cos(2.0 * cfg.match_angle), k=4) >= 0
    w[displaced] *= cfg.displaced_weight
    return float(w.sum()) * stride


def _conflict(
    fa: MapFeatures, fb: MapFeatures, T: Pose, cfg: RegistrationConfig, stride: int = 1,
    b_on_a: float | None = None,
) -> float:
    """Wall length of each map on the other's free probes, B moved by ``T`` (both directions:
    B's walls on A's seen-free space and A's on B's), weighted as in
    :attr:`MapFeatures.conflict_weights` and discounted where displaced. ``b_on_a``: the first
    direction, when already computed (a lower bound of the whole)."""
    if b_on_a is None:
        b_on_a = _conflict_one(fa, fb, T, cfg, stride)
    return b_on_a + _conflict_one(fb, fa, T.inverse(), cfg, stride)


def _residuals(fa: MapFeatures, fb: MapFeatures, T: Pose, ib: IntArray, ia: IntArray) -> FloatArray:
    q = T.apply(fb.points[ib])
    return np.asarray(np.einsum("ij,ij->i", q - fa.points[ia], fa.normals[ia]), dtype=np.float64)


def _score(
    fa: MapFeatures, fb: MapFeatures, T: Pose, gate: float, cfg: RegistrationConfig, votes: float,
    stride: int = 1, refined: bool = False, conflict: bool = True,
) -> Hypothesis:
    """The hypothesis ``T`` scored at ``gate`` (every ``stride``-th sample). Without
    ``conflict``, its conflict and score are left NaN (:func:`_with_conflict` fills them in)."""
    ib, ia = _match(fa, fb, T, gate, cfg, stride)
    support = float(fb.weights[ib].sum()) * stride
    c = _conflict(fa, fb, T, cfg, stride) if conflict else math.nan
    if len(ib):
        r = _residuals(fa, fb, T, ib, ia)
        wb = fb.weights[ib]
        rmse = float(np.sqrt(np.multiply(r**2, wb).sum() / wb.sum()))  # np.average's operations
        n = fa.normals[ia]
        w = fb.weights[ib] * stride
        M = (n * w[:, None]).T @ n
        cross = float(np.linalg.eigvalsh(M)[0])
    else:
        rmse, cross = math.inf, 0.0
    kept = (ib, ia) if stride == 1 and gate == cfg.match_dist else None
    return Hypothesis(T, votes, support, c, support - cfg.conflict_weight * c, rmse, cross, refined, kept)


def _final_matches(
    fa: MapFeatures, fb: MapFeatures, h: Hypothesis, cfg: RegistrationConfig
) -> tuple[IntArray, IntArray]:
    """``(ib, ia)``: the samples ``h`` matches at ``match_dist`` (kept by :func:`_score`, or matched)."""
    return h.matched if h.matched is not None else _match(fa, fb, h.transform, cfg.match_dist, cfg)


def _with_conflict(
    fa: MapFeatures, fb: MapFeatures, h: Hypothesis, cfg: RegistrationConfig, stride: int,
    b_on_a: float | None = None,
) -> Hypothesis:
    """``h`` (scored without its conflict, every ``stride``-th sample) with conflict and score
    (``b_on_a``: as :func:`_conflict` takes it)."""
    if not math.isnan(h.conflict):
        return h
    c = _conflict(fa, fb, h.transform, cfg, stride, b_on_a)
    return replace(h, conflict=c, score=h.support - cfg.conflict_weight * c)


def _refine(fa: MapFeatures, fb: MapFeatures, T: Pose, cfg: RegistrationConfig, stride: int = 1) -> Pose:
    """Iteratively re-matched point-to-line least squares (step 5), about B's wall centre; every
    ``stride``-th sample of B in all iterations but the last. A strided (large) map takes half
    the iterations (at least two), over the same gates from ``coarse_match_dist`` to
    ``match_dist``: with thousands of samples each step is already close to its fixed point."""
    iterations = cfg.refine_iterations if stride <= 1 else max(2, (cfg.refine_iterations + 1) // 2)
    last = iterations - 1
    for it in range(iterations):
        frac = it / max(1, last)
        gate = cfg.coarse_match_dist + (cfg.match_dist - cfg.coarse_match_dist) * frac
        ib, ia = _match(fa, fb, T, gate, cfg, stride if it < last else 1)
        if len(ib) < 3:
            break
        q = T.apply(fb.points[ib])
        c = T.apply(fb.centre[None, :])[0]
        n = fa.normals[ia]
        r = np.einsum("ij,ij->i", q - fa.points[ia], n)
        qc = q - c
        J = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * qc[:, 0] - n[:, 0] * qc[:, 1]])
        w = fb.weights[ib] * np.where(np.abs(r) <= cfg.huber, 1.0, cfg.huber / np.maximum(np.abs(r), 1e-12))
        H = (J * w[:, None]).T @ J + 1e-9 * np.eye(3)
        g = (J * w[:, None]).T @ r
        dx, dy, dth = -np.linalg.solve(H, g)
        # Rotate about c by dth, then shift: composed on the left of T.
        Rd = _rot(float(dth))
        tt = Rd @ (np.array([T.x, T.y]) - c) + c + np.array([dx, dy])
        T = Pose(float(tt[0]), float(tt[1]), T.theta + float(dth))
        if math.hypot(dx, dy) < 1e-4 and abs(dth) < 1e-5:
            break
    return T


def _crop(wf: Wireframe, centre: FloatArray, radius: float) -> Wireframe:
    """Edges with an end within ``radius`` of ``centre`` (unused vertices dropped)."""
    seg = wf.segments()
    near = np.minimum(np.hypot(*(seg[:, 0] - centre).T), np.hypot(*(seg[:, 1] - centre).T)) <= radius
    return wf.subgraph_edges(near)


def _polish(fa: MapFeatures, fb: MapFeatures, h: Hypothesis, cfg: RegistrationConfig) -> Hypothesis:
    """The wireframe ICP on the overlap (step 5); kept only if accepted and the score holds."""
    ib, _ = _final_matches(fa, fb, h, cfg)
    if len(ib) < 3:
        return h
    moved = h.transform.apply(fb.points[ib])
    c = moved.mean(axis=0)
    radius = float(np.max(np.hypot(*(moved - c).T))) + 1.0
    shift = Pose(-float(c[0]), -float(c[1]), 0.0)
    a = _crop(fa.wireframe, c, radius).transformed(shift)
    b = _crop(fb.wireframe.transformed(h.transform), c, radius).transformed(shift)
    if a.n_edges == 0 or b.n_edges == 0 or a.n_edges * b.n_edges > cfg.max_icp_pairs:
        return h
    res = icp(b, a, ICPConfig(gate_start=0.3, gate_end=0.15, prior_sigma_xy=0.2, prior_sigma_theta=0.05,
                              min_matched_fraction=0.1))
    if not res.accepted:
        return h
    # In A's frame: shift^-1 * correction * shift * T.
    T = shift.inverse().compose(res.correction).compose(shift).compose(h.transform)
    new = _score(fa, fb, T, cfg.match_dist, cfg, h.votes, refined=True)
    return new if new.score >= h.score - 1e-9 and new.rmse <= h.rmse + 1e-9 else h


def _distinct(a: Pose, b: Pose, fb: MapFeatures, cfg: RegistrationConfig) -> bool:
    """Whether ``a`` and ``b`` put B's wall centre more than ``distinct_translation`` apart or
    differ in rotation by more than ``distinct_rotation``."""
    x, y = float(fb.centre[0]), float(fb.centre[1])

    def at(T: Pose) -> tuple[float, float]:  # T.apply(centre), the same operations on floats
        c, s = math.cos(T.theta), math.sin(T.theta)
        return c * x - s * y + T.x, s * x + c * y + T.y

    (ax, ay), (bx, by) = at(a), at(b)
    return bool(
        math.hypot(ax - bx, ay - by) > cfg.distinct_translation
        or abs(float(_wrap(np.array(a.theta - b.theta)))) > cfg.distinct_rotation
    )


def _matched_corners(
    fa: MapFeatures, fb: MapFeatures, T: Pose, cfg: RegistrationConfig, dist: float | None = None
) -> int:
    """B's real corners within ``dist`` (default ``corner_match_dist``) of one of A's, B moved by ``T``."""
    if len(fa.corner_points) == 0 or len(fb.corner_points) == 0:
        return 0
    gate = cfg.corner_match_dist if dist is None else dist
    d, _ = fa.corner_tree.query(T.apply(fb.corner_points), k=1, distance_upper_bound=gate)
    return int(np.isfinite(d).sum())


def _matched_ends(fa: MapFeatures, fb: MapFeatures, T: Pose, cfg: RegistrationConfig, dist: float) -> int:
    """B's wall ends (at real corners) that land, B moved by ``T``, within ``dist`` of a wall end
    of A of the same role (start or end of its wall) and direction (within twice
    ``feature_angle_tol``): a corner matched *with its type*. A shift that takes a wall's start
    corner onto another wall's end corner (sliding along a long wall) matches corners but no
    ends."""
    if len(fa.end_points) == 0 or len(fb.end_points) == 0:
        return 0
    d, idx = fa.end_tree.query(T.apply(fb.end_points), k=4, distance_upper_bound=dist)
    ok = np.isfinite(d)
    idx_c = np.where(ok, idx, 0)
    ok &= fa.end_starts[idx_c] == fb.end_starts[:, None]
    ang = _wrap(fb.end_angles + T.theta)
    ok &= _within(fa.end_angles[idx_c] - ang[:, None], 2.0 * cfg.feature_angle_tol)
    return int(ok.any(axis=1).sum())


def _part_hypotheses(
    f: MapFeatures, region: MapFeatures, cfg: RegistrationConfig, besides: Pose | None
) -> list[tuple[float, Pose]]:
    """Placements of the part ``region`` in ``f``'s map by the rotation and vote steps, most
    votes first (those distinct from ``besides`` when given). A large part votes with the starts
    of its walls only: each corner of a wall chain once instead of twice (its two walls), half
    the pairs; the hypotheses are verified on all ends."""
    cands: list[tuple[float, Pose]] = []
    sel = np.flatnonzero(region.end_starts) if len(region.end_points) > SELF_VOTE_ENDS else None
    for theta in rotation_candidates(f, region, cfg).tolist():
        R = _rot(theta)
        for t, v in _vote(f, region, theta, cfg, sel):
            tt = f.centre + t - R @ region.centre
            T = Pose(float(tt[0]), float(tt[1]), theta)
            if besides is None or _distinct(T, besides, region, cfg):
                cands.append((v, T))
    cands.sort(key=lambda c: -c[0])
    return cands


def _self_ratio(f: MapFeatures, samples: IntArray, cfg: RegistrationConfig) -> float:
    """Self-similarity of the part of ``f``'s map whose wall samples are ``samples``.

    The part (its edges) is registered onto the whole map by the same rotation and vote steps;
    each hypothesis distinct from the identity that puts no wall on seen-free space is counted by
    the larger of the fraction of the part's real corners that land on real corners of the map
    and the fraction of its wall ends that land on wall ends of the same role and direction
    (:func:`_matched_ends`). Corners, not wall length: sliding a long wall along itself keeps
    most of its length matched in any rectilinear building, while a shift that maps most
    corners onto corners means a repeated structure. (Typed ends alone let two museum maps of
    four corners each merge 45 m apart: the larger of the two is kept.) Returns 0 when the part
    has no real corner.
    """
    region = _sample_part(f, samples, cfg)
    if len(region.end_points) == 0 or len(region.corner_points) == 0:
        return 0.0
    top = _part_hypotheses(f, region, cfg, Pose.identity())[: cfg.verify_candidates]
    best = 0.0
    # Below the lowest limit a value decides nothing: a hypothesis that cannot land more than
    # that share of the part's ends or corners near the map's (a cell-mask count, an upper bound
    # of the matched count) is not verified.
    floor = _self_floor(cfg)
    for (_, T), bound in zip(top, _share_bounds(f, region, top)):
        if bound <= max(best, floor):
            continue
        n = _placed_share(f, region, T, cfg)
        if n <= best:
            continue
        if _free_of_conflict(f, region, T, cfg):
            best = n
    return best


def _self_floor(cfg: RegistrationConfig) -> float:
    """The lowest of the self-similarity limits: a share at or below it refuses nothing."""
    return min(cfg.max_self_ratio, cfg.contested_self_ratio, cfg.mutual_self_ratio)


def _sample_part(f: MapFeatures, samples: IntArray, cfg: RegistrationConfig) -> MapFeatures:
    """The part of ``f``'s map on the edges of the wall samples ``samples``."""
    mask = np.zeros(f.wireframe.n_edges, dtype=bool)
    mask[f.owner[samples]] = True
    wf = f.wireframe
    if mask.all() and f.config == cfg and np.bincount(wf.edges.reshape(-1), minlength=wf.n_vertices).all():
        # The part is the whole map (same arrays: every vertex is on an edge), whose features
        # are at hand.
        return f
    return _part(f, mask)


def _share_bounds(f: MapFeatures, region: MapFeatures, top: list[tuple[float, Pose]]) -> list[float]:
    """Upper bounds of :func:`_placed_share` for the placements ``top`` (cell-mask counts;
    infinite without cell masks, so that every placement is verified)."""
    ends_cells, corner_cells = f.end_cells, f.corner_cells
    if ends_cells is None or corner_cells is None or not top:
        return [math.inf] * len(top)
    poses = [T for _, T in top]
    n_ends = _near_counts(ends_cells, poses, region.end_points)
    n_corners = _near_counts(corner_cells, poses, region.corner_points)
    shares: list[float] = np.maximum(n_ends / len(region.end_points),
                                     n_corners / len(region.corner_points)).tolist()
    return shares


def _placed_share(f: MapFeatures, region: MapFeatures, T: Pose, cfg: RegistrationConfig) -> float:
    """The larger of the shares of the part's wall ends (typed) and real corners that ``T``
    lands on ``f``'s."""
    return max(_matched_ends(f, region, T, cfg, cfg.corner_match_dist) / len(region.end_points),
               _matched_corners(f, region, T, cfg) / len(region.corner_points))


def _free_of_conflict(f: MapFeatures, region: MapFeatures, T: Pose, cfg: RegistrationConfig) -> bool:
    """Whether the part placed by ``T`` puts no more wall on ``f``'s seen-free space than the
    conflict gate allows."""
    conflict, limit = conflict_of(f, region, T, cfg)
    return conflict <= limit


def _recurrence(f: MapFeatures, region: MapFeatures, cfg: RegistrationConfig) -> float:
    """How well a part of *another* map recurs in ``f``'s map: the share (:func:`_placed_share`)
    of its second-best placement distinct from its best, each free of conflict (0 when it is
    placed well at most once). Shares at or below the self-similarity floor are not verified
    and count 0."""
    if len(region.end_points) == 0 or len(region.corner_points) == 0 or len(f.end_points) == 0:
        return 0.0
    top = _part_hypotheses(f, region, cfg, None)[: cfg.verify_candidates]
    floor = _self_floor(cfg)
    found: list[tuple[float, Pose]] = []
    for (_, T), bound in zip(top, _share_bounds(f, region, top)):
        if bound <= floor:
            continue
        n = _placed_share(f, region, T, cfg)
        if n > floor and _free_of_conflict(f, region, T, cfg):
            found.append((n, T))
    if len(found) < 2:
        return 0.0
    found.sort(key=lambda c: -c[0])
    first = found[0][1]
    return max((n for n, T in found[1:] if _distinct(T, first, region, cfg)), default=0.0)


def conflict_of(
    fa: MapFeatures, fb: MapFeatures, transform: Pose, config: RegistrationConfig | None = None
) -> tuple[float, float]:
    """How a given ``transform`` (``fb`` onto ``fa``) fares on these maps' free space:
    ``(conflict, limit)``, the wall on the other's seen-free space (step 4) and the largest
    conflict acceptance allows for the wall it matches (:meth:`RegistrationConfig.conflict_limit`).
    A fleet checks a pending join's transform with it on the maps as they grew."""
    cfg = config or RegistrationConfig()
    h = _score(fa, fb, transform, cfg.match_dist, cfg, 0.0)
    return h.conflict, cfg.conflict_limit(h.support)


def recurrence_elsewhere(
    fa: MapFeatures, fb: MapFeatures, reg: Registration, others: Sequence[MapFeatures],
    config: RegistrationConfig | None = None,
) -> tuple[float, int]:
    """Whether the overlap of an accepted registration of ``fb`` onto ``fa`` recurs in a third
    map: ``(share, index)`` of the largest :func:`_recurrence` of A's matched part over
    ``others`` (index -1 when none recurs).

    The self-similarity gate (step 6) asks whether either robot has itself seen the overlap's
    structure twice; in a fleet, *any* robot in the building may have, and a fleet asks this
    of every other map it holds before it joins two (:mod:`agents.fleet.fusion.frames`; the
    case that called for it: ``docs/experiments.md``, "Session 20")."""
    cfg = config or RegistrationConfig()
    if reg.best is None or not others:
        return 0.0, -1
    _, ia = _final_matches(fa, fb, reg.best, cfg)
    if len(ia) == 0:
        return 0.0, -1
    region = _sample_part(fa, ia, cfg)
    best, at = 0.0, -1
    for k, fc in enumerate(others):
        r = _recurrence(fc, region, cfg)
        if r > best:
            best, at = r, k
    return best, at


def _near_counts(cells: CellMask, poses: list[Pose], pts: FloatArray) -> IntArray:
    """For each of ``poses``, how many of ``pts`` it moves into a marked cell of ``cells``: all
    poses at once, each point moved by the operations of :meth:`Pose.apply`."""
    c = np.array([math.cos(T.theta) for T in poses])[:, None]
    s = np.array([math.sin(T.theta) for T in poses])[:, None]
    x, y = np.array([T.x for T in poses])[:, None], np.array([T.y for T in poses])[:, None]
    px, py = pts[:, 0][None, :], pts[:, 1][None, :]
    return np.asarray(cells.near_xy(c * px - s * py + x, s * px + c * py + y).sum(axis=1), dtype=np.int64)


def _conflicts_that_count(
    fa: MapFeatures, fb: MapFeatures, hs: list[Hypothesis], cfg: RegistrationConfig, stride: int, k: int
) -> None:
    """Fill in, in place, the conflict (and score) of the hypotheses ``hs`` (scored without it)
    that can rank among the ``k`` best: in order of support, until the support -- an upper
    bound of the score -- is below the ``k``-th best score found. The others keep NaN."""
    known: list[float] = []
    for i in sorted(range(len(hs)), key=lambda i: -hs[i].support):
        if len(known) >= k and hs[i].support < known[k - 1]:
            break
        hs[i] = _with_conflict(fa, fb, hs[i], cfg, stride)
        known = sorted([*known, hs[i].score], reverse=True)


def _score_key(h: Hypothesis) -> float:
    """Sort key, best score first; a hypothesis not yet scored (NaN) after all scored ones."""
    return math.inf if math.isnan(h.score) else -h.score


def _runner_up(
    fa: MapFeatures, fb: MapFeatures, best: Hypothesis, rivals: list[Hypothesis], cfg: RegistrationConfig,
    stride: int = 1,
) -> tuple[Hypothesis | None, float, float]:
    """The best distinct runner-up and its ratio (step 6): ``(runner, ratio, corner_ratio)``.

    A rival's *score ratio* is its score over the best's; its *corner ratio* is the number of
    B's wall ends it lands within ``rival_corner_dist`` of A's wall ends of the same role and
    direction (:func:`_matched_ends`; looser than the best's ``corner_match_dist``) over the
    best's count. The ratio of a rival is the smaller of its corner ratio and the larger of its
    score ratio and, when it matches more wall than the best, its *support ratio* (conflict
    ignored: a rival that matches more wall than the best is one, whatever the free-space conflict that
    lowered its score -- the drift of a filter-built map puts walls on seen-free space), unless
    it is within ``drift_support_ratio`` of the best's wall and has more conflict than
    acceptance allows for its wall. Within that factor, a rival with ``clean_rival_conflict``
    against a best free of conflict is not counted. A rival
    sliding along a long wall keeps most of the wall length but loses the corners around it,
    and is no rival; repeated structure keeps both and is. The ``rival_refine`` rivals of most
    support are refined first, so that an unrefined rival's corners are not missed for want of
    a few centimetres; the others count corners within twice ``rival_corner_dist``. When the
    best matches fewer than ``rival_min_ends`` typed wall ends, the corner ratio is not trusted
    (one corner swings it) and is taken as 1.

    A rival scored without its conflict (NaN score: every ``stride``-th sample when unrefined,
    every sample when refined here) gets it only when its support (an upper bound of its score)
    could make it the runner-up.
    """
    if not rivals or best.score <= 0:
        top = _with_conflict(fa, fb, rivals[0], cfg, 1 if rivals[0].refined else stride) if rivals else None
        return top, (1.0 if top is not None and top.score > 0 else 0.0), 0.0
    n_best = max(1, _matched_ends(fa, fb, best.transform, cfg, cfg.corner_match_dist))
    few = n_best < cfg.rival_min_ends
    clean = best.conflict <= cfg.max_conflict
    runner, ratio, corner_ratio = None, 0.0, 0.0
    # Strongest rivals by matched wall first: those are refined before their corners count.
    for k, h in enumerate(sorted(rivals, key=lambda h: -h.support)):
        first = k < cfg.rival_refine
        if first and not h.refined:
            h = _score(fa, fb, _refine(fa, fb, h.transform, cfg, stride), cfg.match_dist, cfg, h.votes,
                       refined=True, conflict=False)
            if not _distinct(h.transform, best.transform, fb, cfg):
                continue  # it was the best hypothesis, voted off its cell
        # A rival that matches more wall than the best counts even when its score is low: the
        # free-space conflict that lowers it may be the drift of a filter-built map, and then
        # the rival is the truth and the best a coincidence.
        sup = h.support / best.support if best.support > 0 else 1.0
        # Without its corners (and, unscored, with its support for its score: score <= support)
        # the ratio is an upper bound of the rival's: when even that cannot beat the ratio so
        # far, neither its corners nor its conflict are counted.
        score = h.support if math.isnan(h.score) else h.score
        if runner is not None and min(max(0.0, score / best.score, sup if sup >= 1.0 else 0.0), 1.0) <= ratio:
            continue
        # A rival whose walls the other robot saw through: its support beyond the best's counts
        # only when it is far beyond (drift), and against a best free of conflict it is no rival.
        near = sup < cfg.drift_support_ratio
        spared = near and clean  # its conflict alone can rule it out
        s = 1 if h.refined else stride
        b_on_a = None  # B's walls on A's seen-free space: half of the conflict, a lower bound
        if spared and runner is None and math.isnan(h.conflict):
            # Nothing to prune against yet: the cheaper half first, which often decides alone.
            b_on_a = _conflict_one(fa, fb, h.transform, cfg, s)
            if b_on_a >= cfg.clean_rival_conflict:
                continue
        # Corners of the refined rivals at ``rival_corner_dist``, of the others at twice that.
        gate = cfg.rival_corner_dist if first else 2.0 * cfg.rival_corner_dist
        c = 1.0 if few else _matched_ends(fa, fb, h.transform, cfg, gate) / n_best
        if math.isnan(h.score):
            bound = min(max(0.0, h.support / best.score, sup if sup >= 1.0 else 0.0), c, 1.0)
            if runner is not None and bound <= ratio:
                continue
            h = _with_conflict(fa, fb, h, cfg, s, b_on_a)
        if spared and h.conflict >= cfg.clean_rival_conflict:
            continue
        through = near and h.conflict > cfg.conflict_limit(h.support)
        r = min(max(0.0, h.score / best.score, sup if sup >= 1.0 and not through else 0.0), c, 1.0)
        if r > ratio or runner is None:
            runner, ratio, corner_ratio = h, r, c
    return runner, ratio, corner_ratio


# ------------------------------------------------------------------------------ entry points
def register(a: Wireframe, b: Wireframe, config: RegistrationConfig | None = None) -> Registration:
    """Globally register map ``b`` onto map ``a`` (frames unrelated).

    Parameters
    ----------
    a, b : Wireframe
        The two maps, each in its own frame.
    config : RegistrationConfig, optional

    Returns
    -------
    Registration
        ``transform`` maps ``b``'s points into ``a``'s frame (``b.transformed(transform)`` lies
        on ``a``); use it only when ``accepted``.
    """
    cfg = config or RegistrationConfig()
    return register_prepared(prepare(a, cfg), prepare(b, cfg), cfg)


def refine(fa: MapFeatures, fb: MapFeatures, start: Pose, config: RegistrationConfig | None = None) -> Pose:
    """The local refinement alone (step 5 of the module docstring) on features from
    :func:`prepare`: ``start`` (``b``'s frame in ``a``'s) moved to the nearest alignment of
    ``b``'s walls on ``a``'s, by point-to-line least squares with the gate annealed from
    ``coarse_match_dist`` to ``match_dist``. No search and no decision: a transform known to be
    near (a true start pose, a previous registration) made exact where the two maps share walls.
    Returns ``start`` when either map has under three samples."""
    cfg = config or RegistrationConfig()
    if len(fa.points) < 3 or len(fb.points) < 3:
        return start
    return _refine(fa, fb, start, cfg)


def register_prepared(
    fa: MapFeatures, fb: MapFeatures, config: RegistrationConfig | None = None
) -> Registration:
    """:func:`register` on features from :func:`prepare` (computed once per map and reused for
    every pair, as the fusion service would), with the same ``config``."""
    cfg = config or RegistrationConfig()
    if len(fa.points) == 0 or len(fb.points) == 0:
        return Registration(False, None, "a map has no walls")
    if len(fa.end_points) == 0 or len(fb.end_points) == 0:
        return Registration(False, None, "a map has no real corners")
    cands: list[tuple[float, Pose]] = []
    for theta in rotation_candidates(fa, fb, cfg).tolist():
        R = _rot(theta)
        for t, v in _vote(fa, fb, theta, cfg):
            # x_a = R (x_b - c_b) + t + c_a.
            tt = fa.centre + t - R @ fb.centre
            cands.append((v, Pose(float(tt[0]), float(tt[1]), theta)))
    if not cands:
        return Registration(False, None, "no hypothesis")
    cands.sort(key=lambda c: -c[0])
    n_cands = len(cands)
    stride = 2 if len(fb.points) + len(fa.points) > 2000 else 1
    # Matched wall first; the conflict (the costlier half) only where the score may count: in
    # order of support, until the support (an upper bound of the score) is below the
    # ``refine_candidates``-th score. The others are rivals at most, scored when needed.
    scored = [
        _score(fa, fb, T, cfg.coarse_match_dist, cfg, v, stride, conflict=False)
        for v, T in cands[: cfg.verify_candidates]
    ]
    _conflicts_that_count(fa, fb, scored, cfg, stride, cfg.refine_candidates)
    scored.sort(key=_score_key)
    refined = [
        _score(fa, fb, _refine(fa, fb, h.transform, cfg, stride), cfg.match_dist, cfg, h.votes, refined=True,
               conflict=False)
        for h in scored[: cfg.refine_candidates]
    ]
    # a refined hypothesis with less support than the best score so far cannot win
    _conflicts_that_count(fa, fb, refined, cfg, 1, 1)
    refined.sort(key=_score_key)
    best = refined[0]
    if cfg.use_icp and best.score > 0:
        best = _polish(fa, fb, best, cfg)
    # Runner-up: the best distinct hypothesis among all scored ones (refined ones at their
    # refined score; a coarse score at the coarse gate is an overestimate, which errs on the
    # side of refusing).
    pool = refined[1:] + scored[cfg.refine_candidates:]
    rivals = sorted((h for h in pool if _distinct(h.transform, best.transform, fb, cfg)), key=_score_key)
    runner, ratio, corner_ratio = _runner_up(fa, fb, best, rivals, cfg, stride)
    smaller = min(fa.length, fb.length)
    frac = best.support / smaller if smaller > 0 else 0.0
    reason = ""
    if best.support < cfg.min_support:
        reason = f"too little matched wall ({best.support:.1f} m < {cfg.min_support} m)"
    elif frac < cfg.min_support_fraction:
        reason = f"too little of the smaller map matched ({frac:.0%})"
    elif best.conflict > cfg.conflict_limit(best.support):
        reason = f"walls on seen-free space ({best.conflict:.1f} m)"
    elif ratio > cfg.max_runner_up_ratio:
        reason = f"ambiguous: a distinct hypothesis scores {ratio:.0%} of the best"
    elif ratio > cfg.conflict_runner_up_ratio and best.conflict > cfg.contested_max_conflict:
        reason = (f"contested: a distinct hypothesis scores {ratio:.0%} of the best, whose walls lie on "
                  f"seen-free space ({best.conflict:.1f} m)")
    elif best.cross_support < cfg.min_cross_support:
        reason = f"translation not constrained in every direction ({best.cross_support:.1f} m)"
    elif best.rmse > cfg.max_rmse:
        reason = f"residual too large ({best.rmse:.3f} m)"
    corners = _matched_corners(fa, fb, best.transform, cfg)
    self_a = self_b = 0.0
    unique = ratio <= cfg.unique_runner_up_ratio and best.support >= 2.0 * cfg.min_support
    need = min(cfg.min_corners, cfg.min_corners_unique) if unique else cfg.min_corners
    if not reason and corners < need:
        reason = f"too few matched corners ({corners} < {need})"
    if not reason:
        ib, ia = _final_matches(fa, fb, best, cfg)
        self_a = _self_ratio(fa, ia, cfg)
        self_b = _self_ratio(fb, ib, cfg)
        limit = cfg.contested_self_ratio if ratio > cfg.contested_runner_up_ratio else cfg.max_self_ratio
        if max(self_a, self_b) > limit:
            reason = f"repetitive: the overlap recurs within one map ({max(self_a, self_b):.0%})"
        elif min(self_a, self_b) > cfg.mutual_self_ratio:
            reason = f"repetitive: the overlap recurs within both maps ({min(self_a, self_b):.0%})"
    conf = (
        max(0.0, 1.0 - ratio) * best.support / (best.support + cfg.min_support) if best.support > 0 else 0.0
    )
    return Registration(
        accepted=reason == "", transform=best.transform, reason=reason, confidence=float(conf),
        support=best.support, support_fraction=float(frac), conflict=best.conflict, rmse=best.rmse,
        cross_support=best.cross_support, runner_up_ratio=float(ratio), best=best, runner_up=runner,
        hypotheses=n_cands,
        extra={"corners": float(corners), "self_a": self_a, "self_b": self_b,
               "runner_up_corner_ratio": corner_ratio},
    )
