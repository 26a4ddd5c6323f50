"""Lidar SLAM for real scans: scan-to-submap matching and loop closure over a pose graph.

The wireframe filter (:mod:`mapping.filter`) corrects discrete map errors; on a real lidar its
anchors (corners) are too few to hold the pose over a long log. This module gives it a pose
that every scan point holds, the way Cartographer's local and global SLAM do (ideas, not code):

* **Local matching** (:func:`match_scan`): each scan's points are matched point-to-line (Censi's
  PLICP cost) against a *submap*, the points of the recent scans and of the old scans taken
  nearby (scan-to-map) at their estimated poses, with their normals, the wheel odometry's noise
  as the prior. The result is a node of a pose graph
  and an edge to the previous node whose information is the match's own Hessian: a corridor
  pins the pose across itself, not along it. (Where the graph already holds the place, a scan
  may instead be posed on an old node and be none: ``SlamConfig.revisit_xy``.)
* **Loop closure** (:func:`search_loop`): every ``loop_every`` scans, the recent scans
  (``loop_query_scans``) are searched for in an old submap near the estimate -- a correlative
  search (Olson 2009) over a window that grows with the distance driven since, on a
  likelihood field, coarse to fine -- then refined by the same point-to-line match and
  accepted only when most of the points land on the old walls (``loop_min_inliers``).
* **Pose graph** (:func:`optimize`): Gauss-Newton on the relative-pose errors (Grisetti et al.,
  "A tutorial on graph-based SLAM", 2010, eqs. 30-35), loop edges under a Cauchy kernel, so a
  wrong loop that slips through is down-weighted rather than believed.

Everything is deterministic: no randomness, the same scans give the same poses.

Choices (where the papers leave it open)
----------------------------------------
* Point normals come from each scan on its own (the two neighbours in bearing order within
  ``normal_gap``), as PLICP does; a point without a line through its neighbours (a chair leg,
  a person) is matched against but never matched to.
* The submap is thinned to one point per ``voxel`` cell; the newest scan wins a cell.
* An edge's information is the match's Hessian divided by ``information_scale`` (neighbouring
  returns' errors are correlated; the raw Hessian would make the graph overconfident), capped by
  ``floor_sigma_xy`` / ``floor_sigma_theta``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt, maximum_filter

from mapping.kernels import PointGrid, field_scores, gauss_newton
from mapping.se2 import wrap_angle, wrap_angles

FloatArray = NDArray[np.float64]

__all__ = ["Edge", "LidarSlam", "Match", "SlamConfig", "graph_warp", "match_scan", "optimize",
           "scan_normals", "scan_sides", "search_loop"]


@dataclass(frozen=True)
class SlamConfig:
    """Parameters of :class:`LidarSlam` (the ``slam`` group).

    Parameters
    ----------
    local_scans : int
        Scans in the local submap the next scan is matched against (default 15).
    voxel : float
        Submap thinning cell in metres (0.05).
    iterations : int
        Gauss-Newton iterations of a point-to-line match (12).
    gate_start, gate_end : float
        Nearest-neighbour gate of a match, annealed from ``gate_start`` to ``gate_end`` metres
        (0.5, 0.15).
    kernel : float
        Cauchy scale of a point's line residual in metres (0.05).
    sigma : float
        A point's line residual std in metres, before ``information_scale`` (0.03).
    information_scale : float
        Divides a match's Hessian for the graph's edges (10).
    floor_sigma_xy, floor_sigma_theta : float
        Least std of an edge (0.01 m, 0.003 rad).
    odo_trans_per_m, odo_rot_per_m, odo_rot_per_rad, odo_floor_xy, odo_floor_theta : float
        The wheel odometry's noise, the local match's prior (0.05 /m; 0.035 rad/m, the 2 degrees
        per metre of the shared logs' odometry; 0.02 rad/rad, about 3x the turns' measured error on
        the shared logs, as ``odo_calibration_scale`` is for the metres; 0.01 m; 0.005 rad).
    odo_calibration : bool
        Fit ``odo_rot_per_m`` to the log's own wheels before the run
        (:func:`mapping.lidar_frontend.calibrated_slam`): widened to ``odo_calibration_scale``
        times their measured heading noise per metre, at most ``odo_calibration_max``, never
        below the configured value; needs ``odo_calibration_min_pairs`` matched scan pairs
        (False; on in the ``lidar-slam`` profile).
    odo_calibration_scale, odo_calibration_max : float
        3 (the shared logs' wheels: 0.4-1.0 degrees per metre keep the 2 degrees per metre above,
        orebro's 1.8 widens it to 5.4), 0.15 rad/m.
    odo_calibration_min_pairs : int
        50.
    odo_correlation_sigmas : float
        With ``odo_calibration``: when the wheels' heading errors of successive scan pairs are
        correlated (their lag-1 autocorrelation over consecutive pairs at least this many
        standard errors, ``1 / sqrt(n)``, above zero;
        :class:`mapping.lidar_frontend.OdometryNoise`), the prior per metre is widened by
        ``sqrt((1 + r) / (1 - r))`` (r at most 0.95), up to ``odo_calibration_max`` (3;
        ``inf``: never). Real wheels drift smoothly (a wheel's radius, a slipping tyre): an
        error that persists over many scans adds up along the chain as independent errors of
        that size would not, and a prior sized for independent errors holds the drift against
        the scans (simulated smooth drift, ``wiremap bench scanners``: r 0.6-0.85; the shared
        logs' independent noise: -0.19 to -0.06).
    normal_gap : float
        Neighbours farther than this (metres) give a point no normal (0.6: real scanners' beams
        are 1 degree apart, 0.35 m at 20 m on a wall square to the beam; at 0.3 the far walls,
        which hold the heading best, had no normals and took no part in a match).
    loop_every : int
        Try to close a loop every this many scans (2).
    loop_query_scans : int
        The recent scans searched for in an old submap (5).
    loop_submap_scans : int
        Scans either side of the old node in its submap (8).
    loop_min_travel : float
        Least distance driven between the two ends of a loop, metres (12).
    loop_radius, loop_radius_per_m, loop_radius_max : float
        Search window half-width in metres: ``loop_radius + loop_radius_per_m * driven``, at most
        ``loop_radius_max`` (1.0, 0.05, 5.0).
    loop_angle, loop_angle_per_m, loop_angle_max : float
        Heading window half-width in radians, the same way (0.1, 0.006, 0.5).
    loop_min_inliers : float
        Least share of the query's points within ``loop_inlier_distance`` of an old wall (0.6).
    loop_inlier_distance : float
        Metres (0.1).
    loop_kernel : float
        Cauchy scale of a loop edge's chi (3.0).
    effective_points : float
        A match's data term counts as this many independent points at most (2): neighbouring
        returns' errors are correlated, and a raw scan matched against raw scans is good to a
        couple of centimetres, not to ``sigma / sqrt(n)``; with more, the match overrules the
        odometry's translation, which on the logs is better.
    loop_max_chi2 : float
        A loop is refused when, after optimising with it, a link of the chain or the loop's own
        edge is strained beyond this chi-square (25).
    facing_cos, facing_range, scanner_range : float
        Which side of a wall a point was seen from. A point's normal points towards the
        scanner that saw it (:func:`scan_normals`), so the two faces of a wall have opposite
        normals. With a short-range scanner (``scanner_range`` below ``facing_range`` metres),
        a point with a normal is paired only with a submap point whose normal, turned by the
        pose, faces its own to at least ``facing_cos`` (the nearest such of its three nearest;
        :func:`mapping.kernels.gauss_newton`), in every match: the local one, loops, revisits,
        refinement (0: within 90 degrees; 8 m; ``scanner_range``: inf, unknown, which the front
        end replaces by the scans' declared range, :func:`agents.mapping_run.for_scanner`). A scanner that
        sees 3.5-6 m sees a room's nearest walls and, through a door, the other face of the
        same wall 0.1-0.4 m away: a loop or a refinement that pairs the two slides the map by a
        wall's thickness. Long-range scanners are held by far walls, and on the real 10-80 m
        logs the check cost more than it saved (a partition seen from both sides is one line);
        the measurements are in docs/experiments.md ("A short-range scanner's SLAM paired the
        two faces of a wall").
    loop_settled_xy, loop_settled_theta : float
        A loop whose match puts the scan within this many metres and radians of where the
        estimate already has it is *settled*: its edge joins the graph, but the graph is not
        optimised for it (nor checked for strain: optimising would move nothing that matters).
        The next loop that does move the estimate optimises with every edge so far. A robot that
        drives a building it has mapped closes a loop every ``loop_every`` scans, each a
        Gauss-Newton over the whole graph: without this, its time per scan grows with every scan
        it has ever taken (0 and 0: every loop optimises).
    revisit_xy, revisit_theta : float
        A scan is *redundant* when the graph already holds, within ``revisit_xy`` metres and
        ``revisit_theta`` radians of where the local match puts it, nodes of at least
        ``revisit_visits`` earlier visits of the place (runs of nodes at most
        ``refine_visit_gap`` apart on one chain, each taken at least ``loop_min_travel`` of
        driving before), while the robot is
        tied to them -- a loop closed, or a scan located on old nodes, within ``revisit_lock``
        metres of driving -- and when matched again against the nearest such node's visit alone
        (:meth:`LidarSlam._locate`) it lands on the old walls. It then takes that pose and is
        no node: its pose is kept in that node's frame (:meth:`LidarSlam.scan_poses`), and the
        next scan that is not redundant links to that node. So the graph, and with it a scan's
        cost and the SLAM's memory, grows with the ground covered (``revisit_visits`` times)
        and the driving off the old track, not with the time on duty (Johannsson et al.,
        "Temporally scalable visual SLAM using a reduced pose graph", 2013: a revisit re-uses
        the old nodes; the idea, not their code). 0 and 0: every scan is a node.
    revisit_lock : float
        Metres (8).
    revisit_visits : int
        Visits of a place in the graph before a scan there is redundant (1: the first revisit
        adds no node; 2: the first revisit's nodes and loops tie the map together, as a second
        pass over a log does, before the graph stops growing there).
    map_radius : float
        Old scans whose estimated position is within this many metres of the prediction join
        the local submap (4.0; 0: the recent scans only).
    map_scans : int
        At most this many of them, nearest first (15).
    refine_passes : int
        Offline passes of :meth:`LidarSlam.refine` after the last scan (3; 0: none).
    refine_visit_gap : int
        Old scans near a scan form one *visit* of its place while their indices are at most this
        far apart (3).
    refine_online_nodes : int
        The refinement while the robot drives (0: off, the default): before each scan, this many
        nodes of a sweep that goes round the graph are matched again against the other visits
        of their places, as :meth:`LidarSlam.refine` matches every node after a log; each node's
        edges replace those of its last turn, and the graph is optimised with them every
        ``refine_online_batch`` nodes and at the end of each sweep (and a loop's optimisation
        keeps them). Only visits whose nearest node faces within ``refine_online_facing`` of the
        node are matched (the offline refinement matches all). A node whose visits are the same
        nodes, where they were in its frame at its last match (within ``loop_settled_xy`` /
        ``loop_settled_theta``, at least 2 cm / 0.2 degree), is not matched again, and a sweep
        that changed nothing rests until a node is added or the graph moves: a robot driving
        where it has mapped pays nothing for it once the graph has settled. While the graph
        grows, a look at a node costs a pass over the graph's positions (8 looks about 1 ms a
        scan at 1,700 nodes), a match about 0.7 ms, and each optimisation of the sweep (every
        ``refine_online_batch`` nodes matched, 40-100 ms at 1,700 nodes) moves the nodes, so the
        map follows (``frontend.follow_graph``). Without it a live robot's graph is optimised
        only by loops, and a settled loop not even then (docs/experiments.md, "Session 28").
    refine_online_batch : int
        Nodes matched between two optimisations of the sweep (200).
    refine_online_facing : float
        The sweep matches a node against a visit whose nearest node faces at most this many
        radians away from it (pi / 2): a scanner that sees half a circle sees other walls of a
        place from the other way, and such matches are the sweep's wrong ones (on freiburg-101
        and seattle, 9 % and 3 % of them more than 0.2 m or 1 degree off the truth's relative
        pose, against 1 % and 0.2 % of those facing the same way).
    enabled : bool
        Used by the front end (:attr:`mapping.lidar_frontend.FrontendConfig.slam`): run the SLAM
        under the filter (False).
    online : bool
        Used by the front end: the filter maps each scan at the pose the SLAM gave it when it
        came (:meth:`LidarSlam.add`: the scan-to-map match, loops closed so far), as a robot
        mapping while it drives must, instead of at the poses of the whole log smoothed
        afterwards (False; ``refine_passes`` are then not run).
    """

    local_scans: int = 15
    voxel: float = 0.05
    iterations: int = 12
    gate_start: float = 0.5
    gate_end: float = 0.15
    kernel: float = 0.05
    sigma: float = 0.03
    information_scale: float = 1.0
    floor_sigma_xy: float = 0.01
    floor_sigma_theta: float = 0.003
    odo_trans_per_m: float = 0.05
    odo_rot_per_m: float = 0.035
    odo_rot_per_rad: float = 0.02
    odo_floor_xy: float = 0.01
    odo_floor_theta: float = 0.005
    odo_calibration: bool = False
    odo_calibration_scale: float = 3.0
    odo_calibration_max: float = 0.15
    odo_calibration_min_pairs: int = 50
    odo_correlation_sigmas: float = 3.0
    normal_gap: float = 0.6
    loop_every: int = 2
    loop_query_scans: int = 5
    loop_submap_scans: int = 8
    loop_min_travel: float = 12.0
    loop_radius: float = 1.0
    loop_radius_per_m: float = 0.05
    loop_radius_max: float = 5.0
    loop_angle: float = 0.1
    loop_angle_per_m: float = 0.006
    loop_angle_max: float = 0.5
    loop_min_inliers: float = 0.6
    loop_inlier_distance: float = 0.1
    loop_kernel: float = 3.0
    effective_points: float = 2.0
    loop_max_chi2: float = 25.0
    facing_cos: float = 0.0
    facing_range: float = 8.0
    scanner_range: float = math.inf
    loop_settled_xy: float = 0.0
    loop_settled_theta: float = 0.0
    revisit_xy: float = 0.0
    revisit_theta: float = 0.0
    revisit_lock: float = 8.0
    revisit_visits: int = 1
    map_radius: float = 4.0
    map_scans: int = 15
    refine_passes: int = 3
    refine_visit_gap: int = 3
    refine_online_nodes: int = 0
    refine_online_batch: int = 200
    refine_online_facing: float = math.pi / 2
    enabled: bool = False
    online: bool = False

    @property
    def facing(self) -> bool:
        """Whether the matches check the side of a wall a point was seen from (a short-range
        scanner: ``scanner_range`` below ``facing_range``)."""
        return self.scanner_range < self.facing_range

    def __post_init__(self) -> None:
        if self.local_scans < 1 or self.iterations < 1 or self.loop_every < 1:
            raise ValueError("local_scans, iterations and loop_every must be >= 1")
        if not (self.gate_start >= self.gate_end > 0):
            raise ValueError("need gate_start >= gate_end > 0")
        if self.voxel <= 0 or self.kernel <= 0 or self.sigma <= 0 or self.information_scale <= 0:
            raise ValueError("voxel, kernel, sigma and information_scale must be > 0")
        if self.refine_passes < 0 or self.refine_visit_gap < 1:
            raise ValueError("refine_passes must be >= 0 and refine_visit_gap >= 1")
        if not (self.refine_online_nodes >= 0 and self.refine_online_batch >= 1
                and self.refine_online_facing >= 0):
            raise ValueError("refine_online_nodes and refine_online_facing must be >= 0, "
                             "refine_online_batch >= 1")
        if (min(self.odo_calibration_scale, self.odo_calibration_max) <= 0
                or self.odo_calibration_min_pairs < 2):
            raise ValueError("odo_calibration_scale and odo_calibration_max must be > 0, "
                             "odo_calibration_min_pairs >= 2")
        if not (-1.0 <= self.facing_cos <= 1.0 and self.facing_range >= 0 and self.scanner_range > 0):
            raise ValueError("facing_cos must be in [-1, 1], facing_range >= 0 and scanner_range > 0")
        if not (0 < self.loop_min_inliers <= 1):
            raise ValueError("loop_min_inliers must be in (0, 1]")
        if not (self.loop_settled_xy >= 0 and self.loop_settled_theta >= 0):
            raise ValueError("loop_settled_xy and loop_settled_theta must be >= 0")
        if not (self.revisit_xy >= 0 and self.revisit_theta >= 0 and self.revisit_lock >= 0
                and self.revisit_visits >= 1):
            raise ValueError("revisit_xy, revisit_theta and revisit_lock must be >= 0, revisit_visits >= 1")


# ---------------------------------------------------------------------------------------- SE(2)


def _rot(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def _compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a * b`` of two ``(x, y, theta)`` poses."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2])])


def _between(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a^-1 * b``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[2] - a[2])])


def _apply(pose: FloatArray, pts: FloatArray) -> FloatArray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(pts)
    out[:, 0] = c * pts[:, 0] - s * pts[:, 1] + pose[0]
    out[:, 1] = s * pts[:, 0] + c * pts[:, 1] + pose[1]
    return out


def graph_warp(then: FloatArray, now: FloatArray, points: FloatArray, neighbours: int = 8,
               sigma: float = 1.5) -> FloatArray:
    """``points`` (world frame, ``(n, 2)``) carried along as the graph's nodes moved from
    ``then`` to ``now`` (``(m, 3)`` poses, node for node): each point moves rigidly with the nodes
    nearest it in ``then`` -- the map a robot built at the poses its nodes had follows them when
    a loop reshapes the graph (as Cartographer's submaps move with their poses; the idea, not
    their code). The point's places under the moves of its ``neighbours`` nearest nodes are
    averaged with Gaussian weights (``sigma`` metres) of how much farther each node is than the
    nearest: a wall's nearest node is often one of another visit, or across the wall, whose
    move differs (docs/experiments.md, "Session 27")."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0 or len(then) == 0:
        return pts.copy()
    k = min(neighbours, len(then))
    dist, idx = cKDTree(then[:, :2]).query(pts, k=k)
    dist, idx = dist.reshape(len(pts), k), idx.reshape(len(pts), k)
    a, b = then[idx], now[idx]  # (n, k, 3)
    turn = b[..., 2] - a[..., 2]
    c, s = np.cos(turn), np.sin(turn)
    d = pts[:, None, :] - a[..., :2]
    moved = np.stack([b[..., 0] + c * d[..., 0] - s * d[..., 1],
                      b[..., 1] + s * d[..., 0] + c * d[..., 1]], axis=-1)
    w = np.exp(-0.5 * ((dist - dist[:, :1]) / sigma) ** 2)
    return np.asarray(np.einsum("nk,nkd->nd", w / w.sum(axis=1, keepdims=True), moved))


# ------------------------------------------------------------------------------------- normals


def scan_normals(points: FloatArray, gap: float = 0.3) -> FloatArray:
    """Unit normals ``(n, 2)`` of a scan's points (bearing order) from the line through each
    point's two neighbours, pointing towards the scanner (the frame's origin: the side of the
    wall the point was seen from); NaN where a neighbour is missing or farther than ``gap``, or
    where the three points are far from a line."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    out = np.full((n, 2), np.nan)
    if n < 3:
        return out
    prev, nxt = p[:-2], p[2:]
    mid = p[1:-1]
    d1 = np.hypot(*(mid - prev).T)
    d2 = np.hypot(*(nxt - mid).T)
    t = nxt - prev
    tl = np.hypot(*t.T)
    ok = (d1 <= gap) & (d2 <= gap) & (tl > 1e-6)
    # Straightness: the middle point's distance to the chord, relative to the chord.
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.abs(t[:, 0] * (mid[:, 1] - prev[:, 1]) - t[:, 1] * (mid[:, 0] - prev[:, 0])) / tl
        ok &= off <= 0.25 * tl
        nrm = np.stack([-t[:, 1] / tl, t[:, 0] / tl], axis=1)
    # towards the scanner (the frame's origin): the side of the wall it was seen from
    away = np.einsum("ij,ij->i", nrm, mid) > 0.0
    nrm[away] = -nrm[away]
    out[1:-1][ok] = nrm[ok]
    return out


def scan_sides(points: FloatArray, normals: FloatArray) -> FloatArray:
    """The side of a wall each point was seen from, for the facing check: its normal
    (:func:`scan_normals`), or where it has none the direction from it to the scanner (both
    in the scan's frame; NaN for a point at the scanner)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = np.array(normals, dtype=np.float64, copy=True).reshape(-1, 2)
    none = ~np.isfinite(out[:, 0])
    if none.any():
        d = np.hypot(p[none, 0], p[none, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            out[none] = -p[none] / d[:, None]
    return out


# -------------------------------------------------------------------------------------- submap


@dataclass
class Submap:
    """Points (world frame) with unit normals, thinned to a voxel grid, and bucketed for
    nearest-neighbour queries (:class:`mapping.kernels.PointGrid`)."""

    points: FloatArray
    normals: FloatArray
    grid: PointGrid

    @classmethod
    def build(cls, clouds: list[tuple[FloatArray, FloatArray]], voxel: float) -> Submap:
        """From ``(points, normals)`` per scan, world frame, oldest first; points without a
        normal are dropped; the newest point of a voxel wins."""
        if clouds:
            p = np.concatenate([c[0] for c in clouds])
            n = np.concatenate([c[1] for c in clouds])
        else:
            p = np.zeros((0, 2))
            n = np.zeros((0, 2))
        ok = np.isfinite(n[:, 0])
        p, n = p.compress(ok, axis=0), n.compress(ok, axis=0)  # (row gathers: faster than [ ])
        if len(p):
            keys = np.floor(p / voxel).astype(np.int64)
            # Last occurrence of each cell: unique over the reversed order.
            first_rev = _first_of_each_row(keys[::-1])
            keep = np.sort(len(p) - 1 - first_rev)
            p, n = p.take(keep, axis=0), n.take(keep, axis=0)
        return cls(p, n, PointGrid.build(p))


def _first_of_each_row(keys: NDArray[np.int64]) -> NDArray[np.intp]:
    """The index of the first occurrence of each distinct row of ``keys`` (n, 2), in the order
    of the distinct rows sorted: ``numpy.unique(keys, axis=0, return_index=True)[1]``. The
    rows are numbered as single integers first (row-major over their bounding box) when that
    fits 62 bits: a one-dimensional sort of integers, several times faster than ``unique``'s
    sort of rows as records; the same order and the same indices."""
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if int(span[0]) * int(span[1]) < 2**62:
        code = (keys[:, 0] - lo[0]) * span[1] + (keys[:, 1] - lo[1])
        return np.asarray(np.unique(code, return_index=True)[1])
    return np.asarray(np.unique(keys, axis=0, return_index=True)[1])


# --------------------------------------------------------------------------------------- match


@dataclass(frozen=True)
class Match:
    """A point-to-line match's result.

    Attributes
    ----------
    pose : (3,) float64
        The matched pose ``(x, y, theta)`` in the submap's frame.
    hessian : (3, 3) float64
        The data term's Hessian at the optimum (information on ``pose``, world axes).
    inliers : float
        Share of the points within ``inlier_distance`` of a submap line.
    matched : int
        Points matched in the last iteration.
    """

    pose: FloatArray
    hessian: FloatArray
    inliers: float
    matched: int


def match_scan(
    points: FloatArray,
    submap: Submap,
    guess: FloatArray,
    config: SlamConfig,
    prior_information: FloatArray | None = None,
    inlier_distance: float = 0.1,
    sides: FloatArray | None = None,
) -> Match:
    """Point-to-line Gauss-Newton of robot-frame ``points`` against ``submap`` from ``guess``;
    the prior (``prior_information`` on the pose, centred on ``guess``) keeps what the scan
    does not fix. Each iteration pairs every point with its nearest submap point within the
    gate, annealed geometrically from ``gate_start`` to ``gate_end`` over the first half of the
    iterations, and minimises the points' distances to those points' lines (their normals)
    under Cauchy weights of width ``kernel``; the data term counts as ``effective_points``
    independent points at most (neighbouring returns' errors are correlated, and the truth
    itself is only good to a few cm). Stops after half the iterations once a step moves less
    than 0.1 mm and 0.01 mrad. ``sides`` (:func:`scan_sides` of the points): with a
    short-range scanner a point pairs only with a wall face that looks its way
    (``SlamConfig.facing_cos``). Compiled: :func:`mapping.kernels.gauss_newton`."""
    prior = np.zeros((3, 3)) if prior_information is None else prior_information
    facing = sides if config.facing else None
    pose, hess, inliers, matched = gauss_newton(
        points, submap.grid, submap.normals, guess, prior, config.iterations, config.gate_start,
        config.gate_end, config.sigma, config.kernel, config.effective_points, inlier_distance,
        facing, config.facing_cos)
    return Match(pose, hess, inliers, matched)


# ------------------------------------------------------------------------------ correlative search


@dataclass
class _Field:
    """A likelihood field of a submap on a grid: ``exp(-d^2 / 2 s^2)`` of the distance to the
    nearest submap point, and a coarse copy whose cell holds the max over ``coarse`` fine cells
    (an upper bound of any fine translation it covers: Olson's multi-resolution search)."""

    origin: FloatArray
    res: float
    fine: FloatArray
    coarse: FloatArray
    factor: int

    @classmethod
    def build(cls, pts: FloatArray, res: float, sigma: float, margin: float, factor: int) -> _Field:
        lo = pts.min(axis=0) - margin
        hi = pts.max(axis=0) + margin
        shape = (np.ceil((hi - lo) / res).astype(int) + 1)[::-1]  # rows = y, cols = x
        occ = np.ones(tuple(shape), dtype=bool)
        ij = np.floor((pts - lo) / res).astype(int)
        occ[ij[:, 1], ij[:, 0]] = False
        fine = _field_values(occ, res, sigma)
        coarse = maximum_filter(fine, size=factor, mode="constant", origin=-(factor // 2))
        return cls(lo, res, fine, coarse, factor)

    def score(self, grid: FloatArray, pts: FloatArray, offsets: NDArray[np.int64]) -> FloatArray:
        """Mean field value of ``pts`` (world) shifted by each of ``offsets`` (cells, (k, 2)
        as (dx, dy)); points off the grid score 0 (:func:`mapping.kernels.field_scores`)."""
        return field_scores(grid, self.origin, self.res, pts, offsets)


def _field_values(occ: NDArray[np.bool_], res: float, sigma: float) -> FloatArray:
    """``exp(-0.5 * (distance_transform_edt(occ) * res / sigma) ** 2)``, the same numbers with
    fewer passes over the grid: the nearest-feature indices from the transform, their squared
    cell distances in integers (exact, as the transform's own sum of squared integer offsets
    in floats is), then the same float operations in place."""
    ft = distance_transform_edt(occ, return_distances=False, return_indices=True)
    h, w = occ.shape
    dy = ft[0] - np.arange(h, dtype=ft.dtype)[:, None]
    dx = ft[1] - np.arange(w, dtype=ft.dtype)[None, :]
    dy *= dy
    dx *= dx
    dy += dx
    d: FloatArray = dy.astype(np.float64)
    np.sqrt(d, out=d)
    d *= res
    d /= sigma
    np.multiply(d, d, out=d)
    d *= -0.5
    np.exp(d, out=d)
    return d


def search_loop(
    points: FloatArray,
    submap: Submap,
    guess: FloatArray,
    radius: float,
    angle: float,
    config: SlamConfig,
    *,
    res: float = 0.1,
    coarse_factor: int = 4,
    angle_step: float = math.radians(1.0),
    candidates: int = 8,
    sides: FloatArray | None = None,
) -> Match | None:
    """Where robot-frame ``points`` (the recent scans, in the newest scan's frame) lie in an old
    ``submap``: a correlative search within ``radius`` metres and ``angle`` radians of
    ``guess``, coarse (``coarse_factor`` cells) then fine, the best few refined by
    :func:`match_scan` (with ``sides``, the points' :func:`scan_sides` turned into the same
    frame). Returns the best refined match, or None when none has ``loop_min_inliers``."""
    if len(points) < 10 or len(submap.points) < 10:
        return None
    sub = points if len(points) <= 200 else points[np.linspace(0, len(points) - 1, 200).astype(int)]
    fld = _Field.build(submap.points, res, sigma=2.0 * res, margin=radius + 1.0, factor=coarse_factor)
    step_c = coarse_factor
    n_c = math.ceil(radius / (res * step_c))
    ax = np.arange(-n_c, n_c + 1) * step_c
    offs = np.stack(np.meshgrid(ax, ax, indexing="xy"), axis=-1).reshape(-1, 2)
    # The coarse cell of the field holds the max over the cells [o, o + factor), so the search
    # over a coarse offset o covers fine offsets o .. o + factor - 1.
    n_a = math.ceil(angle / angle_step)
    thetas = guess[2] + np.arange(-n_a, n_a + 1) * angle_step
    best: list[tuple[float, float, int, int]] = []
    for th in thetas:
        world = _apply(np.array([guess[0], guess[1], th]), sub)
        s = fld.score(fld.coarse, world, offs)
        top = np.argsort(-s, kind="stable")[:candidates]
        best.extend((float(s[t]), float(th), int(offs[t, 0]), int(offs[t, 1])) for t in top)
    best.sort(key=lambda b: -b[0])
    fine_ax = np.arange(0, step_c)
    fine_offs = np.stack(np.meshgrid(fine_ax, fine_ax, indexing="xy"), axis=-1).reshape(-1, 2)
    refined: list[tuple[float, FloatArray]] = []
    for _score, th, ox, oy in best[:candidates]:
        world = _apply(np.array([guess[0], guess[1], th]), sub)
        s = fld.score(fld.fine, world, fine_offs + np.array([ox, oy]))
        k = int(np.argmax(s))
        dx, dy = (fine_offs[k] + np.array([ox, oy])) * res
        refined.append((float(s[k]), np.array([guess[0] + dx, guess[1] + dy, th])))
    refined.sort(key=lambda r: -r[0])
    out: Match | None = None
    for _s, start in refined[:3]:
        m = match_scan(points, submap, start, config, inlier_distance=config.loop_inlier_distance,
                       sides=sides)
        if m.inliers >= config.loop_min_inliers and (out is None or m.inliers > out.inliers):
            out = m
    return out


# ---------------------------------------------------------------------------------- pose graph


@dataclass(frozen=True)
class Edge:
    """A relative-pose constraint ``z = x_i^-1 * x_j`` with information ``omega`` (in ``i``'s
    frame rotated to ``j``'s, the error's frame); ``robust``: under the Cauchy kernel."""

    i: int
    j: int
    z: FloatArray
    omega: FloatArray
    robust: bool = False


def _edge_errors(x: FloatArray, ii: NDArray[np.int64], jj: NDArray[np.int64], z: FloatArray) -> FloatArray:
    """``t2v(z^-1 (x_i^-1 x_j))`` of every edge ``(m, 3)``: ``e_xy = R_z^T (R_i^T (t_j - t_i) - t_z)``."""
    return _error_terms(x[ii], x[jj], z, np.cos(z[:, 2]), np.sin(z[:, 2]))[0]


def _error_terms(
    xi: FloatArray, xj: FloatArray, z: FloatArray, cz: FloatArray, sz: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`_edge_errors` of the edges' end poses ``xi``, ``xj`` (``cz``, ``sz``: the cosine and
    sine of ``z``'s angles), with what :func:`optimize`'s Jacobians reuse: ``(err, cos th_i,
    sin th_i, dx, dy)``."""
    ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    ax = ci * dx + si * dy - z[:, 0]
    ay = -si * dx + ci * dy - z[:, 1]
    err = np.stack([cz * ax + sz * ay, -sz * ax + cz * ay,
                    (xj[:, 2] - xi[:, 2] - z[:, 2] + np.pi) % (2 * np.pi) - np.pi], axis=1)
    return err, ci, si, dx, dy


class _Assembly:
    """How :func:`optimize` turns its blocks into the CSC matrix that
    ``scipy.sparse.csc_matrix((vals, (rows, cols)))`` makes of them, for a fixed ``(rows,
    cols)``: the constructor orders the entries by column (a stable counting sort), sorts each
    column's rows in place (``sort_indices``, an unstable sort whose moves depend only on the
    row indices) and adds up the duplicates left to right in the order that leaves. Run once on
    the entries' own numbers as values, the same two steps give where each entry lands; each
    Gauss-Newton iteration then adds its values in that order, the same float additions, and
    the matrix is built from the finished arrays (already canonical, so ``spsolve`` does not
    touch it)."""

    def __init__(self, rows: NDArray[np.int64], cols: NDArray[np.int64], size: int) -> None:
        order = np.argsort(cols, kind="stable")
        indptr = np.zeros(size + 1, dtype=np.int64)
        np.cumsum(np.bincount(cols, minlength=size), out=indptr[1:])
        probe = sp.csc_matrix((order.astype(np.float64), rows.take(order), indptr), shape=(size, size))
        probe.sort_indices()
        src = probe.data.astype(np.int64)  # the entry at each position, in the summation order
        pos_rows = probe.indices
        pos_cols = cols.take(src)
        new = np.ones(len(src), dtype=bool)
        new[1:] = (pos_rows[1:] != pos_rows[:-1]) | (pos_cols[1:] != pos_cols[:-1])
        starts = np.flatnonzero(new)
        counts = np.diff(np.append(starts, len(src)))
        self.first = src.take(starts)
        # Entry t (t >= 1) of every group with more than t: (which groups, which entries).
        self.more: list[tuple[NDArray[np.intp], NDArray[np.int64]]] = []
        for t in range(1, int(counts.max(initial=1))):
            g = np.flatnonzero(counts > t)
            self.more.append((g, src.take(starts.take(g) + t)))
        out_indptr = np.zeros(size + 1, dtype=np.int64)
        np.cumsum(np.bincount(pos_cols.take(starts), minlength=size), out=out_indptr[1:])
        idx_dtype = probe.indices.dtype
        self.indices = pos_rows.take(starts).astype(idx_dtype)
        self.indptr = out_indptr.astype(idx_dtype)
        self.size = size

    def matrix(self, vals: FloatArray) -> sp.csc_matrix:
        data = vals.take(self.first)
        for g, src in self.more:
            data[g] += vals.take(src)
        h = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))
        h.has_sorted_indices = True
        h.has_canonical_format = True
        return h


def _near(rel: FloatArray, last: FloatArray, config: SlamConfig) -> bool:
    """Two sets of relative poses (node for node) within ``loop_settled_xy`` / ``_theta`` (at
    least 2 cm / 0.2 degree) of each other: a match between them would find what it found."""
    xy = max(config.loop_settled_xy, 0.02)
    th = max(config.loop_settled_theta, math.radians(0.2))
    return bool(np.all(np.hypot(*(rel[:, :2] - last[:, :2]).T) <= xy)
                and np.all(np.abs(wrap_angles(rel[:, 2] - last[:, 2])) <= th))


def optimize(poses: FloatArray, edges: list[Edge], iterations: int = 10, kernel: float = 3.0) -> FloatArray:
    """Gauss-Newton over the poses ``(n, 3)`` with node 0 fixed; returns the new poses.

    The error of an edge is ``e = t2v(z^-1 (x_i^-1 x_j))`` and its Jacobians are those of
    Grisetti et al. (2010), eqs. 30-35; a robust edge's information is scaled by the Cauchy
    weight ``1 / (1 + chi2 / kernel^2)``.

    What does not change over the iterations (the edges' arrays, the matrix's structure and
    its summation order, :class:`_Assembly`) is set up once; each iteration computes the same
    numbers as the plain formulation (``tests/test_slam_speed.py`` holds it and compares)."""
    x = np.array(poses, dtype=np.float64)
    n = len(x)
    if n < 2 or not edges:
        return x
    m = len(edges)
    ii = np.array([e.i for e in edges])
    jj = np.array([e.j for e in edges])
    z = np.array([e.z for e in edges])
    omega0 = np.array([e.omega for e in edges])
    robust = np.array([e.robust for e in edges])
    any_robust = bool(robust.any())
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    zt = z[:, 2]
    # Block (p, q) of an edge goes to rows 3p.., cols 3q..: the 9 (row, col) pairs of each.
    r3, c3 = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)
    rows, cols = [], []
    for np_ in (ii, jj):
        for nq in (ii, jj):
            rows.append((3 * np_[:, None] + r3).ravel())
            cols.append((3 * nq[:, None] + c3).ravel())
    rows.append(np.arange(3))
    cols.append(np.arange(3))
    asm = _Assembly(np.concatenate(rows), np.concatenate(cols), 3 * n)
    at_i = (3 * ii[:, None] + np.arange(3)).ravel()
    at_j = (3 * jj[:, None] + np.arange(3)).ravel()
    vals = np.empty(36 * m + 3)
    vals[36 * m:] = 1e12  # node 0 is the frame: a stiff prior holds it
    a = np.zeros((m, 3, 3))
    a[:, 2, 2] = -1.0
    b_ = np.zeros((m, 3, 3))
    b_[:, 2, 2] = 1.0
    for _ in range(iterations):
        xi, xj = x.take(ii, axis=0), x.take(jj, axis=0)
        ti = xi[:, 2]
        err, ci, si, dx, dy = _error_terms(xi, xj, z, cz, sz)
        # R_z^T R_i^T = R(-(th_i + th_z)).
        c, s_ = np.cos(ti + zt), np.sin(ti + zt)
        # d(R_i^T)/d th_i dt = (-si dx + ci dy, -ci dx - si dy); then R_z^T.
        ddx, ddy = -si * dx + ci * dy, -ci * dx - si * dy
        a[:, 0, 0] = -c
        a[:, 0, 1] = -s_
        a[:, 1, 0] = s_
        a[:, 1, 1] = -c
        a[:, 0, 2] = cz * ddx + sz * ddy
        a[:, 1, 2] = -sz * ddx + cz * ddy
        b_[:, 0, 0] = c
        b_[:, 0, 1] = s_
        b_[:, 1, 0] = -s_
        b_[:, 1, 1] = c
        om = omega0.copy()
        if any_robust:
            chi2 = np.einsum("mi,mij,mj->m", err, omega0, err)
            om[robust] /= (1.0 + chi2[robust] / kernel**2)[:, None, None]
        b = np.zeros(3 * n)
        out = vals[: 36 * m].reshape(4, m, 3, 3)
        for p, (at, jp) in enumerate(((at_i, a), (at_j, b_))):
            jto = np.einsum("mki,mkl->mil", jp, om)  # J^T omega
            np.add.at(b, at, np.einsum("mil,ml->mi", jto, err).ravel())
            for q, jq in enumerate((a, b_)):
                np.einsum("mil,mlq->miq", jto, jq, out=out[2 * p + q])
        dxs = spla.spsolve(asm.matrix(vals), -b)
        x += dxs.reshape(-1, 3)
        x[:, 2] = (x[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        if float(np.abs(dxs).max()) < 1e-6:
            break
    return x


def _chi2(x: FloatArray, edges: list[Edge]) -> FloatArray:
    """Each edge's ``e^T omega e`` at the poses ``x``."""
    if not edges:
        return np.zeros(0)
    err = _edge_errors(x, np.array([e.i for e in edges]), np.array([e.j for e in edges]),
                       np.array([e.z for e in edges]))
    return np.asarray(np.einsum("mi,mij,mj->m", err, np.array([e.omega for e in edges]), err))


# ------------------------------------------------------------------------------------- the SLAM


#: Scans whose world-frame cloud :class:`LidarSlam` keeps (11.5 KB a scan of 361 beams: 12 MB
#: at most). A scan's submap takes 15-45 scans, most of them recent; the offline refinement
#: visits every scan's neighbours, and computes an evicted cloud again in microseconds.
CLOUD_CACHE = 1024

#: Submaps :meth:`LidarSlam.refine` keeps for reuse (points, normals and grid: 121 KB a submap
#: on fhw on average, 249 KB at the 95th percentile: about 30 MB for all, 64 MB at worst).
_REFINE_SUBMAPS = 256

#: Submaps the online refinement keeps between scans (:attr:`SlamConfig.refine_online_nodes`):
#: a scan's 8 nodes look at a few visits each, and neighbouring nodes share them.
_SWEEP_SUBMAPS = 32


@dataclass
class _Sweep:
    """The online refinement's state (:attr:`SlamConfig.refine_online_nodes`)."""

    next: int = 0  # the next node to match again
    edges: dict[int, list[Edge]] = field(default_factory=dict)  # each node's edges of its last turn
    # each node's visits and their nodes' poses in its frame at its last match
    seen: dict[int, tuple[tuple[tuple[int, ...], ...], FloatArray]] = field(default_factory=dict)
    # nodes matched, or whose edges were dropped, since the last optimisation
    fresh: set[int] = field(default_factory=set)
    refused: int = 0  # optimisations refused for straining the chain
    matched: int = 0  # nodes matched in all (a count for benches and tests)
    submaps: dict[tuple[int, ...], Submap] = field(default_factory=dict)  # valid while poses stay
    at: int = -1  # ``reshaped`` the submaps were built at
    optimised: int = 0  # the sweep's optimisations (a count for benches and tests)
    changed: bool = False  # a node's visits were looked at anew in this sweep
    idle: tuple[int, int] | None = None  # (nodes, ``reshaped``) after a sweep that changed nothing

    def all_edges(self) -> list[Edge]:
        return [e for es in self.edges.values() for e in es]


@dataclass
class _Node:
    points: FloatArray  # robot frame
    normals: FloatArray  # robot frame, NaN where none

    @functools.cached_property
    def sides(self) -> FloatArray:
        """The side of a wall each point was seen from (:func:`scan_sides`; robot frame), made
        once, when the facing check first asks."""
        return scan_sides(self.points, self.normals)


@dataclass
class LidarSlam:
    """Online lidar SLAM over a log's scans: :meth:`add` per scan, in order.

    ``poses`` holds every node's current estimate (a loop closure or the refinement moves them
    all): every scan's,
    unless ``SlamConfig.revisit_xy`` leaves redundant scans out of the graph (``skipped``
    counts them; :meth:`scan_poses` gives every scan's); ``online`` what :meth:`add` returned
    for each scan at the time; ``settled`` counts the loops of ``loops`` that were settled
    (``SlamConfig.loop_settled_xy``).

    A robot runs this for hours: what a scan costs must not grow with the scans before it
    beyond what the graph's own size forces. The scans' world-frame clouds are a cache of at
    most :data:`CLOUD_CACHE` scans (recomputed, the same arrays, when an evicted scan is needed
    again); the loop search finds its old candidates by the travel array's prefix."""

    config: SlamConfig = field(default_factory=SlamConfig)
    start: FloatArray = field(default_factory=lambda: np.zeros(3))
    poses: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    online: list[FloatArray] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)
    loops: list[tuple[int, int]] = field(default_factory=list)
    rejected: list[tuple[int, int]] = field(default_factory=list)
    settled: int = 0
    skipped: int = 0
    reshaped: int = 0  # optimisations that moved the nodes (each replaces ``poses``; none edits it)
    _nodes: list[_Node] = field(default_factory=list)
    # each scan added: the node it is, or the node it was redundant with and its pose in that
    # node's frame
    _scans: list[tuple[int, FloatArray | None]] = field(default_factory=list)
    _driven: float = 0.0  # metres driven from the first scan to the last
    # metres driven from the first scan to each node's (the first len(_nodes)), grown by doubling
    _travel: FloatArray = field(default_factory=lambda: np.zeros(1024))
    # per node: its chain edge is not from the node before (redundant scans came between them),
    # so the two are not one visit; grown with _travel
    _gap: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(1024, dtype=bool))
    _last_loop: tuple[float, int] = (-math.inf, -(10**9))
    _clouds: dict[int, tuple[bytes, tuple[FloatArray, FloatArray]]] = field(default_factory=dict)
    _sweep: _Sweep = field(default_factory=lambda: _Sweep())

    @property
    def refined(self) -> int:
        """Nodes the online refinement matched again (:attr:`SlamConfig.refine_online_nodes`)."""
        return self._sweep.matched

    def _cloud(self, k: int) -> tuple[FloatArray, FloatArray]:
        """Scan ``k``'s points and normals in the world frame at its current pose. Kept with
        the pose they were computed at and reused while the pose is the same bytes: a scan
        joins the submaps of many later scans, and only a loop closure or the refinement
        moves it (the same function of the same numbers, so the same arrays)."""
        pose = self.poses[k]
        key = pose.tobytes()
        kept = self._clouds.pop(k, None)
        if kept is not None and kept[0] == key:
            self._clouds[k] = kept  # the most recently used last
            return kept[1]
        nd = self._nodes[k]
        cloud = (_apply(pose, nd.points), nd.normals @ _rot(pose[2]).T)
        self._clouds[k] = (key, cloud)
        if len(self._clouds) > CLOUD_CACHE:
            del self._clouds[next(iter(self._clouds))]  # the least recently used
        return cloud

    def _edge_information(self, hessian: FloatArray, theta_j: float) -> FloatArray:
        cfg = self.config
        h = hessian / cfg.information_scale + 1e-6 * np.eye(3)
        floor = np.array([cfg.floor_sigma_xy, cfg.floor_sigma_xy, cfg.floor_sigma_theta])
        cov = np.linalg.inv(h) + np.diag(floor**2)
        # The Hessian is on the world-frame pose; the edge's error lives in the j frame.
        rb = np.eye(3)
        rb[:2, :2] = _rot(theta_j)
        return np.asarray(rb.T @ np.linalg.inv(cov) @ rb)

    def add(self, points: FloatArray, odometry: FloatArray) -> FloatArray:
        """One scan: its robot-frame points (bearing order) and the odometry increment since the
        previous scan ``(dx, dy, dtheta)``. Returns the scan's pose estimate."""
        cfg = self.config
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        odo = np.asarray(odometry, dtype=np.float64)
        k = len(self._nodes)
        d = math.hypot(odo[0], odo[1])
        here = 0.0 if k == 0 else self._driven + d
        node = _Node(pts, scan_normals(pts, cfg.normal_gap))
        if k == 0:
            self._add_node(node, here)
            self.poses = np.array([self.start], dtype=np.float64)
            self._scans.append((0, None))
            self.online.append(self.poses[0].copy())
            return np.array(self.poses[0])
        if cfg.refine_online_nodes:
            self._refine_online()
        anchor, rel = self._scans[-1]
        guess = _compose(self.poses[anchor] if rel is None else _compose(self.poses[anchor], rel), odo)
        sxy = max(cfg.odo_floor_xy, cfg.odo_trans_per_m * d)
        sth = max(cfg.odo_floor_theta, cfg.odo_rot_per_m * d + cfg.odo_rot_per_rad * abs(odo[2]))
        prior = np.diag([1 / sxy**2, 1 / sxy**2, 1 / sth**2])
        lo = max(0, k - cfg.local_scans)
        ids = list(range(lo, k))
        if cfg.map_radius > 0 and lo > 0:
            # Scan-to-map: the old scans taken near here join the submap (the nearest
            # ``map_scans`` within ``map_radius``), so the pose holds to what was mapped before.
            d = np.hypot(*(self.poses[:lo, :2] - guess[:2]).T)
            old = np.flatnonzero(d <= cfg.map_radius)
            old = old[np.argsort(d[old], kind="stable")[: cfg.map_scans]]
            ids = sorted(old.tolist()) + ids
        sub = Submap.build([self._cloud(i) for i in ids], cfg.voxel)
        m = match_scan(pts, sub, guess, cfg, prior_information=prior,
                       sides=node.sides if cfg.facing else None)
        pose = m.pose if m.matched >= 10 else guess
        self._driven = here
        twin = self._redundant_with(pose, here) if m.matched >= 10 else None
        located = None if twin is None else self._locate(node, pose, twin, here)
        if twin is not None and located is not None:
            self._scans.append((twin, _between(self.poses[twin], located)))
            self.skipped += 1
            self._last_loop = (here, twin)  # tied to the old nodes as a loop ties it
            self.online.append(located.copy())
            return np.array(located)
        self._add_node(node, here)
        self.poses = np.vstack([self.poses, pose])
        self._scans.append((k, None))
        # The edge from the node the previous scan is, or was posed on (the robot is then back
        # on new ground: a loop is searched for at once, with the recent nodes as the query --
        # from before the redundant scans too, so it is found only where they agree).
        z = _between(self.poses[anchor], pose)
        if m.matched >= 10:
            omega = self._edge_information(m.hessian, pose[2]) + self._odometry_information(prior, pose[2])
        else:
            omega = self._odometry_information(prior, pose[2])
        self.edges.append(Edge(anchor, k, z, omega))
        if k % cfg.loop_every == 0 or rel is not None:
            self._close_loop(k)
        self.online.append(self.poses[k].copy())
        return np.array(self.poses[k])

    def _add_node(self, node: _Node, travel: float) -> None:
        k = len(self._nodes)
        self._nodes.append(node)
        if k == len(self._travel):
            self._travel = np.concatenate([self._travel, np.zeros(len(self._travel))])
            self._gap = np.concatenate([self._gap, np.zeros(len(self._gap), dtype=bool)])
        self._travel[k] = travel
        self._gap[k] = k > 0 and self._scans[-1][1] is not None

    def _visit(self, j: int, span: int, end: int) -> range:
        """Node ``j`` and up to ``span`` nodes either side of it (before ``end``) on the same
        chain, without crossing a gap: nodes that follow each other across redundant scans are
        not one visit of a place. Without gaps, ``j - span`` to ``j + span`` clipped."""
        lo, hi = max(0, j - span), min(end, j + span + 1)
        gaps = np.flatnonzero(self._gap[lo:hi]) + lo
        return range(int(gaps[gaps <= j].max(initial=lo)), int(gaps[gaps > j].min(initial=hi)))

    def _runs(self, nodes: NDArray[np.int64]) -> list[NDArray[np.int64]]:
        """Ascending ``nodes`` split into visits: runs at most ``refine_visit_gap`` apart on one
        chain (no gap between)."""
        chain = np.cumsum(self._gap[: int(nodes[-1]) + 1])[nodes] if len(nodes) else nodes
        cut = (np.diff(nodes) > self.config.refine_visit_gap) | (np.diff(chain) != 0)
        return np.split(nodes, np.flatnonzero(cut) + 1)

    def _redundant_with(self, pose: FloatArray, here: float) -> int | None:
        """The old node a scan matched at ``pose`` is redundant with (``SlamConfig.revisit_xy``),
        the nearest, or None."""
        cfg = self.config
        if cfg.revisit_xy <= 0 or here - self._last_loop[0] > cfg.revisit_lock:
            return None
        n = len(self._nodes)
        old = np.flatnonzero(here - self._travel[:n] >= cfg.loop_min_travel)
        if len(old) == 0:
            return None
        dist = np.hypot(*(self.poses[old, :2] - pose[:2]).T)
        turn = np.abs(wrap_angles(self.poses[old, 2] - pose[2]))
        ok = (dist <= cfg.revisit_xy) & (turn <= cfg.revisit_theta)
        if not ok.any():
            return None
        near = old[ok]
        if len(self._runs(near)) < cfg.revisit_visits:
            return None
        return int(near[np.argmin(dist[ok])])

    def _locate(self, node: _Node, pose: FloatArray, twin: int, here: float) -> FloatArray | None:
        """A redundant scan's pose on the old map: matched, from ``pose``, against the visit of
        node ``twin`` (its ``loop_submap_scans`` either side, as a loop's old submap), with no
        odometry prior -- the local match leans on the wheels, and the loops that would have
        pulled its heading back are not searched for a scan that is no node (docs/experiments.md,
        "Session 27"). None when fewer than
        ``loop_min_inliers`` of its points land on the old walls, or it moves more than
        ``revisit_xy`` / ``revisit_theta``: the scan becomes a node."""
        cfg = self.config
        n = len(self._nodes)
        ids = self._visit(twin, cfg.loop_submap_scans, n)
        old = [self._cloud(i) for i in ids if here - float(self._travel[i]) >= cfg.loop_min_travel]
        m = match_scan(node.points, Submap.build(old, cfg.voxel), pose, cfg,
                       inlier_distance=cfg.loop_inlier_distance, sides=node.sides if cfg.facing else None)
        move = m.pose - pose
        if (m.matched < 10 or m.inliers < cfg.loop_min_inliers
                or math.hypot(move[0], move[1]) > cfg.revisit_xy
                or abs(wrap_angle(float(move[2]))) > cfg.revisit_theta):
            return None
        return m.pose

    def scan_poses(self) -> FloatArray:
        """Every scan's current estimate, in the order :meth:`add` took them: a node's pose, or
        a redundant scan's pose in its node's frame composed with that node's pose now."""
        out = np.empty((len(self._scans), 3))
        for i, (node, rel) in enumerate(self._scans):
            out[i] = self.poses[node] if rel is None else _compose(self.poses[node], rel)
        return out

    def _odometry_information(self, prior: FloatArray, theta_j: float) -> FloatArray:
        rb = np.eye(3)
        rb[:2, :2] = _rot(theta_j)
        return np.asarray(rb.T @ prior @ rb)

    def _close_loop(self, k: int) -> None:
        cfg = self.config
        here = float(self._travel[k])
        cj = np.flatnonzero(here - self._travel[:k] >= cfg.loop_min_travel)
        if len(cj) == 0:
            return
        dist = np.hypot(*(self.poses[cj, :2] - self.poses[k, :2]).T)
        # The window grows with the distance driven since the old scan -- or since the last loop
        # closed, when that loop's old end is near this one's: it tied the two ends together.
        travel = self._travel[cj]
        tied = np.abs(cj - self._last_loop[1]) <= 3 * cfg.loop_submap_scans
        driven = np.where(tied, np.minimum(here - travel, here - self._last_loop[0]), here - travel)
        radius = np.minimum(cfg.loop_radius + cfg.loop_radius_per_m * driven, cfg.loop_radius_max)
        near = dist <= radius + 2.0
        if not near.any():
            return
        j = int(cj[near][np.argmin(dist[near])])
        r = float(radius[near][np.argmin(dist[near])])
        driven_j = float(driven[near][np.argmin(dist[near])])
        ang = float(min(cfg.loop_angle + cfg.loop_angle_per_m * driven_j, cfg.loop_angle_max))
        # The old submap must be old: no scan driven within loop_min_travel of here.
        ids = [i for i in self._visit(j, cfg.loop_submap_scans, k)
               if here - float(self._travel[i]) >= cfg.loop_min_travel]
        sub = Submap.build([self._cloud(i) for i in ids], cfg.voxel)
        # The query: the recent scans in scan k's frame; after redundant scans, the recent
        # nodes, from before them too (placed through the graph: the alternatives tried are in
        # docs/experiments.md, "Session 27").
        rel = [(_between(self.poses[k], self.poses[i]), self._nodes[i])
               for i in range(max(0, k - cfg.loop_query_scans + 1), k + 1)]
        query = np.concatenate([_apply(z, nd.points) for z, nd in rel])
        query_sides = np.concatenate([nd.sides @ _rot(z[2]).T for z, nd in rel]) if cfg.facing else None
        m = search_loop(query, sub, self.poses[k], r, ang, cfg, sides=query_sides)
        if m is None:
            return
        # An edge from j to k: where k is in j's frame, as the match says.
        # m.pose is scan k in the old submap's frame, the world as node j's estimate has it.
        z = _between(self.poses[j], m.pose)
        omega = self._edge_information(m.hessian, m.pose[2])
        edge = Edge(j, k, z, omega, robust=True)
        move = m.pose - self.poses[k]
        settled = (math.hypot(move[0], move[1]) <= cfg.loop_settled_xy
                   and abs(wrap_angle(float(move[2]))) <= cfg.loop_settled_theta)
        if not settled:
            # With the online refinement's edges: the optimum of the chain and loops alone
            # would undo what it found.
            poses = optimize(self.poses, [*self.edges, *self._sweep.all_edges(), edge],
                             kernel=cfg.loop_kernel)
            # Verification by the graph: a loop the chain of matches can only meet by straining
            # some of its links far beyond their noise is an alias (a corridor's other door), not
            # a loop.
            if self._strain(poses) > cfg.loop_max_chi2 or float(_chi2(poses, [edge])[0]) > cfg.loop_max_chi2:
                self.rejected.append((j, k))
                return
            self.poses = poses
            self.reshaped += 1
        self.edges.append(edge)
        self.loops.append((j, k))
        self.settled += settled
        self._last_loop = (here, j)

    def _strain(self, poses: FloatArray) -> float:
        """The largest chi-square of a chain link at ``poses``: the chain's links are the edges
        that are not loops' or the refinement's (each from the node before, or from the node the
        scan before was redundant with)."""
        return float(_chi2(poses, [e for e in self.edges if not e.robust]).max(initial=0.0))

    def refine(self) -> None:
        """One offline pass over the whole trajectory (the log in hand): every node is matched
        again, from its current pose, against each other *visit* of its place -- the scans taken
        within ``map_radius`` of it, at least ``loop_min_travel`` of driving away, split into runs
        of consecutive scans (``refine_visit_gap``), the nearest ``map_scans`` of each run -- and
        each match with ``loop_min_inliers`` becomes a robust edge from the run's nearest scan;
        the graph is optimised with them, those still strained past ``loop_max_chi2`` are
        dropped and it is optimised again. ``edges`` and ``loops`` are left as they were (the
        pass's edges are rebuilt from the poses on every pass).

        The online pass folds its scan-to-map matches into the edge from the previous scan, so
        the graph forgets them when a loop moves the poses (unless ``refine_online_nodes``
        matches them again as it drives); and a corridor driven back the
        other way rarely passes the loop search. Matched from poses the loops have already
        corrected, every revisit becomes a constraint. One visit per edge: a submap mixing
        visits is blurred by the very error the pass corrects."""
        x = self.poses
        if len(x) < 2:
            return
        edges: list[Edge] = []
        # The poses stay put during the pass, so a submap is a function of its scans: the
        # last _REFINE_SUBMAPS submaps are kept, since nearby scans see the same visits (about
        # 40 % of the submaps repeat).
        submaps: dict[tuple[int, ...], Submap] = {}
        for k in range(len(x)):
            edges += self._revisit_edges(k, submaps)
        if not edges:
            return
        self.poses, _ = self._optimise_with(edges)
        self.reshaped += 1

    def _optimise_with(self, edges: list[Edge]) -> tuple[FloatArray, list[Edge]]:
        """The graph optimised with ``edges`` (robust, found by matching) beside its own, those
        strained past ``loop_max_chi2`` by it dropped and the graph optimised again from the
        same poses without them: ``(poses, the edges kept)``."""
        cfg = self.config
        x = self.poses
        moved = optimize(x, [*self.edges, *edges], kernel=cfg.loop_kernel)
        kept = [e for e, c in zip(edges, _chi2(moved, edges)) if c <= cfg.loop_max_chi2]
        if len(kept) < len(edges):  # (with none dropped it is the same optimisation again)
            moved = optimize(x, [*self.edges, *kept], kernel=cfg.loop_kernel)
        return moved, kept

    def _refine_online(self) -> None:
        """The next ``refine_online_nodes`` nodes of the sweep (:attr:`SlamConfig.refine_online_nodes`)
        matched again, unless nothing about them changed since their last turn; the graph
        optimised with every node's last edges every ``refine_online_batch`` nodes and at the
        sweep's end when some node was matched again since the last time."""
        cfg, sw = self.config, self._sweep
        n = len(self.poses)
        if n < 2 or sw.idle == (n, self.reshaped):
            return
        sw.idle = None
        if sw.at != self.reshaped:  # a loop or the sweep moved the nodes the submaps were built at
            sw.submaps.clear()
            sw.at = self.reshaped
        for _ in range(min(cfg.refine_online_nodes, n)):
            k = sw.next
            facing = self.poses[k, 2]
            visits = [(j, ids) for j, ids in self._revisit_visits(k)
                      if abs(wrap_angle(float(self.poses[j, 2] - facing))) <= cfg.refine_online_facing]
            key = tuple(ids for _, ids in visits)
            rel = self._relative(k, np.unique(np.concatenate(key))) if key else np.zeros((0, 3))
            last = sw.seen.get(k)
            if last is None or last[0] != key or not _near(rel, last[1], cfg):
                sw.seen[k] = (key, rel)
                if key:
                    sw.edges[k] = self._revisit_edges(k, sw.submaps, visits, _SWEEP_SUBMAPS)
                    sw.matched += 1
                    sw.fresh.add(k)
                elif sw.edges.pop(k, None):  # its visits are gone (the graph moved): so are its edges
                    sw.fresh.add(k)
                sw.changed = True
            sw.next += 1
            if sw.next >= n:  # the sweep is round
                sw.next = 0
                break
        if sw.fresh and (sw.next == 0 or len(sw.fresh) >= cfg.refine_online_batch):
            self._solve_sweep()
        if sw.next == 0:  # a sweep that changed nothing: none until a node comes or a loop moves them
            if not sw.changed:
                sw.idle = (n, self.reshaped)
                sw.submaps.clear()
            sw.changed = False

    def _relative(self, k: int, ids: NDArray[np.int64]) -> FloatArray:
        """Nodes ``ids``' poses in node ``k``'s frame, ``(len(ids), 3)``."""
        x = self.poses
        c, s = math.cos(x[k, 2]), math.sin(x[k, 2])
        dx, dy = x[ids, 0] - x[k, 0], x[ids, 1] - x[k, 1]
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angles(x[ids, 2] - x[k, 2])])

    def _solve_sweep(self) -> None:
        """The graph optimised with every node's latest edges (:meth:`_optimise_with`); the
        strained ones are dropped, and stay dropped until their node is matched again (when its
        visits move). Refused, the poses kept and the edges of the nodes matched since the last
        time dropped, when it would strain a link of the chain past ``loop_max_chi2``: the
        chain's matches are the graph's backbone, and a loop's own check
        (:meth:`_close_loop`) would then blame every later loop for that strain."""
        cfg, sw = self.config, self._sweep
        fresh, sw.fresh = sw.fresh, set()
        edges = sw.all_edges()
        if not edges:
            return
        moved, kept = self._optimise_with(edges)
        if self._strain(moved) > cfg.loop_max_chi2:
            for k in fresh:
                sw.edges.pop(k, None)
            sw.refused += 1
            return
        if len(kept) < len(edges):
            ids = {id(e) for e in kept}
            for k, es in sw.edges.items():
                sw.edges[k] = [e for e in es if id(e) in ids]
        self.poses = moved
        self.reshaped += 1  # (the next turn of the sweep builds its submaps anew)
        sw.optimised += 1

    def _revisit_visits(self, k: int) -> list[tuple[int, tuple[int, ...]]]:
        """The other visits of node ``k``'s place (:meth:`refine`): per visit, its node nearest
        ``k`` and its ``map_scans`` nearest nodes (ascending)."""
        cfg = self.config
        x = self.poses
        travel = self._travel[: len(x)]
        d = np.hypot(*(x[:, :2] - x[k, :2]).T)
        old = np.flatnonzero((np.abs(travel - travel[k]) >= cfg.loop_min_travel) & (d <= cfg.map_radius))
        if len(old) < 2:
            return []
        out = []
        for run in self._runs(old):
            if len(run) < 2:
                continue
            run = run[np.argsort(d[run], kind="stable")[: cfg.map_scans]]
            out.append((int(run[0]), tuple(np.sort(run).tolist())))
        return out

    def _revisit_edges(self, k: int, submaps: dict[tuple[int, ...], Submap],
                       visits: list[tuple[int, tuple[int, ...]]] | None = None,
                       cache: int = _REFINE_SUBMAPS) -> list[Edge]:
        """Node ``k`` matched, from its current pose, against each other visit of its place
        (``visits``, by default :meth:`_revisit_visits`): a robust edge from each visit's nearest
        node that the match lands on. ``submaps`` is an LRU cache of the visits' submaps, valid
        while the poses stay put, of at most ``cache`` submaps."""
        cfg = self.config
        x = self.poses
        nd = self._nodes[k]
        sides = nd.sides if cfg.facing else None
        edges: list[Edge] = []
        for j, ids in self._revisit_visits(k) if visits is None else visits:
            sub = submaps.pop(ids, None)
            if sub is None:
                sub = Submap.build([self._cloud(i) for i in ids], cfg.voxel)
                if len(submaps) >= cache:
                    del submaps[next(iter(submaps))]  # the least recently used
            submaps[ids] = sub
            m = match_scan(nd.points, sub, x[k], cfg, inlier_distance=cfg.loop_inlier_distance, sides=sides)
            if m.inliers < cfg.loop_min_inliers or m.matched < 10:
                continue
            edges.append(Edge(j, k, _between(x[j], m.pose), self._edge_information(m.hessian, m.pose[2]),
                              robust=True))
        return edges
