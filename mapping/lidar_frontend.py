"""Real-lidar front end: one laser scan's ranges -> the corner scan and the points to match.

The filter takes a labelled corner scan (:mod:`mapping.extract`, split-and-merge) for its
likelihoods and merge, and -- with :attr:`mapping.filter.FilterConfig.point_match` -- the raw
points for a point-to-line match against the map (:mod:`mapping.scan_match`). This module makes
both from one scan of a real scanner, whose ranges differ from the simulator's in ways the
front end has to absorb:

* a **limited field of view** (180 degrees on the CARMEN logs), so a scan's ends are frontiers
  on the first and last beam (the extractor handles that) and the filter's predicted scan must
  use the same ``fov``;
* a **saturation value** for "no return" (81.91, 51.2 or 32.767 m depending on the scanner) and
  long, grazing returns far beyond the range the map is built to (``max_range``): the caller
  maps both to ``inf``; the points keep returns up to ``point_range`` (far points still pin the
  heading down);
* **clutter** (chairs, people, glass): the extractor drops short pieces; the point matcher's
  robust kernel and normal test drop the points.

Choices
-------
* Points are every ``point_stride``-th return (a 0.5-degree scanner gives twice the points of
  a 1-degree one at twice the cost and the same information, their errors being correlated).
* Points nearer than ``min_range`` are dropped (the robot's own body, a person next to it).
* **Scan odometry** (``scan_odometry``): the wheel odometry's increment between two scans is
  refined by matching the scan's points against the previous scan's, taken as a polyline
  (consecutive returns joined where they are close, as in Censi's PLICP), with the odometry
  noise as the prior (:func:`scan_increment`). The CARMEN logs' wheels err by ~2 degrees per
  metre with a scan every metre; two consecutive 180-degree scans share most of their walls
  and pin the turn down to a fraction of that, before the map is involved at all.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mapping.extract import ExtractConfig, extract_corners
from mapping.lidar_slam import LidarSlam, Match, SlamConfig, Submap, match_scan, scan_normals, scan_sides
from mapping.scan_match import PointMatchConfig, match_points
from mapping.se2 import Pose, increments
from mapping.wireframe import Wireframe

FloatArray = NDArray[np.float64]

__all__ = [
    "CalibrationPair",
    "FrontendConfig",
    "LidarFrontend",
    "OdometryNoise",
    "ScaleEstimate",
    "YawEstimate",
    "calibrated_slam",
    "calibration_pairs",
    "dense_share",
    "deskew",
    "lag_correlation",
    "laser_yaw",
    "match_to_previous",
    "motion_filter",
    "odometry_noise",
    "odometry_overrides",
    "run_slam",
    "scan_increment",
    "scan_points",
    "scan_polyline",
    "slam_increments",
    "wheel_scale",
    "within_motion_limits",
]


@dataclass(frozen=True)
class FrontendConfig:
    """Parameters of :class:`LidarFrontend`.

    Parameters
    ----------
    point_range : float
        Returns farther than this (metres) are not matched (default 20).
    min_range : float
        Returns nearer than this are not matched (default 0.3).
    point_stride : int
        Keep every ``point_stride``-th beam's return (default 1).
    max_beam_spacing : float
        Beam spacing (radians) above which ``point_stride`` is 1 whatever it says (default 1.5
        degrees): coarse scanners keep all their points.
    scan_odometry : bool
        Refine each odometry increment by matching the scan against the previous one
        (:func:`scan_increment`; default False).
    odo_trans_per_m, odo_rot_per_m, odo_rot_per_rad : float
        The wheel odometry's noise, the scan odometry's prior: translation std per metre,
        heading std per metre and per radian turned (defaults 0.07, 0.05, 0.05).
    odo_floor_xy, odo_floor_theta : float
        Least prior std (0.05 m, 0.02 rad): a robot standing still may still be pushed.
    link_gap : float
        Consecutive returns of the previous scan farther apart than this, or than three times
        the arc between them at their range, are not joined (metres; default 0.3).
    slam : mapping.lidar_slam.SlamConfig
        Lidar SLAM under the filter (:func:`slam_increments`; off by default, on in the
        real-lidar profile).
    yaw_calibration : bool
        Estimate the laser's yaw against the wheel odometry (:func:`laser_yaw`) and turn the
        bearings by it when it is pinned down (default False; on in the real-lidar profiles).
    yaw_min_step : float
        Scan pairs whose odometry moved less than this (metres) give no direction (0.3).
        ``yaw_min_step``, ``yaw_max_pairs`` and ``yaw_min_inliers`` choose the scan pairs of
        both calibrations, the laser's yaw and the wheels' heading noise
        (:func:`calibration_pairs`).
    yaw_max_pairs : int
        At most this many pairs, evenly spread over the log (400: a standard error of ~0.1
        degree on the shared logs, ~0.3 ms per pair).
    yaw_min_pairs : int
        Fewer matched pairs than this estimate nothing (50).
    yaw_sigmas : float
        The yaw is applied when it is at least this many standard errors from zero (3).
    yaw_min_inliers : float
        A pair's match counts when at least this share of the scan's points lie within
        0.1 m of the other scan's lines (0.5).
    calibration_scans : int
        The laser's yaw and the wheels' heading noise are measured on the first this many scans
        only (0, the default: on the whole log). A robot mapping as it drives has only what it
        has seen: the online profile calibrates on its first 100 scans (a warm-up: those
        scans are mapped once it has them).
    laser_yaw : float
        The laser's yaw in degrees when known (measured once for the robot, e.g. the
        ``laser_yaw_estimate_deg`` of ``wiremap map --carmen`` on an earlier log): taken off
        every bearing instead of estimated; NaN (the default) when not known.
    follow_graph : bool
        With the online SLAM (``slam.online``, :class:`OnlineSlam`): when a loop or the online
        refinement (``slam.refine_online_nodes``) reshapes the SLAM's graph, the map built so far
        moves with it before the next scan is mapped
        (:func:`mapping.lidar_slam.graph_warp`, each vertex under its 8 nearest nodes' moves;
        :func:`agents.mapping_run.feed`) (default False; on in ``lidar-slam-online``).
    scale_calibration : bool
        Estimate the wheels' distance scale against the scans (:func:`wheel_scale`) and take it
        off every wheel increment when it is pinned down (default False; on in the real-lidar
        profiles). A worn tyre or a wrong wheel radius makes every metre of the wheels 1-3 %
        long or short; along a corridor the scans cannot see it (its walls look alike all
        along), and the map is stretched or shrunk by it.
    scale_min_pairs : int
        Fewer matched pairs than this estimate nothing (20).
    scale_sigmas, scale_min : float
        The scale is applied when it is at least ``scale_sigmas`` standard errors and
        ``scale_min`` away from 1 (3; 0.01: the shared logs' wheels, without a scale error,
        measure 0.986-1.006 with standard errors of 0.002-0.006, and are left as they are).
    deskew : bool
        A scan whose beams were not simultaneous (its ``time_increment``: a spinning lidar takes
        0.1-0.2 s a turn) while the robot moved is bent by the motion; each return is placed
        where the laser stood when it came, at the wheels' velocity (:func:`deskew`; default
        True: a scan without a ``time_increment``, every shared CARMEN log's, is left as it is).
    sweep_reversed : bool
        The beams came in the order opposite to the one ``time_increment``'s sign says; the
        de-skew takes them the other way round (False). The TurtleBot3 LDS-01's ROS driver
        does this by default (``hls_lfcd_lds_driver``, ``chronological_order: false``): it lists
        the returns by increasing bearing with a positive time increment while the lidar sweeps
        the bearings downwards, so a turn would be added to the scan rather than taken off.
        Its ``chronological_order: true`` says it right (decreasing bearings) and needs nothing.
    sweep_check : bool
        Offline, judge the order on the log itself (True): the log's turning scans (the wheels
        turning ``SWEEP_CHECK_TURN`` or faster, up to ``SWEEP_CHECK_SCANS``), each de-skewed both
        ways and matched against the scan before it de-skewed the same way; the order opposite
        to ``sweep_reversed`` is taken when its matches hold more of the points, by at least 1 %
        and three standard errors (:func:`agents.mapping_run.sweep_check`). Fewer than
        ``SWEEP_CHECK_MIN`` turning scans: ``sweep_reversed`` as set.
    min_travel, min_turn : float
        The **motion filter**'s limits (metres, radians; 0.5 m and 10 degrees): a scan whose
        wheels have moved less than ``min_travel`` and turned less than ``min_turn`` since the
        last scan kept is left out (:func:`motion_filter`), as Cartographer's motion filter and
        GMapping's ``linearUpdate`` / ``angularUpdate`` do. The SLAM's settings were tuned on
        logs with a scan every 0.5-1 m; a lidar sends 10-40 scans a second, one every few
        centimetres, and every scan mapped grows the pose graph and costs its time.
    dense_share : float
        A log is *dense* when more than this share of its consecutive scans lie within the
        motion filter's limits of each other (:func:`dense_share`; default 0.5): the offline
        paths (``wiremap map``, ``bench lidar``, ``run --carmen``) thin a dense log by the
        motion filter and map every scan of any other (the shared CARMEN logs: 0-4 % of pairs
        within the limits; a 10 Hz lidar at walking pace: over 90 %). 0 thins every log, 1
        none. A live robot filters always (its ``--min-travel``, ``--min-turn``).
    """

    point_range: float = 20.0
    min_range: float = 0.3
    point_stride: int = 1
    max_beam_spacing: float = math.radians(1.5)
    scan_odometry: bool = False
    odo_trans_per_m: float = 0.07
    odo_rot_per_m: float = 0.05
    odo_rot_per_rad: float = 0.05
    odo_floor_xy: float = 0.05
    odo_floor_theta: float = 0.02
    link_gap: float = 0.3
    slam: SlamConfig = field(default_factory=SlamConfig)
    follow_graph: bool = False
    yaw_calibration: bool = False
    yaw_min_step: float = 0.3
    yaw_max_pairs: int = 400
    yaw_min_pairs: int = 50
    yaw_sigmas: float = 3.0
    yaw_min_inliers: float = 0.5
    calibration_scans: int = 0
    laser_yaw: float = math.nan
    deskew: bool = True
    sweep_reversed: bool = False
    sweep_check: bool = True
    scale_calibration: bool = False
    scale_min_pairs: int = 20
    scale_sigmas: float = 3.0
    scale_min: float = 0.01
    min_travel: float = 0.5
    min_turn: float = math.radians(10.0)
    dense_share: float = 0.5

    def __post_init__(self) -> None:
        if not (self.point_range > self.min_range >= 0):
            raise ValueError("need point_range > min_range >= 0")
        if self.point_stride < 1:
            raise ValueError("point_stride must be >= 1")
        if self.calibration_scans < 0:
            raise ValueError("calibration_scans must be >= 0 (0: the whole log)")
        if math.isinf(self.laser_yaw) or abs(self.laser_yaw) > 180.0:
            raise ValueError("laser_yaw must be degrees in [-180, 180], or NaN for not known")
        if not (self.yaw_min_step > 0 and self.yaw_max_pairs >= self.yaw_min_pairs >= 2
                and self.yaw_sigmas >= 0 and 0 < self.yaw_min_inliers <= 1):
            raise ValueError("need yaw_min_step > 0, yaw_max_pairs >= yaw_min_pairs >= 2, "
                             "yaw_sigmas >= 0 and 0 < yaw_min_inliers <= 1")
        if not (self.scale_min_pairs >= 3 and self.scale_sigmas >= 0 and self.scale_min >= 0):
            raise ValueError("need scale_min_pairs >= 3, scale_sigmas >= 0 and scale_min >= 0")
        if not (self.min_travel >= 0 and self.min_turn >= 0 and 0 <= self.dense_share <= 1):
            raise ValueError("need min_travel >= 0, min_turn >= 0 and 0 <= dense_share <= 1")


def odometry_overrides(trans_per_m: float = 0.05, rot_per_m: float = math.radians(2.0)) -> dict[str, float]:
    """:class:`mapping.filter.FilterConfig` overrides (dotted keys,
    :func:`mapping.config.with_overrides`) whose odometry noise model covers a robot
    whose odometry errs by ``trans_per_m`` of the distance and ``rot_per_m`` radians per metre
    (defaults: the CARMEN development logs' 5 % and 2 degrees per metre), with the filter's
    usual margin of about 1.4 (it should not trust its odometry more than it deserves).

    The filter's defaults (3 % and 0.17 degrees per metre) are 1.5 times the *simulator's*
    odometry noise. On the real logs -- a scan every metre, turning 15 degrees between scans
    (median) -- they made the pose prior ten times too tight in heading: the ICP's gate and
    Mahalanobis test then rejected the right correction, and the pose ran on odometry. This
    alone took the seven logs' median ATE from 1.59 m to 0.42 m (docs/experiments.md, "Real
    lidar")."""
    return {"odometry.trans_per_m": round(1.4 * trans_per_m, 3),
            "odometry.rot_per_m": round(1.43 * rot_per_m, 3)}


#: The scan odometry's matcher: the usual point matcher with a wider first gate and a looser
#: residual test (two raw scans, each with its own noise, rather than a scan and a fitted map).
SCAN_ODOMETRY_MATCH = PointMatchConfig(
    enabled=True, max_iterations=15, anneal_iterations=5, gate_end=0.3, kernel=0.05, sigma=0.03,
    information_scale=0.05, end_margin=0.3, max_rmse=0.08, min_inliers=30, min_inlier_fraction=0.3,
)


def deskew(
    ranges: FloatArray, angles: FloatArray, time_increment: float, velocity: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """A scan's ``(ranges, bearings)`` as seen from where the laser stood at the scan's time (its
    first beam's) when its beams came ``time_increment`` seconds apart (in the order of
    ``angles``; negative: the last beam first) while it moved at ``velocity`` (``vx, vy`` m/s in
    its own frame, ``turn`` rad/s): a return fired ``t`` seconds later is placed where the laser
    then stood, ``t`` times the velocity on (a straight line: at 0.5 m/s turning 1 rad/s, over a
    0.2 s sweep the arc is a centimetre off it), a no-return beam turned with the laser. Turning
    on the spot at 1 rad/s a 10 Hz scan spans 5.7 degrees, 10 cm at the far end of a wall a
    metre away; driving at 0.5 m/s the laser moves 5 cm.

    The result's bearings strictly increase: they are sorted (a near return that moved past its
    neighbours' bearings lands among them, where it is; an exact repeat is dropped). A turn
    against the sweep at least as fast as the beams come (``|turn * time_increment|`` half a beam
    step or more: no scanner spins that slowly) is not a scan's motion, and the scan is left as
    it is. A full turn's scan whose bearings then span more than a turn loses its beams past it,
    the later ones (they saw again, a sweep later, what the first beams saw)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    n = a.size
    vx, vy, turn = velocity
    if n < 2 or time_increment == 0.0 or (vx == 0.0 and vy == 0.0 and turn == 0.0):
        return r, a
    step = (a[-1] - a[0]) / (n - 1)
    if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(turn)) \
            or abs(turn * time_increment) >= 0.5 * abs(step):
        return r, a
    k = np.arange(n, dtype=np.float64)
    t = k * time_increment if time_increment > 0.0 else (k - (n - 1)) * time_increment
    out_a = a + turn * t
    hit = np.isfinite(r)
    out_r = r
    if hit.any() and (vx or vy):
        x = r[hit] * np.cos(out_a[hit]) + vx * t[hit]
        y = r[hit] * np.sin(out_a[hit]) + vy * t[hit]
        out_r = r.copy()
        out_r[hit] = np.hypot(x, y)
        change = np.remainder(np.arctan2(y, x) - out_a[hit] + math.pi, 2.0 * math.pi) - math.pi
        out_a = out_a.copy()  # the bearing's change, added to the turned beam's: no wrap at +-pi
        out_a[hit] += change
    order = np.argsort(out_a, kind="stable")
    out_r, out_a = out_r[order], out_a[order]
    fresh = np.concatenate(([True], np.diff(out_a) > 0.0))
    out_r, out_a = out_r[fresh], out_a[fresh]
    turn_span = 2.0 * math.pi - 0.5 * abs(step)
    if out_a.size > 1 and out_a[-1] - out_a[0] >= turn_span:  # past a full turn
        if time_increment > 0.0:  # the later beams are at the end
            keep = out_a - out_a[0] < turn_span
        else:  # the last beam first: the later beams are at the start
            keep = out_a[-1] - out_a < turn_span
        out_r, out_a = out_r[keep], out_a[keep]
    return out_r, out_a


def within_motion_limits(step: Pose, min_travel: float, min_turn: float) -> bool:
    """Whether the wheels' ``step`` since the last scan kept is too small for the motion filter
    to keep this one: moved less than ``min_travel`` and turned less than ``min_turn``."""
    turn = abs(math.remainder(step.theta, 2.0 * math.pi))
    return math.hypot(step.x, step.y) < min_travel and turn < min_turn


def motion_filter(odometry: Sequence[Pose], min_travel: float, min_turn: float) -> list[int]:
    """Indices of the scans the motion filter keeps, given the wheels' pose at each: the first,
    then each scan not :func:`within_motion_limits` of the last one kept."""
    kept: list[int] = []
    last: Pose | None = None
    for k, pose in enumerate(odometry):
        if last is not None and within_motion_limits(last.between(pose), min_travel, min_turn):
            continue
        kept.append(k)
        last = pose
    return kept


def dense_share(odometry: Sequence[Pose], min_travel: float, min_turn: float) -> float:
    """The share of consecutive scans (the wheels' pose at each) within the motion filter's
    limits of each other; 0 for fewer than two scans."""
    if len(odometry) < 2:
        return 0.0
    pairs = itertools.pairwise(odometry)
    close = sum(within_motion_limits(a.between(b), min_travel, min_turn) for a, b in pairs)
    return close / (len(odometry) - 1)


def scan_polyline(points: FloatArray, link_gap: float = 0.3) -> FloatArray:
    """Segments (m, 2, 2) joining consecutive points (bearing order) that are close: within
    ``link_gap`` or three times the arc between them at the nearer one's range."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        return np.zeros((0, 2, 2))
    a, b = p[:-1], p[1:]
    step = np.hypot(*(b - a).T)
    rmin = np.minimum(np.hypot(*a.T), np.hypot(*b.T))
    ang = np.abs(np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.einsum("ij,ij->i", a, b)))
    ok = (step > 1e-6) & (step <= np.maximum(link_gap, 3.0 * rmin * ang))
    return np.stack([a[ok], b[ok]], axis=1)


def scan_increment(
    prev_points: FloatArray, points: FloatArray, odometry: Pose, config: FrontendConfig
) -> tuple[Pose, bool]:
    """The motion between two scans: the wheel ``odometry`` increment (previous robot frame)
    refined by matching ``points`` against ``prev_points`` joined into a polyline
    (:func:`scan_polyline`, :func:`mapping.scan_match.match_points`), the odometry's noise
    (``odo_*`` of ``config``) as the prior. Returns ``(increment, matched)``; the wheel
    increment itself when the match is not accepted."""
    d = math.hypot(odometry.x, odometry.y)
    sxy = max(config.odo_floor_xy, config.odo_trans_per_m * d)
    sth = max(config.odo_floor_theta, config.odo_rot_per_m * d + config.odo_rot_per_rad * abs(odometry.theta))
    prior = np.diag([sxy**2, sxy**2, sth**2])
    segs = scan_polyline(prev_points, config.link_gap)
    if len(segs) < 3 or len(points) < 3:
        return odometry, False
    # The previous scan in the frame the odometry predicts for this one.
    inv = odometry.inverse()
    segs_here = inv.apply(segs.reshape(-1, 2)).reshape(-1, 2, 2)
    reach = float(min(2.0, 3.0 * (sxy + sth * 5.0)))
    pm = match_points(points, segs_here, prior, SCAN_ODOMETRY_MATCH, gate_start=reach)
    if not pm.accepted:
        return odometry, False
    return odometry.compose(pm.correction), True


def scan_points(ranges: FloatArray, angles: FloatArray, config: FrontendConfig) -> FloatArray:
    """The points to match (robot frame, bearing order): finite returns within
    ``[min_range, point_range]``, every ``point_stride``-th beam."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    stride = config.point_stride
    if len(a) > 1 and abs(a[1] - a[0]) > config.max_beam_spacing:
        stride = 1
    r, a = r[::stride], a[::stride]
    ok = np.isfinite(r) & (r >= config.min_range) & (r <= config.point_range)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)


@dataclass(frozen=True)
class YawEstimate:
    """What :func:`laser_yaw` found.

    ``yaw``: radians, the angle from the odometry's direction of travel to the scans' (10 %
    trimmed mean over the pairs; positive: the scans see the motion turned counter-clockwise,
    so the bearings are to be turned by ``-yaw``); ``se``: its standard error;
    ``pairs``: the matched pairs it rests on; ``applied``: whether it passed the test of
    ``yaw_min_pairs`` and ``yaw_sigmas`` (``correction`` is then ``yaw``, else 0)."""

    yaw: float
    se: float
    pairs: int
    applied: bool

    @property
    def correction(self) -> float:
        """The turn to take off every bearing (radians; 0 when not applied)."""
        return self.yaw if self.applied else 0.0


def laser_yaw(
    points: list[FloatArray], odometry: list[Pose], config: FrontendConfig,
    pairs: list[CalibrationPair] | None = None,
) -> YawEstimate:
    """The laser's yaw against the wheel odometry's direction of travel (module notes).

    For up to ``yaw_max_pairs`` consecutive scans ``k - 1, k`` (evenly spread) whose odometry
    increment moved at least ``yaw_min_step``: scan ``k``'s points matched against scan ``k -
    1``'s alone (:func:`mapping.lidar_slam.match_scan` with the SLAM's settings, from the
    odometry's increment, no prior), kept with ``yaw_min_inliers``; the angle from the
    odometry's translation to the matched one; their 10 % trimmed mean. ``points``: each scan's
    points (robot frame);
    ``odometry``: the wheel increment into each scan (``odometry[0]`` unused); ``pairs``: their
    :func:`calibration_pairs` when already made."""
    if pairs is None:
        pairs = calibration_pairs(points, odometry, config)
    angles = [math.atan2(o.x * m[1] - o.y * m[0], o.x * m[0] + o.y * m[1]) for o, m, _ in pairs]
    if len(angles) < 2:
        return YawEstimate(0.0, math.inf, len(angles), False)
    # A 10 % trimmed mean and its standard error from the winsorized variance (Tukey-McLaughlin):
    # the differences have long tails (a pair matched to the wrong wall), and the median's error
    # from the MAD is half again as wide on the shared logs.
    a = np.sort(np.asarray(angles))
    g = int(0.1 * len(a))
    core = a[g: len(a) - g]
    yaw = float(np.mean(core))
    wins = np.clip(a, core[0], core[-1])
    se = float(np.std(wins, ddof=1) / ((1.0 - 2.0 * g / len(a)) * math.sqrt(len(a))))
    applied = len(a) >= config.yaw_min_pairs and abs(yaw) >= config.yaw_sigmas * se and yaw != 0.0
    return YawEstimate(yaw, se, len(a), applied)


@dataclass(frozen=True)
class ScaleEstimate:
    """What :func:`wheel_scale` found: ``scale``, the wheels' distance over the scans' (median
    over the pairs), ``se`` its standard error, the ``pairs`` it rests on and whether it passed
    the test of ``scale_min_pairs``, ``scale_sigmas`` and ``scale_min`` (``correction`` is then
    ``scale``, else 1)."""

    scale: float
    se: float
    pairs: int
    applied: bool

    @property
    def correction(self) -> float:
        """What every wheel increment's translation is divided by (1 when not applied)."""
        return self.scale if self.applied else 1.0


def wheel_scale(pairs: list[CalibrationPair], config: FrontendConfig) -> ScaleEstimate:
    """The wheels' distance scale from matched consecutive scans (:func:`calibration_pairs`):
    per pair, the wheels' distance over the matched motion along the wheels' direction
    (``|o|^2 / (o . m)``: a pair in a corridor, whose match slides along it, errs along the
    motion as much as it errs at all, but a sideways error does not count), their median and its
    standard error (1.2533 times the robust sigma, 1.4826 times the median absolute deviation,
    over the root of their number)."""
    ratios = []
    for o, m, _ in pairs:
        along = o.x * float(m[0]) + o.y * float(m[1])
        if along > 0.01:
            ratios.append((o.x * o.x + o.y * o.y) / along)
    if len(ratios) < 3:
        return ScaleEstimate(1.0, math.inf, len(ratios), False)
    r = np.asarray(ratios)
    scale = float(np.median(r))
    se = 1.2533 * 1.4826 * float(np.median(np.abs(r - scale))) / math.sqrt(len(r))
    off = abs(scale - 1.0)
    applied = (len(r) >= config.scale_min_pairs and off >= config.scale_sigmas * se
               and off >= config.scale_min and off > 0.0)
    return ScaleEstimate(scale, se, len(r), applied)


class CalibrationPair(NamedTuple):
    """Two consecutive scans matched (:func:`calibration_pairs`): the wheels' increment from scan
    ``scan - 1`` to scan ``scan`` and the matched one (``x, y, theta``)."""

    odometry: Pose
    matched: FloatArray
    scan: int


def calibration_pairs(
    points: list[FloatArray], odometry: list[Pose], config: FrontendConfig
) -> list[CalibrationPair]:
    """The scan pairs the calibrations rest on (:func:`laser_yaw`, :func:`odometry_noise`,
    :func:`wheel_scale`): ``(odometry increment, matched increment, k)`` of up to
    ``yaw_max_pairs`` consecutive scans ``k - 1, k`` (evenly spread) whose odometry moved at
    least ``yaw_min_step`` metres: scan ``k``'s points matched against scan ``k - 1``'s alone
    (:func:`mapping.lidar_slam.match_scan` with ``config.slam``'s settings, from the odometry's
    increment, no prior), kept when at least ``yaw_min_inliers`` of them lie on the other scan's
    lines."""
    moved = _moved(points, odometry, config)
    if len(moved) > config.yaw_max_pairs:
        moved = [moved[i] for i in np.linspace(0, len(moved) - 1, config.yaw_max_pairs).round().astype(int)]
    return [p for p in (_matched_pair(points, odometry, k, config) for k in moved) if p is not None]


def _moved(points: list[FloatArray], odometry: list[Pose], config: FrontendConfig) -> list[int]:
    """The scans ``k`` whose odometry moved at least ``yaw_min_step`` from scan ``k - 1``."""
    return [k for k in range(1, min(len(points), len(odometry)))
            if math.hypot(odometry[k].x, odometry[k].y) >= config.yaw_min_step]


def _matched_pair(
    points: list[FloatArray], odometry: list[Pose], k: int, config: FrontendConfig
) -> CalibrationPair | None:
    """Scan ``k`` matched against scan ``k - 1`` alone (:func:`calibration_pairs`), or None."""
    o = odometry[k]
    m = match_to_previous(points[k - 1], points[k], o, config.slam)
    return CalibrationPair(o, m.pose, k) if m is not None and m.inliers >= config.yaw_min_inliers else None


def match_to_previous(prev: FloatArray, here: FloatArray, step: Pose, slam: SlamConfig) -> Match | None:
    """A scan's points ``here`` matched against the scan before it alone (``prev``; both robot
    frame) from the wheels' ``step`` between them, no prior (:func:`mapping.lidar_slam.match_scan`
    with ``slam``'s settings, the facing check as they say): the :class:`mapping.lidar_slam.Match`,
    or None when either scan has fewer than 3 points."""
    if len(prev) < 3 or len(here) < 3:
        return None
    sub = Submap.build([(prev, scan_normals(prev, slam.normal_gap))], slam.voxel)
    sides = scan_sides(here, scan_normals(here, slam.normal_gap))
    return match_scan(here, sub, np.array(step.as_tuple()), slam, sides=sides)


@dataclass(frozen=True)
class OdometryNoise:
    """What :func:`odometry_noise` found: ``rot_per_m``, the wheel odometry's heading error per
    metre driven (radians; a robust standard deviation), the matched ``pairs`` it rests on, and
    ``correlation``, the lag-1 autocorrelation of those errors from one pair to the next, over
    the ``neighbours`` pairs of pairs that are consecutive scans (NaN with fewer than 2): near 0
    for independent noise, near 1 for a smooth drift."""

    rot_per_m: float
    pairs: int
    correlation: float = math.nan
    neighbours: int = 0


def odometry_noise(
    points: list[FloatArray], odometry: list[Pose], config: FrontendConfig,
    pairs: list[CalibrationPair] | None = None,
) -> OdometryNoise:
    """The wheel odometry's heading noise per metre, from the log itself: for consecutive scans
    matched against each other alone (:func:`calibration_pairs`), the odometry's turn minus the
    scans' turn, divided by the distance; their spread about zero as 1.4826 times the median
    absolute value (a pair matched to the wrong wall is an outlier, not noise; about zero, so
    that a heading bias -- unequal wheels -- counts as much as noise). The scans' own turn
    is good to about 0.1-0.2 degrees; the wheels err by 0.4-2 degrees per metre on the
    shared logs, so the estimate is the wheels'. ``points``: each scan's points (robot frame);
    ``odometry``: the wheel increment into each scan (``odometry[0]`` unused); ``pairs``: their
    :func:`calibration_pairs` when already made. The errors' correlation
    (:attr:`OdometryNoise.correlation`) is taken between consecutive scan pairs: on a long log,
    whose calibration pairs are spread out, each pair is joined by the one after it, matched
    for this alone."""
    if pairs is None:
        pairs = calibration_pairs(points, odometry, config)
    if len(pairs) < 2:
        return OdometryNoise(math.nan, len(pairs))
    def per_metre(ps: list[CalibrationPair]) -> FloatArray:
        return np.array([math.remainder(o.theta - float(m[2]), math.tau) / math.hypot(o.x, o.y)
                         for o, m, _ in ps])

    spread = 1.4826 * float(np.median(np.abs(per_metre(pairs))))
    # The correlation needs pairs of consecutive scans; on a long log the calibration's pairs are
    # spread out, so each is given the pair after it (matched for this alone).
    have = {p.scan for p in pairs}
    moved = set(_moved(points, odometry, config))
    extra = [_matched_pair(points, odometry, p.scan + 1, config) for p in pairs
             if p.scan + 1 not in have and p.scan + 1 in moved]
    both = sorted([*pairs, *(p for p in extra if p is not None)], key=lambda p: p.scan)
    correlation, neighbours = lag_correlation(per_metre(both), 3.0 * spread, np.array([p.scan for p in both]))
    return OdometryNoise(spread, len(pairs), correlation, neighbours)


def lag_correlation(
    values: FloatArray, clip: float, index: NDArray[np.int_] | None = None
) -> tuple[float, int]:
    """``(r, n)``: the lag-1 autocorrelation of ``values`` (in order), each clipped to ``[-clip,
    clip]`` first (a pair matched to the wrong wall is one wild value, not a trend), over the
    ``n`` neighbours whose ``index`` differs by one when given (the calibration's pairs are
    spread over a long log: at a stride of ``s`` an AR(1) series' correlation is ``r**s``); r is
    NaN with fewer than 2 such neighbours or without spread."""
    v = np.asarray(values, dtype=np.float64)
    if clip > 0:
        v = np.clip(v, -clip, clip)
    a, b = v[:-1], v[1:]
    if index is not None:
        next_to = np.diff(np.asarray(index)) == 1
        a, b = a[next_to], b[next_to]
    n = len(a)
    if n < 2:
        return math.nan, n
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return (float(a @ b) / den if den > 0 else math.nan), n


def calibrated_slam(config: SlamConfig, noise: OdometryNoise) -> SlamConfig:
    """``config`` with the local match's heading prior per metre (``odo_rot_per_m``) widened to
    ``odo_calibration_scale`` times the measured noise when that is wider, up to
    ``odo_calibration_max`` (with fewer than ``odo_calibration_min_pairs`` pairs, not), then
    by the errors' correlation when it is significant (``odo_correlation_sigmas``: the prior
    times ``sqrt((1 + r) / (1 - r))``, the spread of a sum of errors correlated as an AR(1)
    series over that of independent ones, up to ``odo_calibration_max``). The configured value
    stays the floor: a log whose wheels are better than it keeps it."""
    prior = config.odo_rot_per_m
    if noise.pairs >= config.odo_calibration_min_pairs and math.isfinite(noise.rot_per_m):
        prior = max(prior, min(config.odo_calibration_scale * noise.rot_per_m, config.odo_calibration_max))
    r = noise.correlation
    if math.isfinite(r) and noise.neighbours >= 2 \
            and r > config.odo_correlation_sigmas / math.sqrt(noise.neighbours):
        r = min(r, 0.95)
        prior = max(prior, min(prior * math.sqrt((1.0 + r) / (1.0 - r)), config.odo_calibration_max))
    return config if prior == config.odo_rot_per_m else replace(config, odo_rot_per_m=prior)


def run_slam(points: list[FloatArray], odometry: list[Pose], config: SlamConfig,
             start: FloatArray | None = None, noise: OdometryNoise | None = None) -> LidarSlam:
    """Lidar SLAM over a whole log (:class:`mapping.lidar_slam.LidarSlam`): every scan added
    in order (its points, robot frame; the wheel odometry's increment since the previous scan,
    ``odometry[0]`` ignored), then ``config.refine_passes`` passes of
    :meth:`~mapping.lidar_slam.LidarSlam.refine`. ``start``: the first pose (the origin).
    With ``config.odo_calibration`` the heading prior is first fitted to the log's own wheels
    (:func:`calibrated_slam`) by ``noise``, or when not given by :func:`odometry_noise` over the
    front end's default pairs; the SLAM's ``config`` is the one used."""
    if config.odo_calibration:
        if noise is None:
            noise = odometry_noise(points, odometry, FrontendConfig(slam=config))
        config = calibrated_slam(config, noise)
    slam = LidarSlam(config, start=np.zeros(3) if start is None else np.asarray(start, dtype=np.float64))
    for k, (pts, odo) in enumerate(zip(points, odometry)):
        slam.add(pts, np.zeros(3) if k == 0 else np.array(odo.as_tuple()))
    for _ in range(config.refine_passes):
        slam.refine()
    return slam


def slam_increments(
    points: list[FloatArray], odometry: list[Pose], config: SlamConfig, noise: OdometryNoise | None = None
) -> tuple[list[Pose], LidarSlam]:
    """The motion between consecutive scans after lidar SLAM over the whole log
    (:func:`run_slam`), from each scan's points and the wheel odometry's increments. Returns the
    increments of the final, smoothed trajectory (the first is the identity) and the SLAM itself
    (its ``online`` poses are what it knew at each scan).

    This is the offline (whole log in hand) use, like Cartographer's offline mode: a loop
    closed at the end straightens the increments of the whole loop before the filter maps it.
    """
    slam = run_slam(points, odometry, config, noise=noise)
    return increments([Pose(*map(float, p)) for p in slam.scan_poses()]), slam


#: :class:`OnlineSlam` measures the wheels' heading noise again every this many scans while
#: the first ``calibration_scans`` gave too few scan pairs for it.
ONLINE_RECALIBRATE = 25
#: ... and gives up after this many scans (the scans it measures on are kept until then).
ONLINE_RECALIBRATE_MAX_SCANS = 5000


class OnlineSlam:
    """The lidar SLAM scan by scan, as a robot mapping while it drives runs it
    (``config.slam.online``): :meth:`add` takes one scan's points and the wheels' motion into it
    and gives the motion from the pose the SLAM gave the scan before to the pose it gives this
    one (the scan-to-map match, loops closed so far, the online refinement's sweep when
    ``slam.refine_online_nodes`` is on; no offline refine passes). ``noise``: the wheels'
    heading noise measured so far (``odo_calibration``); while it rests on too few scan pairs and
    ``config.calibration_scans`` limited it to the first scans, it is measured again on every
    scan so far each :data:`ONLINE_RECALIBRATE` scans, and ``on_noise`` is given the measure the
    SLAM then runs with. The scans are kept only until then, and at most
    :data:`ONLINE_RECALIBRATE_MAX_SCANS` of them: a stream that has not pinned the noise down by
    then keeps the prior it has. With ``config.follow_graph``, ``warp`` is the SLAM's nodes
    before and after the loops or refinement that moved them during the last :meth:`add` (else None): the map
    built so far follows them (:func:`agents.mapping_run.feed`)."""

    def __init__(
        self, config: FrontendConfig, noise: OdometryNoise | None = None,
        on_noise: Callable[[OdometryNoise], None] | None = None,
    ) -> None:
        self.config = config
        self.on_noise = on_noise
        slam_cfg = config.slam if noise is None else calibrated_slam(config.slam, noise)
        self.slam = LidarSlam(slam_cfg, start=np.zeros(3))
        self.pending = (config.slam.odo_calibration and config.calibration_scans > 0
                        and (noise is None or noise.pairs < config.slam.odo_calibration_min_pairs))
        self._points: list[FloatArray] = []
        self._odometry: list[Pose] = []
        self._last: Pose | None = None
        self.scans = 0
        self._graph = np.zeros((0, 3))  # the nodes after the scan before (config.follow_graph)
        self._reshaped = 0
        self.warp: tuple[FloatArray, FloatArray] | None = None

    def add(self, points: FloatArray, odometry: Pose) -> Pose:
        k = self.scans
        cfg = self.config
        if self.pending and k > cfg.calibration_scans and k % ONLINE_RECALIBRATE == 0:
            now_noise = odometry_noise(self._points, self._odometry, cfg)
            if now_noise.pairs >= cfg.slam.odo_calibration_min_pairs:
                self.slam.config = calibrated_slam(cfg.slam, now_noise)
                self.pending = False
                self._points, self._odometry = [], []
                if self.on_noise is not None:
                    self.on_noise(now_noise)
        if self.pending and k >= ONLINE_RECALIBRATE_MAX_SCANS:
            self.pending = False  # a stream that never pins the noise down: the prior stays as it is
            self._points, self._odometry = [], []
        if self.pending:
            self._points.append(points)
            self._odometry.append(odometry)
        prior = np.zeros(3) if k == 0 else np.array(odometry.as_tuple())
        now = Pose(*map(float, self.slam.add(points, prior)))
        self.warp = None
        if cfg.follow_graph:  # a loop moved the nodes scans were mapped at
            nodes, n = self.slam.poses, len(self._graph)
            if self.slam.reshaped != self._reshaped and n and np.isfinite(nodes[:n]).all():
                self.warp = (self._graph, nodes[:n])
            self._reshaped = self.slam.reshaped
            self._graph = nodes  # the SLAM replaces its poses, never edits them: no copy
        step = Pose.identity() if self._last is None else self._last.between(now)
        self._last = now
        self.scans += 1
        return step


class LidarFrontend:
    """Turns one real scan into ``(corner scan, points)`` for :meth:`mapping.filter.WireframeFilter.step`.

    Parameters
    ----------
    config : FrontendConfig, optional
    extract : ExtractConfig, optional
        The split-and-merge settings (:func:`mapping.extract.extract_corners`).
    """

    def __init__(self, config: FrontendConfig | None = None, extract: ExtractConfig | None = None) -> None:
        self.config = config or FrontendConfig()
        self.extract = extract

    def scan(self, ranges: FloatArray, angles: FloatArray, max_range: float) -> tuple[Wireframe, FloatArray]:
        """The corner scan (returns at or beyond ``max_range`` are no return) and the points."""
        r = np.asarray(ranges, dtype=np.float64)
        corners = r.copy()
        with np.errstate(invalid="ignore"):
            corners[~(corners < max_range)] = np.inf
        if self.extract is None:
            wf = extract_corners(corners, angles, max_range)
        else:
            wf = extract_corners(corners, angles, max_range, self.extract)
        return wf, scan_points(r, angles, self.config)
